//! The collection window: is there enough motion to calibrate yet?
//!
//! Contract:
//! - [`Coverage`] divides a joint's anatomical range into [`COVERAGE_BINS`] equal bins; a bin
//!   counts as visited once [`BIN_MIN_SAMPLES`] samples fell in it. Coverage is the visited
//!   fraction: a single spike cannot fake excitation the way a min/max span could. Samples
//!   outside the range are counted apart (they hint at a wrong offset or a bad sensor), never
//!   binned. NaN samples are ignored.
//! - [`Window`] accumulates per-joint coverage and per-stream sample counts and, given the
//!   elapsed time, says [`Phase::Collecting`], [`Phase::Ready`] (minimum duration reached,
//!   every joint covered, enough samples) or [`Phase::Failed`] (maximum duration reached
//!   without that, with the reasons).
//! - With `stop_at_expected_error` set (stop when good enough), [`Phase::Ready`] further needs
//!   the expected table error ([`Window::set_expected`], estimated by the runner from the
//!   motion so far) within both limits at [`STOP_GUARD`] consecutive estimates — until
//!   `max_duration_s`, when the motion alone decides (Ready if it suffices, else Failed). The
//!   guard is against early optimism: stopping at the first estimate within the limits selects
//!   the sessions whose estimate is low, and states 1.3–1.4× less than the table really has
//!   (calib-core's `--example window`, BENCHMARKS.md).
//! - [`Progress`] is the snapshot the reporters show and the MCAP log records.

use std::fmt;

use serde::Serialize;

use calib_core::JointRanges;

use crate::validate::Expected;
use crate::{WindowRules, MAX_JOINTS};

/// Bins of a joint's range.
pub const COVERAGE_BINS: usize = 36;
pub use crate::rules::DURATION_SLACK_S;
/// Samples needed in a bin to count it as visited.
pub const BIN_MIN_SAMPLES: u32 = 3;
/// Smallest relative gain of the expected table error (0..1) the progress line advises motion
/// for ([`Progress::advice`]).
pub const GUIDANCE_MIN_GAIN: f64 = 0.05;
/// Consecutive expected-error estimates within the limits before the window closes when good
/// enough (see the module docs).
pub const STOP_GUARD: u32 = 3;

/// Visited fraction of one joint's anatomical range.
#[derive(Debug, Clone, PartialEq)]
pub struct Coverage {
    /// `(min, max)` (rad).
    range: (f64, f64),
    bins: [u32; COVERAGE_BINS],
    /// Samples outside the range.
    pub outside: u64,
    /// Samples inside the range.
    pub inside: u64,
}

impl Coverage {
    /// Empty coverage of `range` (`(min, max)`, rad).
    pub fn new(range: (f64, f64)) -> Coverage {
        Coverage {
            range,
            bins: [0; COVERAGE_BINS],
            outside: 0,
            inside: 0,
        }
    }

    /// Records one angle (rad).
    pub fn add(&mut self, angle: f64) {
        if angle.is_nan() {
            return;
        }
        let (min, max) = self.range;
        if !(min..=max).contains(&angle) {
            self.outside += 1;
            return;
        }
        let u = (angle - min) / (max - min);
        let bin = ((u * COVERAGE_BINS as f64) as usize).min(COVERAGE_BINS - 1);
        self.bins[bin] = self.bins[bin].saturating_add(1);
        self.inside += 1;
    }

    /// Visited fraction in [0, 1].
    pub fn fraction(&self) -> f64 {
        let visited = self.bins.iter().filter(|&&n| n >= BIN_MIN_SAMPLES).count();
        visited as f64 / COVERAGE_BINS as f64
    }
}

/// Where the collection stands.
#[derive(Debug, Clone, PartialEq)]
pub enum Phase {
    /// Keep collecting.
    Collecting,
    /// Enough: calibrate now.
    Ready,
    /// The maximum duration passed without enough data: the reasons.
    Failed(Vec<Shortfall>),
}

