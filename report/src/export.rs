//! Exports: the calibrated table as the daemon's TOML configuration and as URDF joint origins,
//! and recorded frames as a `candump -L` log.
//!
//! Contract:
//! - [`config_toml`] rewrites only the four `[nominal]` arrays of a configuration text (the one
//!   the daemon ran with, or its shipped default), keeping every other key, comment and layout:
//!   the result is a complete configuration the daemon loads, whose nominal table is the
//!   calibrated one (lengths in metres, angles in degrees, as the file speaks);
//! - [`urdf`] writes a chain `base_link → link1 … link7 → tool0` whose revolute joint `jointN`
//!   turns about its z axis by the joint's *reading*: each joint's origin carries the previous
//!   row's `Tz(d) Tx(a) Rx(α)` and its own `Rz(θ offset)`, the fixed joint `tool0_joint` the last
//!   row's; forward kinematics of the URDF equals the table's (tested);
//! - [`write_candump`] writes one `(seconds.micros) iface ID#DATA` line per frame, the format
//!   `candump -L` writes and `canplayer` and [`crate::readers::parse_candump`] read.

use std::fmt::{self, Write as _};
use std::io;

use calib_core::DhTable;
use nalgebra::Rotation3;
use toml_edit::{Array, DocumentMut, Item, Value};

use crate::input::JOINTS;
use crate::readers::RecordedFrame;

/// Why an export failed.
#[derive(Debug, Clone, PartialEq)]
pub enum ExportError {
    /// The base configuration is not valid TOML (the parser's message).
    BaseToml(String),
    /// The base configuration has no `[nominal]` table.
    NoNominal,
    /// A parameter is not finite (`a3`, …).
    NotFinite(String),
}

impl fmt::Display for ExportError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            ExportError::BaseToml(e) => write!(f, "the base configuration is not TOML: {e}"),
            ExportError::NoNominal => write!(f, "the base configuration has no [nominal] table"),
            ExportError::NotFinite(p) => write!(f, "parameter {p} is not finite"),
        }
    }
}

impl std::error::Error for ExportError {}

fn check_finite(table: &DhTable<JOINTS>) -> Result<(), ExportError> {
    for (i, r) in table.rows.iter().enumerate() {
        for (name, v) in [
            ("a", r.a),
            ("alpha", r.alpha),
            ("d", r.d),
            ("offset", r.theta_offset),
        ] {
            if !v.is_finite() {
                return Err(ExportError::NotFinite(format!("{name}{}", i + 1)));
            }
        }
    }
    Ok(())
}

