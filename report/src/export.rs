//! Exports: the calibrated table as URDF joint origins.
//!
//! Contract:
//! - [`urdf`] writes a chain `base_link → link1 … linkN → tool0` (an arm of N joints) whose
//!   revolute joint `jointI` turns about its z axis by the joint's *reading*: each joint's
//!   origin carries the previous row's `Tz(d) Tx(a) Rx(α)` and its own `Rz(θ offset)`, the fixed
//!   joint `tool0_joint` the last row's; forward kinematics of the URDF equals the table's
//!   (tested).

use std::fmt::{self, Write as _};

use calib_core::DhTable;
use nalgebra::Rotation3;

/// Why an export failed.
#[derive(Debug, Clone, PartialEq)]
pub enum ExportError {
    /// A parameter is not finite (`a3`, …).
    NotFinite(String),
}

impl fmt::Display for ExportError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            ExportError::NotFinite(p) => write!(f, "parameter {p} is not finite"),
        }
    }
}

impl std::error::Error for ExportError {}

fn check_finite<const N: usize>(table: &DhTable<N>) -> Result<(), ExportError> {
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

fn origin(out: &mut String, xyz: [f64; 3], rpy: (f64, f64, f64)) {
    let _ = writeln!(
        out,
        "    <origin xyz=\"{} {} {}\" rpy=\"{} {} {}\"/>",
        xyz[0], xyz[1], xyz[2], rpy.0, rpy.1, rpy.2
    );
}

/// A joint's origin (a link's frame at zero reading, `calib_core::DhTable::links`): translation
/// and roll-pitch-yaw (URDF's fixed-axis convention, `R = Rz(yaw) Ry(pitch) Rx(roll)`).
fn joint_origin(frame: &calib_core::Frame) -> ([f64; 3], (f64, f64, f64)) {
    let r = Rotation3::from_matrix_unchecked(frame.r);
    ([frame.p.x, frame.p.y, frame.p.z], r.euler_angles())
}

/// URDF of the arm described by `table` (see the module docs). `limits` are the joint ranges
/// (rad) of the readings, written as the revolute joints' limits. An arm of any length `N`.
pub fn urdf<const N: usize>(
    robot: &str,
    table: &DhTable<N>,
    limits: &[(f64, f64); N],
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
    for i in 1..=N {
        let _ = writeln!(out, "  <link name=\"link{i}\"/>");
    }
    let _ = writeln!(out, "  <link name=\"tool0\"/>");
    let (links, tool) = table.links(&[0.0; N]);
    for (i, link) in links.iter().enumerate() {
        let parent = if i == 0 {
            "base_link".to_string()
        } else {
            format!("link{i}")
        };
        let (xyz, rpy) = joint_origin(link);
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
    let (xyz, rpy) = joint_origin(&tool);
    let _ = writeln!(out, "  <joint name=\"tool0_joint\" type=\"fixed\">");
    let _ = writeln!(out, "    <parent link=\"link{N}\"/>");
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::input::MAX_JOINTS;
    use calib_core::Frame;

    fn calibrated() -> DhTable<MAX_JOINTS> {
        DhTable::paper_actual()
    }

    #[test]
    fn a_non_finite_table_is_not_exported() {
        let mut bad = calibrated();
        bad.rows[2].d = f64::NAN;
        assert_eq!(
            urdf("x", &bad, &[(-1.0, 1.0); MAX_JOINTS])
                .unwrap_err()
                .to_string(),
            "parameter d3 is not finite"
        );
    }

    /// Forward kinematics of a parsed URDF chain at readings `q`.
    fn urdf_fk(robot: &urdf_rs::Robot, q: &[f64; MAX_JOINTS]) -> Frame {
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
        assert_eq!(k, MAX_JOINTS);
        Frame::from_isometry(&t)
    }

    #[test]
    fn the_urdf_parses_and_its_forward_kinematics_is_the_tables() {
        let t = calibrated();
        let limits = [(-1.5, 1.5); MAX_JOINTS];
        let text = urdf("exocal <suit>", &t, &limits).unwrap();
        let robot = urdf_rs::read_from_string(&text).unwrap();
        assert_eq!(robot.name, "exocal <suit>");
        assert_eq!(robot.joints.len(), MAX_JOINTS + 1);
        assert_eq!(robot.joints[3].limit.lower, -1.5);
        let mut rng = calib_core::Rng::new(4);
        for _ in 0..20 {
            let q: [f64; MAX_JOINTS] = std::array::from_fn(|_| 3.0 * rng.uniform() - 1.5);
            let a = urdf_fk(&robot, &q);
            let b = t.fk(&q);
            assert!((a.p - b.p).norm() < 1e-12, "{:?} vs {:?}", a.p, b.p);
            assert!((a.r - b.r).norm() < 1e-12);
        }
    }
}