/// What a collection still lacks: why a window that closed at its maximum duration yields
/// no calibration. [`fmt::Display`] gives the line summaries and reports show.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Shortfall {
    /// A joint visited too little of its range.
    Coverage {
        /// 1-based joint.
        joint: usize,
        /// Fraction of its range visited.
        covered: f64,
        /// Fraction required.
        required: f64,
    },
    /// A recording shorter than the window's minimum duration: a live session would still be
    /// collecting.
    RecordingTooShort {
        /// The recording's length, s.
        duration_s: f64,
        /// The minimum window, s.
        min_duration_s: f64,
    },
    /// The scarcest stream has too few samples.
    Samples {
        /// Its samples.
        have: u64,
        /// Samples required.
        need: usize,
    },
    /// Spans of the sensor streams failed authentication and were dropped
    /// ([`crate::gate`]): the window counted verified samples only.
    Unverified {
        /// Spans dropped.
        spans: u64,
        /// Frames they held.
        frames: u64,
        /// Seconds of stream they held.
        seconds: f64,
        /// Spans in all (verified and dropped).
        of: u64,
    },
    /// Frames the node did not sign arrived on its identifiers ([`crate::gate`]): a second
    /// sender on the bus. Its spans were dropped; the session is refused all the same.
    SecondSender {
        /// The node whose identifiers were used.
        node: exocal_dbc::NodeId,
        /// Spans that held more frames than the node's digests cover.
        spans: u64,
    },
}

impl fmt::Display for Shortfall {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            Shortfall::Coverage {
                joint,
                covered,
                required,
            } => write!(
                f,
                "joint {joint} covered {:.0}% of its range, {:.0}% required",
                covered * 100.0,
                required * 100.0
            ),
            Shortfall::RecordingTooShort {
                duration_s,
                min_duration_s,
            } => write!(
                f,
                "the recording is {duration_s:.1} s long; session.min_duration_s is \
                 {min_duration_s} s (a live session would still be collecting)"
            ),
            Shortfall::Samples { have, need } => {
                write!(
                    f,
                    "{have} samples from the scarcest stream, {need} required"
                )
            }
            Shortfall::Unverified {
                spans,
                frames,
                seconds,
                of,
            } => write!(
                f,
                "the verified data fall short: {spans} of {of} spans of the sensor streams \
                 ({frames} frames, {seconds:.1} s) failed authentication and were dropped \
                 (lost frames, or frames the nodes did not sign)"
            ),
            Shortfall::SecondSender { node, spans } => write!(
                f,
                "a second sender on {node}'s identifiers: {spans} spans held frames {node} \
                 did not sign (dropped; the session is refused: someone else is on the bus)"
            ),
        }
    }
}

impl Serialize for Shortfall {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.collect_str(self)
    }
}

/// A snapshot of the collection, for reporters and the log.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Progress {
    /// Time since the collection window opened (s).
    pub elapsed_s: f64,
    /// Samples of the scarcest stream (joints and pose).
    pub samples: u64,
    /// Coverage of each joint of the arm, 0..1.
    pub coverage: Vec<f64>,
    /// Condition number of the identification problem, when computed.
    pub condition_number: Option<f64>,
    /// Expected table error of the motion so far, when estimated (stop when good enough).
    pub expected: Option<Expected>,
    /// Per joint, the expected table error after more motion of that joint as a fraction of
    /// now's, when estimated (`exocal_session::estimate`'s guidance), for each joint of the arm.
    pub guidance: Option<Vec<f64>>,
    /// Overall readiness 0..1: the least advanced of time, coverage and samples.
    pub readiness: f64,
    /// The expected table error the window stops at (stop when good enough), if it does.
    pub target: Option<Expected>,
}

impl Progress {
    /// One line for a log or `STATUS=`.
    pub fn line(&self, required: f64) -> String {
        let cov: Vec<String> = self
            .coverage
            .iter()
            .map(|c| format!("{:.0}", c * 100.0))
            .collect();
        let mut s = format!(
            "collecting {:.1} s, {} samples, coverage % [{}] (need {:.0})",
            self.elapsed_s,
            self.samples,
            cov.join(" "),
            required * 100.0
        );
        if let Some(k) = self.condition_number {
            s.push_str(&format!(", condition number {k:.1}"));
        }
        if let Some(e) = self.expected {
            s.push_str(&format!(", expected table error {e}"));
        }
        if let Some(t) = self.target {
            s.push_str(&format!(
                ", stops within ±{:.1} mm, ±{:.1} mrad",
                t.position_mm, t.rotation_mrad
            ));
        }
        if let Some(advice) = self.advice() {
            s.push_str(&format!(", {advice}"));
        }
        s
    }

