//! What a report is made of: plain data that a live session and an offline run fill alike.
//!
//! Contract: [`ReportInput`] holds no references and no daemon types. The calibration part
//! ([`Calibration`]) comes from the daemon's calibration pipeline; the data-quality part
//! ([`Quality`]) is filled by whoever read the data (the daemon's ingest and alignment for
//! frame-level inputs, the CSV reader for sample files).

use calib_core::{DhTable, DriftConfidence, DriftParams, Sample, TableError};

/// Joints of the suit.
pub const JOINTS: usize = 7;
/// D-H parameters of the suit (`4 × JOINTS`), indexed `kind·7 + joint` with kinds a, d, α, θ.
pub const PARAMS: usize = 4 * JOINTS;

/// A calibration sample and its time (s since the start of the session).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TimedSample {
    /// Seconds since the start of the session.
    pub t: f64,
    /// The joint angles and the measured end-effector pose.
    pub sample: Sample<JOINTS>,
}

/// Least-squares step, as the report shows it.
#[derive(Debug, Clone, PartialEq)]
pub struct LsDetail {
    /// The LS table.
    pub table: DhTable<JOINTS>,
    /// Gauss–Newton/LM iterations taken.
    pub iterations: usize,
    /// Numerical rank of the column-scaled Jacobian.
    pub rank: usize,
    /// Column-scaled condition number.
    pub condition: f64,
    /// RMS of the 6-vector pose residual at the solution.
    pub rms: f64,
    /// 1σ of each parameter from the information matrix (white-noise model), `kind·7 + joint`.
    pub std_errors: [f64; PARAMS],
}

/// Drift EM step, as the report shows it.
#[derive(Debug, Clone, PartialEq)]
pub struct EmDetail {
    /// The EM table.
    pub table: DhTable<JOINTS>,
    /// EM iterations taken.
    pub iterations: usize,
    /// Whether the EM met its tolerance (otherwise it hit its iteration limit).
    pub converged: bool,
    /// Log-likelihood at the start of every iteration, then at the final parameters.
    pub log_likelihood: Vec<f64>,
    /// τ and σ per joint.
    pub drift: [DriftParams; JOINTS],
    /// Their standard errors (calib-core's `drift_confidence`), when asked for.
    pub drift_confidence: Option<[DriftConfidence; JOINTS]>,
    /// Cramér-Rao 1σ of every parameter under the drift model, `kind·7 + joint`.
    pub std_errors: [f64; PARAMS],
    /// Expected table error (1σ) under that bound, over the session's poses.
    pub expected_error: TableError,
    /// What the LS table alone is expected to reach (1σ) under the drift and noise the EM
    /// fitted, over the same poses (calib-core's `ls_expected_table_error`); `None` when its
    /// normal equations were too ill-conditioned to say, or it was not asked for.
    pub ls_expected_error: Option<TableError>,
    /// RMS FK difference between the LS and the EM table over the same poses (`None` when not
    /// asked for).
    pub ls_em_difference: Option<TableError>,
    /// Smoothed drift (rad) per fitted sample.
    pub drift_series: Vec<[f64; JOINTS]>,
}

/// One entry of the strongest-correlations list.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Correlation {
    /// Parameter indices (`kind·7 + joint`), `first < second`.
    pub first: usize,
    /// The other parameter index.
    pub second: usize,
    /// Correlation coefficient in [−1, 1].
    pub r: f64,
}

/// What the calibration produced.
#[derive(Debug, Clone, PartialEq)]
pub struct Calibration {
    /// The least-squares step.
    pub ls: LsDetail,
    /// The EM, or why it failed (the LS table is then the result).
    pub em: Result<EmDetail, String>,
    /// The resulting table: the EM's, or the LS's when the EM failed.
    pub calibrated: DhTable<JOINTS>,
    /// Strongest parameter correlations at the calibrated table, strongest first.
    pub correlations: Vec<Correlation>,
}

/// One data stream (a node) of the session.
#[derive(Debug, Clone, PartialEq)]
pub struct StreamQuality {
    /// `Joint1`…`Joint7`, `EndEffector`, or a CSV column group.
    pub name: String,
    /// Samples in the stream.
    pub samples: usize,
    /// Mean sample rate (Hz) over the stream's span.
    pub rate_hz: f64,
    /// Estimated fraction of samples lost (from the median sample interval), if known.
    pub loss: Option<f64>,
    /// Samples the alignment could not map to host time (excluded).
    pub excluded: usize,
    /// The node's own clock jumps or reboots detected.
    pub jumps: usize,
    /// Node clock skew against the host (ppm), if fitted.
    pub skew_ppm: Option<f64>,
    /// RMS residual of the clock fit (µs), if fitted.
    pub jitter_us: Option<f64>,
}

