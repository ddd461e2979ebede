//! The text formats of recorded sessions: `candump -L` logs (frames) and CSV samples.
//!
//! Contract:
//! - [`CandumpReader`] (and [`parse_candump`] on a whole text) returns the frames in file order
//!   with their recorded receive times (each line read by the protocol crate's one candump
//!   reader, [`Received::from_candump`]); it neither decodes nor reorders — the session's
//!   ingest does that, as for a live bus;
//! - [`CsvReader`] (and [`parse_csv`]) returns calibration samples directly (no alignment) in
//!   the format below;
//! - both take the input a line at a time and keep at most what one session under the window's
//!   rules can hold ([`Budget`]: its count, and its span from the earliest to the latest time):
//!   the first line beyond it is refused, so a file of any length is read with bounded memory;
//! - bad input is a [`ReadError`] naming the input kind, the 1-based line (where there is one)
//!   and what is wrong; nothing here panics on any input. Parsing takes text, never a file.
//!
//! # The CSV sample format
//!
//! One header line, then one sample per line; blank lines and lines starting with `#` are
//! ignored. Columns, comma-separated, in this order:
//!
//! ```text
//! t,q1,q2,q3,q4,q5,q6,q7,x,y,z,qw,qx,qy,qz
//! ```
//!
//! for the paper's arm of seven joints; an arm of `n` joints has the columns `q1`…`qn`
//! ([`csv_header`]), and a file of another arm is refused, naming both counts. `t` is the time
//! in seconds (strictly increasing), `q1`…`qn` the joint readings in radians (joint 1 =
//! shoulder), `x,y,z` the measured end-effector position in metres in the
//! base frame, and `qw,qx,qy,qz` its orientation as a unit quaternion (scalar first; a norm
//! within 1e-3 of 1 is normalised, anything else is an error).

use std::fmt;

use calib_core::{Frame, Sample};
use exocal_dbc::Received;
use nalgebra::{Quaternion, UnitQuaternion, Vector3};

use crate::detail::TimedSample;
use crate::rules::{Budget, WindowRules};
use crate::MAX_JOINTS;

/// Largest joint reading a CSV sample may carry (rad): beyond it the file is in degrees.
pub const MAX_JOINT_READING_RAD: f64 = core::f64::consts::TAU;
/// Farthest end-effector position from the base a CSV sample may carry (m): beyond it the file
/// is in millimetres.
pub const MAX_POSITION_M: f64 = 5.0;
/// Characters of a bad line quoted in its error.
pub const MAX_QUOTED: usize = 80;

/// The CSV header of the longest arm ([`MAX_JOINTS`] joints), exactly.
pub const CSV_HEADER: &str = "t,q1,q2,q3,q4,q5,q6,q7,x,y,z,qw,qx,qy,qz";

/// Most columns a CSV line has (the longest arm's).
const MAX_COLUMNS: usize = 1 + MAX_JOINTS + 7;

/// The CSV header of an arm of `joints` joints, exactly: `t,q1,…,qn,x,y,z,qw,qx,qy,qz`.
pub fn csv_header(joints: usize) -> String {
    let q: Vec<String> = (1..=joints).map(|j| format!("q{j}")).collect();
    format!("t,{},x,y,z,qw,qx,qy,qz", q.join(","))
}

/// Which reader failed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum InputKind {
    /// A candump log (`candump -L` format).
    Candump,
    /// CSV samples (joint angles and poses).
    Csv,
}

impl fmt::Display for InputKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            InputKind::Candump => "candump log",
            InputKind::Csv => "CSV samples",
        })
    }
}

/// Bad input: which kind, where (1-based line), what.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ReadError {
    /// Which reader failed.
    pub kind: InputKind,
    /// 1-based line.
    pub line: Option<usize>,
    /// What is wrong.
    pub what: String,
}

impl fmt::Display for ReadError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.line {
            Some(l) => write!(f, "{}, line {l}: {}", self.kind, self.what),
            None => write!(f, "{}: {}", self.kind, self.what),
        }
    }
}

impl std::error::Error for ReadError {}