    /// The line for a terminal's progress bar: at most [`SHORT_LINE_MAX`] characters, so that
    /// it fits 80 columns beside the bar (`12 s cov 80 ✓ 61 ✓ ✓ 75 ✓/80 ±1.3 mm j7→1.1`): the
    /// elapsed time, each joint's coverage (✓ once it has the required), the expected error
    /// and the joint to move.
    pub fn short(&self, required: f64) -> String {
        let need = (required * 100.0).round();
        let cov: Vec<String> = self
            .coverage
            .iter()
            .map(|c| {
                let pc = (c * 100.0).floor();
                if pc >= need {
                    "✓".into()
                } else {
                    format!("{pc:.0}")
                }
            })
            .collect();
        let mut s = format!("{:.0} s cov {}/{need:.0}", self.elapsed_s, cov.join(" "));
        if let Some(e) = self.expected {
            s.push_str(&format!(" ±{:.1} mm", e.position_mm));
        }
        if let Some((j, r)) = self.best_move() {
            match self.expected {
                Some(e) => s.push_str(&format!(" j{}→{:.1}", j + 1, e.position_mm * r)),
                None => s.push_str(&format!(" move j{} −{:.0}%", j + 1, (1.0 - r) * 100.0)),
            }
        }
        s
    }

    /// The joint (0-based) whose motion would most reduce the expected table error and the
    /// error after it as a fraction of now's, when that gains at least [`GUIDANCE_MIN_GAIN`]:
    /// what [`Progress::advice`] says.
    pub fn best_move(&self) -> Option<(usize, f64)> {
        let (j, r) = (self.guidance.as_ref()?.iter())
            .copied()
            .enumerate()
            .min_by(|a, b| a.1.total_cmp(&b.1))?;
        (!r.is_nan() && r <= 1.0 - GUIDANCE_MIN_GAIN).then_some((j, r))
    }

    /// What to move: the joint whose motion would most reduce the expected table error, when
    /// that is at least [`GUIDANCE_MIN_GAIN`] of it (`move joint 7: ±3.10 → ±2.20 mm
    /// expected`, or `move joint 7: −29% expected error` before the error is estimated).
    pub fn advice(&self) -> Option<String> {
        let (j, r) = self.best_move()?;
        Some(match self.expected {
            Some(e) => format!(
                "move joint {}: ±{:.2} → ±{:.2} mm expected",
                j + 1,
                e.position_mm,
                e.position_mm * r
            ),
            None => format!(
                "move joint {}: −{:.0}% expected error",
                j + 1,
                (1.0 - r) * 100.0
            ),
        })
    }
}

/// The longest [`Progress::short`] line (characters): 80 columns less a progress bar's
/// `calibrating [============] ` (27).
pub const SHORT_LINE_MAX: usize = 53;

/// The collection window of one calibration session.
#[derive(Debug, Clone)]
pub struct Window {
    rules: WindowRules,
    /// Per joint of the arm.
    coverage: Vec<Coverage>,
    /// Per joint of the arm.
    joint_samples: Vec<u64>,
    pose_samples: u64,
    condition_number: Option<f64>,
    expected: Option<Expected>,
    guidance: Option<Vec<f64>>,
    /// Consecutive estimates within the limits, up to the latest.
    within: u32,
}

impl Window {
    /// A new window with these rules over the ranges (rad) of the arm's `joints` first joints:
    /// the joints past them are not the arm's, and their streams are not waited for.
    pub fn new(rules: WindowRules, ranges: JointRanges<MAX_JOINTS>, joints: usize) -> Window {
        let joints = joints.min(MAX_JOINTS);
        Window {
            rules,
            coverage: ranges.limits[..joints]
                .iter()
                .copied()
                .map(Coverage::new)
                .collect(),
            joint_samples: vec![0; joints],
            pose_samples: 0,
            condition_number: None,
            expected: None,
            guidance: None,
            within: 0,
        }
    }

    /// One joint angle (rad) of joint index `joint` (0-based); out-of-range indices are ignored.
    pub fn joint_sample(&mut self, joint: usize, angle: f64) {
        if let (Some(c), Some(n)) = (
            self.coverage.get_mut(joint),
            self.joint_samples.get_mut(joint),
        ) {
            c.add(angle);
            if !angle.is_nan() {
                *n += 1;
            }
        }
    }

    /// One end-effector pose arrived.
    pub fn pose_sample(&mut self) {
        self.pose_samples += 1;
    }

