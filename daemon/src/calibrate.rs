//! The calibration pipeline on aligned samples: LS, then our EM, then validation.
//!
//! Contract: [`run`] is pure (no I/O, no clock). It holds out the end of the session
//! (`validation.holdout_fraction`), identifies the 28 D-H parameters by least squares from the
//! nominal table (calib-core `identify_ls`), refines them with calib-core's drift EM (Kalman +
//! RTS smoother; it also yields each joint's drift τ and σ), and validates the EM table — or the
//! LS table if the EM fails — with [`crate::validate::validate`]. The per-node tables to push are
//! in [`Outcome::node_rows`]; whether they may be pushed is [`Outcome::verdict`]. LS and EM run
//! through [`exocal_report::analysis::calibrate`], so the HTML report shows exactly what was
//! computed ([`run_detailed`]).
//!
//! The EM models the drift at a constant step `1 / session.grid_hz`; grid points dropped as
//! gaps are skipped, so a gap shortens the step sequence slightly (gaps are rare and short: a
//! session with many is refused earlier for lack of samples).

use calib_core::{DhTable, DriftEmOptions, Frame, InputChecks, JointRanges, LsOptions, Sample};
use exocal_report::{analysis, Calibration};
use nalgebra::{Quaternion, UnitQuaternion, Vector3};
use serde::Serialize;

use crate::align::AlignedSample;
use crate::config::{Config, JOINTS};
use crate::validate::{split_holdout, table_from_rows, validate, Verdict};

/// One node's row as pushed: D-H parameters and the drift model.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct NodeRow {
    pub a: f64,
    pub alpha: f64,
    pub d: f64,
    pub theta_offset: f64,
    /// Drift correlation time τ (s).
    pub tau: f64,
    /// The paper's σ (eq. 8, rad/s).
    pub sigma: f64,
}

/// Summary of the LS step.
#[derive(Debug, Clone, Serialize)]
pub struct LsSummary {
    pub iterations: usize,
    pub rank: usize,
    pub condition_number: f64,
    pub rms: f64,
}

/// Summary of the EM step.
#[derive(Debug, Clone, Serialize)]
pub struct EmSummary {
    pub iterations: usize,
    pub converged: bool,
    pub tau: [f64; JOINTS],
    pub sigma_paper: [f64; JOINTS],
    pub sigma_stationary: [f64; JOINTS],
    pub log_likelihood_first: f64,
    pub log_likelihood_last: f64,
}

/// What a calibration produced.
#[derive(Debug, Clone, Serialize)]
pub struct Outcome {
    pub fit_samples: usize,
    pub heldout_samples: usize,
    pub ls: LsSummary,
    /// `None` when the EM failed (the reason is in `em_error`); the LS table is then used.
    pub em: Option<EmSummary>,
    pub em_error: Option<String>,
    /// Rows before (nominal) and after.
    pub before: [NodeRow; JOINTS],
    pub node_rows: [NodeRow; JOINTS],
    pub verdict: Verdict,
}

/// Why no calibration could be computed at all.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum CalibrateError {
    /// Fewer samples than the configuration requires.
    TooFewSamples { have: usize, need: usize },
    /// The least-squares identification failed (calib-core's reason).
    Ls(calib_core::CalibError),
}

impl std::fmt::Display for CalibrateError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            CalibrateError::TooFewSamples { have, need } => {
                write!(f, "{have} aligned samples, {need} required")
            }
            CalibrateError::Ls(e) => write!(f, "least-squares identification failed: {e}"),
        }
    }
}

impl std::error::Error for CalibrateError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            CalibrateError::Ls(e) => Some(e),
            CalibrateError::TooFewSamples { .. } => None,
        }
    }
}

/// A calib-core sample from an aligned one (quaternion normalised).
pub fn to_sample(s: &AlignedSample) -> Sample<JOINTS> {
    let [w, x, y, z] = s.pose.orientation;
    let q = UnitQuaternion::from_quaternion(Quaternion::new(w, x, y, z));
    let [px, py, pz] = s.pose.position;
    Sample {
        joints: s.joints,
        pose: Frame {
            r: q.to_rotation_matrix().into_inner(),
            p: Vector3::new(px, py, pz),
        },
    }
}