/// A `candump -L` log read line by line: `(seconds.fraction) iface ID#DATA` per line, optionally
/// followed by a direction flag `R` or `T` (as can-utils' `asc2log` and python-can write it), blank
/// lines skipped; at most what one session under the window's rules can hold ([`Budget`]).
#[derive(Debug, Clone)]
pub struct CandumpReader {
    budget: Budget,
    line: usize,
    frames: Vec<Received>,
}

impl CandumpReader {
    /// A reader bounded by `rules` ([`Budget::frames`]).
    pub fn new(rules: &WindowRules) -> CandumpReader {
        CandumpReader {
            budget: Budget::frames(rules),
            line: 0,
            frames: Vec::new(),
        }
    }

    /// Takes the file's next line (without its line ending).
    pub fn line(&mut self, line: &str) -> Result<(), ReadError> {
        self.line += 1;
        let line = line.trim();
        if line.is_empty() {
            return Ok(());
        }
        let err = |what: String| ReadError {
            kind: InputKind::Candump,
            line: Some(self.line),
            what,
        };
        let shown = || -> String { line.chars().take(MAX_QUOTED).collect() };
        let rx = Received::from_candump(line).map_err(|e| err(format!("{e}, in {:?}", shown())))?;
        self.budget
            .admit(rx.timestamp.as_secs_f64())
            .map_err(|e| err(format!("{e}, in {:?}", shown())))?;
        self.frames.push(rx);
        Ok(())
    }

    /// The frames, in file order.
    pub fn finish(self) -> Vec<Received> {
        self.frames
    }
}

/// Parses a `candump -L` log ([`CandumpReader`], line by line).
pub fn parse_candump(text: &str, rules: &WindowRules) -> Result<Vec<Received>, ReadError> {
    let mut r = CandumpReader::new(rules);
    for line in text.lines() {
        r.line(line)?;
    }
    Ok(r.finish())
}

/// `frames` as a `candump -L` log on interface `iface`, one line each.
pub fn candump_text(frames: &[Received], iface: &str) -> String {
    let mut out = String::new();
    for f in frames {
        out.push_str(&f.candump(iface).to_string());
        out.push('\n');
    }
    out
}

fn csv_err(line: usize, what: impl Into<String>) -> ReadError {
    ReadError {
        kind: InputKind::Csv,
        line: Some(line),
        what: what.into(),
    }
}

/// CSV samples read line by line (format in the module docs); at most what one session under
/// the window's rules can hold ([`Budget::samples`]).
#[derive(Debug, Clone)]
pub struct CsvReader {
    budget: Budget,
    /// Joints of the arm: its columns.
    joints: usize,
    line: usize,
    header: bool,
    samples: Vec<TimedSample>,
}

impl CsvReader {
    /// A reader of an arm of `joints` joints (1..=[`MAX_JOINTS`]), bounded by `rules`
    /// ([`Budget::samples`]).
    pub fn new(rules: &WindowRules, joints: usize) -> CsvReader {
        CsvReader {
            budget: Budget::samples(rules),
            joints: joints.clamp(1, MAX_JOINTS),
            line: 0,
            header: false,
            samples: Vec::new(),
        }
    }

