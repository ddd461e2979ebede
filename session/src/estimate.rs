//! What the collection knows of the calibration to come, estimated on the data so far.
//!
//! Contract: [`EstimateJob::of`] takes what an estimate needs from the collection now (cheap:
//! a few thousand joint readings, or for stop-when-good-enough a copy of the collection), and
//! [`EstimateJob::run`] computes it — the heavy part, which a live session runs off its event
//! loop. Without `window.stop_at_expected_error`, the estimate is the condition number of the
//! identification problem at the nominal table over at most [`CONDITION_SAMPLES`]
//! configurations the arm visited ([`Ingest::joint_snapshot`](crate::ingest::Ingest::joint_snapshot):
//! no clock fit, no alignment, so its cost does not grow with the session). With it, once
//! `window.min_samples` are in: the streams aligned, then LS and our EM on every sample, as the
//! calibration will (the EM's expected table error, the LS's condition number).

use calib_core::{DhTable, Sample};

use crate::align::AlignedSample;
use crate::collect::Collector;
use crate::pipeline;
use crate::validate::Expected;
use crate::{Settings, JOINTS, PARAMS};

/// Bus-clock seconds between two estimates of the condition number during collection.
pub const CONDITION_EVERY_S: f64 = 10.0;
/// Bus-clock seconds between two estimates of the expected table error, when the session
/// stops when good enough (`window.stop_at_expected_error`).
pub const EXPECTED_EVERY_S: f64 = 5.0;
/// Samples (at most) the in-collection condition estimate runs LS on.
pub const CONDITION_SAMPLES: usize = 600;

/// What the collection knows of the calibration to come.
#[derive(Debug, Clone, Copy)]
pub struct Estimate {
    /// Condition number of the identification problem.
    pub condition: f64,
    /// Expected table error, when estimated (stop when good enough).
    pub expected: Option<Expected>,
}

/// An estimate to compute, owning what it needs (see the module docs).
#[derive(Debug, Clone)]
pub enum EstimateJob {
    /// The condition number at `nominal` over these joint readings.
    Condition {
        /// Readings the arm visited.
        joints: Vec<[f64; JOINTS]>,
        /// The nominal table.
        nominal: Box<DhTable<JOINTS>>,
    },
    /// LS and our EM on the collection so far.
    Expected {
        /// A copy of the collection.
        collector: Box<Collector>,
        /// The settings.
        settings: Box<Settings>,
    },
}

impl EstimateJob {
    /// Seconds of bus time between two estimates under `settings`.
    pub fn every_s(settings: &Settings) -> f64 {
        match settings.window.stop_at_expected_error {
            Some(_) => EXPECTED_EVERY_S,
            None => CONDITION_EVERY_S,
        }
    }

    /// The estimate of `collector` so far under `settings` (cheap; see the module docs).
    pub fn of(collector: &Collector, settings: &Settings) -> EstimateJob {
        if settings.window.stop_at_expected_error.is_some() {
            EstimateJob::Expected {
                collector: Box::new(collector.clone()),
                settings: Box::new(settings.clone()),
            }
        } else {
            EstimateJob::Condition {
                joints: collector.ingest.joint_snapshot(CONDITION_SAMPLES),
                nominal: Box::new(settings.nominal),
            }
        }
    }

    /// Computes it; `None` with too little data.
    pub fn run(self) -> Option<Estimate> {
        match self {
            EstimateJob::Condition { joints, nominal } => condition_estimate(&joints, &nominal),
            EstimateJob::Expected {
                collector,
                settings,
            } => expected_estimate(&collector, &settings),
        }
    }
}

/// The condition number of LS from `nominal` on `joints`, each with the pose nominal's FK puts
/// it at: LS stops at once (no residual), its condition number is the problem's at nominal.
fn condition_estimate(joints: &[[f64; JOINTS]], nominal: &DhTable<JOINTS>) -> Option<Estimate> {
    if joints.len() < 50 {
        return None;
    }
    let samples: Vec<Sample<JOINTS>> = joints
        .iter()
        .map(|q| Sample {
            joints: *q,
            pose: nominal.fk(q),
        })
        .collect();
    let opts = calib_core::LsOptions::new();
    calib_core::identify_ls::<JOINTS, PARAMS>(nominal, &samples, &opts)
        .ok()
        .map(|r| Estimate {
            condition: r.condition,
            expected: None,
        })
}

/// LS and our EM on every aligned sample so far, once `window.min_samples` are in; before
/// that, the condition number alone.
fn expected_estimate(collector: &Collector, settings: &Settings) -> Option<Estimate> {
    let collected = collector.collected(settings);
    if collected.samples.len() < settings.window.min_samples.max(50) {
        let joints = collector.ingest.joint_snapshot(CONDITION_SAMPLES);
        return condition_estimate(&joints, &settings.nominal);
    }
    let mut samples: Vec<Sample<JOINTS>> = collected
        .samples
        .iter()
        .map(AlignedSample::sample)
        .collect();
    pipeline::separate_readings(&mut samples, settings);
    let (ls_opts, em_opts) = pipeline::options(settings);
    let c = pipeline::ls_then_em(&settings.nominal, &samples, &ls_opts, &em_opts, false).ok()?;
    Some(Estimate {
        condition: c.ls.condition,
        expected: c.stated.map(Expected::from),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_condition_estimate_is_the_problems_at_nominal_and_flags_a_frozen_joint() {
        use calib_core::{DhTable, LsOptions, Scenario, ScenarioConfig};
        let nominal = DhTable::paper_nominal();
        let session: Vec<_> = Scenario::new(ScenarioConfig::<JOINTS>::paper(), 3)
            .take(3000)
            .step_by(5)
            .map(|s| s.sample)
            .collect();
        let joints: Vec<[f64; JOINTS]> = session.iter().map(|s| s.joints).collect();
        let k = condition_estimate(&joints, &nominal).unwrap().condition;
        // What LS on the measured poses reports (from nominal, on the same configurations).
        let ls = calib_core::identify_ls::<JOINTS, PARAMS>(&nominal, &session, &LsOptions::new())
            .unwrap();
        assert!(
            (k / ls.condition - 1.0).abs() < 0.25,
            "{k} vs LS {}",
            ls.condition
        );
        let frozen: Vec<[f64; JOINTS]> = joints
            .iter()
            .map(|q| {
                let mut q = *q;
                q[6] = 0.0;
                q
            })
            .collect();
        // LS refuses a frozen joint's problem or reports it as ill-conditioned, as before.
        let still = condition_estimate(&frozen, &nominal).map(|e| e.condition);
        assert!(still.is_none_or(|c| c > 1e3 * k), "{still:?} vs {k}");
        assert!(condition_estimate(&joints[..49], &nominal).is_none());
    }
}