/// Data-quality summary of a session.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Quality {
    /// Session length (s).
    pub duration_s: f64,
    /// Rate of the common grid (Hz); for CSV the file's own mean rate.
    pub grid_hz: f64,
    /// Grid points excluded as gaps.
    pub gaps: usize,
    /// Frame counters, in display order (`("received", n)`, `("unknown", n)`, …); empty for CSV.
    pub counters: Vec<(String, u64)>,
    /// Every data stream, in display order.
    pub streams: Vec<StreamQuality>,
    /// Anatomical range of each joint (rad), for the excitation figures.
    pub joint_ranges: [(f64, f64); JOINTS],
    /// The excitation the session rules require (fraction of each range), if any.
    pub excitation_required: Option<f64>,
    /// Times the receiver stalled (every node's frames late together; not counted as any
    /// stream's clock jumps), and the longest stall's lateness (ms).
    pub receiver_stalls: usize,
    /// The longest receiver stall's lateness (ms), if there was one.
    pub longest_stall_ms: Option<f64>,
}

/// The validation verdict, if the caller validated the table.
#[derive(Debug, Clone, PartialEq)]
pub struct VerdictSummary {
    /// Whether the table may be pushed.
    pub accepted: bool,
    /// Every reason to refuse (empty when accepted).
    pub reasons: Vec<String>,
}

/// Everything a report shows.
#[derive(Debug, Clone, PartialEq)]
pub struct ReportInput {
    /// Headline, e.g. "exocald calibration — 2026-11-21 20:40 UTC".
    pub title: String,
    /// Where the data came from (an interface, a file).
    pub source: String,
    /// The nominal table (the configuration's), the "before" of every comparison.
    pub nominal: DhTable<JOINTS>,
    /// The calibration; fitted on `fit` (and, when `judged` is given, `held_out` too).
    pub calibration: Calibration,
    /// When the calibrated table was refitted on every sample: the table fitted on `fit` only,
    /// which the held-out slice judged (the report's held-out figures show it).
    pub judged: Option<DhTable<JOINTS>>,
    /// The start of the session: the samples the judged table was fitted on, time-ordered.
    pub fit: Vec<TimedSample>,
    /// The held-out slice (the end of the session), time-ordered; may be empty.
    pub held_out: Vec<TimedSample>,
    /// Data quality of the session.
    pub quality: Quality,
    /// The validation verdict, if the caller validated the table.
    pub verdict: Option<VerdictSummary>,
}

/// A session that ended without a calibration — too short, too little motion, too few samples —
/// as its report shows it: why, and the data it had.
#[derive(Debug, Clone, PartialEq)]
pub struct SessionInput {
    /// Headline, as [`ReportInput::title`].
    pub title: String,
    /// Where the data came from, as [`ReportInput::source`].
    pub source: String,
    /// Why no table was calibrated, one line per rule not met.
    pub reasons: Vec<String>,
    /// The aligned samples the session had, time-ordered (may be empty).
    pub samples: Vec<TimedSample>,
    /// Data quality of the session.
    pub quality: Quality,
}

/// Name of parameter `index` (`kind·7 + joint`), e.g. `a3`, `θ7`.
pub fn param_name(index: usize) -> String {
    let kind = ["a", "d", "α", "θ"][(index / JOINTS).min(3)];
    format!("{kind}{}", index % JOINTS + 1)
}

/// Value of parameter `index` (`kind·7 + joint`) of `table` (m or rad).
pub fn param_value(table: &DhTable<JOINTS>, index: usize) -> f64 {
    let row = &table.rows[index % JOINTS];
    match index / JOINTS {
        0 => row.a,
        1 => row.d,
        2 => row.alpha,
        _ => row.theta_offset,
    }
}

/// Excitation of each joint: the fraction of its range covered by `samples` (max − min over
/// the range width, clamped to [0, 1]); 0 without samples or with an empty range.
pub fn excitation(samples: &[TimedSample], ranges: &[(f64, f64); JOINTS]) -> [f64; JOINTS] {
    std::array::from_fn(|j| {
        let (lo, hi) = samples
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), s| {
                (lo.min(s.sample.joints[j]), hi.max(s.sample.joints[j]))
            });
        let width = ranges[j].1 - ranges[j].0;
        if hi < lo || width <= 0.0 {
            0.0
        } else {
            ((hi - lo) / width).clamp(0.0, 1.0)
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use calib_core::Frame;

    #[test]
    fn parameter_names_and_values_follow_kind_times_seven_plus_joint() {
        let t = DhTable::<JOINTS>::paper_nominal();
        assert_eq!(param_name(0), "a1");
        assert_eq!(param_name(9), "d3");
        assert_eq!(param_name(20), "α7");
        assert_eq!(param_name(27), "θ7");
        assert_eq!(param_value(&t, 2), t.rows[2].a);
        assert_eq!(param_value(&t, 14), t.rows[0].alpha);
        assert_eq!(param_value(&t, 22), t.rows[1].theta_offset);
    }

    #[test]
    fn excitation_is_the_visited_fraction_of_each_range() {
        let at = |q: f64| TimedSample {
            t: 0.0,
            sample: Sample {
                joints: [q; JOINTS],
                pose: Frame::identity(),
            },
        };
        let ranges = [(-1.0, 1.0); JOINTS];
        let e = excitation(&[at(-0.5), at(0.5), at(0.0)], &ranges);
        assert!(e.iter().all(|&x| (x - 0.5).abs() < 1e-12), "{e:?}");
        assert_eq!(excitation(&[], &ranges), [0.0; JOINTS]);
        assert_eq!(excitation(&[at(-9.0), at(9.0)], &ranges), [1.0; JOINTS]);
    }
}