fn rows_of(table: &DhTable<JOINTS>, tau: [f64; JOINTS], sigma: [f64; JOINTS]) -> [NodeRow; JOINTS] {
    std::array::from_fn(|i| {
        let r = table.rows[i];
        NodeRow {
            a: r.a,
            alpha: r.alpha,
            d: r.d,
            theta_offset: r.theta_offset,
            tau: tau[i],
            sigma: sigma[i],
        }
    })
}

/// Runs LS, EM and validation on `samples` (time-ordered, on the grid).
pub fn run(samples: &[AlignedSample], config: &Config) -> Result<Outcome, CalibrateError> {
    run_detailed(samples, config).map(|(outcome, _)| outcome)
}

/// [`run`], also returning the detail the HTML report shows (likelihood history, smoothed
/// drift, standard deviations, correlations). The tables are the same: both come from one call
/// of [`exocal_report::analysis::calibrate`], which runs calib-core's `identify_ls` and
/// `em_drift` with the options below.
pub fn run_detailed(
    samples: &[AlignedSample],
    config: &Config,
) -> Result<(Outcome, Calibration), CalibrateError> {
    let need = config.session.min_samples;
    if samples.len() < need {
        return Err(CalibrateError::TooFewSamples {
            have: samples.len(),
            need,
        });
    }
    let all: Vec<Sample<JOINTS>> = samples.iter().map(to_sample).collect();
    let (fit, held) = split_holdout(&all, config.validation.holdout_fraction);
    let nominal = table_from_rows(&config.nominal);
    let (ls_opts, em_opts) = options(config);
    let detail =
        analysis::calibrate(&nominal, fit, &ls_opts, &em_opts).map_err(CalibrateError::Ls)?;
    let ls = &detail.ls;
    let ls_summary = LsSummary {
        iterations: ls.iterations,
        rank: ls.rank,
        condition_number: ls.condition,
        rms: ls.rms,
    };
    let (em, em_error, tau, sigma) = match &detail.em {
        Ok(r) => {
            let tau = r.drift.map(|d| d.tau);
            let sigma = r.drift.map(|d| d.paper_sigma);
            let summary = EmSummary {
                iterations: r.iterations,
                converged: r.converged,
                tau,
                sigma_paper: sigma,
                sigma_stationary: r.drift.map(|d| d.stationary_sigma),
                log_likelihood_first: r.log_likelihood.first().copied().unwrap_or(f64::NAN),
                log_likelihood_last: r.log_likelihood.last().copied().unwrap_or(f64::NAN),
            };
            (Some(summary), None, tau, sigma)
        }
        Err(e) => (None, Some(e.clone()), [0.0; JOINTS], [0.0; JOINTS]),
    };
    let table = detail.calibrated;
    let expected = detail.em.as_ref().ok().map(|em| em.expected_error);
    let verdict = validate(&table, ls.condition, expected, held, config);
    let outcome = Outcome {
        fit_samples: fit.len(),
        heldout_samples: held.len(),
        ls: ls_summary,
        em,
        em_error,
        before: rows_of(&nominal, [0.0; JOINTS], [0.0; JOINTS]),
        node_rows: rows_of(&table, tau, sigma),
        verdict,
    };
    Ok((outcome, detail))
}