    /// Records the latest condition number of the identification problem.
    pub fn set_condition_number(&mut self, k: f64) {
        self.condition_number = Some(k);
    }

    /// Records the latest expected table error of the motion so far.
    pub fn set_expected(&mut self, e: Expected) {
        self.expected = Some(e);
        let within = match self.rules.stop_at_expected_error {
            Some((mm, mrad)) => e.position_mm <= mm && e.rotation_mrad <= mrad,
            None => false,
        };
        self.within = if within { self.within + 1 } else { 0 };
    }

    /// Records the latest guidance (see [`Progress::guidance`]; padded, [`crate::arm`]).
    pub fn set_guidance(&mut self, g: [f64; MAX_JOINTS]) {
        self.guidance = Some(g[..self.coverage.len()].to_vec());
    }

    /// Whether the expected table error was within `stop_at_expected_error` at the latest
    /// [`STOP_GUARD`] estimates (false when unset or not estimated as often yet).
    pub fn good_enough(&self) -> bool {
        self.within >= STOP_GUARD
    }

    /// Per-joint coverage, for each joint of the arm.
    pub fn coverage(&self) -> &[Coverage] {
        &self.coverage
    }

    /// Samples of the scarcest stream.
    pub fn samples(&self) -> u64 {
        self.joint_samples
            .iter()
            .copied()
            .chain([self.pose_samples])
            .min()
            .unwrap_or(0)
    }

    /// The snapshot at `elapsed_s`.
    pub fn progress(&self, elapsed_s: f64) -> Progress {
        let coverage: Vec<f64> = self.coverage.iter().map(Coverage::fraction).collect();
        let r = &self.rules;
        let time = (elapsed_s / r.min_duration_s).clamp(0.0, 1.0);
        let cov = coverage
            .iter()
            .map(|c| (c / r.excitation_required).min(1.0))
            .fold(1.0, f64::min);
        let samples = (self.samples() as f64 / r.min_samples as f64).min(1.0);
        Progress {
            elapsed_s,
            samples: self.samples(),
            coverage,
            condition_number: self.condition_number,
            expected: self.expected,
            guidance: self.guidance.clone(),
            readiness: time.min(cov).min(samples),
            target: r.stop_at_expected_error.map(|(mm, mrad)| Expected {
                position_mm: mm,
                rotation_mrad: mrad,
            }),
        }
    }

    /// What is still missing (empty when the data suffices, duration aside).
    pub fn shortfalls(&self) -> Vec<Shortfall> {
        let required = self.rules.excitation_required;
        let mut out: Vec<Shortfall> = (self.coverage.iter().enumerate())
            .map(|(i, c)| Shortfall::Coverage {
                joint: i + 1,
                covered: c.fraction(),
                required,
            })
            .filter(|s| matches!(s, Shortfall::Coverage { covered, .. } if *covered < required))
            .collect();
        let (have, need) = (self.samples(), self.rules.min_samples);
        if have < need as u64 {
            out.push(Shortfall::Samples { have, need });
        }
        out
    }

    /// What a recording `duration_s` long (first to last frame) lacks, judged as the live
    /// window would have been when it ended: empty when it would have calibrated. A live window
    /// runs from the daemon's start to the tick that ends it, a recording from its first to its
    /// last frame, which starts a little later: [`DURATION_SLACK_S`] makes up for that.
    pub fn at_end(&self, duration_s: f64) -> Vec<Shortfall> {
        let elapsed = duration_s + DURATION_SLACK_S;
        match self.phase(elapsed) {
            Phase::Ready => Vec::new(),
            Phase::Failed(why) => why,
            Phase::Collecting => {
                let mut why = self.shortfalls();
                if elapsed < self.rules.min_duration_s {
                    why.insert(
                        0,
                        Shortfall::RecordingTooShort {
                            duration_s,
                            min_duration_s: self.rules.min_duration_s,
                        },
                    );
                }
                why
            }
        }
    }

