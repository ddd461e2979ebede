//! The calibration pipeline: a session's aligned samples and the configuration in, everything
//! the daemon pushes, logs and reports out.
//!
//! Contract: [`run`] is pure (no I/O, no clock) and deterministic (the LS linearises fixed
//! blocks of samples on every core, [`crate::parallel`], merged in block order: the same bits
//! on any number of cores); the live session
//! and `exocald offline` both call it, and the report renders what it returns. In order:
//! 1. **split**: the end of the session (`validation.holdout_fraction`) is held out;
//! 2. **LS**: calib-core's `identify_ls_with` from the nominal table on the rest;
//! 3. **EM**: calib-core's drift EM (Kalman + RTS smoother) from the LS table; it also yields
//!    each joint's drift τ and σ and the table's expected error (its Cramér-Rao bound);
//!    that EM table — or the LS table if the EM fails — is the one the held-out slice judges
//!    ([`Calibrated::judged`]);
//! 4. **refit** on every sample: LS from the judged table, then the EM. A user gets the table
//!    the whole session supports, not one that ignored its last fifth;
//! 5. **validation** by [`crate::validate::validate`]: the refitted table's bounds,
//!    conditioning and expected error, and the held-out slice against the judged table;
//! 6. the per-node rows to push ([`Outcome::node_rows`]; whether they may be pushed is
//!    [`Outcome::verdict`]) and the detail the report shows ([`Calibrated::detail`]: likelihood
//!    history, smoothed drift, standard deviations, the strongest parameter correlations).
//!
//! The EM models the drift at a constant step `1 / session.grid_hz`; grid points dropped as
//! gaps are skipped, so a gap shortens the step sequence slightly (gaps are rare and short: a
//! session with many is refused earlier for lack of samples). A drift step the EM calls a jump
//! right after a gap is judged at the gap's length ([`jump_beyond_gap`]): the drift moved for
//! that long. A point alignment kept by interpolating across lost readings (a fill,
//! [`AlignedSample::unseen_s`]) counts as a gap of that length ([`unobserved_steps`]): across
//! it the drift was not observed either, and the fill's own error, when the arm moves fast,
//! is what the EM then sees as a step.

use crate::detail::{Calibration, Correlation, EmDetail, LsDetail, TimedSample};
use crate::parallel::Parallel;
use calib_core::drift_conf::Z_95;
use calib_core::{
    drift_confidence, em_drift, em_versus_ls, identify_ls_with, ls_white_expected_error, separate,
    table_error, DhTable, DriftEmOptions, DriftSlot, ErrorPoses, GyroAtRest, GyroBias, InputChecks,
    JointDrift, LsOptions, RateBias, Sample, SeparationSlot, TableChoice, TableError,
};
use nalgebra::{DMatrix, SMatrix};
use serde::Serialize;

use crate::align::AlignedSample;
use crate::arm::{narrow, narrow_sample, widen, widen_params, widen_sample, widen_table};
use crate::rules::UNCONFIGURED_RATE_BIAS_DEG_S;
use crate::validate::{onto_bounds, split_holdout, validate, HeldOut, OntoBound, Refusal, Verdict};
use crate::{with_joints, Settings, MAX_JOINTS};

/// How many parameter correlations the report lists.
pub const TOP_CORRELATIONS: usize = 10;

/// One node's row as pushed: D-H parameters and the drift model.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct NodeRow {
    /// D-H link length a (m).
    pub a: f64,
    /// D-H link twist α (rad).
    pub alpha: f64,
    /// D-H link offset d (m).
    pub d: f64,
    /// D-H joint-angle offset (rad).
    pub theta_offset: f64,
    /// Drift correlation time τ (s).
    pub tau: f64,
    /// The paper's σ (eq. 8, rad/s).
    pub sigma: f64,
}

/// Summary of the EM step.
#[derive(Debug, Clone, Serialize)]
pub struct EmSummary {
    /// ECME iterations (filter and smoother passes).
    pub iterations: usize,
    /// Whether the tolerance was reached.
    pub converged: bool,
    /// Drift correlation time τ of each joint (s).
    pub tau: Vec<f64>,
    /// The paper's σ (eq. 8) of each joint (rad/s).
    pub sigma_paper: Vec<f64>,
    /// Stationary deviation of each joint's angle error (rad).
    pub sigma_stationary: Vec<f64>,
    /// 95% confidence intervals of every joint's τ and stationary σ (calib-core's
    /// `drift_confidence`; a joint whose τ the session cannot pin down has `[0, ∞]`); `None`
    /// when they were not computed.
    pub drift_95: Option<Vec<DriftInterval>>,
    /// Per joint, the drift model and why (its line: `Gauss-Markov (2ΔlnL 3.1 ≤ 17.4)`).
    #[serde(serialize_with = "display_each")]
    pub models: Vec<JointDrift>,
    /// Reference samples discounted as glitches (weight below calib-core's `DISCOUNT_WEIGHT`).
    pub discounted: usize,
    /// Where: the first and last time (s since the session's start) of each run of discounted
    /// samples, in time order (the first [`calib_core::drift_em::MAX_DISCOUNTED_RUNS`]).
    pub discounted_s: Vec<[f64; 2]>,
    /// The reference's fitted Student-t degrees of freedom (∞: taken as Gaussian).
    pub reference_dof: f64,
    /// Per joint, the long-run variance of its normalised drift innovations (1 when its drift
    /// follows the model).
    pub consistency: Vec<f64>,
    /// Log-likelihood at the first iterate of the EM's final objective (NaN if none).
    pub log_likelihood_first: f64,
    /// Log-likelihood at the last iterate (NaN if none); within one objective it never
    /// decreases.
    pub log_likelihood_last: f64,
    /// Without the sensors' spec (`[sensors]`), what a rate bias of
    /// [`crate::rules::UNCONFIGURED_RATE_BIAS_DEG_S`], too small for the session to show,
    /// would add to the table error (1σ, not part of the stated error); `None` with the spec,
    /// or where the drift model has the rate bias.
    pub unmodelled_rate_bias: Option<UnmodelledRateBias>,
    /// The EM's table against LS's; `None` when LS's normal equations were too
    /// ill-conditioned to say.
    pub versus_ls: Option<VersusLs>,
}

/// The EM's table against LS's (calib-core's `em_versus_ls`, a Hausman test): where they
/// disagree beyond LS's own error, the EM's model does not hold for the session and LS's table
/// is the result, stated by LS's expected error.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct VersusLs {
    /// RMS FK difference of the two tables over the poses the error is stated on (mm).
    pub difference_mm: f64,
    /// The same in rotation (mrad).
    pub difference_mrad: f64,
    /// LS's expected table error there, under the drift and noise the EM fitted (mm, 1σ).
    pub ls_expected_mm: f64,
    /// The same in rotation (mrad).
    pub ls_expected_mrad: f64,
    /// The squared difference over what the EM's model lets it be (about 1 where it holds).
    pub statistic: f64,
    /// Whether LS's table is the result (the statistic above calib-core's
    /// `MAX_EM_LS_STATISTIC`).
    pub ls_kept: bool,
}

impl VersusLs {
    fn of(v: calib_core::EmVersusLs) -> VersusLs {
        VersusLs {
            difference_mm: v.difference.position_m * 1e3,
            difference_mrad: v.difference.rotation_rad * 1e3,
            ls_expected_mm: v.ls_expected.position_m * 1e3,
            ls_expected_mrad: v.ls_expected.rotation_rad * 1e3,
            statistic: v.statistic,
            ls_kept: v.choice() == TableChoice::Ls,
        }
    }
}

/// What an unmodelled rate bias of `rate_deg_s` would add to the table error (1σ).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct UnmodelledRateBias {
    /// The rate bias weighed (°/s, a ramp from the session's start).
    pub rate_deg_s: f64,
    /// What it adds to the position error (mm, RMS over the joint ranges).
    pub position_mm: f64,
    /// What it adds to the rotation error (mrad).
    pub rotation_mrad: f64,
}