/// The LS and EM options the daemon calibrates with: input checks against the configured
/// joint ranges, the EM step `1 / session.grid_hz`.
pub fn options(config: &Config) -> (LsOptions<JOINTS>, DriftEmOptions<JOINTS>) {
    let ranges = JointRanges {
        limits: config.bounds.joint_range.map(|r| (r.min, r.max)),
    };
    let checks = InputChecks::new(Some(ranges));
    let ls_opts = LsOptions {
        checks,
        ..LsOptions::new()
    };
    let em_opts = DriftEmOptions {
        checks,
        ..DriftEmOptions::new(1.0 / config.session.grid_hz)
    };
    (ls_opts, em_opts)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::align::Pose;
    use calib_core::{Scenario, ScenarioConfig, SUIT_PARAMS};
    use nalgebra::Rotation3;

    /// Aligned samples from calib-core's Section 4 scenario (Table 4 arm, drift, noise).
    fn scenario(seconds: f64, seed: u64) -> Vec<AlignedSample> {
        scenario_of(ScenarioConfig::paper(), seconds, seed)
    }

    /// Aligned samples of a simulated session of `cfg`.
    fn scenario_of(cfg: ScenarioConfig<JOINTS>, seconds: f64, seed: u64) -> Vec<AlignedSample> {
        let k = (seconds / cfg.drift.dt).round() as usize;
        Scenario::new(cfg, seed)
            .take(k)
            .enumerate()
            .map(|(i, s)| {
                let q =
                    UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix(&s.sample.pose.r));
                AlignedSample {
                    t: i as f64 * cfg.drift.dt,
                    joints: s.sample.joints,
                    pose: Pose {
                        position: s.sample.pose.p.into(),
                        orientation: [q.w, q.i, q.j, q.k],
                    },
                }
            })
            .collect()
    }

    /// The default configuration with fewer samples required, to keep the tests short.
    fn config() -> Config {
        let mut c = Config::default_config();
        c.session.min_samples = 500;
        c
    }

    #[test]
    fn the_paper_scenario_calibrates_and_validates() {
        let config = config();
        let samples = scenario(30.0, 7);
        let out = run(&samples, &config).unwrap();
        assert_eq!(out.fit_samples + out.heldout_samples, samples.len());
        assert_eq!(out.heldout_samples, 600);
        assert!(out.verdict.accepted(), "{:?}", out.verdict.reasons);
        assert!(out.verdict.improvement > 0.8, "{}", out.verdict.improvement);
        assert_eq!(out.ls.rank, SUIT_PARAMS);
        let em = out.em.as_ref().unwrap();
        // τ of the scenario is 1 s: the EM finds the order of magnitude.
        assert!(
            em.tau.iter().all(|&t| (0.3..3.0).contains(&t)),
            "{:?}",
            em.tau
        );
        // The pushed rows are close to Table 4.
        let truth = DhTable::paper_actual();
        for (row, t) in out.node_rows.iter().zip(&truth.rows) {
            assert!((row.a - t.a).abs() < 0.01, "{row:?} vs {t:?}");
        }
        // The round trip through quaternions keeps the poses.
        let s = to_sample(&samples[3]);
        assert!((s.pose.p.x - samples[3].pose.position[0]).abs() < 1e-15);
    }

    #[test]
    fn too_few_samples_is_an_error_not_a_guess() {
        let config = config();
        let samples = scenario(1.0, 1);
        assert_eq!(
            run(&samples, &config).unwrap_err(),
            CalibrateError::TooFewSamples {
                have: 100,
                need: 500
            }
        );
    }

    #[test]
    fn a_motionless_session_is_refused() {
        let config = config();
        let mut samples = scenario(6.0, 3);
        let still = samples[0];
        for s in &mut samples {
            s.joints = still.joints;
            s.pose = still.pose;
        }
        match run(&samples, &config) {
            Err(CalibrateError::Ls(_)) => {}
            Ok(out) => assert!(!out.verdict.accepted()),
            Err(e) => panic!("{e}"),
        }
    }

    /// Table error (mm, mrad) of `rows` against `truth` over fresh poses of the paper's motion.
    fn table_error_of(rows: &[NodeRow; JOINTS], truth: &DhTable<JOINTS>) -> (f64, f64) {
        let table = DhTable {
            rows: rows.map(|r| calib_core::DhRow {
                a: r.a,
                alpha: r.alpha,
                d: r.d,
                theta_offset: r.theta_offset,
            }),
        };
        let poses: Vec<[f64; JOINTS]> = calib_core::Scenario::new(ScenarioConfig::paper(), 999)
            .step_by(7)
            .take(500)
            .map(|s| s.sample.joints)
            .collect();
        let e = calib_core::table_error(&table, truth, &poses);
        (e.position_m * 1e3, e.rotation_rad * 1e3)
    }

    #[test]
    fn a_near_nominal_suit_the_calibration_improves_is_pushed() {
        // Issue 18: errors a fifth of the paper's, 30 s of motion. The old rule (held-out
        // pose error 50% below nominal's) refused this suit ("26.9% better").
        let nominal = DhTable::paper_nominal();
        let paper = DhTable::paper_actual();
        let mut truth = nominal;
        for p in 0..SUIT_PARAMS {
            *truth.param_mut(p) += 0.2 * (paper.param(p) - nominal.param(p));
        }
        let cfg = ScenarioConfig {
            actual: truth,
            ..ScenarioConfig::paper()
        };
        let out = run(&scenario_of(cfg, 30.0, 11), &config()).unwrap();
        let v = &out.verdict;
        assert!(v.accepted(), "{:?}", v.reasons);
        let (before_mm, before_mrad) = table_error_of(&out.before, &truth);
        let (after_mm, after_mrad) = table_error_of(&out.node_rows, &truth);
        eprintln!(
            "near-nominal: table error {before_mm:.2} mm, {before_mrad:.2} mrad -> {after_mm:.2} mm, {after_mrad:.2} mrad; expected {:?}; held-out {:.1}% better, t {:.1}",
            v.expected, v.improvement * 100.0, v.heldout_t
        );
        assert!(
            after_mm < 0.5 * before_mm && after_mrad < 0.5 * before_mrad,
            "table error {before_mm:.2} mm, {before_mrad:.2} mrad -> {after_mm:.2} mm, {after_mrad:.2} mrad"
        );
        // The expected accuracy is of the right size: the table error it reaches is within a few σ.
        let e = v.expected.unwrap();
        assert!(
            after_mm < 4.0 * e.position_mm && after_mrad < 4.0 * e.rotation_mrad,
            "{e} vs {after_mm:.2} mm, {after_mrad:.2} mrad"
        );
    }

    #[test]
    fn a_frozen_joint_is_refused() {
        let mut samples = scenario(30.0, 5);
        let frozen = samples[0].joints[3];
        let cfg = ScenarioConfig::paper();
        for s in &mut samples {
            // The elbow never moves (and the pose is what the true arm does with it frozen).
            s.joints[3] = frozen;
        }
        let mut scen = calib_core::Scenario::new(cfg, 5);
        for s in &mut samples {
            let mut sim = scen.next().unwrap();
            let mut q = sim.sample.joints;
            q[3] = frozen;
            let _ = &mut sim;
            let pose = cfg.actual.fk(&q);
            let quat =
                UnitQuaternion::from_rotation_matrix(&nalgebra::Rotation3::from_matrix(&pose.r));
            s.pose.position = pose.p.into();
            s.pose.orientation = [quat.w, quat.i, quat.j, quat.k];
        }
        match run(&samples, &config()) {
            Err(CalibrateError::Ls(e)) => eprintln!("frozen: LS {e}"),
            Ok(out) => {
                eprintln!("frozen: {:?}", out.verdict.reasons);
                assert!(!out.verdict.accepted(), "a frozen elbow was accepted")
            }
            Err(e) => panic!("{e}"),
        }
    }

    #[test]
    fn too_short_a_motion_is_refused_by_its_expected_accuracy() {
        // 6 s: enough samples for the configured minimum, too little motion for 3 mm.
        let out = run(&scenario(6.0, 2), &config()).unwrap();
        let v = &out.verdict;
        eprintln!("6 s: {:?}", v.reasons);
        assert!(
            v.reasons
                .iter()
                .any(|r| r.starts_with("expected table error")),
            "{:?} {:?}",
            v.reasons,
            v.expected
        );
    }

    #[test]
    fn nonsense_data_is_refused() {
        // Poses that have nothing to do with the joint angles (another session's).
        let mut samples = scenario(30.0, 8);
        let other = scenario(30.0, 9);
        for (s, o) in samples.iter_mut().zip(&other) {
            s.pose = o.pose;
        }
        match run(&samples, &config()) {
            Err(CalibrateError::Ls(e)) => eprintln!("nonsense: LS {e}"),
            Ok(out) => {
                let v = &out.verdict;
                eprintln!("nonsense: {:?}", v.reasons);
                assert!(!v.accepted(), "nonsense accepted: {:?}", v.expected);
                assert!(
                    v.reasons
                        .iter()
                        .any(|r| r.starts_with("expected table error")),
                    "{:?}",
                    v.reasons
                );
            }
            Err(e) => panic!("{e}"),
        }
    }

    #[test]
    fn a_pose_stream_lost_in_noise_is_refused() {
        // The true arm's poses under 5 cm and 0.1 rad of white noise, a tracker that lost lock:
        // LS converges (measured: expected ±4.1 mm > 3 mm), validation refuses.
        let cfg = ScenarioConfig {
            position_noise: 0.05,
            rotation_noise: 0.1,
            ..ScenarioConfig::paper()
        };
        let v = run(&scenario_of(cfg, 30.0, 4), &config()).unwrap().verdict;
        assert!(
            v.reasons
                .iter()
                .any(|r| r.starts_with("expected table error")),
            "{:?}",
            v.reasons
        );
    }
}
