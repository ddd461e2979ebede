//! End-effector poses: splitting one pose into its four `EePose` pages, and joining them back.
//!
//! Contract: the four pages of a pose share `seq` (mod 64); page 0 carries the node timestamp.
//! [`PoseAssembler`] emits a [`Pose`] once all four pages of one `seq` arrived (in any order,
//! duplicates tolerated, interleaved with the pages of up to [`IN_PROGRESS`] − 1 other poses: a
//! page held back in transit lands among later poses' pages and still completes its own). An
//! incomplete pose is dropped once [`IN_PROGRESS`] newer ones have started, long before its
//! `seq` comes round again. A quaternion whose norm is off by more than [`UNIT_TOLERANCE`] is
//! reported as an error.

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

/// Poses the assembler keeps in progress at once. A reordered or delayed frame arrives after
/// the pages of the poses sent after it (a 50 ms delay at 100 Hz: five of them); one that
/// arrives later than this many poses is lost with its pose. Eight poses are 80 ms at 100 Hz and
/// an eighth of `seq`'s 64-pose wrap, so two poses of one `seq` are never in progress together.
pub const IN_PROGRESS: usize = 8;

/// The pages of one pose so far.
#[derive(Clone, Copy, Debug)]
struct Partial {
    seq: u8,
    /// The assembler's count of poses started when this one started.
    started: u64,
    pages: [Option<PosePage>; 4],
}

/// Joins pages into poses.
#[derive(Clone, Debug, Default)]
pub struct PoseAssembler {
    partial: [Option<Partial>; IN_PROGRESS],
    started: u64,
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
        let at = match self
            .partial
            .iter()
            .position(|p| p.is_some_and(|p| p.seq == frame.seq))
        {
            Some(at) => at,
            None => {
                // A new pose: the ones that started IN_PROGRESS poses ago are given up.
                self.started += 1;
                for slot in &mut self.partial {
                    if slot.is_some_and(|p| self.started - p.started >= IN_PROGRESS as u64) {
                        *slot = None;
                        self.dropped += 1;
                    }
                }
                // The others started within the last IN_PROGRESS − 1 poses: a slot is free.
                let at = self.partial.iter().position(Option::is_none)?;
                self.partial[at] = Some(Partial {
                    seq: frame.seq,
                    started: self.started,
                    pages: [None; 4],
                });
                at
            }
        };
        let slot = &mut self.partial[at];
        let partial = slot.as_mut()?;
        partial.pages[usize::from(frame.page.number())] = Some(frame.page);
        let [Some(p0), Some(p1), Some(p2), Some(p3)] = partial.pages else {
            return None;
        };
        *slot = None;
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

    /// A page held back in transit (reordering, a delayed frame) arrives after the pages of
    /// the poses sent after it: it still completes its own pose, and those poses come out too.
    /// (Taking a new `seq` as the end of the last pose lost both this pose and the one the late
    /// page interrupted: 10-17% of the poses under 5% reordering or delay, without a frame lost.)
    #[test]
    fn a_page_held_back_behind_later_poses_still_completes_its_pose() {
        let mut a = PoseAssembler::new();
        let late = pose(1).pages();
        for i in [0, 2, 3] {
            assert_eq!(a.push(late[i]), None);
        }
        // Five poses later (50 ms at 100 Hz), the held-back page lands inside the sixth pose.
        for seq in 2..7 {
            let pages = pose(seq).pages();
            assert_eq!(pages[..3].iter().map(|p| a.push(*p)).find_map(|x| x), None);
            assert_eq!(a.push(pages[3]), Some(Ok(pose(seq))));
        }
        let sixth = pose(7).pages();
        assert_eq!(a.push(sixth[0]), None);
        assert_eq!(a.push(late[1]), Some(Ok(pose(1))));
        for page in &sixth[1..3] {
            assert_eq!(a.push(*page), None);
        }
        assert_eq!(a.push(sixth[3]), Some(Ok(pose(7))));
        assert_eq!(a.dropped(), 0);
    }

    #[test]
    fn an_incomplete_pose_is_dropped_once_in_progress_newer_ones_started() {
        let mut a = PoseAssembler::new();
        a.push(pose(1).pages()[0]);
        for seq in 2..=IN_PROGRESS as u8 {
            let next = pose(seq).pages();
            for page in &next[..3] {
                assert_eq!(a.push(*page), None);
            }
            assert_eq!(a.push(next[3]), Some(Ok(pose(seq))));
        }
        assert_eq!(a.dropped(), 0, "pose 1 is still in progress");
        a.push(pose(IN_PROGRESS as u8 + 1).pages()[0]);
        assert_eq!(a.dropped(), 1);
        // Its other pages no longer complete it.
        for page in &pose(1).pages()[1..] {
            assert_eq!(a.push(*page), None);
        }
    }

    /// An incomplete pose never takes the pages of the pose that has its `seq` 64 poses later.
    #[test]
    fn an_incomplete_pose_is_gone_before_its_seq_comes_round() {
        let mut a = PoseAssembler::new();
        let mut old = pose(5);
        old.position = [9.0, 9.0, 9.0];
        for page in &old.pages()[..3] {
            assert_eq!(a.push(*page), None);
        }
        for k in 6..69u8 {
            for page in pose(k % 64).pages() {
                a.push(page);
            }
        }
        let new = pose(5).pages();
        assert_eq!(a.push(new[3]), None);
        for page in &new[..2] {
            assert_eq!(a.push(*page), None);
        }
        assert_eq!(a.push(new[2]), Some(Ok(pose(5))));
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