/// One joint's drift with its 95% confidence interval, as summaries state it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct DriftInterval {
    /// Correlation time τ (s).
    pub tau_s: f64,
    /// τ's 95% interval (s).
    pub tau_95_s: [f64; 2],
    /// Stationary deviation σ of the joint's angle error (mrad).
    pub sigma_mrad: f64,
    /// σ's 95% interval (mrad).
    pub sigma_95_mrad: [f64; 2],
}

impl DriftInterval {
    /// The 95% intervals of `c` (calib-core's `DriftConfidence`).
    pub fn of(c: &calib_core::DriftConfidence) -> DriftInterval {
        let (t0, t1) = c.tau_interval(Z_95);
        let (s0, s1) = c.sigma_interval(Z_95);
        DriftInterval {
            tau_s: c.tau,
            tau_95_s: [t0, t1],
            sigma_mrad: c.sigma * 1e3,
            sigma_95_mrad: [s0 * 1e3, s1 * 1e3],
        }
    }
}

impl std::fmt::Display for DriftInterval {
    /// `τ 1.19 s (0.78–1.81), σ 7.68 mrad (6.23–9.48)`; an unbounded interval as `(0.00–∞)`.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let hi = |v: f64, p: usize| {
            if v.is_finite() {
                format!("{v:.p$}")
            } else {
                "∞".to_string()
            }
        };
        write!(
            f,
            "τ {:.2} s ({:.2}–{}), σ {:.2} mrad ({:.2}–{})",
            self.tau_s,
            self.tau_95_s[0],
            hi(self.tau_95_s[1], 2),
            self.sigma_mrad,
            self.sigma_95_mrad[0],
            hi(self.sigma_95_mrad[1], 2)
        )
    }
}

/// What a calibration produced, as the daemon logs and prints it.
#[derive(Debug, Clone, Serialize)]
pub struct Outcome {
    /// Samples the judged table was fitted on (the start of the session).
    pub fit_samples: usize,
    /// Samples held out to judge it (the end). The pushed table is fitted on both.
    pub heldout_samples: usize,
    /// The least-squares step of the fit on every sample.
    pub ls: LsDetail,
    /// `None` when the EM failed (the reason is in `em_error`); the LS table is then used.
    pub em: Option<EmSummary>,
    /// Why the EM failed; `None` when it succeeded.
    #[serde(serialize_with = "display_opt")]
    pub em_error: Option<calib_core::CalibError>,
    /// Rows before (nominal) and after, one per joint of the arm.
    pub before: Vec<NodeRow>,
    /// The calibrated table and drift model, as pushed: one row per joint of the arm.
    pub node_rows: Vec<NodeRow>,
    /// Whether validation accepts the table, and why not.
    pub verdict: Verdict,
    /// The parameters estimated just outside their bounds and moved onto them before
    /// validation (the node rows hold the moved values; empty: none).
    pub onto_bounds: Vec<OntoBound>,
    /// Per joint, the RMS of the rough drift taken out of its reading (rad; 0 where the
    /// reading is smooth).
    pub reading_drift_rms: Vec<f64>,
    /// The gyros' bias measured while the suit was still and taken out of the unaided joints'
    /// readings ([`gyro_at_rest`]; no runs where the suit was never still long enough); `None`
    /// where no joint is unaided.
    pub at_rest: Option<AtRest>,
}

/// The gyro at rest, as the summary and the report show it.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct AtRest {
    /// How long the suit was counted still (s).
    pub still_s: f64,
    /// Runs of stillness counted (0: never still for `calib_core::rest::MIN_REST_S`, nothing
    /// taken out).
    pub runs: usize,
    /// The joints corrected (`[sensors] unaided_joints`), one per joint of the arm.
    pub joints: Vec<bool>,
    /// Each joint's bias (°/s) and its standard error (°/s).
    pub bias_deg_s: Vec<f64>,
    /// Standard errors of [`AtRest::bias_deg_s`] (°/s).
    pub se_deg_s: Vec<f64>,
}

impl AtRest {
    /// `None` where no joint is unaided.
    fn of<const N: usize>(b: Option<&GyroBias<N>>, joints: &[bool; N]) -> Option<AtRest> {
        let deg = |v: [f64; N]| v.map(f64::to_degrees).to_vec();
        joints.iter().any(|&u| u).then(|| AtRest {
            still_s: b.map_or(0.0, |b| b.seconds),
            runs: b.map_or(0, |b| b.runs),
            joints: joints.to_vec(),
            bias_deg_s: b.map_or(vec![f64::NAN; N], |b| deg(b.bias)),
            se_deg_s: b.map_or(vec![f64::NAN; N], |b| deg(b.se)),
        })
    }
}

impl std::fmt::Display for AtRest {
    /// `still 4.6 s: gyro bias joint 1 +0.021 ± 0.007 °/s, joint 3 …, taken out of their readings`.
    /// Without a run: `never still for 1 s: the gyro bias of joints 1, 3, 5 not measured, their
    /// heading not taken out (stand still for a few seconds at the start)`.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        if self.runs == 0 {
            return write!(
                f,
                "never still for {} s: the gyro bias of joints {} not measured, their heading not \
                 taken out (stand still for a few seconds at the start)",
                calib_core::rest::MIN_REST_S,
                crate::rules::joint_list(&self.joints)
            );
        }
        let joints = (0..self.joints.len()).filter(|&j| self.joints[j]);
        write!(f, "still {:.1} s: gyro bias", self.still_s)?;
        let mut sep = " ";
        for j in joints {
            write!(
                f,
                "{sep}joint {} {:+.3} ± {:.3} °/s",
                j + 1,
                self.bias_deg_s[j],
                self.se_deg_s[j]
            )?;
            sep = ", ";
        }
        write!(f, ", taken out of their readings")
    }
}

impl Outcome {
    /// The calibrated D-H table (the rows' geometry), padded ([`crate::arm`]).
    pub fn table(&self) -> DhTable<MAX_JOINTS> {
        DhTable {
            rows: std::array::from_fn(|j| {
                self.node_rows
                    .get(j)
                    .map_or(crate::arm::ZERO_ROW, |r| calib_core::DhRow {
                        a: r.a,
                        alpha: r.alpha,
                        d: r.d,
                        theta_offset: r.theta_offset,
                    })
            }),
        }
    }
}

/// Every item serialised as its line.
fn display_each<T: std::fmt::Display, S: serde::Serializer>(
    items: &[T],
    s: S,
) -> Result<S::Ok, S::Error> {
    s.collect_seq(items.iter().map(ToString::to_string))
}

/// An optional error serialised as its line (or null).
fn display_opt<E: std::fmt::Display, S: serde::Serializer>(
    e: &Option<E>,
    s: S,
) -> Result<S::Ok, S::Error> {
    match e {
        Some(e) => s.collect_str(e),
        None => s.serialize_none(),
    }
}

/// Everything [`run`] computed.
#[derive(Debug, Clone)]
pub struct Calibrated {
    /// The summary (logged, printed, pushed from).
    pub outcome: Outcome,
    /// The detail the report shows, of the table fitted on every sample.
    pub detail: Calibration,
    /// The table fitted without the held-out slice, which the slice judged (padded).
    pub judged: DhTable<MAX_JOINTS>,
    /// Every sample, time-ordered, as calib-core takes them: the first
    /// [`Outcome::fit_samples`] were fitted, the rest held out.
    pub samples: Vec<TimedSample>,
}

impl Calibrated {
    /// The samples the judged table was fitted on.
    pub fn fit(&self) -> &[TimedSample] {
        &self.samples[..self.outcome.fit_samples]
    }

    /// The held-out slice (may be empty).
    pub fn held_out(&self) -> &[TimedSample] {
        &self.samples[self.outcome.fit_samples..]
    }
}

/// Why no calibration could be computed at all.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum CalibrateError {
    /// Fewer samples than the configuration requires.
    TooFewSamples {
        /// Aligned samples collected.
        have: usize,
        /// Samples required (`session.min_samples`).
        need: usize,
    },
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

/// Samples with their time, as calib-core and the report take them.
pub fn timed(samples: &[AlignedSample]) -> Vec<TimedSample> {
    samples
        .iter()
        .map(|s| TimedSample {
            t: s.t,
            sample: s.sample(),
        })
        .collect()
}