/// `base` (a daemon configuration) with its `[nominal]` table replaced by `table`.
pub fn config_toml(base: &str, table: &DhTable<JOINTS>) -> Result<String, ExportError> {
    check_finite(table)?;
    let mut doc: DocumentMut = base
        .parse()
        .map_err(|e: toml_edit::TomlError| ExportError::BaseToml(e.to_string()))?;
    let nominal = doc
        .get_mut("nominal")
        .and_then(Item::as_table_like_mut)
        .ok_or(ExportError::NoNominal)?;
    type Column = (&'static str, fn(&calib_core::DhRow) -> f64);
    let columns: [Column; 4] = [
        ("a", |r| r.a),
        ("alpha_deg", |r| r.alpha.to_degrees()),
        ("d", |r| r.d),
        ("offset_deg", |r| r.theta_offset.to_degrees()),
    ];
    for (key, get) in columns {
        let values: Array = table.rows.iter().map(get).collect();
        match nominal.get_mut(key).and_then(Item::as_value_mut) {
            // Keep the key's decoration (comments, spacing) and replace the value.
            Some(old) => {
                let decor = old.decor().clone();
                *old = Value::Array(values);
                *old.decor_mut() = decor;
            }
            None => {
                nominal.insert(key, Item::Value(Value::Array(values)));
            }
        }
    }
    Ok(doc.to_string())
}

fn origin(out: &mut String, xyz: [f64; 3], rpy: (f64, f64, f64)) {
    let _ = writeln!(
        out,
        "    <origin xyz=\"{} {} {}\" rpy=\"{} {} {}\"/>",
        xyz[0], xyz[1], xyz[2], rpy.0, rpy.1, rpy.2
    );
}

/// The static part `Tz(d) Tx(a) Rx(α)` of a row, then `Rz(offset_next)`: translation and
/// roll-pitch-yaw (URDF's fixed-axis convention, `R = Rz(yaw) Ry(pitch) Rx(roll)`).
fn joint_origin(prev: Option<&calib_core::DhRow>, offset: f64) -> ([f64; 3], (f64, f64, f64)) {
    let (p, r) = match prev {
        Some(row) => (
            [row.a, 0.0, row.d],
            Rotation3::from_axis_angle(&nalgebra::Vector3::x_axis(), row.alpha),
        ),
        None => ([0.0; 3], Rotation3::identity()),
    };
    let r = r * Rotation3::from_axis_angle(&nalgebra::Vector3::z_axis(), offset);
    // Tz(d) Tx(a) puts the origin at (a, 0, d) before Rx(α): the translation is in the parent.
    (p, r.euler_angles())
}

/// URDF of the arm described by `table` (see the module docs). `limits` are the joint ranges
/// (rad) of the readings, written as the revolute joints' limits.
pub fn urdf(
    robot: &str,
    table: &DhTable<JOINTS>,
    limits: &[(f64, f64); JOINTS],
) -> Result<String, ExportError> {
    check_finite(table)?;
    let mut out = String::new();
    let _ = writeln!(out, "<?xml version=\"1.0\"?>");
    let _ = writeln!(
        out,
        "<!-- exocal calibrated kinematics: standard D-H rows as joint origins. -->"
    );
    let _ = writeln!(out, "<robot name=\"{}\">", xml_escape(robot));
    let _ = writeln!(out, "  <link name=\"base_link\"/>");
    for i in 1..=JOINTS {
        let _ = writeln!(out, "  <link name=\"link{i}\"/>");
    }
    let _ = writeln!(out, "  <link name=\"tool0\"/>");
    for (i, row) in table.rows.iter().enumerate() {
        let parent = if i == 0 {
            "base_link".to_string()
        } else {
            format!("link{i}")
        };
        let (xyz, rpy) = joint_origin(i.checked_sub(1).map(|p| &table.rows[p]), row.theta_offset);
        let _ = writeln!(out, "  <joint name=\"joint{}\" type=\"revolute\">", i + 1);
        let _ = writeln!(out, "    <parent link=\"{parent}\"/>");
        let _ = writeln!(out, "    <child link=\"link{}\"/>", i + 1);
        origin(&mut out, xyz, rpy);
        let _ = writeln!(out, "    <axis xyz=\"0 0 1\"/>");
        let (lo, hi) = limits[i];
        let _ = writeln!(
            out,
            "    <limit lower=\"{lo}\" upper=\"{hi}\" effort=\"0\" velocity=\"0\"/>"
        );
        let _ = writeln!(out, "  </joint>");
    }
    let (xyz, rpy) = joint_origin(Some(&table.rows[JOINTS - 1]), 0.0);
    let _ = writeln!(out, "  <joint name=\"tool0_joint\" type=\"fixed\">");
    let _ = writeln!(out, "    <parent link=\"link{JOINTS}\"/>");
    let _ = writeln!(out, "    <child link=\"tool0\"/>");
    origin(&mut out, xyz, rpy);
    let _ = writeln!(out, "  </joint>");
    let _ = writeln!(out, "</robot>");
    Ok(out)
}

fn xml_escape(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

/// One `candump -L` line (no newline).
pub fn candump_line(frame: &RecordedFrame, iface: &str) -> String {
    let mut s = format!(
        "({}.{:06}) {iface} ",
        frame.t.as_secs(),
        frame.t.subsec_micros()
    );
    if frame.extended {
        let _ = write!(s, "{:08X}#", frame.id);
    } else {
        let _ = write!(s, "{:03X}#", frame.id);
    }
    if frame.remote {
        s.push('R');
    } else {
        for b in &frame.data {
            let _ = write!(s, "{b:02X}");
        }
    }
    s
}

/// Writes `frames` as a `candump -L` log on interface `iface`.
pub fn write_candump(
    frames: &[RecordedFrame],
    iface: &str,
    out: &mut impl io::Write,
) -> io::Result<()> {
    for f in frames {
        writeln!(out, "{}", candump_line(f, iface))?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use calib_core::Frame;
    use std::time::Duration;

    fn calibrated() -> DhTable<JOINTS> {
        DhTable::paper_actual()
    }

    #[test]
    fn config_export_replaces_only_the_nominal_arrays() {
        let base = "# head\n[can]\ninterface = \"can0\" # keep me\n\n[nominal]\n# rows\na = [1.0]\nalpha_deg = [0.0] # twist\nd = [0.0]\noffset_deg = [0.0]\n\n[push]\nretries = 3\n";
        let t = calibrated();
        let out = config_toml(base, &t).unwrap();
        assert!(out.contains("interface = \"can0\" # keep me"), "{out}");
        assert!(out.contains("# rows"));
        assert!(out.contains("# twist"));
        assert!(out.contains("retries = 3"));
        let doc: toml_edit::DocumentMut = out.parse().unwrap();
        let read = |k: &str| -> Vec<f64> {
            doc["nominal"][k]
                .as_array()
                .unwrap()
                .iter()
                .map(|v| v.as_float().unwrap())
                .collect()
        };
        assert_eq!(read("a"), t.rows.map(|r| r.a).to_vec());
        assert_eq!(read("d"), t.rows.map(|r| r.d).to_vec());
        for (deg, r) in read("alpha_deg").iter().zip(&t.rows) {
            assert!((deg.to_radians() - r.alpha).abs() < 1e-15);
        }
        for (deg, r) in read("offset_deg").iter().zip(&t.rows) {
            assert!((deg.to_radians() - r.theta_offset).abs() < 1e-15);
        }
    }

    #[test]
    fn config_export_errors_name_the_problem() {
        let t = calibrated();
        assert!(matches!(
            config_toml("a = [", &t),
            Err(ExportError::BaseToml(_))
        ));
        assert_eq!(
            config_toml("[can]\nx = 1\n", &t),
            Err(ExportError::NoNominal)
        );
        let mut bad = t;
        bad.rows[2].d = f64::NAN;
        assert_eq!(
            config_toml("[nominal]\n", &bad),
            Err(ExportError::NotFinite("d3".into()))
        );
        assert_eq!(
            urdf("x", &bad, &[(-1.0, 1.0); JOINTS])
                .unwrap_err()
                .to_string(),
            "parameter d3 is not finite"
        );
    }

    /// Forward kinematics of a parsed URDF chain at readings `q`.
    fn urdf_fk(robot: &urdf_rs::Robot, q: &[f64; JOINTS]) -> Frame {
        let mut t = nalgebra::Isometry3::identity();
        let mut link = "base_link".to_string();
        let mut k = 0;
        while let Some(j) = robot.joints.iter().find(|j| j.parent.link == link) {
            let o = &j.origin;
            let rot = nalgebra::UnitQuaternion::from_euler_angles(o.rpy[0], o.rpy[1], o.rpy[2]);
            let tr = nalgebra::Translation3::new(o.xyz[0], o.xyz[1], o.xyz[2]);
            t *= nalgebra::Isometry3::from_parts(tr, rot);
            if matches!(j.joint_type, urdf_rs::JointType::Revolute) {
                assert_eq!(*j.axis.xyz, [0.0, 0.0, 1.0]);
                t *= nalgebra::Isometry3::rotation(nalgebra::Vector3::z() * q[k]);
                k += 1;
            }
            link = j.child.link.clone();
        }
        assert_eq!(link, "tool0");
        assert_eq!(k, JOINTS);
        Frame::from_isometry(&t)
    }

    #[test]
    fn the_urdf_parses_and_its_forward_kinematics_is_the_tables() {
        let t = calibrated();
        let limits = [(-1.5, 1.5); JOINTS];
        let text = urdf("exocal <suit>", &t, &limits).unwrap();
        let robot = urdf_rs::read_from_string(&text).unwrap();
        assert_eq!(robot.name, "exocal <suit>");
        assert_eq!(robot.joints.len(), JOINTS + 1);
        assert_eq!(robot.joints[3].limit.lower, -1.5);
        let mut rng = calib_core::Rng::new(4);
        for _ in 0..20 {
            let q: [f64; JOINTS] = std::array::from_fn(|_| 3.0 * rng.uniform() - 1.5);
            let a = urdf_fk(&robot, &q);
            let b = t.fk(&q);
            assert!((a.p - b.p).norm() < 1e-12, "{:?} vs {:?}", a.p, b.p);
            assert!((a.r - b.r).norm() < 1e-12);
        }
    }

    #[test]
    fn candump_lines_are_candump_dash_l() {
        let f = RecordedFrame {
            t: Duration::new(1_700_000_000, 123_456_789),
            id: 0x123,
            extended: false,
            remote: false,
            data: vec![0xDE, 0xAD, 0xBE, 0xEF],
        };
        assert_eq!(
            candump_line(&f, "vcan0"),
            "(1700000000.123456) vcan0 123#DEADBEEF"
        );
        let e = RecordedFrame {
            id: 0x1ABCDE,
            extended: true,
            remote: true,
            data: vec![],
            ..f.clone()
        };
        assert_eq!(
            candump_line(&e, "can1"),
            "(1700000000.123456) can1 001ABCDE#R"
        );
        let mut out = Vec::new();
        write_candump(&[f.clone(), f], "vcan0", &mut out).unwrap();
        assert_eq!(String::from_utf8(out).unwrap().lines().count(), 2);
    }
}
