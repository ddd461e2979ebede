//! End-effector poses: splitting one pose into its four `EePose` pages, and joining them back.
//!
//! Contract: the four pages of a pose share `seq` (mod 64); page 0 carries the node timestamp.
//! [`PoseAssembler`] emits a [`Pose`] once all four pages of one `seq` arrived (in any order,
//! duplicates tolerated); a page with a new `seq` starts over, dropping an incomplete pose. A
//! quaternion whose norm is off by more than [`UNIT_TOLERANCE`] is reported as an error.

use crate::message::{PoseFrame, PosePage};

/// Allowed deviation of |q| from 1 (the wire rounds each component to 1e-6).
pub const UNIT_TOLERANCE: f64 = 1e-4;

/// One end-effector pose in the base frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Pose {
    /// Sequence number 0..64.
    pub seq: u8,
    /// Node clock at sampling, µs.
    pub timestamp_us: u32,
    /// Position, m.
    pub position: [f64; 3],
    /// Unit quaternion `[w, x, y, z]`.
    pub quat: [f64; 4],
}

impl Pose {
    /// The four pages of this pose, page 0 first.
    pub fn pages(&self) -> [PoseFrame; 4] {
        let [x, y, z] = self.position;
        let [qw, qx, qy, qz] = self.quat;
        let seq = self.seq;
        [
            PoseFrame {
                seq,
                page: PosePage::TimePosX {
                    timestamp_us: self.timestamp_us,
                    x,
                },
            },
            PoseFrame {
                seq,
                page: PosePage::PosYZ { y, z },
            },
            PoseFrame {
                seq,
                page: PosePage::QuatWX { w: qw, x: qx },
            },
            PoseFrame {
                seq,
                page: PosePage::QuatYZ { y: qy, z: qz },
            },
        ]
    }
}

/// Why an assembled pose was refused.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum PoseError {
    /// The quaternion is not of unit norm (its norm is given).
    NotUnit(f64),
}

impl core::fmt::Display for PoseError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            PoseError::NotUnit(n) => write!(f, "pose quaternion has norm {n}, not 1"),
        }
    }
}

/// Joins pages into poses.
#[derive(Clone, Debug, Default)]
pub struct PoseAssembler {
    seq: Option<u8>,
    pages: [Option<PosePage>; 4],
    dropped: u64,
}

impl PoseAssembler {
    /// An empty assembler.
    pub fn new() -> Self {
        Self::default()
    }

    /// Incomplete poses abandoned so far.
    pub fn dropped(&self) -> u64 {
        self.dropped
    }

    /// Feeds one page; returns a pose when this page completes one.
    pub fn push(&mut self, frame: PoseFrame) -> Option<Result<Pose, PoseError>> {
        if self.seq != Some(frame.seq) {
            if self.pages.iter().any(Option::is_some) {
                self.dropped += 1;
            }
            self.seq = Some(frame.seq);
            self.pages = [None; 4];
        }
        self.pages[usize::from(frame.page.number())] = Some(frame.page);
        let [Some(p0), Some(p1), Some(p2), Some(p3)] = self.pages else {
            return None;
        };
        self.pages = [None; 4];
        self.seq = None;
        let (
            PosePage::TimePosX { timestamp_us, x },
            PosePage::PosYZ { y, z },
            PosePage::QuatWX { w, x: qx },
            PosePage::QuatYZ { y: qy, z: qz },
        ) = (p0, p1, p2, p3)
        else {
            unreachable!("pages are stored at their own page number")
        };
        let norm2 = w * w + qx * qx + qy * qy + qz * qz;
        let (lo, hi) = (1.0 - UNIT_TOLERANCE, 1.0 + UNIT_TOLERANCE);
        if !(lo * lo..=hi * hi).contains(&norm2) {
            return Some(Err(PoseError::NotUnit(sqrt(norm2))));
        }
        Some(Ok(Pose {
            seq: frame.seq,
            timestamp_us,
            position: [x, y, z],
            quat: [w, qx, qy, qz],
        }))
    }
}

/// Newton square root, enough for an error message without `std`.
fn sqrt(x: f64) -> f64 {
    if x <= 0.0 || x.is_nan() {
        return if x == 0.0 { 0.0 } else { f64::NAN };
    }
    let mut r = if x > 1.0 { x } else { 1.0 };
    for _ in 0..60 {
        r = 0.5 * (r + x / r);
    }
    r
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pose(seq: u8) -> Pose {
        let h = core::f64::consts::FRAC_1_SQRT_2;
        Pose {
            seq,
            timestamp_us: 1234,
            position: [0.1, -0.2, 0.3],
            quat: [h, 0.0, h, 0.0],
        }
    }

    #[test]
    fn pages_in_any_order_with_duplicates_assemble() {
        let p = pose(5);
        let pages = p.pages();
        let mut a = PoseAssembler::new();
        for i in [3, 1, 1, 0] {
            assert_eq!(a.push(pages[i]), None);
        }
        assert_eq!(a.push(pages[2]), Some(Ok(p)));
        assert_eq!(a.dropped(), 0);
    }

    #[test]
    fn a_new_seq_drops_the_incomplete_pose() {
        let mut a = PoseAssembler::new();
        a.push(pose(1).pages()[0]);
        let next = pose(2).pages();
        for page in &next[..3] {
            assert_eq!(a.push(*page), None);
        }
        assert_eq!(a.push(next[3]), Some(Ok(pose(2))));
        assert_eq!(a.dropped(), 1);
    }

    #[test]
    fn non_unit_quaternion_is_an_error() {
        let mut p = pose(0);
        p.quat = [0.5, 0.0, 0.0, 0.0];
        let mut a = PoseAssembler::new();
        let out: Vec<_> = p.pages().into_iter().filter_map(|f| a.push(f)).collect();
        match out[..] {
            [Err(PoseError::NotUnit(n))] => assert!((n - 0.5).abs() < 1e-12),
            _ => panic!("{out:?}"),
        }
    }
}