    /// Takes the file's next line (without its line ending).
    pub fn line(&mut self, line: &str) -> Result<(), ReadError> {
        self.line += 1;
        let n = self.line;
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            return Ok(());
        }
        let mut fields = [""; MAX_COLUMNS];
        let mut count = 0;
        for (i, field) in line.split(',').enumerate() {
            if let Some(f) = fields.get_mut(i) {
                *f = field.trim();
            }
            count = i + 1;
        }
        let header = csv_header(self.joints);
        let width = 1 + self.joints + 7;
        let fields = &fields[..width];
        if !self.header {
            if count != width || fields.iter().zip(header.split(',')).any(|(a, b)| *a != b) {
                let theirs = (1..=MAX_JOINTS).find(|&m| line.replace(' ', "") == csv_header(m));
                return Err(csv_err(
                    n,
                    match theirs {
                        Some(m) => format!(
                            "the file has {m} joint columns (q1…q{m}), the configured arm has \
                             {} joints ([nodes] joints): header must be `{header}`",
                            self.joints
                        ),
                        None => format!("header must be `{header}`"),
                    },
                ));
            }
            self.header = true;
            return Ok(());
        }
        if count != width {
            return Err(csv_err(n, format!("{count} columns, expected {width}")));
        }
        let mut v = [0.0; MAX_COLUMNS];
        for ((x, field), name) in v.iter_mut().zip(fields).zip(header.split(',')) {
            *x = field
                .parse::<f64>()
                .ok()
                .filter(|x| x.is_finite())
                .ok_or_else(|| {
                    let shown: String = field.chars().take(MAX_QUOTED).collect();
                    csv_err(n, format!("{name} = {shown:?} is not a finite number"))
                })?;
        }
        // Unit mistakes get a hint naming the unit, not a calibration that fails later.
        let (q, pose) = v[1..width].split_at(self.joints);
        for (j, q) in q.iter().enumerate() {
            if q.abs() > MAX_JOINT_READING_RAD {
                return Err(csv_err(
                    n,
                    format!(
                        "q{} = {q}: a joint reading beyond ±2π; the CSV takes radians (in \
                         degrees? divide by 57.2958)",
                        j + 1
                    ),
                ));
            }
        }
        for (name, x) in ["x", "y", "z"].iter().zip(&pose[..3]) {
            if x.abs() > MAX_POSITION_M {
                return Err(csv_err(
                    n,
                    format!(
                        "{name} = {x}: an end-effector position {MAX_POSITION_M} m or more from \
                         the base; the CSV takes metres (in millimetres? divide by 1000)"
                    ),
                ));
            }
        }
        let t = v[0];
        if let Some(prev) = self.samples.last() {
            if t <= prev.t {
                return Err(csv_err(
                    n,
                    format!("t = {t} does not increase (previous {})", prev.t),
                ));
            }
        }
        let joints: [f64; MAX_JOINTS] = std::array::from_fn(|j| q.get(j).copied().unwrap_or(0.0));
        let q = Quaternion::new(pose[3], pose[4], pose[5], pose[6]);
        let norm = q.norm();
        if (norm - 1.0).abs() > 1e-3 {
            return Err(csv_err(n, format!("quaternion norm {norm:.6}, expected 1")));
        }
        self.budget
            .admit(t)
            .map_err(|e| csv_err(n, e.to_string()))?;
        let rot = UnitQuaternion::from_quaternion(q);
        self.samples.push(TimedSample {
            t,
            sample: Sample {
                joints,
                pose: Frame {
                    r: rot.to_rotation_matrix().into_inner(),
                    p: Vector3::new(pose[0], pose[1], pose[2]),
                },
            },
        });
        Ok(())
    }

    /// The samples, in file order; an error if there is no header or no sample.
    pub fn finish(self) -> Result<Vec<TimedSample>, ReadError> {
        let what = match (self.header, self.samples.is_empty()) {
            (false, _) => "empty file: no header",
            (true, true) => "no samples after the header",
            (true, false) => return Ok(self.samples),
        };
        Err(ReadError {
            kind: InputKind::Csv,
            line: None,
            what: what.into(),
        })
    }
}

/// Parses CSV samples of an arm of `joints` joints ([`CsvReader`], line by line).
pub fn parse_csv(
    text: &str,
    rules: &WindowRules,
    joints: usize,
) -> Result<Vec<TimedSample>, ReadError> {
    let mut r = CsvReader::new(rules, joints);
    for line in text.lines() {
        r.line(line)?;
    }
    r.finish()
}

