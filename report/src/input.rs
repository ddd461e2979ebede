//! What a report is made of: plain data that a live session and an offline run fill alike.
//!
//! Contract: [`ReportInput`] holds no references and no daemon types. The calibration part
//! ([`Calibration`]) comes from the daemon's calibration pipeline; the data-quality part
//! ([`Quality`]) is filled by whoever read the data (the daemon's ingest and alignment for
//! frame-level inputs, the CSV reader for sample files).

use calib_core::DhTable;
pub use exocal_log::proto::NodePush;
pub use exocal_session::detail::{
    Calibration, Correlation, EmDetail, LsDetail, Quality, StreamQuality, TimedSample,
};
pub use exocal_session::pipeline::AtRest;
pub use exocal_session::{MAX_JOINTS, MAX_PARAMS};

/// The validation verdict, if the caller validated the table.
#[derive(Debug, Clone, PartialEq)]
pub struct VerdictSummary {
    /// Whether the table may be pushed.
    pub accepted: bool,
    /// Every reason to refuse (empty when accepted).
    pub reasons: Vec<String>,
    /// Parameters estimated just outside their bounds and moved onto them, one line each
    /// (the session crate's `OntoBound`; empty: none).
    pub onto_bounds: Vec<String>,
}

/// Everything a report shows.
#[derive(Debug, Clone, PartialEq)]
pub struct ReportInput {
    /// Headline, e.g. "exocald calibration — 2026-11-21 20:40 UTC".
    pub title: String,
    /// Where the data came from (an interface, a file).
    pub source: String,
    /// The nominal table (the configuration's), the "before" of every comparison.
    pub nominal: DhTable<MAX_JOINTS>,
    /// The calibration; fitted on `fit` (and, when `judged` is given, `held_out` too).
    pub calibration: Calibration,
    /// When the calibrated table was refitted on every sample: the table fitted on `fit` only,
    /// which the held-out slice judged (the report's held-out figures show it).
    pub judged: Option<DhTable<MAX_JOINTS>>,
    /// The start of the session: the samples the judged table was fitted on, time-ordered.
    pub fit: Vec<TimedSample>,
    /// The held-out slice (the end of the session), time-ordered; may be empty.
    pub held_out: Vec<TimedSample>,
    /// Data quality of the session.
    pub quality: Quality,
    /// The validation verdict, if the caller validated the table.
    pub verdict: Option<VerdictSummary>,
    /// The gyros' bias measured where the suit was still, for the unaided joints
    /// (`[sensors] unaided_joints`); `None` when no joint is unaided.
    pub at_rest: Option<AtRest>,
    /// The push's outcome per node (the log's `/calibration` push records), once the table
    /// was pushed; `None` before the push, in a dry run and offline.
    pub push: Option<Vec<NodePush>>,
}

/// A session that ended without a calibration — too short, too little motion, too few samples —
/// as its report shows it: why, and the data it had.
#[derive(Debug, Clone, PartialEq)]
pub struct SessionInput {
    /// Headline, as [`ReportInput::title`].
    pub title: String,
    /// Where the data came from, as [`ReportInput::source`].
    pub source: String,
    /// Why no table was calibrated, one line per rule not met (or what an interruption cut
    /// short).
    pub reasons: Vec<String>,
    /// Whether the session was stopped (SIGTERM, SIGINT) before it could calibrate, rather
    /// than ending without meeting its rules.
    pub interrupted: bool,
    /// The aligned samples the session had, time-ordered (may be empty).
    pub samples: Vec<TimedSample>,
    /// Data quality of the session.
    pub quality: Quality,
}

/// Name of parameter `index` (`kind·7 + joint`), e.g. `a3`, `θ7`.
pub fn param_name(index: usize) -> String {
    let kind = ["a", "d", "α", "θ"][(index / MAX_JOINTS).min(3)];
    format!("{kind}{}", index % MAX_JOINTS + 1)
}

/// Value of parameter `index` (`kind·7 + joint`) of `table` (m or rad).
pub fn param_value(table: &DhTable<MAX_JOINTS>, index: usize) -> f64 {
    let row = &table.rows[index % MAX_JOINTS];
    match index / MAX_JOINTS {
        0 => row.a,
        1 => row.d,
        2 => row.alpha,
        _ => row.theta_offset,
    }
}

/// Excitation of each joint: the fraction of its range covered by `samples` (max − min over
/// the range width, clamped to [0, 1]); 0 without samples or with an empty range.
pub fn excitation(samples: &[TimedSample], ranges: &[(f64, f64)]) -> Vec<f64> {
    (0..ranges.len().min(MAX_JOINTS))
        .map(|j| {
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
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use calib_core::{Frame, Sample};

    #[test]
    fn parameter_names_and_values_follow_kind_times_seven_plus_joint() {
        let t = DhTable::<MAX_JOINTS>::paper_nominal();
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
                joints: [q; MAX_JOINTS],
                pose: Frame::identity(),
            },
        };
        let ranges = [(-1.0, 1.0); MAX_JOINTS];
        let e = excitation(&[at(-0.5), at(0.5), at(0.0)], &ranges);
        assert!(e.iter().all(|&x| (x - 0.5).abs() < 1e-12), "{e:?}");
        assert_eq!(excitation(&[], &ranges), [0.0; MAX_JOINTS]);
        assert_eq!(excitation(&[at(-9.0), at(9.0)], &ranges), [1.0; MAX_JOINTS]);
    }
}
