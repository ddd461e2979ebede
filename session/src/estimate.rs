//! What the collection knows of the calibration to come, estimated on the data so far.
//!
//! Contract: `EstimateJob::of` (called by [`crate::Session::on_tick`]) takes what an estimate
//! needs from the collection now (cheap: a few thousand joint readings, or for
//! stop-when-good-enough a copy of the collection), and
//! [`EstimateJob::run`] computes it — the heavy part, which a live session runs off its event
//! loop. Without `window.stop_at_expected_error`, the estimate is the condition number of the
//! identification problem at the nominal table over at most [`CONDITION_SAMPLES`]
//! configurations the arm visited ([`Ingest::joint_snapshot`](crate::ingest::Ingest::joint_snapshot):
//! no clock fit, no alignment, so its cost does not grow with the session). With it, once
//! `window.min_samples` are in: the streams aligned, then LS and our EM on every sample, as the
//! calibration will (the EM's expected table error, the LS's condition number).

use calib_core::{DhTable, JointRanges, Sample};

use crate::align::AlignedSample;
use crate::arm::{narrow, narrow_sample, widen};
use crate::collect::Collector;
use crate::pipeline;
use crate::validate::Expected;
use crate::{with_joints, Settings, MAX_JOINTS};

/// Bus-clock seconds between two estimates of the condition number during collection.
pub const CONDITION_EVERY_S: f64 = 10.0;
/// Bus-clock seconds between two estimates of the expected table error, when the session
/// stops when good enough (`window.stop_at_expected_error`).
pub const EXPECTED_EVERY_S: f64 = 5.0;
/// Samples (at most) the in-collection condition estimate runs LS on.
pub const CONDITION_SAMPLES: usize = 600;
/// Seconds of added motion the guidance weighs each joint's sweep by.
pub const GUIDANCE_S: f64 = 10.0;
/// Noise variance of each pose component the guidance assumes (position m², rotation rad²:
/// 1 mm, 2 mrad): it ranks the joints, the stated error scales the figures.
pub const GUIDANCE_NOISE_VAR: [f64; 6] = [1e-6, 1e-6, 1e-6, 4e-6, 4e-6, 4e-6];

/// What the collection knows of the calibration to come.
#[derive(Debug, Clone, Copy)]
pub struct Estimate {
    /// Condition number of the identification problem.
    pub condition: f64,
    /// Expected table error, when estimated (stop when good enough).
    pub expected: Option<Expected>,
    /// Per joint, the expected table error after [`GUIDANCE_S`] s of that joint's motion as a
    /// fraction (0, 1] of the error now (see the module docs); 1 past the arm's joints.
    pub guidance: Option<[f64; MAX_JOINTS]>,
}

/// What guidance needs of the collection so far.
#[derive(Debug, Clone)]
pub struct GuidanceInput {
    /// Aligned samples so far (the scarcest stream's count).
    pub samples: u64,
    /// The grid's rate (Hz).
    pub grid_hz: f64,
    /// The joints' anatomical ranges.
    pub ranges: JointRanges<MAX_JOINTS>,
}

impl GuidanceInput {
    /// Guidance for the arm of `N` joints at `table` over the configurations `joints` (a
    /// subsample of the collection).
    pub fn run<const N: usize, const P: usize>(
        &self,
        table: &DhTable<MAX_JOINTS>,
        joints: &[[f64; MAX_JOINTS]],
    ) -> Option<[f64; MAX_JOINTS]> {
        if joints.is_empty() || self.samples == 0 {
            return None;
        }
        let per_config = self.samples as f64 / joints.len() as f64;
        let arm: Vec<[f64; N]> = joints.iter().map(narrow).collect();
        calib_core::guidance::<N, P>(
            &table.first(),
            &arm,
            per_config,
            &GUIDANCE_NOISE_VAR,
            &self.ranges.first(),
            GUIDANCE_S * self.grid_hz,
        )
        .map(|g| widen(&g.ratio(), 1.0))
    }
}