/// The first `tau.len()` rows of `table`, with their drift.
fn rows_of(table: &DhTable<MAX_JOINTS>, tau: &[f64], sigma: &[f64]) -> Vec<NodeRow> {
    (table.rows.iter().zip(tau).zip(sigma))
        .map(|((r, &tau), &sigma)| NodeRow {
            a: r.a,
            alpha: r.alpha,
            d: r.d,
            theta_offset: r.theta_offset,
            tau,
            sigma,
        })
        .collect()
}

/// Grid points before a drift step where a gap can still show in it: the smoothed drift
/// spreads a gap's step over the samples after it (measured: up to 7 at 100 Hz).
pub const GAP_REACH: usize = 10;

/// Grid steps over which each sample's drift went unobserved since the sample before it:
/// 1 normally; `m` after a gap of `m − 1` dropped grid points; `1 + unseen / dt` for a fill
/// across lost readings ([`AlignedSample::unseen_s`]). What [`jump_beyond_gap`] judges by.
pub fn unobserved_steps(samples: &[AlignedSample], dt: f64) -> Vec<f64> {
    samples
        .iter()
        .enumerate()
        .map(|(i, s)| {
            let gap = match i {
                0 => 1.0,
                _ => (s.t - samples[i - 1].t) / dt,
            };
            let fill = 1.0 + s.unseen_s / dt;
            gap.max(fill).round().max(1.0)
        })
        .collect()
}

/// Whether calib-core's jump of `sigma` (a normalised drift innovation, at sample `k`) is one
/// still, once a gap or fill before it is counted (`steps`: [`unobserved_steps`]). The EM
/// steps the drift one grid step `dt` from sample to sample; across `m` unobserved steps (grid
/// points dropped by alignment or filled across lost readings: a stalled node, frames lost)
/// the drift of time constant `tau` moves as in `m` steps, its variance
/// `(1 − φ^{2m}) / (1 − φ²)` times one step's (φ = e^{−dt/τ}): a 0.2 s gap at τ = 1.2 s is
/// 4.2σ of a step, often "6σ" on one of seven joints. Judged at that variance, the step is a
/// jump only beyond `max_jump` still.
pub fn jump_beyond_gap(
    steps: &[f64],
    k: usize,
    sigma: f64,
    dt: f64,
    tau: f64,
    max_jump: f64,
) -> bool {
    let steps = (k.saturating_sub(GAP_REACH - 1)..=k)
        .filter_map(|i| steps.get(i).copied())
        .fold(1.0f64, f64::max);
    if steps <= 1.0 || tau.is_nan() || tau <= 0.0 {
        return true;
    }
    let phi2 = (-2.0 * dt / tau).exp();
    let ratio = (1.0 - phi2.powf(steps)) / (1.0 - phi2);
    sigma / ratio.sqrt() > max_jump
}

/// Runs the pipeline on `samples` (time-ordered, on the grid; see the module docs), for the
/// arm of `settings.joints` joints.
pub fn run(samples: &[AlignedSample], settings: &Settings) -> Result<Calibrated, CalibrateError> {
    let need = settings.window.min_samples;
    if samples.len() < need {
        return Err(CalibrateError::TooFewSamples {
            have: samples.len(),
            need,
        });
    }
    with_joints!(settings.joints, |N, P| run_arm::<N, P>(samples, settings))
}

/// [`run`] for an arm of `N` joints (`P = 4N` parameters): calib-core at the arm's length,
/// its results padded ([`crate::arm`]).
fn run_arm<const N: usize, const P: usize>(
    samples: &[AlignedSample],
    settings: &Settings,
) -> Result<Calibrated, CalibrateError> {
    let mut all = timed(samples);
    let mut plain: Vec<Sample<N>> = all.iter().map(|s| narrow_sample(&s.sample)).collect();
    let at_rest = take_out_gyro_bias(samples, &mut plain, settings);
    let reading_drift_rms = separate_readings(&mut plain, settings);
    for (s, moved) in all.iter_mut().zip(&plain) {
        s.sample = widen_sample(moved);
    }
    let (fit, held) = split_holdout(&all, settings.validation.holdout_fraction);
    let fit: Vec<Sample<N>> = fit.iter().map(|s| narrow_sample(&s.sample)).collect();
    let held: Vec<Sample<MAX_JOINTS>> = held.iter().map(|s| s.sample).collect();
    let (ls_opts, em_opts) = options::<N>(settings, at_rest.as_ref());
    // The judged pass states nothing: the allowance is the detail pass's alone (`consider` changes
    // neither table nor stated error, calib-core's tests check it bit for bit).
    let judged_opts = DriftEmOptions {
        consider: RateBias::NONE,
        ..em_opts
    };
    let nominal = settings.nominal.first::<N>();
    let judged = ls_then_em::<N, P>(&nominal, &fit, &ls_opts, &judged_opts, false)?.calibrated;
    let every = &plain;
    let mut detail = ls_then_em::<N, P>(&judged.first(), every, &ls_opts, &em_opts, true)?;
    // A parameter just outside its bound, by chance, goes onto it (validate's `onto_bounds`),
    // by the standard errors of the table kept; the stated error grows by the move.
    let sigmas = match &detail.em {
        Ok(em) if !em.ls_kept() => em.std_errors,
        _ => detail.ls.std_errors,
    };
    let (inside, onto_bounds) = onto_bounds(&detail.calibrated, &sigmas, settings);
    if !onto_bounds.is_empty() {
        let moved = table_error(
            &inside.first::<N>(),
            &detail.calibrated.first::<N>(),
            em_opts.error_poses.of(every),
        );
        detail.stated = detail.stated.map(|s| TableError {
            position_m: s.position_m + moved.position_m,
            rotation_rad: s.rotation_rad + moved.rotation_rad,
        });
        detail.calibrated = inside;
    }
    let (em, em_error, tau, sigma) = match &detail.em {
        Ok(r) => {
            let tau: Vec<f64> = r.drift.iter().map(|d| d.tau).collect();
            let sigma: Vec<f64> = r.drift.iter().map(|d| d.paper_sigma).collect();
            let at = |k: usize| all.get(k).map_or(f64::NAN, |s| s.t);
            let summary = EmSummary {
                iterations: r.iterations,
                converged: r.converged,
                models: r.models.clone(),
                discounted: r.discounted.count,
                discounted_s: r
                    .discounted
                    .runs
                    .iter()
                    .map(|&(a, b)| [at(a), at(b)])
                    .collect(),
                reference_dof: r.discounted.dof,
                consistency: r.consistency.iter().map(|c| c.long_run).collect(),
                tau: tau.clone(),
                sigma_paper: sigma.clone(),
                sigma_stationary: r.drift.iter().map(|d| d.stationary_sigma).collect(),
                drift_95: (r.drift_confidence.as_ref())
                    .map(|c| c.iter().map(DriftInterval::of).collect()),
                log_likelihood_first: r.last_objective().first().copied().unwrap_or(f64::NAN),
                log_likelihood_last: r.last_objective().last().copied().unwrap_or(f64::NAN),
                unmodelled_rate_bias: (r.allowance.position_m > 0.0).then_some(
                    UnmodelledRateBias {
                        rate_deg_s: UNCONFIGURED_RATE_BIAS_DEG_S,
                        position_mm: r.allowance.position_m * 1e3,
                        rotation_mrad: r.allowance.rotation_rad * 1e3,
                    },
                ),
                versus_ls: r.versus_ls.map(VersusLs::of),
            };
            (Some(summary), None, tau, sigma)
        }
        Err(e) => (None, Some(*e), vec![0.0; N], vec![0.0; N]),
    };
    let table = detail.calibrated;
    let expected = detail.stated;
    let heldout = HeldOut {
        table: &judged,
        samples: &held,
    };
    let mut verdict = validate(&table, detail.ls.condition, expected, heldout, settings);
    let unaided = settings.sensors.unaided;
    if at_rest.is_none() && unaided[..N].iter().any(|&u| u) {
        verdict
            .reasons
            .push(Refusal::NeverStill { joints: unaided });
    }
    if let Ok(em) = &detail.em {
        let at = |k: usize| all.get(k).map(|s| s.t);
        let dt = 1.0 / settings.window.grid_hz;
        let steps = unobserved_steps(samples, dt);
        verdict.reasons.extend(
            em.refusals
                .iter()
                .filter(|why| match **why {
                    calib_core::Refusal::Jump {
                        joint,
                        sample,
                        sigma,
                    } => {
                        let tau = em.drift[joint].tau;
                        jump_beyond_gap(&steps, sample, sigma, dt, tau, em_opts.max_jump)
                    }
                    _ => true,
                })
                .map(|&why| Refusal::Model {
                    why,
                    at_s: match why {
                        calib_core::Refusal::Jump { sample, .. } => at(sample),
                        _ => None,
                    },
                }),
        );
    }
    let outcome = Outcome {
        fit_samples: fit.len(),
        heldout_samples: held.len(),
        ls: detail.ls.clone(),
        em,
        em_error,
        before: rows_of(&settings.nominal, &[0.0; N], &[0.0; N]),
        node_rows: rows_of(&table, &tau, &sigma),
        verdict,
        onto_bounds,
        reading_drift_rms: reading_drift_rms.to_vec(),
        at_rest: AtRest::of(at_rest.as_ref(), &narrow(&settings.sensors.unaided)),
    };
    Ok(Calibrated {
        outcome,
        detail,
        judged,
        samples: all,
    })
}