    /// The phase at `elapsed_s`.
    pub fn phase(&self, elapsed_s: f64) -> Phase {
        let missing = self.shortfalls();
        let enough = match self.rules.stop_at_expected_error {
            None => true,
            Some(_) => self.good_enough() || elapsed_s >= self.rules.max_duration_s,
        };
        if elapsed_s >= self.rules.min_duration_s && missing.is_empty() && enough {
            Phase::Ready
        } else if elapsed_s >= self.rules.max_duration_s {
            Phase::Failed(missing)
        } else {
            Phase::Collecting
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Settings;

    fn range() -> (f64, f64) {
        (-1.0, 2.6)
    }

    /// On an 80-column terminal the bar's line keeps every joint's coverage, the
    /// expected error and the joint to move, at its widest.
    #[test]
    fn the_short_line_fits_beside_the_bar_at_its_widest() {
        let widest = Progress {
            elapsed_s: 359.6,
            samples: 999_999,
            coverage: vec![0.995; MAX_JOINTS],
            condition_number: Some(1.234e5),
            expected: Some(Expected {
                position_mm: 99.99,
                rotation_mrad: 999.9,
            }),
            guidance: Some(vec![0.99, 0.99, 0.99, 0.99, 0.99, 0.99, 0.949]),
            readiness: 0.5,
            target: Some(Expected {
                position_mm: 2.0,
                rotation_mrad: 6.0,
            }),
        };
        let line = widest.short(1.0);
        assert_eq!(line, "360 s cov 99 99 99 99 99 99 99/100 ±100.0 mm j7→94.9");
        assert!(line.chars().count() <= SHORT_LINE_MAX, "{line}");
        let early = Progress {
            coverage: vec![0.95, 0.2, 0.8, 0.8, 0.8, 0.8, 0.8],
            expected: None,
            guidance: Some(vec![1.0, 0.7, 1.0, 1.0, 1.0, 1.0, 1.0]),
            ..widest
        };
        assert_eq!(early.short(0.8), "360 s cov ✓ 20 ✓ ✓ ✓ ✓ ✓/80 move j2 −30%");
    }

    #[test]
    fn coverage_counts_visited_bins_not_spikes() {
        let mut c = Coverage::new(range());
        // A single excursion to both ends: no bin has 3 samples except the resting one.
        c.add(-0.99);
        c.add(2.59);
        for _ in 0..100 {
            c.add(0.0);
        }
        assert!((c.fraction() - 1.0 / 36.0).abs() < 1e-12);
        // A sweep across the lower half, three times.
        for _ in 0..3 {
            for k in 0..180 {
                c.add(-1.0 + k as f64 * 0.01);
            }
        }
        assert!((c.fraction() - 0.5).abs() < 1e-12, "{}", c.fraction());
        assert_eq!(c.outside, 0);
    }

    #[test]
    fn coverage_counts_out_of_range_and_ignores_nan() {
        let mut c = Coverage::new(range());
        c.add(3.0);
        c.add(-1.5);
        c.add(f64::NAN);
        c.add(2.6); // the upper bound itself is in the last bin
        assert_eq!((c.outside, c.inside), (2, 1));
        assert_eq!(c.fraction(), 0.0);
    }

    /// The default rules with a 20 s minimum and a 120 s maximum duration.
    fn window() -> Window {
        let c = Settings::suit_default();
        let rules = WindowRules {
            min_duration_s: 20.0,
            max_duration_s: 120.0,
            stop_at_expected_error: None,
            ..c.window
        };
        Window::new(rules, c.bounds.joint_range, c.joints)
    }

    /// Sweeps every joint over `fraction` of its range, `n` samples per joint, and as many poses.
    fn sweep(s: &mut Window, fraction: f64, n: usize) {
        let ranges = Settings::suit_default().bounds.joint_range;
        for k in 0..n {
            let u = (k as f64 / n as f64 * 7.0).fract() * fraction;
            for (j, &(min, max)) in ranges.limits.iter().enumerate() {
                s.joint_sample(j, min + u * (max - min));
            }
            s.pose_sample();
        }
    }

    #[test]
    fn ready_only_after_min_duration_with_coverage_and_samples() {
        let mut s = window();
        assert_eq!(s.phase(0.0), Phase::Collecting);
        sweep(&mut s, 0.3, 1500);
        // Coverage 30% < 50%: collecting, then failed at the maximum duration.
        assert_eq!(s.phase(30.0), Phase::Collecting);
        match s.phase(120.0) {
            Phase::Failed(why) => {
                assert_eq!(why.len(), 7, "{why:?}");
                assert!(
                    matches!(why[0], Shortfall::Coverage { joint: 1, covered, required: 0.5 }
                        if covered < 0.5),
                    "{why:?}"
                );
                assert!(why[0].to_string().starts_with("joint 1 covered 31%"));
            }
            p => panic!("{p:?}"),
        }
        sweep(&mut s, 1.0, 1500);
        assert_eq!(s.phase(10.0), Phase::Collecting); // before the minimum duration
        assert_eq!(s.phase(20.0), Phase::Ready);
        let p = s.progress(20.0);
        assert_eq!(p.samples, 3000);
        assert_eq!(p.readiness, 1.0);
        assert!(p.coverage.iter().all(|&c| c == 1.0));
    }

    #[test]
    fn stop_when_good_enough_waits_for_the_expected_error_until_the_maximum() {
        let c = Settings::suit_default();
        let rules = WindowRules {
            min_duration_s: 20.0,
            max_duration_s: 120.0,
            stop_at_expected_error: Some((2.0, 6.0)),
            ..c.window
        };
        let mut s = Window::new(rules.clone(), c.bounds.joint_range, c.joints);
        sweep(&mut s, 1.0, 3000);
        // Motion suffices, nothing estimated yet: keep collecting.
        assert_eq!(s.phase(30.0), Phase::Collecting);
        // Estimated, position above its limit: keep collecting.
        s.set_expected(Expected {
            position_mm: 2.5,
            rotation_mrad: 5.0,
        });
        assert!(!s.good_enough());
        assert_eq!(s.phase(30.0), Phase::Collecting);
        assert!(s.progress(30.0).line(0.5).ends_with(
            ", expected table error ±2.50 mm, ±5.00 mrad (1σ), stops within ±2.0 mm, ±6.0 mrad"
        ));
        // At the maximum the motion alone decides: calibrate what there is.
        assert_eq!(s.phase(120.0), Phase::Ready);
        // Within both limits: ready after STOP_GUARD estimates in a row, never before the
        // minimum duration; one estimate above the limits starts the count again.
        let good = Expected {
            position_mm: 1.9,
            rotation_mrad: 5.9,
        };
        let bad = Expected {
            position_mm: 1.9,
            rotation_mrad: 6.1,
        };
        for e in [good, good, bad] {
            s.set_expected(e);
            assert!(!s.good_enough());
            assert_eq!(s.phase(30.0), Phase::Collecting);
        }
        for _ in 1..STOP_GUARD {
            s.set_expected(good);
            assert!(!s.good_enough());
        }
        s.set_expected(good);
        assert!(s.good_enough());
        assert_eq!(s.phase(15.0), Phase::Collecting);
        assert_eq!(s.phase(20.0), Phase::Ready);
        // Good enough but a joint never moved: fails at the maximum as without the rule.
        let mut frozen = Window::new(rules, c.bounds.joint_range, c.joints);
        for _ in 0..STOP_GUARD {
            frozen.set_expected(Expected {
                position_mm: 1.0,
                rotation_mrad: 1.0,
            });
        }
        assert_eq!(frozen.phase(60.0), Phase::Collecting);
        assert!(matches!(frozen.phase(120.0), Phase::Failed(_)));
    }

    #[test]
    fn the_scarcest_stream_sets_the_sample_count() {
        let mut s = window();
        sweep(&mut s, 1.0, 2000);
        // Poses stop: 2000 of each joint, 2000 poses; then 5000 more joint-1 samples.
        for _ in 0..5000 {
            s.joint_sample(0, 0.1);
        }
        assert_eq!(s.samples(), 2000);
        s.joint_sample(99, 0.0); // ignored, no panic
        let mut lean = window();
        sweep(&mut lean, 1.0, 500);
        let why = lean.shortfalls();
        assert_eq!(
            why,
            [Shortfall::Samples {
                have: 500,
                need: 1000
            }]
        );
        assert_eq!(
            why[0].to_string(),
            "500 samples from the scarcest stream, 1000 required"
        );
        let p = lean.progress(40.0);
        assert!((p.readiness - 0.5).abs() < 1e-12);
    }

    #[test]
    fn progress_line_is_readable() {
        let mut s = window();
        s.set_condition_number(123.0);
        let line = s.progress(3.25).line(0.5);
        assert!(
            line.starts_with("collecting 3.2 s, 0 samples, coverage % [0 0 0 0 0 0 0] (need 50)"),
            "{line}"
        );
        assert!(line.ends_with("condition number 123.0"), "{line}");
    }
}