/// An estimate to compute, owning what it needs (see the module docs).
#[derive(Debug, Clone)]
pub enum EstimateJob {
    /// The condition number at `nominal` over these joint readings.
    Condition {
        /// Joints of the arm ([`Settings::joints`]).
        arm: usize,
        /// Readings the arm visited (padded, [`crate::arm`]).
        joints: Vec<[f64; MAX_JOINTS]>,
        /// The nominal table.
        nominal: Box<DhTable<MAX_JOINTS>>,
        /// For the guidance.
        guidance: GuidanceInput,
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
    pub(crate) fn of(collector: &Collector, settings: &Settings) -> EstimateJob {
        if settings.window.stop_at_expected_error.is_some() {
            EstimateJob::Expected {
                collector: Box::new(collector.clone()),
                settings: Box::new(settings.clone()),
            }
        } else {
            EstimateJob::Condition {
                arm: settings.joints,
                joints: collector.ingest.joint_snapshot(CONDITION_SAMPLES),
                nominal: Box::new(settings.nominal),
                guidance: guidance_input(collector, settings),
            }
        }
    }

    /// Computes it; `None` with too little data.
    pub fn run(self) -> Option<Estimate> {
        match self {
            EstimateJob::Condition {
                arm,
                joints,
                nominal,
                guidance,
            } => with_joints!(arm, |N, P| condition_estimate::<N, P>(&joints, &nominal)
                .map(|e| Estimate {
                    guidance: guidance.run::<N, P>(&nominal, &joints),
                    ..e
                })),
            EstimateJob::Expected {
                collector,
                settings,
            } => with_joints!(settings.joints, |N, P| expected_estimate::<N, P>(
                &collector, &settings
            )),
        }
    }
}

/// The condition number of LS from `nominal` on `joints`, each with the pose nominal's FK puts
/// it at: LS stops at once (no residual), its condition number is the problem's at nominal.
fn condition_estimate<const N: usize, const P: usize>(
    joints: &[[f64; MAX_JOINTS]],
    nominal: &DhTable<MAX_JOINTS>,
) -> Option<Estimate> {
    if joints.len() < 50 {
        return None;
    }
    let nominal = nominal.first::<N>();
    let samples: Vec<Sample<N>> = joints
        .iter()
        .map(|q| {
            let q = narrow(q);
            Sample {
                joints: q,
                pose: nominal.fk(&q),
            }
        })
        .collect();
    let opts = calib_core::LsOptions::new();
    calib_core::identify_ls::<N, P>(&nominal, &samples, &opts)
        .ok()
        .map(|r| Estimate {
            condition: r.condition,
            expected: None,
            guidance: None,
        })
}

fn guidance_input(collector: &Collector, settings: &Settings) -> GuidanceInput {
    GuidanceInput {
        samples: collector.window.samples(),
        grid_hz: settings.window.grid_hz,
        ranges: settings.bounds.joint_range,
    }
}

/// LS and our EM on every aligned sample so far, once `window.min_samples` are in; before
/// that, the condition number alone.
fn expected_estimate<const N: usize, const P: usize>(
    collector: &Collector,
    settings: &Settings,
) -> Option<Estimate> {
    let collected = collector.collected(settings);
    let joints = collector.ingest.joint_snapshot(CONDITION_SAMPLES);
    let guidance = guidance_input(collector, settings);
    if collected.samples.len() < settings.window.min_samples.max(50) {
        return condition_estimate::<N, P>(&joints, &settings.nominal).map(|e| Estimate {
            guidance: guidance.run::<N, P>(&settings.nominal, &joints),
            ..e
        });
    }
    let mut samples: Vec<Sample<N>> = (collected.samples.iter())
        .map(|s| narrow_sample(&AlignedSample::sample(s)))
        .collect();
    let at_rest = pipeline::take_out_gyro_bias(&collected.samples, &mut samples, settings);
    pipeline::separate_readings(&mut samples, settings);
    let (ls_opts, em_opts) = pipeline::options::<N>(settings, at_rest.as_ref());
    let nominal = settings.nominal.first::<N>();
    let c = pipeline::ls_then_em::<N, P>(&nominal, &samples, &ls_opts, &em_opts, false).ok()?;
    Some(Estimate {
        condition: c.ls.condition,
        expected: c.stated.map(Expected::from),
        guidance: guidance.run::<N, P>(&c.ls.table, &joints),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_condition_estimate_is_the_problems_at_nominal_and_flags_a_frozen_joint() {
        use calib_core::{DhTable, LsOptions, Scenario, ScenarioConfig};
        let nominal = DhTable::paper_nominal();
        let session: Vec<_> = Scenario::new(ScenarioConfig::<MAX_JOINTS>::paper(), 3)
            .take(3000)
            .step_by(5)
            .map(|s| s.sample)
            .collect();
        let joints: Vec<[f64; MAX_JOINTS]> = session.iter().map(|s| s.joints).collect();
        let k = condition_estimate::<7, 28>(&joints, &nominal)
            .unwrap()
            .condition;
        // What LS on the measured poses reports (from nominal, on the same configurations).
        let ls = calib_core::identify_ls::<MAX_JOINTS, { crate::MAX_PARAMS }>(
            &nominal,
            &session,
            &LsOptions::new(),
        )
        .unwrap();
        assert!(
            (k / ls.condition - 1.0).abs() < 0.25,
            "{k} vs LS {}",
            ls.condition
        );
        let frozen: Vec<[f64; MAX_JOINTS]> = joints
            .iter()
            .map(|q| {
                let mut q = *q;
                q[6] = 0.0;
                q
            })
            .collect();
        // LS refuses a frozen joint's problem or reports it as ill-conditioned, as before.
        let still = condition_estimate::<7, 28>(&frozen, &nominal).map(|e| e.condition);
        assert!(still.is_none_or(|c| c > 1e3 * k), "{still:?} vs {k}");
        assert!(condition_estimate::<7, 28>(&joints[..49], &nominal).is_none());
    }

    #[test]
    fn a_session_whose_wrist_never_moves_is_told_to_move_the_wrist() {
        use crate::window::Window;
        use calib_core::{Scenario, ScenarioConfig};
        let settings = Settings::suit_default();
        let joints: Vec<[f64; MAX_JOINTS]> =
            Scenario::new(ScenarioConfig::<MAX_JOINTS>::paper(), 5)
                .take(3000)
                .step_by(5)
                .map(|s| {
                    let mut q = s.sample.joints;
                    q[6] = 0.2; // the wrist's last joint never moves
                    q
                })
                .collect();
        let input = GuidanceInput {
            samples: 3000,
            grid_hz: settings.window.grid_hz,
            ranges: settings.bounds.joint_range,
        };
        let g = input.run::<7, 28>(&settings.nominal, &joints).unwrap();
        let best = (0..MAX_JOINTS)
            .min_by(|&a, &b| g[a].total_cmp(&g[b]))
            .unwrap();
        assert_eq!(best, 6, "{g:?}");
        let mut w = Window::new(
            settings.window.clone(),
            settings.bounds.joint_range,
            settings.joints,
        );
        w.set_guidance(g);
        let line = w.progress(10.0).line(0.5);
        assert!(line.contains(", move joint 7: −"), "{line}");
        w.set_expected(Expected {
            position_mm: 3.1,
            rotation_mrad: 9.0,
        });
        let line = w.progress(15.0).line(0.5);
        assert!(line.contains(", move joint 7: ±3.10 → ±"), "{line}");
        // Every joint moved: no joint stands out by much, and nothing to advise is said.
        let moved: Vec<[f64; MAX_JOINTS]> = Scenario::new(ScenarioConfig::<MAX_JOINTS>::paper(), 5)
            .take(3000)
            .step_by(5)
            .map(|s| s.sample.joints)
            .collect();
        let g = input.run::<7, 28>(&settings.nominal, &moved).unwrap();
        assert!(g.iter().all(|&r| r > 0.5), "{g:?}");
    }
}