/// Moves each joint's readings in `samples` (a session on the grid, in time order) off the
/// rough part of its drift, and each pose with them (calib-core's `separate`, through the
/// nominal table's FK, with the EM's starting τ); returns the RMS move per joint (rad).
pub fn separate_readings<const N: usize>(
    samples: &mut [Sample<N>],
    settings: &Settings,
) -> [f64; N] {
    let (_, em_opts) = options::<N>(settings, None);
    let mut slots = vec![SeparationSlot::default(); samples.len()];
    separate(
        samples,
        &settings.nominal.first(),
        em_opts.dt,
        em_opts.initial_tau,
        &mut slots,
    )
    .map(|j| j.correction_rms)
}

/// The gyros' bias where the suit was still (calib-core's `rest`: the joints' rates of
/// `samples` and the measured pose of `plain`, the same samples as calib-core takes them), when
/// `[sensors]` names unaided joints; `None` otherwise, or where the suit was never still for
/// `calib_core::rest::MIN_REST_S`.
pub fn gyro_at_rest<const N: usize>(
    samples: &[AlignedSample],
    plain: &[Sample<N>],
    settings: &Settings,
) -> Option<GyroBias<N>> {
    if !settings.sensors.unaided[..N].iter().any(|&u| u) {
        return None;
    }
    debug_assert_eq!(
        samples.len(),
        plain.len(),
        "one calib-core sample per aligned sample"
    );
    let mut rest = GyroAtRest::new(1.0 / settings.window.grid_hz);
    for (s, p) in samples.iter().zip(plain) {
        rest.push(&p.pose, &narrow(&s.rates));
    }
    rest.estimate()
}

/// [`gyro_at_rest`] on `samples`, its bias taken out of the unaided joints of `plain` (the
/// same samples as calib-core takes them), in seconds from the first sample.
pub fn take_out_gyro_bias<const N: usize>(
    samples: &[AlignedSample],
    plain: &mut [Sample<N>],
    settings: &Settings,
) -> Option<GyroBias<N>> {
    let bias = gyro_at_rest(samples, plain, settings)?;
    let t0 = samples.first().map_or(0.0, |s| s.t);
    let unaided = narrow(&settings.sensors.unaided);
    for (s, a) in plain.iter_mut().zip(samples) {
        bias.correct(s, a.t - t0, &unaided);
    }
    Some(bias)
}

/// The LS and EM options the daemon calibrates with: input checks against the configured
/// joint ranges (the error stated over them), the EM step `1 / window.grid_hz`, the sensors'
/// rate-bias spec; where the gyros' bias was measured at rest (`at_rest`) and no spec is
/// configured, what is left of it (its standard error) is the spec.
pub fn options<const N: usize>(
    settings: &Settings,
    at_rest: Option<&GyroBias<N>>,
) -> (LsOptions<N>, DriftEmOptions<N>) {
    let ranges = settings.bounds.joint_range.first::<N>();
    let checks = InputChecks::new(Some(ranges));
    let ls_opts = LsOptions {
        checks,
        ..LsOptions::new()
    };
    let spec = match at_rest {
        Some(b) if settings.sensors.rate_bias.is_none() => {
            b.residual(&narrow(&settings.sensors.unaided))
        }
        _ => settings.sensors.rate_bias,
    };
    let em_opts = DriftEmOptions {
        checks,
        rate_bias_spec: spec,
        // Without the spec: what a rate bias too small to show would do, stated apart.
        consider: if spec.is_none() {
            RateBias {
                ramp: UNCONFIGURED_RATE_BIAS_DEG_S.to_radians(),
                walk: 0.0,
            }
        } else {
            RateBias::NONE
        },
        // A table is worn over the joints' whole ranges, however much of them its session went
        // through: its error is stated there.
        error_poses: ErrorPoses::Ranges(ranges),
        ..DriftEmOptions::new(1.0 / settings.window.grid_hz)
    };
    (ls_opts, em_opts)
}

/// LS from `nominal` on `fit`, then the drift EM from the LS table, keeping the detail the
/// report shows, and the EM's table checked against LS's (calib-core's `em_versus_ls`). When
/// the EM fails, the LS table is the result and the EM's error is kept as text; when its table
/// disagrees with LS's beyond LS's own error, LS's table is the result, stated by LS's
/// expected error ([`Calibration::ls_kept`]). With `detail` (the pushed table's pass, the one
/// summaries show), also the confidence of every joint's τ and σ: `6N + 1` more filter passes,
/// skipped where nobody shows them. Computed for the arm of `N` joints, returned padded
/// ([`crate::arm`]).
pub fn ls_then_em<const N: usize, const P: usize>(
    nominal: &DhTable<N>,
    fit: &[Sample<N>],
    ls_opts: &LsOptions<N>,
    em_opts: &DriftEmOptions<N>,
    detail: bool,
) -> Result<Calibration, CalibrateError> {
    let lin = Parallel::on_all_cores(fit);
    let ls = identify_ls_with::<N, P>(nominal, fit, ls_opts, &lin).map_err(CalibrateError::Ls)?;
    let ls_table = ls.table;
    let ls = LsDetail {
        table: widen_table(&ls.table),
        iterations: ls.iterations,
        rank: ls.rank,
        condition: ls.condition,
        rms: ls.rms,
        std_errors: widen_params::<N>(&ls.std_errors, f64::NAN),
    };
    let mut workspace = vec![DriftSlot::default(); fit.len()];
    let em = em_drift::<N, P>(&ls_table, fit, em_opts, &mut workspace).map(|r| {
        let slots = &workspace[..fit.len()];
        let k = fit.len();
        let drift_series = (slots.iter().enumerate())
            .map(|(i, slot)| {
                let (drift, trend) = (slot.drift(), r.rate_bias_at(i, k));
                widen(
                    &std::array::from_fn::<f64, N, _>(|j| drift[j] + trend[j]),
                    0.0,
                )
            })
            .collect();
        // Against LS's table, over the poses the EM stated its error on (the report's LS
        // figures, and whether the EM's table is to be believed).
        let versus_ls = em_versus_ls::<N, P>(&ls_table, &r, fit, &em_opts.error_poses);
        let std_errors: [f64; P] = std::array::from_fn(|p| r.std_errors[p / N][p % N]);
        EmDetail {
            table: widen_table(&r.table),
            iterations: r.iterations,
            converged: r.converged,
            log_likelihood: r.log_likelihood.to_vec(),
            objectives: r.objectives.to_vec(),
            drift: r.drift.to_vec(),
            // Only fails for slots of another session: these are this one's.
            drift_confidence: (detail.then(|| drift_confidence(&r, slots).ok()))
                .flatten()
                .map(|c| c.to_vec()),
            std_errors: widen_params::<N>(&std_errors, f64::NAN),
            expected_error: r.expected_error,
            stated_error: r.stated_error,
            allowance: r.allowance,
            models: r.models.to_vec(),
            discounted: r.discounted.clone(),
            consistency: r.consistency.joints.to_vec(),
            // The arbiter's refusal beside the EM's own: a rate bias the EM found that its model
            // does not reconcile with LS's table.
            refusals: r
                .refusals
                .iter()
                .copied()
                .chain(versus_ls.and_then(|v| v.refusal(&r)))
                .collect(),
            versus_ls,
            drift_series,
        }
    });
    let (calibrated, stated) = match &em {
        // The EM's table where it agrees with LS's; where not, its Gauss-Markov model does not
        // hold for this session and LS's table is kept, stated by LS's own expected error.
        // Where the EM found a rate bias it does not reconcile with LS's table, neither is
        // right: the refusal above stops the push, the EM's table is what an export gets.
        Ok(em) => match em.versus_ls.map(|v| v.choice()) {
            Some(TableChoice::Ls) => (ls.table, em.versus_ls.map(|v| v.ls_expected)),
            _ => (em.table, Some(em.stated_error)),
        },
        Err(_) => (
            ls.table,
            ls_white_expected_error::<N, P>(&ls_table, fit, &em_opts.error_poses),
        ),
    };
    let correlations = strongest_correlations::<N, P>(&calibrated.first(), fit, TOP_CORRELATIONS);
    Ok(Calibration {
        joints: N,
        ls,
        em,
        calibrated,
        stated,
        correlations,
    })
}