/// `samples` of an arm of `joints` joints in the CSV format [`parse_csv`] reads (full
/// precision).
pub fn csv_text(samples: &[TimedSample], joints: usize) -> String {
    use fmt::Write as _;
    let joints = joints.clamp(1, MAX_JOINTS);
    let mut out = format!("{}\n", csv_header(joints));
    for s in samples {
        let q = UnitQuaternion::from_matrix(&s.sample.pose.r);
        let p = s.sample.pose.p;
        let _ = write!(out, "{}", s.t);
        for j in s.sample.joints.iter().take(joints) {
            let _ = write!(out, ",{j}");
        }
        let _ = writeln!(
            out,
            ",{},{},{},{},{},{},{}",
            p.x, p.y, p.z, q.w, q.i, q.j, q.k
        );
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use calib_core::ScenarioConfig;
    use std::time::Duration;

    fn rules() -> WindowRules {
        crate::Settings::suit_default().window
    }

    #[test]
    fn candump_logs_parse_exactly() {
        let log = "(1700000000.123456) vcan0 123#DEADBEEF\n\n(1700000001.5) can1 1ABCDEF0#\n(1700000002.000000001) vcan0 7FF#R\n";
        let f = parse_candump(log, &rules()).unwrap();
        assert_eq!(f.len(), 3);
        assert_eq!(f[0].timestamp, Duration::new(1_700_000_000, 123_456_000));
        assert_eq!(f[0].frame.raw_id(), 0x123);
        assert_eq!(f[1].timestamp, Duration::new(1_700_000_001, 500_000_000));
        assert_eq!(f[1].frame.raw_id(), 0x1ABC_DEF0);
        assert_eq!(f[2].timestamp.subsec_nanos(), 1);
    }

    #[test]
    fn candump_errors_name_the_line_and_the_problem() {
        let e = parse_candump("(0.5) vcan0 001#\n(1.0) vcan0 800#00\n", &rules()).unwrap_err();
        assert_eq!((e.kind, e.line), (InputKind::Candump, Some(2)));
        assert!(
            e.to_string()
                .starts_with("candump log, line 2: bad identifier"),
            "{e}"
        );
    }

    #[test]
    fn a_written_candump_log_reads_back_to_the_same_frames() {
        let log: String = (0..100u32)
            .map(|i| {
                let id = if i % 3 == 0 {
                    format!("{:08X}", 0x1000 + i)
                } else {
                    format!("{:03X}", 0x100 + i)
                };
                let data: String = match i % 17 {
                    5 => "R".into(),
                    _ => (0..(i % 9) as u8).map(|b| format!("{b:02X}")).collect(),
                };
                format!(
                    "({}.{:06}) vcan0 {id}#{data}\n",
                    1_700_000_000 + i / 10,
                    i * 9_876
                )
            })
            .collect();
        let frames = parse_candump(&log, &rules()).unwrap();
        assert_eq!(frames.len(), 100);
        assert_eq!(candump_text(&frames, "vcan0"), log);
    }

    fn samples(k: usize) -> Vec<TimedSample> {
        TimedSample::simulated(ScenarioConfig::paper(), 2, k)
    }

    #[test]
    fn an_arms_csv_has_its_joint_columns_and_another_arms_is_named() {
        let s: Vec<TimedSample> = (samples(20).into_iter())
            .map(|mut s| {
                s.sample.joints[4..].fill(0.0);
                s
            })
            .collect();
        let text = csv_text(&s, 4);
        assert_eq!(text.lines().next(), Some("t,q1,q2,q3,q4,x,y,z,qw,qx,qy,qz"));
        let back = parse_csv(&text, &rules(), 4).unwrap();
        for (a, b) in back.iter().zip(&s) {
            assert_eq!(a.sample.joints, b.sample.joints, "the padding reads 0");
        }
        let e = parse_csv(&text, &rules(), 6).unwrap_err().to_string();
        assert!(
            e.contains("4 joint columns") && e.contains("has 6 joints"),
            "{e}"
        );
        let e = parse_csv(&format!("{CSV_HEADER}\n"), &rules(), 4)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("7 joint columns") && e.contains("has 4 joints"),
            "{e}"
        );
    }

    #[test]
    fn csv_round_trips_through_csv_text() {
        let s = samples(50);
        let text = format!("# a comment\n\n{}", csv_text(&s, 7));
        let back = parse_csv(&text, &rules(), 7).unwrap();
        assert_eq!(back.len(), s.len());
        for (a, b) in back.iter().zip(&s) {
            assert_eq!(a.t, b.t);
            assert_eq!(a.sample.joints, b.sample.joints);
            assert_eq!(a.sample.pose.p, b.sample.pose.p);
            assert!((a.sample.pose.r - b.sample.pose.r).norm() < 1e-14);
        }
    }

    #[test]
    fn csv_errors_name_the_line_and_column() {
        let ok = "0.1,0,0,0,0,0,0,0,0.1,0.2,0.3,1,0,0,0";
        let cases = [
            (format!("t,q1\n{ok}"), 1, "header"),
            (format!("{CSV_HEADER}\n{ok},9"), 2, "16 columns"),
            (
                format!("{CSV_HEADER}\n{}", ok.replace("0.2", "nan")),
                2,
                "y = \"nan\"",
            ),
            (format!("{CSV_HEADER}\n{ok}\n{ok}"), 3, "does not increase"),
            (
                format!("{CSV_HEADER}\n{}", ok.replace(",1,0,0,0", ",2,0,0,0")),
                2,
                "quaternion norm",
            ),
            // Degrees and millimetres get a hint naming the unit.
            (
                format!(
                    "{CSV_HEADER}\n{ok}\n{}",
                    ok.replacen("0.1,0,0,0,0", "0.2,0,0,0,95.5", 1)
                ),
                3,
                "q4 = 95.5: a joint reading beyond ±2π; the CSV takes radians (in degrees?",
            ),
            (
                format!("{CSV_HEADER}\n{}", ok.replace("0.2,0.3", "200,0.3")),
                2,
                "y = 200: an end-effector position 5 m or more from the base; the CSV takes \
                 metres (in millimetres?",
            ),
        ];
        for (text, line, what) in cases {
            let e = parse_csv(&text, &rules(), 7).unwrap_err();
            assert_eq!(e.line, Some(line), "{text}");
            assert!(e.to_string().contains(what), "{e}");
        }
        assert!(parse_csv("", &rules(), 7)
            .unwrap_err()
            .to_string()
            .contains("no header"));
        assert!(parse_csv(CSV_HEADER, &rules(), 7)
            .unwrap_err()
            .to_string()
            .contains("no samples"));
    }

    /// A recording longer than one session (the default window: at most 180 s, + 1 s) is
    /// refused at its first line beyond, naming the line and the rule: a candump log whose
    /// first lines are at time 0 (the alignment grid would size itself from that span), more
    /// frames than a saturated bus carries, and CSV samples beyond the grid's count or span.
    #[test]
    fn recordings_longer_than_a_session_are_refused_at_the_first_line_beyond() {
        let r = rules();
        let log = "(0.000000) vcan0 001#\n(0.001000) vcan0 002#\n(1700000000.000000) vcan0 003#\n";
        let e = parse_candump(log, &r).unwrap_err();
        assert_eq!((e.kind, e.line), (InputKind::Candump, Some(3)));
        assert!(e.to_string().contains("session.max_duration_s"), "{e}");
        assert!(e.to_string().contains("spans more than"), "{e}");
        // Every frame at the same time: the count bounds it.
        let max = r.max_frames();
        let mut reader = CandumpReader::new(&r);
        let line = "(5.000000) vcan0 001#";
        for _ in 0..max {
            reader.line(line).unwrap();
        }
        let e = reader.line(line).unwrap_err();
        assert_eq!(e.line, Some(max + 1));
        assert!(
            e.to_string().contains(&format!("more than {max} frames")),
            "{e}"
        );
        // CSV: the grid's count at 100 Hz over 181 s, then the span.
        let row = |t: f64| format!("{t},0,0,0,0,0,0,0,0.1,0.2,0.3,1,0,0,0");
        let n = r.max_samples();
        assert_eq!(n, 18_101);
        let mut csv = CsvReader::new(&r, 7);
        csv.line(CSV_HEADER).unwrap();
        for k in 0..n {
            csv.line(&row(k as f64 * 0.001)).unwrap();
        }
        let e = csv.line(&row(100.0)).unwrap_err();
        assert_eq!(e.line, Some(n + 2));
        assert!(e.to_string().contains("session.grid_hz"), "{e}");
        let text = format!("{CSV_HEADER}\n{}\n{}\n", row(0.0), row(181.5));
        let e = parse_csv(&text, &r, 7).unwrap_err();
        assert_eq!(e.line, Some(3));
        assert!(e.to_string().contains("181.5"), "{e}");
    }
}