/// The `top` strongest parameter correlations of the linearised problem at `table`:
/// information matrix `Σ JᵀJ` of the tool-frame pose Jacobian over `samples`, pseudo-inverted
/// in column-scaled coordinates (directions outside the numerical rank are left out). The
/// parameters are named in the padded order ([`crate::arm`]).
pub fn strongest_correlations<const N: usize, const P: usize>(
    table: &DhTable<N>,
    samples: &[Sample<N>],
    top: usize,
) -> Vec<Correlation> {
    let mut info = SMatrix::<f64, P, P>::zeros();
    for s in samples {
        let (_, cols) = table.fk_jacobian(&s.joints);
        let mut j = SMatrix::<f64, 6, P>::zeros();
        for p in 0..P {
            j.set_column(p, &cols[p / N][p % N]);
        }
        info += j.transpose() * j;
    }
    let padded = |p: usize| {
        let (kind, joint) = calib_core::ParamKind::of_index(p, N);
        kind.index(joint, MAX_JOINTS)
    };
    let scale: Vec<f64> = (0..P)
        .map(|p| {
            let d = info[(p, p)];
            if d > 0.0 {
                1.0 / d.sqrt()
            } else {
                0.0
            }
        })
        .collect();
    let scaled = DMatrix::from_fn(P, P, |r, c| info[(r, c)] * scale[r] * scale[c]);
    let eig = scaled.symmetric_eigen();
    let max = eig.eigenvalues.iter().fold(0.0f64, |m, &v| m.max(v));
    let mut cov = DMatrix::<f64>::zeros(P, P);
    for (k, &lambda) in eig.eigenvalues.iter().enumerate() {
        if lambda > 1e-10 * max {
            let v = eig.eigenvectors.column(k);
            cov += (v * v.transpose()) / lambda;
        }
    }
    let mut out = Vec::new();
    for a in 0..P {
        for b in a + 1..P {
            let denom = (cov[(a, a)] * cov[(b, b)]).sqrt();
            if denom > 0.0 && denom.is_finite() {
                let r = (cov[(a, b)] / denom).clamp(-1.0, 1.0);
                out.push(Correlation {
                    first: padded(a),
                    second: padded(b),
                    r,
                });
            }
        }
    }
    out.sort_by(|x, y| y.r.abs().total_cmp(&x.r.abs()));
    out.truncate(top);
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::validate::Expected;
    use crate::MAX_PARAMS;
    use calib_core::{identify_ls, Scenario, ScenarioConfig, SUIT_PARAMS};

    /// Aligned samples from calib-core's Section 4 scenario (Table 4 arm, drift, noise).
    fn scenario(seconds: f64, seed: u64) -> Vec<AlignedSample> {
        scenario_of(ScenarioConfig::paper(), seconds, seed)
    }

    /// Aligned samples of a simulated session of `cfg`.
    fn scenario_of(cfg: ScenarioConfig<MAX_JOINTS>, seconds: f64, seed: u64) -> Vec<AlignedSample> {
        let k = (seconds / cfg.drift.dt).round() as usize;
        Scenario::new(cfg, seed)
            .take(k)
            .enumerate()
            .map(|(i, s)| AlignedSample::of(i as f64 * cfg.drift.dt, &s.sample))
            .collect()
    }

    /// Aligned samples of a simulated session of `cfg` with the drift in the reading, as a
    /// real sensor (and the emulated suit) reports it: the arm at the smooth motion q, the
    /// pose FK(q), the reading `q − δ`. (The Scenario's own convention is the other one: the
    /// smooth q read, the arm at q + δ.)
    fn drift_in_the_reading(
        cfg: ScenarioConfig<MAX_JOINTS>,
        seconds: f64,
        seed: u64,
    ) -> Vec<AlignedSample> {
        let k = (seconds / cfg.drift.dt).round() as usize;
        Scenario::new(cfg, seed)
            .take(k)
            .enumerate()
            .map(|(i, s)| {
                let q = s.sample.joints;
                let read = Sample {
                    joints: std::array::from_fn(|j| q[j] - s.drift[j]),
                    pose: cfg.actual.fk(&q),
                };
                AlignedSample::of(i as f64 * cfg.drift.dt, &read)
            })
            .collect()
    }

    /// A drift step across a gap is judged at the gap's length: 7σ of one step after 21
    /// dropped grid points (τ 1.2 s) is 1.7σ of that span, no jump; without a gap, or 30σ, it is.
    #[test]
    fn a_jump_after_a_gap_is_judged_over_the_gap() {
        let dt = 0.01;
        let at = |t: f64| AlignedSample {
            t,
            joints: [0.0; MAX_JOINTS],
            rates: [0.0; MAX_JOINTS],
            pose: crate::align::Pose {
                position: [0.0; 3],
                orientation: [1.0, 0.0, 0.0, 0.0],
            },
            unseen_s: 0.0,
        };
        let mut samples: Vec<AlignedSample> = (0..100).map(|k| at(k as f64 * dt)).collect();
        for s in &mut samples[50..] {
            s.t += 0.21;
        }
        let steps = unobserved_steps(&samples, dt);
        assert_eq!(steps[50], 22.0);
        assert!(!jump_beyond_gap(&steps, 50, 7.0, dt, 1.2, 6.0));
        assert!(!jump_beyond_gap(&steps, 59, 7.0, dt, 1.2, 6.0));
        assert!(
            jump_beyond_gap(&steps, 60, 7.0, dt, 1.2, 6.0),
            "past the gap's reach"
        );
        assert!(jump_beyond_gap(&steps, 30, 7.0, dt, 1.2, 6.0), "no gap");
        assert!(
            jump_beyond_gap(&steps, 50, 30.0, dt, 1.2, 6.0),
            "a slip across a gap"
        );
        // A fill across three lost readings is judged as a gap of four steps.
        samples[30].unseen_s = 0.03;
        let steps = unobserved_steps(&samples, dt);
        assert_eq!(steps[30], 4.0);
        assert!(!jump_beyond_gap(&steps, 30, 7.0, dt, 1.2, 6.0));
        assert!(!jump_beyond_gap(&steps, 39, 7.0, dt, 1.2, 6.0));
        assert!(
            jump_beyond_gap(&steps, 40, 7.0, dt, 1.2, 6.0),
            "past its reach"
        );
        assert!(
            jump_beyond_gap(&steps, 30, 30.0, dt, 1.2, 6.0),
            "a slip at a fill"
        );
    }

    /// Every stream loses `lost` readings from sample `from` on: alignment interpolates the
    /// samples between the readings either side (linear angles and position, slerp), as
    /// [`crate::align::align`] does for a hole shorter than `max_gap`, and marks them.
    fn fill(samples: &mut [AlignedSample], from: usize, lost: usize, dt: f64) {
        let (a, b) = (samples[from - 1], samples[from + lost]);
        for (i, s) in samples[from..from + lost].iter_mut().enumerate() {
            let u = (i + 1) as f64 / (lost + 1) as f64;
            let lerp = |x: f64, y: f64| x + u * (y - x);
            s.joints = std::array::from_fn(|j| lerp(a.joints[j], b.joints[j]));
            s.pose.position = std::array::from_fn(|j| lerp(a.pose.position[j], b.pose.position[j]));
            s.pose.orientation = crate::align::slerp(a.pose.orientation, b.pose.orientation, u);
            s.unseen_s = lost as f64 * dt;
        }
    }

    /// End to end, the fault matrix's loss bursts: every stream loses three readings at once,
    /// 39 times in 40 s, and the fills (off by their interpolation error while the arm turns)
    /// are not sensors that jumped; calib-core's EM, taking the fills as readings, does call
    /// some of them jumps.
    #[test]
    fn fills_across_lost_readings_are_not_sensors_that_jumped() {
        let cfg = ScenarioConfig::paper();
        let dt = cfg.drift.dt;
        let mut samples = drift_in_the_reading(cfg, 40.0, 11);
        for burst in 1..40 {
            fill(&mut samples, burst * 100 + 37, 3, dt);
        }
        let out = super::run(&samples, &settings()).unwrap();
        let raw = jumps(&out.detail.em.as_ref().unwrap().refusals);
        let judged = judged_jumps(&out.outcome.verdict.reasons);
        assert!(
            raw > 0,
            "no jump at the fills to judge: the test tests nothing"
        );
        assert!(judged.is_empty(), "{judged:?}");
    }

    /// End to end: a session whose alignment dropped grid points (a node starved for 0.2 s,
    /// eight times) is not refused as a sensor that jumped; calib-core's EM, stepping over the
    /// gaps as over one grid step, does call some of them jumps.
    #[test]
    fn gaps_in_the_session_are_not_sensors_that_jumped() {
        let cfg = ScenarioConfig::paper();
        let all = drift_in_the_reading(cfg, 40.0, 11);
        let samples: Vec<AlignedSample> = all
            .iter()
            .enumerate()
            .filter(|(k, _)| !(1..=8).any(|g| (g * 400..g * 400 + 21).contains(k)))
            .map(|(_, s)| *s)
            .collect();
        let out = super::run(&samples, &settings()).unwrap();
        let raw = jumps(&out.detail.em.as_ref().unwrap().refusals);
        assert!(
            raw > 0,
            "no jump at the gaps to judge: the test tests nothing"
        );
        let judged = judged_jumps(&out.outcome.verdict.reasons);
        assert!(judged.is_empty(), "{judged:?}");
    }

    /// Slow drift in the reading is not a sensor that jumped, a step is: τ 3
    /// and 10 s, 7 mrad, at 50 Hz with reading and pose noise, 60 s, 4 seeds each, none refused
    /// for a jump (measured, with τ 5 s and 100 Hz too, 60 sessions: the largest normalised
    /// drift innovation 5.4 against the limit of 6); the same session with joint 2's sensor
    /// re-seated 20 mrad off at 30 s is refused for it, naming the joint and the time.
    #[test]
    fn slow_drift_in_the_reading_is_not_a_jump_and_a_step_is() {
        use calib_core::{Discretisation, DriftSite, GaussMarkov, Slip};
        let dt = 0.02;
        let session = |tau: f64, seed: u64, slip: Option<Slip>| {
            let cfg = ScenarioConfig {
                drift: GaussMarkov {
                    dt,
                    tau,
                    sigma: 7e-3,
                    discretisation: Discretisation::Exact,
                },
                site: DriftSite::Reading,
                reading_noise: 2e-4,
                position_noise: 5e-4,
                rotation_noise: 1e-3,
                slip,
                ..ScenarioConfig::paper()
            };
            let mut s = settings();
            s.window.grid_hz = 1.0 / dt;
            super::run(&scenario_of(cfg, 60.0, seed), &s).unwrap()
        };
        for tau in [3.0, 10.0] {
            for seed in 1..=4 {
                let out = session(tau, seed, None);
                let judged = judged_jumps(&out.outcome.verdict.reasons);
                assert!(judged.is_empty(), "τ {tau} s, seed {seed}: {judged:?}");
            }
        }
        let slip = Slip {
            joint: 1,
            time: 30.0,
            angle: 0.02,
        };
        let out = session(3.0, 1, Some(slip));
        let judged = judged_jumps(&out.outcome.verdict.reasons);
        let why = judged.first().map(|r| r.to_string()).unwrap_or_default();
        assert!(why.contains("joint 2"), "{:?}", out.outcome.verdict.reasons);
    }

    /// A heading (0.05 °/s on joints 1, 3, 5, integrated without bound, 60 s at 50 Hz, the drift
    /// in the reading) is the EM's to fit, not a reason to keep LS's table: LS's is tens of
    /// millimetres off where the EM's holds its statement. Keeping LS's table would state LS's
    /// sandwich: ±2.7 mm for a table 17.6 mm off.
    #[test]
    fn a_heading_keeps_the_ems_table_and_its_statement_holds() {
        use calib_core::{Discretisation, DriftSite, GaussMarkov};
        let (dt, h) = (0.02, 0.05f64.to_radians());
        let cfg = ScenarioConfig {
            drift: GaussMarkov {
                dt,
                tau: 1.0,
                sigma: 7e-3,
                discretisation: Discretisation::Exact,
            },
            heading: [h, 0.0, -h, 0.0, h, 0.0, 0.0],
            site: DriftSite::Reading,
            reading_noise: 2e-4,
            position_noise: 5e-4,
            rotation_noise: 1e-3,
            ..ScenarioConfig::paper()
        };
        let mut s = settings();
        s.window.grid_hz = 1.0 / dt;
        let out = super::run(&scenario_of(cfg, 60.0, 3), &s).unwrap();
        let ranges = calib_core::JointRanges::paper();
        let poses: Vec<[f64; MAX_JOINTS]> = (0..256).map(|i| ranges.spread(i)).collect();
        let real = |t: &DhTable<MAX_JOINTS>| table_error(t, &cfg.actual, poses.iter());
        let em = out.detail.em.as_ref().unwrap();
        let v = em.versus_ls.unwrap();
        assert_eq!(v.choice(), TableChoice::Em, "{v:?}");
        assert!(!out.detail.ls_kept());
        let stated = out.detail.stated.unwrap();
        let (ours, ls) = (real(&out.detail.calibrated), real(&out.detail.ls.table));
        assert!(
            ours.position_m < 2.0 * stated.position_m,
            "{ours:?} stated {stated:?}"
        );
        assert!(
            ls.position_m > 3.0 * v.ls_expected.position_m,
            "LS {ls:?}, its sandwich {:?}",
            v.ls_expected
        );
    }

    /// The drift steps calib-core's EM calls jumps.
    fn jumps(r: &[calib_core::Refusal]) -> usize {
        r.iter()
            .filter(|w| matches!(w, calib_core::Refusal::Jump { .. }))
            .count()
    }

    /// The jumps the session refuses for, once gaps and fills are counted.
    fn judged_jumps(reasons: &[Refusal]) -> Vec<&Refusal> {
        reasons
            .iter()
            .filter(|r| {
                matches!(
                    r,
                    Refusal::Model {
                        why: calib_core::Refusal::Jump { .. },
                        ..
                    }
                )
            })
            .collect()
    }

    #[test]
    fn a_drift_in_the_reading_is_taken_out_before_the_fit_and_reported() {
        // The Scenario's smooth readings: nothing to take out, the samples fitted as given.
        let given = scenario(30.0, 3);
        let arm = super::run(&given, &settings()).unwrap();
        assert_eq!(arm.outcome.reading_drift_rms, [0.0; MAX_JOINTS]);
        assert!(arm
            .samples
            .iter()
            .zip(&given)
            .all(|(s, g)| s.sample.joints == g.joints));
        // The same motion and drift with the drift in the reading: every joint's rough drift
        // (steps of ~1 mrad) is found, and the samples fitted are the moved ones.
        let read = drift_in_the_reading(ScenarioConfig::paper(), 30.0, 3);
        let c = super::run(&read, &settings()).unwrap();
        let rms = c.outcome.reading_drift_rms;
        assert!(rms.iter().all(|&r| r > 2e-4 && r < 5e-3), "{rms:?}");
        let moved = c
            .samples
            .iter()
            .zip(&read)
            .filter(|(s, r)| s.sample.joints != r.joints)
            .count();
        assert_eq!(moved, read.len());
    }

    /// The pipeline's summary of `samples`.
    fn run(samples: &[AlignedSample], settings: &Settings) -> Result<Outcome, CalibrateError> {
        super::run(samples, settings).map(|c| c.outcome)
    }

    /// The default configuration with fewer samples required, to keep the tests short.
    fn settings() -> Settings {
        let mut c = Settings::suit_default();
        c.window.min_samples = 500;
        c
    }

    /// A 40 s Section 4 session of the arm of the paper's first `N` joints through the
    /// pipeline configured for that arm: accepted, one row per joint, every parameter
    /// identified, the rows past the arm's zero, and the table as close to the true one as it
    /// states (one session: within 3× its 1σ).
    fn an_arm_of<const N: usize>(seed: u64) {
        let cfg = ScenarioConfig::paper().first::<N>();
        let k = (40.0 / cfg.drift.dt).round() as usize;
        let samples: Vec<AlignedSample> = (Scenario::new(cfg, seed).take(k).enumerate())
            .map(|(i, s)| AlignedSample::of(i as f64 * cfg.drift.dt, &widen_sample(&s.sample)))
            .collect();
        let settings = settings().first(N);
        let c = super::run(&samples, &settings).unwrap();
        let out = &c.outcome;
        assert!(
            out.verdict.accepted(),
            "{N} joints: {:?}",
            out.verdict.reasons
        );
        assert_eq!(out.node_rows.len(), N);
        assert_eq!(out.before.len(), N);
        assert_eq!(out.ls.rank, 4 * N, "{N} joints: every parameter identified");
        assert_eq!(c.detail.joints, N);
        let em = out.em.as_ref().expect("the EM ran");
        assert_eq!((em.tau.len(), em.models.len()), (N, N));
        for table in [out.table(), c.detail.calibrated, c.judged] {
            assert!(table.rows[N..].iter().all(|r| *r == crate::arm::ZERO_ROW));
        }
        assert!((c.detail.correlations.iter())
            .all(|r| r.first % MAX_JOINTS < N && r.second % MAX_JOINTS < N));
        let poses: Vec<[f64; N]> = (0..256).map(|i| cfg.ranges.spread(i)).collect();
        let real = table_error(&out.table().first::<N>(), &cfg.actual, poses.iter());
        let stated = c.detail.stated.expect("a stated error");
        let before = table_error(&settings.nominal.first::<N>(), &cfg.actual, poses.iter());
        assert!(
            real.position_m < 0.2 * before.position_m,
            "{N}: {real:?} from {before:?}"
        );
        assert!(
            real.position_m < 3.0 * stated.position_m
                && real.rotation_rad < 3.0 * stated.rotation_rad,
            "{N} joints: {real:?} against ±{stated:?}"
        );
    }

    #[test]
    fn arms_of_six_four_and_one_joints_calibrate_and_state_their_error() {
        an_arm_of::<6>(21);
        an_arm_of::<4>(22);
        an_arm_of::<1>(23);
    }

    #[test]
    fn the_paper_scenario_calibrates_and_validates() {
        let config = settings();
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
        let s = samples[3].sample();
        assert!((s.pose.p.x - samples[3].pose.position[0]).abs() < 1e-15);
    }

    /// An arm whose `a_4` lies right at its bound (the paper's lies 3 mm inside it): a session
    /// estimating it just outside, by chance, pushes the table with `a_4` on the bound and its
    /// stated error grown by the move; one estimating it outside by more than
    /// [`crate::validate::BOUND_SLACK_SIGMAS`] is refused, naming the bound.
    #[test]
    fn a_table_just_outside_a_bound_is_moved_onto_it_and_one_further_out_refused() {
        let samples = scenario(30.0, 7);
        let free = super::run(&samples, &settings()).unwrap();
        assert!(free.outcome.onto_bounds.is_empty());
        let (a4, sigma) = (
            free.outcome.node_rows[3].a,
            free.detail.em.as_ref().unwrap().std_errors[3],
        );
        let stated = free.detail.stated.unwrap();

        let mut config = settings();
        config.bounds.a[3].1 = a4 - 0.5 * sigma;
        let near = super::run(&samples, &config).unwrap();
        let out = &near.outcome;
        assert!(out.verdict.accepted(), "{:?}", out.verdict.reasons);
        assert_eq!(out.onto_bounds.len(), 1, "{:?}", out.onto_bounds);
        assert!(
            (out.onto_bounds[0].sigmas - 0.5).abs() < 0.05,
            "{:?}",
            out.onto_bounds
        );
        assert!((out.node_rows[3].a - config.bounds.a[3].1).abs() < 1e-9);
        assert_eq!(
            near.detail.calibrated,
            out.table(),
            "the report shows what is pushed"
        );
        // The same EM, stated by the same bound plus the move (0.5σ of a_4, through FK).
        let grown = near.detail.stated.unwrap();
        let added = grown.position_m - stated.position_m;
        // a_4 is a length along the link: every pose moves by it.
        assert!(
            (added - 0.5 * sigma).abs() < 1e-9,
            "{added} for a move of {}",
            0.5 * sigma
        );
        assert!(grown.rotation_rad >= stated.rotation_rad);

        config.bounds.a[3].1 = a4 - 2.0 * sigma;
        let far = super::run(&samples, &config).unwrap().outcome;
        assert!(far.onto_bounds.is_empty());
        let reasons: Vec<String> = far
            .verdict
            .reasons
            .iter()
            .map(ToString::to_string)
            .collect();
        assert!(
            reasons.iter().any(|r| r.starts_with("joint 4: a = ")),
            "{reasons:?}"
        );
    }

    /// The report's LS-against-EM figures for one session: under the drift the EM fitted, LS
    /// alone is expected to do worse than the pushed EM table, and the two tables differ by
    /// about that much.
    #[test]
    fn the_report_compares_ls_alone_with_the_em_for_the_session() {
        let samples = scenario(30.0, 7);
        let em = super::run(&samples, &settings())
            .unwrap()
            .detail
            .em
            .unwrap();
        let v = em.versus_ls.expect("well conditioned");
        let (ls, e, d) = (v.ls_expected, em.expected_error, v.difference);
        assert!(v.agrees(), "the paper's model holds: {v:?}");
        assert!(ls.position_m > 1.1 * e.position_m, "LS {ls:?}, EM {e:?}");
        assert!(ls.rotation_rad > e.rotation_rad, "LS {ls:?}, EM {e:?}");
        assert!(
            d.position_m > 0.2 * ls.position_m && d.position_m < 5.0 * ls.position_m,
            "{d:?} vs {ls:?}"
        );
    }

    #[test]
    fn the_summary_states_every_joints_drift_with_its_confidence() {
        let truth = ScenarioConfig::<MAX_JOINTS>::paper().drift;
        let (tau, sigma_mrad) = (truth.tau, truth.stationary_variance().sqrt() * 1e3);
        let c = super::run(&scenario(30.0, 7), &settings()).unwrap();
        let em = c.outcome.em.as_ref().expect("the EM ran");
        let drift = em
            .drift_95
            .clone()
            .expect("the pushed table's pass has them");
        let mut covered = (0, 0);
        for (j, d) in drift.iter().enumerate() {
            // Each interval brackets its estimate, bounded on a 30-τ session.
            assert!(
                d.tau_95_s[0] < d.tau_s && d.tau_s < d.tau_95_s[1],
                "{j}: {d}"
            );
            assert!(d.tau_95_s[1] / d.tau_95_s[0] < 10.0, "{j}: {d}");
            assert!(d.sigma_95_mrad[0] < d.sigma_mrad && d.sigma_mrad < d.sigma_95_mrad[1]);
            assert_eq!(d.tau_s, em.tau[j]);
            covered.0 += usize::from(d.tau_95_s[0] <= tau && tau <= d.tau_95_s[1]);
            covered.1 +=
                usize::from(d.sigma_95_mrad[0] <= sigma_mrad && sigma_mrad <= d.sigma_95_mrad[1]);
        }
        // The truth (τ = 1 s, σ = 7.07 mrad) inside most joints' intervals (calib-core's Monte
        // Carlo: ~75% coverage at 30 τ).
        assert!(
            covered.0 >= 4 && covered.1 >= 4,
            "{covered:?} of 7: {drift:?}"
        );
        // The judged fit (the collection estimates too) skips them: `detail` only.
        let fit: Vec<Sample<MAX_JOINTS>> = c.samples.iter().map(|s| s.sample).collect();
        let (ls_opts, em_opts) = options(&settings(), None);
        let quick =
            ls_then_em::<7, 28>(&settings().nominal, &fit, &ls_opts, &em_opts, false).unwrap();
        assert!(quick.em.unwrap().drift_confidence.is_none());
    }

    #[test]
    fn a_session_without_drift_has_a_stated_accuracy_and_is_pushed() {
        // Degenerate drift (none at all, a little pose noise) never leaves a session
        // without an expected accuracy; the table is accepted on it.
        let mut cfg = ScenarioConfig::paper();
        cfg.drift.sigma = 0.0;
        cfg.position_noise = 2e-4;
        cfg.rotation_noise = 5e-4;
        let c = super::run(&scenario_of(cfg, 30.0, 6), &settings()).unwrap();
        let v = &c.outcome.verdict;
        assert!(v.accepted(), "{:?}", v.reasons);
        let e = v.expected.expect("an expected accuracy");
        assert!(e.position_mm > 0.0 && e.position_mm < 3.0, "{e}");
        assert_eq!(c.detail.stated.map(Expected::from), Some(e));
    }

    #[test]
    fn a_glitching_reference_is_discounted_counted_and_timed() {
        // 2 % of the poses jump by centimetres; the EM discounts them, the summary
        // counts them and says when.
        let mut cfg = ScenarioConfig::paper();
        cfg.outliers = calib_core::Outliers {
            probability: 0.02,
            burst: 1,
            position: 0.03,
            rotation: 0.03,
        };
        let samples = scenario_of(cfg, 30.0, 5);
        let c = super::run(&samples, &settings()).unwrap();
        let em = c.outcome.em.as_ref().expect("the EM ran");
        assert!(em.discounted > 20, "{} discounted", em.discounted);
        assert!(!em.discounted_s.is_empty());
        for &[a, b] in &em.discounted_s {
            assert!(
                0.0 <= a && a <= b && b <= samples.last().unwrap().t,
                "{a} {b}"
            );
        }
        assert_eq!(em.models.len(), MAX_JOINTS);
    }

    #[test]
    fn too_few_samples_is_an_error_not_a_guess() {
        let config = settings();
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
        let config = settings();
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
    fn table_error_of(rows: &[NodeRow], truth: &DhTable<MAX_JOINTS>) -> (f64, f64) {
        let table = DhTable {
            rows: std::array::from_fn(|j| calib_core::DhRow {
                a: rows[j].a,
                alpha: rows[j].alpha,
                d: rows[j].d,
                theta_offset: rows[j].theta_offset,
            }),
        };
        let poses: Vec<[f64; MAX_JOINTS]> = calib_core::Scenario::new(ScenarioConfig::paper(), 999)
            .step_by(7)
            .take(500)
            .map(|s| s.sample.joints)
            .collect();
        let e = calib_core::table_error(&table, truth, &poses);
        (e.position_m * 1e3, e.rotation_rad * 1e3)
    }

    #[test]
    fn a_near_nominal_suit_the_calibration_improves_is_pushed() {
        // Errors a fifth of the paper's, 30 s of motion: a fixed-improvement rule (held-out
        // pose error 50% below nominal's) would refuse this suit ("26.9% better").
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
        let out = run(&scenario_of(cfg, 30.0, 11), &settings()).unwrap();
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
            let mut q = scen.next().unwrap().sample.joints;
            q[3] = frozen;
            s.pose = AlignedSample::of(
                s.t,
                &Sample {
                    joints: q,
                    pose: cfg.actual.fk(&q),
                },
            )
            .pose;
        }
        match run(&samples, &settings()) {
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
        let out = run(&scenario(6.0, 2), &settings()).unwrap();
        let v = &out.verdict;
        eprintln!("6 s: {:?}", v.reasons);
        assert!(
            v.reasons.iter().any(|r| matches!(
                r,
                Refusal::ExpectedPosition { .. } | Refusal::ExpectedRotation { .. }
            )),
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
        match run(&samples, &settings()) {
            Err(CalibrateError::Ls(e)) => eprintln!("nonsense: LS {e}"),
            Ok(out) => {
                let v = &out.verdict;
                eprintln!("nonsense: {:?}", v.reasons);
                assert!(!v.accepted(), "nonsense accepted: {:?}", v.expected);
                assert!(
                    v.reasons.iter().any(|r| matches!(
                        r,
                        Refusal::ExpectedPosition { .. } | Refusal::ExpectedRotation { .. }
                    )),
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
        let v = run(&scenario_of(cfg, 30.0, 4), &settings())
            .unwrap()
            .verdict;
        assert!(
            v.reasons.iter().any(|r| matches!(
                r,
                Refusal::ExpectedPosition { .. } | Refusal::ExpectedRotation { .. }
            )),
            "{:?}",
            v.reasons
        );
    }

    fn paper_samples(k: usize, seed: u64) -> Vec<Sample<MAX_JOINTS>> {
        Scenario::new(ScenarioConfig::paper(), seed)
            .take(k)
            .map(|s| s.sample)
            .collect()
    }

    #[test]
    fn ls_then_em_matches_calib_core_and_keeps_the_detail() {
        let fit = paper_samples(800, 3);
        let nominal = DhTable::paper_nominal();
        let ls_opts = LsOptions::new();
        let em_opts = DriftEmOptions {
            max_iterations: 15,
            ..DriftEmOptions::new(0.01)
        };
        let c = ls_then_em::<7, 28>(&nominal, &fit, &ls_opts, &em_opts, false).unwrap();
        let ls = identify_ls::<MAX_JOINTS, MAX_PARAMS>(&nominal, &fit, &ls_opts).unwrap();
        assert_eq!(c.ls.table, ls.table);
        let em = c.em.as_ref().unwrap();
        assert_eq!(c.calibrated, em.table);
        assert_eq!(em.drift_series.len(), fit.len());
        assert!(em.log_likelihood.len() >= 2);
        assert!(em.std_errors.iter().all(|s| s.is_finite() && *s > 0.0));
        assert!(c.ls.std_errors.iter().all(|s| s.is_finite() && *s > 0.0));
        assert_eq!(c.correlations.len(), TOP_CORRELATIONS);
        assert!(c
            .correlations
            .windows(2)
            .all(|w| w[0].r.abs() >= w[1].r.abs()));
    }

    #[test]
    fn a_still_joint_shows_as_perfectly_correlated_parameters() {
        // Joint 7 still at θ7 + offset7 = 0: Tx(a6) Rx(α6) Tx(a7) Rx(α7) = Tx(a6 + a7)
        // Rx(α6 + α7), so only the sums are identifiable (calib-core README) and the
        // pseudo-inverse leaves each pair fully correlated.
        let mut fit = paper_samples(400, 5);
        for s in &mut fit {
            s.joints[6] = 0.0;
        }
        let c = strongest_correlations::<7, 28>(&DhTable::paper_nominal(), &fit, 3);
        assert!(c[0].r.abs() > 0.999, "{c:?}");
        let moving =
            strongest_correlations::<7, 28>(&DhTable::paper_nominal(), &paper_samples(400, 5), 1);
        assert!(moving[0].r.abs() < c[0].r.abs());
    }

    #[test]
    fn the_report_detail_is_of_the_pushed_table_and_the_split_is_kept() {
        let c = super::run(&scenario(12.0, 4), &settings()).unwrap();
        assert_eq!(c.detail.calibrated, c.outcome.table());
        assert_eq!(c.fit().len(), c.outcome.fit_samples);
        assert_eq!(c.held_out().len(), c.outcome.heldout_samples);
        assert_eq!(c.samples.len(), 1200);
        // The pushed table is fitted on every sample, the judged one on the fit only.
        let em = c.detail.em.as_ref().unwrap();
        assert_eq!(em.drift_series.len(), 1200);
        assert_ne!(c.judged, c.detail.calibrated);
    }
}
