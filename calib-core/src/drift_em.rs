//! Our EM: the drift as a time series (Kalman filter + Rauch-Tung-Striebel smoother), with the
//! drift, the reference and the stated error as real sensors need them.
//!
//! # Contract (what a caller shows, logs and refuses on)
//! [`em_drift`] takes the session's samples (readings already separated from the rough part of
//! their drift, [`crate::separate`]) and the LS table, and returns a [`DriftEmResult`]; the
//! workspace then holds every sample's smoothed drift and weight.
//! * **The table** [`DriftEmResult::table`] and **the accuracy to state**
//!   [`DriftEmResult::stated_error`] (1σ table error; the Cramér-Rao part alone is
//!   [`DriftEmResult::expected_error`]). When [`em_drift`] fails (an `Err`), state
//!   [`crate::ls_white_expected_error`] of the LS table instead: a session always has an
//!   expected accuracy.
//! * **The drift model of each joint** [`DriftEmResult::models`]: [`DriftModel::GaussMarkov`]
//!   (the paper's) or [`DriftModel::RateBias`] (plus an integrated rate bias), with the reason
//!   (`2 Δ ln L` against the BIC threshold, or the sensors' spec) and the rate bias found;
//!   [`JointDrift`]'s `Display` is the line to show.
//! * **The discounted reference samples** [`DriftEmResult::discounted`]: their count, runs of
//!   sample indices (map them to times) and the fitted Student-t ν; [`discounted_samples`] lists
//!   every index from the workspace.
//! * **Consistency** [`DriftEmResult::consistency`]: per joint, the long-run variance, lag-one
//!   autocorrelation and largest value of its normalised drift innovations (1, 0 and ≲ 4 under
//!   the model); per pose component the same of the standardised innovations.
//! * **Refusals** [`DriftEmResult::refusals`]: non-empty when the data contradict the model; each
//!   [`Refusal`] is small, `Copy`, names the joint (or the share of glitches) and has a `Display`
//!   with the reason: too many discounted samples, a joint whose angle jumped (a sensor that
//!   slipped), a joint whose drift is grossly not what the model says.
//!
//! # Model
//! Linearised at the current geometry G, the pose error of sample k is
//! `e_k = H_k Δg + J_k (δ_k + c_k) + v_k`, with H_k the `6 × 4N` residual Jacobian, J_k its θ
//! block, and per joint j
//! * the Gauss-Markov drift `δ_{k+1,j} = φ_j δ_{k,j} + ρ`, `ρ ~ N(0, q_j)`,
//!   `δ_{0,j} ~ N(0, q_j / (1 − φ_j²))` (the paper's model);
//! * where the model has it, an integrated rate bias `c_{k,j} = t_{j1} s_k + t_{j2} s_k²` (`s_k`
//!   the sample's fraction of the session; a ramp and a rate that changes linearly: the first
//!   terms of a slowly wandering bias, zero at the session's start), with the coefficients random
//!   effects `t_{jm} ~ N(0, v_m)` whose intensities `v` the joints share (their sensors are of
//!   one kind; one joint's single ramp cannot tell its own intensity);
//! * a Student-t reference: `v_k ~ N(0, diag(r) / w_k)` with `w_k` the Student-t weight of the
//!   sample (its squared Mahalanobis distance `m_k`: `w_k = (ν + 6) / (ν + m_k)`).
//!
//! The estimate maximises the likelihood with the drift (and the rate bias) integrated out;
//! the drift parameters are restricted (REML) estimates; the per-sample kernels are in the
//! private `kalman` module, the static parameters' information in `info`.
//!
//! # Iteration
//! 1. **Iterate on every `stride`-th sample** (at most [`DriftEmOptions::max_stride`], and at
//!    least [`MIN_ITERATION_SAMPLES`] of them): the drift of a decimated session is the same
//!    Gauss-Markov process at the step `stride·Δt`, so φ, q and r are estimated from it at a
//!    fraction of the cost; the table is fitted on every sample at the end (5.). The geometry is
//!    an offset `x` from the linearisation. A drift faster than [`TAU_STEPS`] iterated steps is
//!    hard to tell from white pose noise on decimated samples: when the iteration converges with
//!    such a τ, it goes on at a smaller stride (from where it is).
//! 2. **ECME map.** One filter + smoother pass at `(x, t, φ, q, r)` gives the likelihood, the
//!    M-step of φ and q (per joint, a 1-D profile search of the expected complete-data
//!    log-likelihood with the stationary prior of δ_0), the noise update and the exact
//!    gradient of the log-likelihood in `x` and `t`. The noise update is EM's
//!    `r = Σ w E[(y − Jδ)²] / K` corrected for the leverage of the drift: the same fixed point,
//!    reached at once where EM creeps. The static step is the gradient times the inverse of the
//!    exact information from the two-stage (Friedland) filter that carries `x` and `t` in the
//!    drift mean (the rate bias eliminated by its Schur complement, `info`); that information is
//!    recomputed, with an exact step, whenever a drift parameter has moved by more than a
//!    factor `1 + `[`REFRESH`] since, or a map lowered the likelihood. While the rate bias is
//!    being fitted its intensities are refitted there too (their ECME step: the marginal
//!    likelihood's maximum at fixed drift), at least every [`PRIOR_REFRESH_MAPS`] maps.
//! 3. **SQUAREM** (Varadhan & Roland 2008) extrapolates two maps at a time along the slow
//!    directions. Every iterate is accepted only if its likelihood (with the rate bias's prior)
//!    is no lower than the last accepted one, so the recorded likelihood never decreases (within
//!    one objective: a refit of the intensities or of the weights starts a new one).
//! 4. **Stops** when, between accepted iterates, the geometry moved less than
//!    [`DriftEmOptions::se_tolerance`] of its standard errors and either every τ, q, r changed
//!    by less than [`DriftEmOptions::param_tolerance`] (relative) or the likelihood rose by less
//!    than [`DriftEmOptions::tolerance`]. Then, each followed by 2–4 again when it changed
//!    something: the reference's weights (a robust filter for the first: a glitch discounted
//!    before it moves the drift; then the smoother's; ν fitted); the model choice (the rate
//!    bias, started as large as the starting drift so that τ and σ do not absorb a ramp first,
//!    stays where `2 Δ ln L > `[`rate_bias_threshold`] or the sensors' spec has it; else the
//!    Gauss-Markov drift is refitted without it); optionally ([`DriftEmOptions::relinearisations`],
//!    off) a re-linearisation at the smoothed drift.
//! 5. **Restricted drift parameters** ([`REML_ITERATIONS`] at most): maximum likelihood fixes the
//!    θ offsets at their estimate, which absorbs the slowest part of the drift, so τ and σ come
//!    out low when τ is not small against the session (slow drift, short sessions), and the
//!    stated error with them. The M-step's second moments get what the offsets' uncertainty adds
//!    to the smoothed drift, through the smoother's exact sensitivity to them and the
//!    drift-visible part of the geometry's covariance (`Π V Πᵀ`, see `restricted`).
//! 6. **All samples, once.** The drift parameters are converted to the step Δt, every sample
//!    is linearised at the iterated geometry (and drift, if re-linearised), weighted (robust
//!    filter, then the smoother), and one two-stage pass gives the exact static step (the final
//!    table and rate bias), the intensities refitted on all samples and the model chosen again,
//!    and the Fisher information of the geometry with the drift and the rate bias integrated out
//!    (`std_errors`, `expected_error`). The stated error adds the model not chosen at its BIC
//!    weight (its covariance, and its table's difference). A filter and smoother pass at the
//!    final table leaves the smoothed drift in the workspace ([`DriftSlot::drift`]); a last
//!    read-only pass measures the consistency.
//!
//! On the paper's scenario (K = 6,000) that is about 19 maps on 1,500 samples and 9 exact
//! informations (`cargo test -p calib-core --release em_cost_at_k_6000 -- --ignored
//! --nocapture` prints the counts and the time beside the paper's model alone,
//! [`DriftEmOptions::plain`]).
//!
//! # What is left off, and why
//! Re-linearising at the smoothed drift (the iterated extended smoother): the pseudo-measurement
//! is right to second order (tested), yet on the paper's noise-free scenario the table gets
//! worse (8 seeds, 20 s: real error 2.69 → 3.30 mm), and as much when re-linearised at the
//! *true* drift: the regressors then move with the drift they are regressed against.
//! Inflating the stated error by the per-joint long-run variance of the innovations: it stays
//! in its null band where the model is wrong in a way that matters (the drift in the reading
//! left unseparated) and leaves it only by chance elsewhere; it is reported, not applied.
//!
//! A static θ offset and a slow drift are separable only to about `σ·√(2τ/T)` for a session of
//! length T (the standard error of the mean of a Gauss-Markov process); the result reports this
//! per joint as [`DriftEmResult::separability`].

use nalgebra::Vector6;

use crate::drift::{DriftParams, RateBias};
use crate::error::CalibError;
use crate::info::{Info, InfoAcc, TrendPrior};
use crate::kalman::{
    consistency, filter, filter_robust, linearise_at, rate_bias, residual, restricted_moments, smooth, JointInnovations, Params,
    Stats, TwoStage,
};
pub use crate::kalman::{DriftSlot, Trend, RATE_BIAS_TERMS};
use crate::linalg::{Analysis, QrAccumulator};
use crate::ls::{positive, validate_samples, InputChecks};
use crate::metrics::{expected_table_error, ErrorPoses, TableError};
use crate::model::{DhTable, Sample};

const M: usize = RATE_BIAS_TERMS;

/// Capacity of every EM likelihood history (the iteration limit of our EM and of the paper's).
pub const MAX_EM_ITERATIONS: usize = 256;

/// The iteration runs on at least this many samples (fewer only if the session is shorter).
pub const MIN_ITERATION_SAMPLES: usize = 1000;

/// The iteration moves to a smaller stride when a joint's estimated correlation time is below
/// this many iterated steps.
pub const TAU_STEPS: f64 = 10.0;

/// The geometry step's information is recomputed when a drift parameter has changed by more
/// than a factor `1 + REFRESH` since it was (measured: a stale information still gives steps
/// that raise the likelihood at a factor of 4; a refresh costs about two maps).
pub const REFRESH: f64 = 3.0;

/// A sample whose weight ([`DriftSlot::weight`]) is below this is *discounted*: it counts for
/// less than a quarter of a sample (a glitch of the reference, as the heavy-tailed model sees it).
pub const DISCOUNT_WEIGHT: f64 = 0.25;

/// Range of the Student-t degrees of freedom fitted to the reference; at the top the reference
/// is Gaussian for every purpose (weights within ±3% of 1).
pub const DOF_RANGE: (f64, f64) = (2.0, 200.0);

/// While the rate-bias model is fitted, its intensities are refitted (an information pass) at
/// least every this many maps.
pub const PRIOR_REFRESH_MAPS: usize = 6;

/// The weights are settled when an update changes them by less than this (RMS over samples).
const REWEIGHT_TOLERANCE: f64 = 0.02;

/// Weight updates of the iteration, at most.
const MAX_REWEIGHTS: usize = 4;

/// A reference whose fitted ν is at least this is taken as Gaussian on every sample (weights
/// within ±5% of 1).
const GAUSSIAN_DOF: f64 = 100.0;

/// The most objectives one fit records ([`DriftEmResult::objectives`]): finer strides, prior
/// refits and re-linearisations together; later ones are merged into the last.
pub const MAX_OBJECTIVES: usize = 16;

/// Degrees of freedom of the robust filter that gives the reference's first weights.
const DOF_START: f64 = 4.0;

/// Runs of discounted samples [`Discounted::runs`] lists (the count is always complete).
pub const MAX_DISCOUNTED_RUNS: usize = 16;

/// Most refusals a result carries.
pub const MAX_REFUSALS: usize = 8;

/// Fixed-point iterations of the restricted (REML) drift parameters, at most.
pub const REML_ITERATIONS: usize = 4;

/// The rate bias enters the model when `2 Δ ln L` of it against the Gauss-Markov drift exceeds
/// BIC's penalty of the intensities it has, `terms · ln K` (K samples; `terms` those of the
/// fitted intensities that are not zero, at least one, at most [`RATE_BIAS_TERMS`]): a steady
/// rate bias (a heading that no gravity reference corrects) has one, a wandering one two.
/// Measured, the likelihood-ratio test at 5% (5.99) takes it on 1 in 8 short sessions without
/// one, and the table is then worse than LS's.
pub fn rate_bias_threshold(samples: usize, terms: usize) -> f64 {
    terms.clamp(1, RATE_BIAS_TERMS) as f64 * libm::log(samples.max(2) as f64)
}

/// [`rate_bias_threshold`] for the intensities `prior`.
fn threshold_of(samples: usize, prior: &TrendPrior) -> f64 {
    rate_bias_threshold(samples, prior.iter().filter(|v| **v > 0.0).count())
}

/// Options of [`em_drift`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DriftEmOptions<const N: usize> {
    /// Sample period Δt (s).
    pub dt: f64,
    /// Limit on ECME maps (filter + smoother passes over the iterated samples; below
    /// [`MAX_EM_ITERATIONS`]).
    pub max_iterations: usize,
    /// Also converged when the geometry settled (see `se_tolerance`) and one SQUAREM cycle
    /// raised the log-likelihood by less than this (absolute: a gain of 0.01 is what a step of
    /// about 0.14 standard errors gives near the maximum), however the drift parameters still
    /// move (the likelihood is flat along the measurement noise on noise-free data).
    pub tolerance: f64,
    /// Converged when, over one SQUAREM cycle, every τ_j, q_j and r_i changed by less than
    /// this (relative) and the geometry by less than `se_tolerance`.
    pub param_tolerance: f64,
    /// See `param_tolerance`: the geometry's change in units of its own standard errors.
    pub se_tolerance: f64,
    /// Largest stride of the iterated samples (1: iterate on every sample).
    pub max_stride: usize,
    /// Fail with [`CalibError::NotConverged`] when the limit is reached first.
    pub require_convergence: bool,
    /// Starting correlation time (s) of every joint.
    pub initial_tau: f64,
    /// Starting stationary drift deviation (rad) of every joint.
    pub initial_drift_std: f64,
    /// Starting measurement-noise deviation (m, rad) of every pose component.
    pub initial_noise_std: f64,
    /// Floor of the measurement-noise variance.
    pub noise_floor: f64,
    /// Relative singular-value tolerance of the geometry step.
    pub rank_tolerance: f64,
    /// Input validation.
    pub checks: InputChecks<N>,
    /// Let a joint's drift model gain the integrated rate bias where the data support it
    /// (BIC; [`DriftModel`]). Off: every joint keeps the paper's Gauss-Markov drift.
    pub rate_bias: bool,
    /// Heavy-tailed reference: Student-t pose errors (per-sample weights, degrees of freedom
    /// fitted in [`DOF_RANGE`]). Off: Gaussian.
    pub robust: bool,
    /// Re-linearisations of the iterated samples at the smoothed drift, at most (0: linearised
    /// once, at the reported angles).
    pub relinearisations: usize,
    /// Restricted (REML) drift parameters: the M-step counts the uncertainty of the static
    /// angle level (θ offsets and rate bias) the drift is told from. Off: maximum likelihood,
    /// whose τ and σ are biased low when τ is not small against the session.
    pub restricted: bool,
    /// The rate bias the suit's sensors are known to have (their spec; [`RateBias::NONE`]: not
    /// known). A rate bias below what a session can detect still moves the θ offsets by its
    /// mean over the session, which no estimator can tell from the drift's slow part: with a
    /// spec, every joint's model has the rate bias at least this large, and the stated error
    /// includes it.
    pub rate_bias_spec: RateBias,
    /// A rate bias to weigh without modelling it ([`RateBias::NONE`]: none): where the chosen
    /// model leaves the rate bias out, [`DriftEmResult::allowance`] is what one of this size
    /// would add to the table error (Schmidt's *consider* covariance: the table's response
    /// `A⁻¹ B t` to the rate bias's coefficients `t` at their intensities). Below what a session
    /// detects, such a bias moves the table without a trace in the data. It changes neither the
    /// estimate nor [`DriftEmResult::stated_error`]: state
    /// [`DriftEmResult::stated_with_allowance`] where the sensors may have it.
    pub consider: RateBias,
    /// Refuse ([`Refusal::TooManyDiscounted`]) when more than this share of the samples is
    /// discounted.
    pub max_discounted_share: f64,
    /// Refuse ([`Refusal::Inconsistent`]) when a joint's normalised drift innovations have
    /// more than this many times their long-run variance under the model.
    pub max_inconsistency: f64,
    /// Refuse ([`Refusal::Jump`]) when a joint's normalised drift innovation exceeds this many
    /// standard deviations (a standard normal under the model: above 6 about once in 10⁹
    /// samples).
    pub max_jump: f64,
    /// The poses [`DriftEmResult::expected_error`], [`DriftEmResult::stated_error`] and
    /// [`DriftEmResult::allowance`] are averaged over: the session's own
    /// ([`ErrorPoses::Session`], the default) or the joints' ranges, which a session that
    /// left part of a range unvisited is honest only over ([`ErrorPoses::Ranges`]).
    pub error_poses: ErrorPoses<N>,
}

impl<const N: usize> DriftEmOptions<N> {
    /// Defaults for a sample period `dt`. The starting values are deliberately not the
    /// simulator's truth: τ = 3 s, 5 mrad drift, 1 mm / 1 mrad noise. The drift starts small
    /// so that a steady rate bias is fitted before τ and σ grow to absorb it (from 20 mrad, a
    /// 0.05 °/s heading is absorbed on 1 seed in 8,
    /// `a_heading_is_found_before_the_drift_absorbs_it`).
    pub fn new(dt: f64) -> Self {
        DriftEmOptions {
            dt,
            max_iterations: 100,
            tolerance: 1.0,
            param_tolerance: 1e-2,
            se_tolerance: 0.1,
            max_stride: 4,
            require_convergence: false,
            initial_tau: 3.0,
            initial_drift_std: 0.005,
            initial_noise_std: 1e-3,
            noise_floor: 1e-14,
            rank_tolerance: 1e-9,
            checks: InputChecks::new(None),
            rate_bias: true,
            robust: true,
            relinearisations: 0,
            restricted: true,
            rate_bias_spec: RateBias::NONE,
            consider: RateBias::NONE,
            max_discounted_share: 0.1,
            max_inconsistency: 9.0,
            max_jump: 6.0,
            error_poses: ErrorPoses::Session,
        }
    }

    /// The paper's drift model and none of what real sensors add: Gauss-Markov drift on every
    /// joint, a Gaussian reference, one linearisation, maximum-likelihood drift parameters.
    pub fn plain(dt: f64) -> Self {
        DriftEmOptions {
            rate_bias: false,
            robust: false,
            relinearisations: 0,
            restricted: false,
            ..Self::new(dt)
        }
    }
}

/// A joint's drift model.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DriftModel {
    /// The paper's first-order Gauss-Markov drift.
    GaussMarkov,
    /// Gauss-Markov plus a rate bias integrated into the angle: a ramp and a rate that changes
    /// linearly over the session (the first two terms of a slowly wandering bias), random
    /// effects whose intensities the joints share.
    RateBias,
}

impl core::fmt::Display for DriftModel {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(match self {
            DriftModel::GaussMarkov => "Gauss-Markov",
            DriftModel::RateBias => "Gauss-Markov + rate bias",
        })
    }
}

/// Which drift model a joint got, and why.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct JointDrift {
    /// The model of the result.
    pub model: DriftModel,
    /// `2 Δ ln L` of the rate bias against the Gauss-Markov drift on all samples (the session's:
    /// the intensities are shared by the joints, so it is the same for every joint; NaN when
    /// the rate bias was not considered).
    pub statistic: f64,
    /// The threshold it is compared with ([`rate_bias_threshold`]).
    pub threshold: f64,
    /// Whether the rate bias is in the model because the sensors' spec says so
    /// ([`DriftEmOptions::rate_bias_spec`]) rather than by the statistic.
    pub by_spec: bool,
    /// Weight of the model not chosen (`1 / (1 + e^{±(statistic − threshold)/2})`); the stated
    /// error includes it ([`DriftEmResult::stated_error`]).
    pub other_weight: f64,
    /// Rate bias (rad/s) at the session's start and end (0 without one).
    pub rate: [f64; 2],
    /// The angle the rate bias added by the session's end (rad) and its standard error.
    pub angle: f64,
    /// Standard error of `angle` (rad).
    pub angle_se: f64,
}

impl core::fmt::Display for JointDrift {
    /// `Gauss-Markov + rate bias (2ΔlnL 85.3 > 14.6): 0.0120 → 0.0180 °/s, +9.8 ± 0.6 mrad`;
    /// `(sensor spec, 2ΔlnL 3.1)` when the spec put it there.
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        if self.by_spec {
            write!(f, "{} (sensor spec, 2ΔlnL {:.1})", self.model, self.statistic)?;
        } else {
            let cmp = if self.statistic > self.threshold { ">" } else { "≤" };
            write!(f, "{} (2ΔlnL {:.1} {cmp} {:.1})", self.model, self.statistic, self.threshold)?;
        }
        if self.model == DriftModel::RateBias {
            write!(
                f,
                ": {:.4} → {:.4} °/s, {:+.1} ± {:.1} mrad",
                self.rate[0].to_degrees(),
                self.rate[1].to_degrees(),
                self.angle * 1e3,
                self.angle_se * 1e3
            )?;
        }
        Ok(())
    }
}

/// The reference samples the heavy-tailed model discounted (weight below
/// [`DISCOUNT_WEIGHT`]): how many, and where (runs of consecutive sample indices, the first
/// [`MAX_DISCOUNTED_RUNS`]; [`discounted_samples`] lists every index from the workspace).
#[derive(Clone, Debug, PartialEq)]
pub struct Discounted {
    /// Discounted samples.
    pub count: usize,
    /// Samples in the session.
    pub samples: usize,
    /// First and last sample index of each run of discounted samples, in time order.
    pub runs: heapless::Vec<(usize, usize), MAX_DISCOUNTED_RUNS>,
    /// Whether there were more runs than `runs` holds.
    pub more_runs: bool,
    /// Fitted degrees of freedom of the reference's Student-t ([`DOF_RANGE`]; ∞ when the
    /// reference was taken as Gaussian).
    pub dof: f64,
}

impl Discounted {
    /// `count / samples`.
    pub fn share(&self) -> f64 {
        self.count as f64 / self.samples.max(1) as f64
    }
}

/// Indices of the samples [`em_drift`] discounted, from its workspace (`&workspace[..K]`).
pub fn discounted_samples<const N: usize>(slots: &[DriftSlot<N>]) -> impl Iterator<Item = usize> + '_ {
    slots
        .iter()
        .enumerate()
        .filter(|(_, s)| s.w < DISCOUNT_WEIGHT)
        .map(|(k, _)| k)
}

/// How well one joint's drift follows its model, from the final filter pass.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct JointConsistency {
    /// Long-run variance of the joint's normalised drift innovations (batch means over
    /// [`Consistency::blocks`] blocks): 1 when the data follow the model, above 1 when the drift
    /// has structure the model leaves out (then the session says more about the joint's angle
    /// level than it should).
    pub long_run: f64,
    /// Lag-one autocorrelation of those innovations (0 under the model).
    pub lag1: f64,
    /// The largest |normalised innovation| (a standard normal under the model: about 4 at most
    /// in a few thousand samples) and the sample it was at: a jump of the joint's angle error.
    pub largest: f64,
    /// The sample of `largest`.
    pub at: usize,
}

/// Consistency of the fitted model with the data (final filter pass, every sample).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Consistency<const N: usize> {
    /// Per joint.
    pub joints: [JointConsistency; N],
    /// Per pose component: mean squared standardised innovation (1 under the model).
    pub pose_nis: [f64; 6],
    /// Per pose component: long-run variance of the standardised innovations (batch means).
    pub pose_long_run: [f64; 6],
    /// Batch-means blocks (a long-run variance estimate has a relative standard deviation of
    /// `√(2 / blocks)` under the model).
    pub blocks: usize,
}

/// Why the data contradict the model (the session should be refused; [`DriftEmResult::refusals`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Refusal {
    /// More of the reference glitched than [`DriftEmOptions::max_discounted_share`] allows.
    TooManyDiscounted {
        /// Discounted samples.
        count: usize,
        /// Samples in the session.
        samples: usize,
        /// The share allowed.
        limit: f64,
    },
    /// A joint's angle error jumped (see [`JointConsistency::largest`]): a sensor that slipped or
    /// was re-zeroed during the session.
    Jump {
        /// The joint (0-based).
        joint: usize,
        /// The sample it jumped at.
        sample: usize,
        /// The jump's normalised innovation (standard deviations).
        sigma: f64,
    },
    /// The EM found rate biases (`joints`, a bit per joint), and its model does not explain LS's
    /// table ([`crate::EmVersusLs`]'s `statistic` above [`crate::MAX_EM_LS_STATISTIC`]): LS's
    /// table is off by what it integrates of them and the EM's by what its model misses, so
    /// neither is to be pushed ([`crate::TableChoice::Neither`]).
    Unexplained {
        /// The joints with a rate bias, bit `j` for joint `j` (0-based).
        joints: u32,
        /// The largest rate bias found (rad/s, signed).
        rate: f64,
        /// The statistic of the EM's table against LS's.
        statistic: f64,
    },
    /// A joint's drift does not follow its model (see [`JointConsistency::long_run`]).
    Inconsistent {
        /// The joint (0-based).
        joint: usize,
        /// Its long-run variance.
        long_run: f64,
        /// The limit ([`DriftEmOptions::max_inconsistency`]).
        limit: f64,
    },
}

impl core::fmt::Display for Refusal {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match *self {
            Refusal::TooManyDiscounted { count, samples, limit } => write!(
                f,
                "{count} of {samples} reference poses ({:.1}%) look like glitches, more than the {:.0}% allowed: check the tracker's line of sight and mounting",
                100.0 * count as f64 / samples.max(1) as f64,
                100.0 * limit
            ),
            Refusal::Jump { joint, sample, sigma } => write!(
                f,
                "joint {}'s angle sensor jumped at sample {sample} (a {sigma:.1}σ step of its drift): a sensor that slipped or was re-zeroed; re-seat it and calibrate again",
                joint + 1
            ),
            Refusal::Unexplained { joints, rate, statistic } => {
                write!(f, "the angle sensors of joint")?;
                let mut sep = if joints.count_ones() > 1 { "s " } else { " " };
                for j in (0..32).filter(|j| joints & (1 << j) != 0) {
                    write!(f, "{sep}{}", j + 1)?;
                    sep = ", ";
                }
                write!(
                    f,
                    " drift at a steady rate (up to {:.3} °/s) that neither the drift model nor LS accounts for: the two tables differ {statistic:.1}× beyond what either model allows; hold the suit still for the gyros' bias, or calibrate again",
                    libm::fabs(rate).to_degrees()
                )
            }
            Refusal::Inconsistent { joint, long_run, limit } => write!(
                f,
                "joint {}'s drift does not follow its model (its innovations carry {long_run:.1}× their expected long-run variance, above {limit:.0}): its angle sensor drifts in a way the calibration cannot account for",
                joint + 1
            ),
        }
    }
}

/// Result of [`em_drift`]. The drift trajectory is in the workspace.
///
/// # What to show and what to refuse on
/// * [`DriftEmResult::stated_error`]: the table's expected error (1σ) to state and validate
///   with; [`DriftEmResult::expected_error`] is the Cramér-Rao part alone.
/// * [`DriftEmResult::models`]: per joint, the drift model and why ([`JointDrift`]'s
///   `Display`).
/// * [`DriftEmResult::discounted`]: how many reference samples were discounted, and where
///   ([`discounted_samples`] for every index).
/// * [`DriftEmResult::consistency`]: per joint, how well the drift followed its model.
/// * [`DriftEmResult::refusals`]: non-empty when the data contradict the model; each has a
///   `Display` naming the joint or the share and the reason.
#[derive(Clone, Debug)]
pub struct DriftEmResult<const N: usize> {
    /// The corrected table (static geometry).
    pub table: DhTable<N>,
    /// Per joint AR(1) coefficient φ_j = e^{−Δt/τ_j}.
    pub phi: [f64; N],
    /// Per joint process variance q_j (rad²).
    pub process_variance: [f64; N],
    /// Per joint τ and σ (both conventions).
    pub drift: [DriftParams; N],
    /// Measurement-noise variance per pose component (m², rad²), for a sample of weight 1.
    pub measurement_variance: [f64; 6],
    /// Per joint `σ·√(2τ/T)`: how well a static θ offset can be told from the drift (rad).
    pub separability: [f64; N],
    /// Log-likelihood of the iterated samples at every accepted iterate, every objective's in
    /// turn: the objective changes when the iteration moves to finer samples, refits the rate
    /// bias's prior or re-linearises ([`Self::objectives`] says where). Within one objective it
    /// never decreases; across two the values are not comparable.
    pub log_likelihood: heapless::Vec<f64, MAX_EM_ITERATIONS>,
    /// Where in [`Self::log_likelihood`] each objective after the first starts (ascending).
    pub objectives: heapless::Vec<usize, MAX_OBJECTIVES>,
    /// Log-likelihood of all samples at the final table and drift parameters (linearised at
    /// the iterated geometry and the smoothed drift).
    pub final_log_likelihood: f64,
    /// The iteration ended on every `stride`-th sample.
    pub stride: usize,
    /// ECME maps (filter + smoother passes over the iterated samples).
    pub iterations: usize,
    /// Exact geometry informations (two-stage passes over the iterated samples).
    pub information_passes: usize,
    /// Re-linearisations at the smoothed drift.
    pub relinearisations: usize,
    /// Whether the tolerance was reached.
    pub converged: bool,
    /// Numerical rank of the last geometry step.
    pub rank: usize,
    /// Cramér-Rao bound (1σ) of every geometric parameter under the fitted drift and noise
    /// model, `std_errors[kind][joint]` (m, rad): the inverse of the exact Fisher information
    /// of the static parameters with the drift integrated out (from the two-stage filter).
    pub std_errors: [[f64; N]; 4],
    /// Expected table error (1σ) of [`DriftEmResult::table`] under that bound: the RMS over
    /// [`DriftEmOptions::error_poses`] ([`EXPECTED_ERROR_POSES`] of them) of the position and
    /// rotation error its FK would have against the true table ([`crate::metrics`]).
    pub expected_error: TableError,
    /// The expected table error to state (1σ): [`DriftEmResult::expected_error`] with the
    /// uncertainty of the drift-model choice (the model not chosen at its BIC weight: its
    /// covariance and the difference of its table).
    pub stated_error: TableError,
    /// What a rate bias of [`DriftEmOptions::consider`]'s size would add to the table error
    /// where the chosen model leaves it out (1σ; zero without one, or where the model has the
    /// rate bias). Not part of [`Self::stated_error`].
    pub allowance: TableError,
    /// Per joint, the drift model and why.
    pub models: [JointDrift; N],
    /// Per joint, the integrated rate bias's coefficients (rad; 0 for Gauss-Markov joints):
    /// the angle error gains `Σ_m rate_bias[j][m]·s^(m+1)` at the session fraction `s`.
    pub rate_bias: Trend<N>,
    /// The reference samples discounted as glitches.
    pub discounted: Discounted,
    /// How well the data follow the fitted model.
    pub consistency: Consistency<N>,
    /// Where the data contradict the model (empty: none).
    pub refusals: heapless::Vec<Refusal, MAX_REFUSALS>,
}

impl<const N: usize> DriftEmResult<N> {
    /// [`Self::stated_error`] with [`Self::allowance`] added (root sum of squares): the error to
    /// state where the sensors may have the considered rate bias.
    pub fn stated_with_allowance(&self) -> TableError {
        let (s, a) = (self.stated_error, self.allowance);
        TableError {
            position_m: libm::hypot(s.position_m, a.position_m),
            rotation_rad: libm::hypot(s.rotation_rad, a.rotation_rad),
        }
    }

    /// The log-likelihoods of the final objective (the last part of [`Self::log_likelihood`]):
    /// never decreasing.
    pub fn last_objective(&self) -> &[f64] {
        &self.log_likelihood[self.objectives.last().copied().unwrap_or(0)..]
    }

    /// The integrated rate bias of every joint at sample `k` of the session's `samples` (rad):
    /// the slow part of the angle error beside [`DriftSlot::drift`].
    pub fn rate_bias_at(&self, k: usize, samples: usize) -> [f64; N] {
        rate_bias(&self.rate_bias, k as f64 / (samples.max(2) - 1) as f64)
    }
}

/// Poses [`DriftEmResult::expected_error`] is averaged over ([`ErrorPoses`]; a session with fewer
/// samples: all of its own).
pub const EXPECTED_ERROR_POSES: usize = 256;

fn degenerate(what: &'static str) -> CalibError {
    CalibError::InvalidInput { what }
}

/// Expected complete-data log-likelihood of one joint's drift (constants dropped).
fn q_joint(phi: f64, q: f64, k: f64, e0: f64, s00: f64, s10: f64, s11: f64) -> f64 {
    let p0 = q / (1.0 - phi * phi);
    -0.5 * (libm::log(p0) + e0 / p0 + (k - 1.0) * libm::log(q) + (s11 - 2.0 * phi * s10 + phi * phi * s00) / q)
}

fn m_step<const N: usize>(st: &Stats<N>, par: &Params<N>, kn: usize, noise_floor: f64, leverage: bool) -> Params<N> {
    let k = kn as f64;
    let mut out = *par;
    for j in 0..N {
        let (e0, s00, s10, s11) = (st.e0[j], st.s00[j], st.s10[j], st.s11[j]);
        let qstar = |phi: f64| ((e0 * (1.0 - phi * phi) + s11 - 2.0 * phi * s10 + phi * phi * s00) / k).max(1e-300);
        let f = |phi: f64| k * libm::log(qstar(phi)) - libm::log(1.0 - phi * phi);
        // Golden-section search of the profile over φ ∈ [0, 1 − 1e-9].
        let (mut lo, mut hi) = (0.0, 1.0 - 1e-9);
        let gr = 0.618_033_988_749_894_9;
        let (mut x1, mut x2) = (hi - gr * (hi - lo), lo + gr * (hi - lo));
        let (mut f1, mut f2) = (f(x1), f(x2));
        for _ in 0..100 {
            if f1 < f2 {
                hi = x2;
                (x2, f2) = (x1, f1);
                x1 = hi - gr * (hi - lo);
                f1 = f(x1);
            } else {
                lo = x1;
                (x1, f1) = (x2, f2);
                x2 = lo + gr * (hi - lo);
                f2 = f(x2);
            }
        }
        let phi = 0.5 * (lo + hi);
        let q = qstar(phi);
        let new = q_joint(phi, q, k, e0, s00, s10, s11);
        let old = q_joint(par.phi[j], par.q[j], k, e0, s00, s10, s11);
        if new >= old {
            out.phi[j] = phi;
            out.q[j] = q;
        }
    }
    for i in 0..6 {
        // EM: r = (res + var) / K. With small noise each sample's drift absorbs most of its
        // residual (leverage c = var / (K r) near 1) and EM creeps at the rate c; the
        // leverage-corrected update res / (K (1 − c)) has the same fixed point and gets there
        // at once when res and var scale with r.
        let c = st.var[i] / (k * par.r[i]);
        out.r[i] = if leverage && c < 0.995 {
            st.res[i] / (k * (1.0 - c))
        } else {
            (st.res[i] + st.var[i]) / k
        }
        .max(noise_floor);
    }
    out
}

/// The iterate of the ECME map: the static parameters (geometry offset, rate bias) and the
/// drift parameters, the latter as logarithms (`ln(−ln φ)`, `ln q`, `ln r`) so that any
/// extrapolation stays admissible.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Iterate<const N: usize, const P: usize> {
    x: [f64; P],
    t: Trend<N>,
    lphi: [f64; N],
    lq: [f64; N],
    lr: [f64; 6],
}

/// Scales of the static parameters (standard errors) that iterates are compared in.
#[derive(Clone, Copy, Debug)]
struct Scale<const N: usize, const P: usize> {
    x: [f64; P],
    t: Trend<N>,
}

impl<const N: usize, const P: usize> Scale<N, P> {
    const UNIT: Self = Scale {
        x: [1.0; P],
        t: [[1.0; M]; N],
    };

    fn of(info: &Info<N, P>) -> Self {
        let (x, t) = info.std_errors();
        let ok = |s: f64| if s > 0.0 && s.is_finite() { s } else { 1.0 };
        Scale {
            x: x.map(ok),
            t: t.map(|r| r.map(ok)),
        }
    }
}

impl<const N: usize, const P: usize> Iterate<N, P> {
    fn new(x: [f64; P], t: Trend<N>, par: &Params<N>) -> Self {
        Iterate {
            x,
            t,
            lphi: par.phi.map(|p| libm::log(-libm::log(p))),
            lq: par.q.map(libm::log),
            lr: par.r.map(libm::log),
        }
    }

    fn params(&self, noise_floor: f64) -> Params<N> {
        Params {
            // φ ≤ 1 − 1e-9 (the M-step's range), and a finite, positive q.
            phi: self.lphi.map(|l| libm::exp(-libm::exp(l)).min(1.0 - 1e-9)),
            q: self.lq.map(|l| libm::exp(l).clamp(1e-300, 1e300)),
            r: self.lr.map(|l| libm::exp(l).clamp(noise_floor, 1e300)),
        }
    }

    /// The same drift parameters at other static parameters.
    fn with_static(&self, x: [f64; P], t: Trend<N>) -> Self {
        Iterate { x, t, ..*self }
    }

    /// `self + a·u + b·w` (componentwise).
    fn combine(&self, a: f64, u: &Self, b: f64, w: &Self) -> Self {
        fn mix<const K: usize>(s: &[f64; K], a: f64, u: &[f64; K], b: f64, w: &[f64; K]) -> [f64; K] {
            core::array::from_fn(|i| s[i] + a * u[i] + b * w[i])
        }
        Iterate {
            x: mix(&self.x, a, &u.x, b, &w.x),
            t: core::array::from_fn(|j| mix(&self.t[j], a, &u.t[j], b, &w.t[j])),
            lphi: mix(&self.lphi, a, &u.lphi, b, &w.lphi),
            lq: mix(&self.lq, a, &u.lq, b, &w.lq),
            lr: mix(&self.lr, a, &u.lr, b, &w.lr),
        }
    }

    /// `self − other`.
    fn minus(&self, other: &Self) -> Self {
        self.combine(-1.0, other, 0.0, other)
    }

    /// Squared norm with the static parameters in units of `se`.
    fn norm2(&self, se: &Scale<N, P>) -> f64 {
        let g: f64 = self.x.iter().zip(&se.x).map(|(x, s)| (x / s) * (x / s)).sum();
        let t: f64 = self
            .t
            .as_flattened()
            .iter()
            .zip(se.t.as_flattened())
            .map(|(x, s)| (x / s) * (x / s))
            .sum();
        let d: f64 = self.lphi.iter().chain(&self.lq).chain(&self.lr).map(|v| v * v).sum();
        g + t + d
    }

    /// Largest static-parameter change in units of `se`, and largest change of a drift
    /// parameter's logarithm, from `other` to `self`.
    fn change(&self, other: &Self, se: &Scale<N, P>) -> (f64, f64) {
        let g = (0..P).fold(0.0f64, |m, p| m.max(((self.x[p] - other.x[p]) / se.x[p]).abs()));
        let t = (0..N * M).fold(0.0f64, |m, a| {
            let (j, k) = (a / M, a % M);
            m.max(((self.t[j][k] - other.t[j][k]) / se.t[j][k]).abs())
        });
        let tau = (0..N).fold(0.0f64, |m, j| m.max((self.lphi[j] - other.lphi[j]).abs()));
        let q = (0..N).fold(0.0f64, |m, j| m.max((self.lq[j] - other.lq[j]).abs()));
        let r = (0..6).fold(0.0f64, |m, i| m.max((self.lr[i] - other.lr[i]).abs()));
        (g.max(t), tau.max(q).max(r))
    }

    fn is_finite(&self) -> bool {
        self.x
            .iter()
            .chain(self.t.as_flattened())
            .chain(&self.lphi)
            .chain(&self.lq)
            .chain(&self.lr)
            .all(|v| v.is_finite())
    }
}

/// One exact two-stage pass over stored linearisations at the static parameters `(x, t)`: the
/// likelihood and the accumulated information (with every joint's rate-bias columns when
/// `trend`).
fn accumulate<const N: usize, const P: usize>(
    slots: &mut [DriftSlot<N>],
    x: &[f64; P],
    t: &Trend<N>,
    par: &Params<N>,
    trend: bool,
) -> Result<(f64, InfoAcc<N, P>), CalibError> {
    let mut acc = InfoAcc::<N, P>::new(trend);
    let mut ts = TwoStage::<N, P>::new(par, trend);
    for slot in slots.iter_mut() {
        slot.y = residual(slot, x, t);
        ts.absorb(&slot.y, &slot.h, slot.s, slot.w, par, &mut |rows, trows, rhs| {
            acc.add(rows, trows, rhs)
        })?;
    }
    Ok((ts.ll, acc))
}

/// The analysis of the static parameters at the geometry `x` (rows at `t = 0`: the step gives
/// the absolute rate bias) under the rate bias's intensities `prior`; with `fit`, those are
/// first refitted to this accumulation (their ECME step) and `statistic` set to `2 Δ ln L` of
/// them against none. Through the QR, without rate bias, when the normal equations are
/// ill-conditioned.
#[allow(clippy::too_many_arguments)]
fn information<const N: usize, const P: usize>(
    slots: &mut [DriftSlot<N>],
    x: &[f64; P],
    par: &Params<N>,
    trend: bool,
    fit: Option<&TrendPrior>,
    prior: &mut TrendPrior,
    statistic: &mut f64,
    rank_tolerance: f64,
) -> Result<(f64, Info<N, P>), CalibError> {
    let (ll, acc) = accumulate(slots, x, &[[0.0; M]; N], par, trend)?;
    if let (true, Some(floor)) = (trend, fit) {
        if let Some((v, lr)) = acc.choose_prior(rank_tolerance, floor, libm::log(slots.len().max(2) as f64)) {
            *statistic = lr;
            *prior = v;
        }
    }
    let info = match acc.analyse(prior, rank_tolerance) {
        Some(a) => a,
        None => {
            *prior = [0.0; M];
            qr_information(slots, par, rank_tolerance)?
        }
    };
    Ok((ll, info))
}

/// `ln p(t)` of the rate bias under its prior, up to a constant.
fn prior_ll<const N: usize>(prior: &TrendPrior, t: &Trend<N>) -> f64 {
    let mut s = 0.0;
    for row in t {
        for (c, v) in row.iter().zip(prior) {
            if *v > 0.0 {
                s -= 0.5 * c * c / v;
            }
        }
    }
    s
}

/// [`information`] through the QR (rank-deficient or ill-conditioned geometry), from the
/// residuals the slots hold, without rate bias.
#[inline(never)]
fn qr_information<const N: usize, const P: usize>(
    slots: &[DriftSlot<N>],
    par: &Params<N>,
    rank_tolerance: f64,
) -> Result<Info<N, P>, CalibError> {
    let mut qr = QrAccumulator::<P>::new();
    let mut ts = TwoStage::<N, P>::new(par, false);
    for slot in slots {
        ts.absorb(&slot.y, &slot.h, slot.s, slot.w, par, &mut |rows, _, rhs| {
            for (row, y) in rows.iter().zip(rhs) {
                qr.add_row(row, *y);
            }
        })?;
    }
    Ok(Info::geometry(qr.analyse(rank_tolerance)))
}

/// The drift parameters at the step `from·Δt` converted to the step `to·Δt` (a decimated
/// session's drift is the same Gauss-Markov process): the same stationary variance,
/// `φ_to = φ_from^{to/from}`.
fn restride<const N: usize>(par: &Params<N>, from: usize, to: usize) -> Params<N> {
    let mut out = *par;
    for j in 0..N {
        let v = par.q[j] / (1.0 - par.phi[j] * par.phi[j]);
        let phi = libm::pow(par.phi[j], to as f64 / from as f64).min(1.0 - 1e-9);
        out.phi[j] = phi;
        out.q[j] = v * (1.0 - phi * phi);
    }
    out
}

/// SQUAREM's extrapolation steps are bounded by this, then by four times more after each
/// extrapolation that used the whole bound (the scheme of Varadhan & Roland's `squarem`).
const STEP_MAX0: f64 = 1.0;

/// Weight of the richer model given its `2 Δ ln L` statistic and threshold.
fn rich_weight(statistic: f64, threshold: f64) -> f64 {
    let d = 0.5 * (statistic - threshold);
    if d > 40.0 {
        1.0
    } else if d < -40.0 {
        0.0
    } else {
        1.0 / (1.0 + libm::exp(-d))
    }
}

/// Student-t degrees of freedom of 6-dimensional residuals with squared Mahalanobis distances
/// `m2` (maximum likelihood, golden section on ln ν in [`DOF_RANGE`]).
fn fit_dof<const N: usize>(slots: &[DriftSlot<N>]) -> f64 {
    let d = 6.0;
    let ll = |nu: f64| {
        let c = libm::lgamma(0.5 * (nu + d)) - libm::lgamma(0.5 * nu) - 0.5 * d * libm::log(nu);
        slots.iter().map(|s| c - 0.5 * (nu + d) * libm::log1p(s.m2 / nu)).sum::<f64>()
    };
    let (mut lo, mut hi) = (libm::log(DOF_RANGE.0), libm::log(DOF_RANGE.1));
    let gr = 0.618_033_988_749_894_9;
    let (mut a, mut b) = (hi - gr * (hi - lo), lo + gr * (hi - lo));
    let (mut fa, mut fb) = (ll(libm::exp(a)), ll(libm::exp(b)));
    for _ in 0..40 {
        if fa >= fb {
            hi = b;
            (b, fb) = (a, fa);
            a = hi - gr * (hi - lo);
            fa = ll(libm::exp(a));
        } else {
            lo = a;
            (a, fa) = (b, fb);
            b = lo + gr * (hi - lo);
            fb = ll(libm::exp(b));
        }
    }
    libm::exp(0.5 * (lo + hi))
}

/// Sets every slot's weight from its `m2` at `dof` degrees of freedom; returns the RMS change.
fn reweight<const N: usize>(slots: &mut [DriftSlot<N>], dof: f64) -> f64 {
    let mut change = 0.0;
    for s in slots.iter_mut() {
        let w = (dof + 6.0) / (dof + s.m2);
        change += (w - s.w) * (w - s.w);
        s.w = w;
    }
    libm::sqrt(change / slots.len().max(1) as f64)
}

/// The iteration on the decimated samples (steps 1–4 of the module docs).
struct Iteration<'a, const N: usize, const P: usize> {
    samples: &'a [Sample<N>],
    opts: &'a DriftEmOptions<N>,
    kn: usize,
    stride: usize,
    ks: usize,
    /// Reference geometry of the linearisation; the iterate's `x` is relative to it.
    g_ref: DhTable<N>,
    /// Intensities of the rate bias (0: the Gauss-Markov model), and `2 Δ ln L` of the last fit.
    prior: TrendPrior,
    statistic: f64,
    /// Whether the intensities are refitted at every information pass (the rate-bias model is
    /// being fitted; once chosen or rejected, they are fixed).
    fitting: bool,
    /// The intensities of the sensors' spec ([`DriftEmOptions::rate_bias_spec`]), a floor.
    floor_prior: TrendPrior,
    z: Iterate<N, P>,
    history: heapless::Vec<f64, MAX_EM_ITERATIONS>,
    /// Where in `history` each objective after the first starts.
    objectives: heapless::Vec<usize, MAX_OBJECTIVES>,
    iterations: usize,
    information_passes: usize,
    converged: bool,
    cols: [[Vector6<f64>; N]; 4],
}

impl<const N: usize, const P: usize> Iteration<'_, N, P> {
    fn floor(&self) -> f64 {
        self.opts.noise_floor
    }

    /// Linearises the iterated samples at `g_ref`, at the reported angles or (`relinearise`)
    /// at the angle error the slots' smoothed drift and the rate bias give.
    fn linearise(&mut self, ws: &mut [DriftSlot<N>], relinearise: bool) {
        let prepared = self.g_ref.prepare();
        let last = (self.kn - 1).max(1) as f64;
        for (i, slot) in ws[..self.ks].iter_mut().enumerate() {
            let k = i * self.stride;
            slot.s = k as f64 / last;
            let offset: Option<[f64; N]> = relinearise.then(|| {
                let c = rate_bias(&self.z.t, slot.s);
                core::array::from_fn(|j| slot.mean[j] + c[j])
            });
            linearise_at(&prepared, &self.samples[k], offset.as_ref(), &mut self.cols, slot);
        }
    }

    /// Moves the reference geometry to the iterate's and re-linearises there at the smoothed
    /// drift (the slots must hold the smoothing at the iterate). Returns the mean squared change
    /// of the pose errors in units of the noise.
    fn relinearise(&mut self, ws: &mut [DriftSlot<N>]) -> f64 {
        let r = self.z.params(self.floor()).r;
        let before: f64 = ws[..self.ks]
            .iter()
            .map(|s| (0..6).map(|i| s.y[i] * s.y[i] / r[i]).sum::<f64>())
            .sum();
        self.g_ref = self.g_ref.perturbed(&self.z.x);
        self.z = self.z.with_static([0.0; P], self.z.t);
        self.linearise(ws, true);
        let after: f64 = ws[..self.ks]
            .iter()
            .map(|s| {
                let y = residual(s, &self.z.x, &self.z.t);
                (0..6).map(|i| y[i] * y[i] / r[i]).sum::<f64>()
            })
            .sum();
        (before - after).abs() / self.ks as f64
    }

    /// Filter and smoother at the iterate (the slots then hold the smoothed drift and `m2`).
    fn smooth_at_iterate(&mut self, ws: &mut [DriftSlot<N>]) -> Result<(f64, Stats<N>, [f64; P], Trend<N>), CalibError> {
        let par = self.z.params(self.floor());
        let sub = &mut ws[..self.ks];
        let ll = filter(sub, &self.z.x, &self.z.t, &par)?;
        let (st, gx, gt) = smooth::<N, P>(sub, &par)?;
        Ok((ll, st, gx, gt))
    }

    /// The objective changes (finer samples, the rate bias's prior refitted, a new
    /// linearisation): the likelihoods recorded from here on are comparable only with each other.
    fn new_objective(&mut self) {
        let at = self.history.len();
        if at > 0 && self.objectives.last() != Some(&at) {
            let _ = self.objectives.push(at);
        }
    }

    /// The likelihoods of the last objective (see [`DriftEmResult::objectives`]).
    fn last_objective(&self) -> &[f64] {
        &self.history[self.objectives.last().copied().unwrap_or(0)..]
    }

    /// ECME maps, accelerated, from the iterate until converged or out of maps (steps 2–4).
    /// `best` is the last accepted iterate (its likelihood known); `z` the next candidate,
    /// accepted when the filter pass that starts its map finds its likelihood no lower.
    fn run(&mut self, ws: &mut [DriftSlot<N>]) -> Result<(), CalibError> {
        let opts = *self.opts;
        let floor = self.floor();
        self.new_objective();
        self.converged = false;
        let mut z = self.z;
        let mut best: Option<(f64, Iterate<N, P>)> = None;
        let mut pre: Option<(Info<N, P>, Iterate<N, P>, Scale<N, P>)> = None;
        let mut step_max = STEP_MAX0;
        // After a rejected candidate: plain EM updates (monotone) for one map.
        let mut safe = false;
        let stale = |z: &Iterate<N, P>, pre: &Option<(Info<N, P>, Iterate<N, P>, Scale<N, P>)>| match pre {
            None => true,
            Some((_, at, _)) => z.change(at, &Scale::UNIT).1 > libm::log(1.0 + REFRESH),
        };
        // Maps since the last information pass, and whether the intensities were refitted at
        // the converged iterate.
        let mut since = 0;
        let mut checked = false;
        while self.iterations < opts.max_iterations {
            let ks = self.ks;
            if self.fitting && since >= PRIOR_REFRESH_MAPS {
                pre = None;
            }
            if stale(&z, &pre) {
                since = 0;
                // The exact information at the current drift parameters, and an exact step.
                let par = z.params(floor);
                let before = self.prior;
                let (_, info) = information(
                    &mut ws[..ks],
                    &z.x,
                    &par,
                    opts.rate_bias && (self.fitting || self.prior.iter().any(|v| *v > 0.0)),
                    self.fitting.then_some(&self.floor_prior),
                    &mut self.prior,
                    &mut self.statistic,
                    opts.rank_tolerance,
                )?;
                self.information_passes += 1;
                if self.prior != before {
                    // Another objective (the rate bias's prior is part of it).
                    best = None;
                    self.new_objective();
                }
                let (dx, t) = info.step();
                z = z.with_static(core::array::from_fn(|p| z.x[p] + dx[p]), t);
                let se = Scale::of(&info);
                pre = Some((info, z, se));
            }
            let Some((info, _, se)) = &pre else {
                return Err(degenerate("geometry information"));
            };
            let map = |z: &Iterate<N, P>,
                       sub: &mut [DriftSlot<N>],
                       ll: Option<f64>,
                       safe: bool|
             -> Result<(f64, Iterate<N, P>), CalibError> {
                let par = z.params(floor);
                let ll = match ll {
                    Some(ll) => ll,
                    None => filter(sub, &z.x, &z.t, &par)? + prior_ll(&info.prior(), &z.t),
                };
                let (st, gx, gt) = smooth::<N, P>(sub, &par)?;
                let new = m_step(&st, &par, sub.len(), floor, !safe);
                let gt = add_trend(&gt, &info.prior_gradient(&z.t));
                let (dx, dt) = info.solve(&gx, &gt);
                Ok((
                    ll,
                    Iterate::new(core::array::from_fn(|p| z.x[p] + dx[p]), add_trend(&z.t, &dt), &new),
                ))
            };
            let (ll0, z1) = map(&z, &mut ws[..ks], None, safe)?;
            self.iterations += 1;
            since += 1;
            if let Some((ll_b, z_b)) = best {
                if ll0 < ll_b {
                    z = z_b;
                    pre = None;
                    safe = true;
                    continue;
                }
                let (dg, dp) = z.change(&z_b, se);
                if dg < opts.se_tolerance && (dp < opts.param_tolerance || ll0 - ll_b <= opts.tolerance) {
                    // A drift faster than TAU_STEPS iterated steps is poorly told from white noise
                    // on the decimated samples: iterate on more of them (from the current
                    // estimate, linearised afresh at the reported angles).
                    let par = z.params(floor);
                    let tau_steps = par.phi.iter().fold(f64::INFINITY, |m, p| m.min(-1.0 / libm::log(*p)));
                    if self.stride > 1 && tau_steps < TAU_STEPS {
                        let finer = ((tau_steps * self.stride as f64 / (1.5 * TAU_STEPS)) as usize).clamp(1, self.stride - 1);
                        self.g_ref = self.g_ref.perturbed(&z.x);
                        let par = restride(&par, self.stride, finer);
                        self.stride = finer;
                        self.ks = self.kn.div_ceil(finer);
                        for s in ws[..self.ks].iter_mut() {
                            s.w = 1.0;
                        }
                        z = Iterate::new([0.0; P], z.t, &par);
                        self.z = z;
                        self.linearise(ws, false);
                        best = None;
                        pre = None;
                        self.new_objective();
                        continue;
                    }
                    if self.fitting && !checked && since > 0 {
                        // Refit the intensities at the converged drift once more.
                        checked = true;
                        pre = None;
                        continue;
                    }
                    let _ = self.history.push(ll0);
                    best = Some((ll0, z));
                    self.converged = true;
                    break;
                }
            }
            let _ = self.history.push(ll0);
            best = Some((ll0, z));
            if safe || stale(&z1, &pre) || self.iterations + 2 > opts.max_iterations {
                // Warming up (the drift parameters still move fast), or recovering: plain maps.
                safe = false;
                z = z1;
                continue;
            }
            let (ll1, z2) = map(&z1, &mut ws[..ks], None, false)?;
            self.iterations += 1;
            since += 1;
            if ll1 < ll0 {
                // The geometry step's information is stale after all: recompute it.
                pre = None;
                continue;
            }
            // SQUAREM: z' = z − 2α r + α² v with r = z1 − z, v = z2 − z1 − r; α = −1 gives z2.
            let r = z1.minus(&z);
            let v = z2.minus(&z1).minus(&r);
            let (nr, nv) = (libm::sqrt(r.norm2(se)), libm::sqrt(v.norm2(se)));
            let mut alpha = if nv > 0.0 { -(nr / nv) } else { -1.0 };
            alpha = alpha.min(-1.0).max(-step_max);
            if alpha == -step_max {
                step_max *= 4.0;
            }
            let mut next: Option<(f64, Iterate<N, P>)> = None;
            while alpha < -1.0 {
                let cand = z.combine(-2.0 * alpha, &r, alpha * alpha, &v);
                if cand.is_finite() {
                    let par = cand.params(floor);
                    if let Ok(ll_c) = filter(&mut ws[..ks], &cand.x, &cand.t, &par) {
                        let ll_c = ll_c + prior_ll(&info.prior(), &cand.t);
                        if ll_c >= ll1 {
                            next = Some((ll_c, cand));
                            break;
                        }
                    }
                }
                alpha = (alpha - 1.0) / 2.0;
                if alpha > -1.01 {
                    alpha = -1.0;
                }
            }
            // The stabilising map from the extrapolated point (its filter pass is done), or the
            // plain one from z2.
            let (cand, ll_c) = match next {
                Some((ll_c, cand)) => (cand, Some(ll_c)),
                None => (z2, None),
            };
            let (_, z_new) = map(&cand, &mut ws[..ks], ll_c, false)?;
            self.iterations += 1;
            since += 1;
            z = z_new;
        }
        // Out of maps before any was accepted: the iterate stays where it got to.
        self.z = best.map_or(z, |(_, z)| z);
        Ok(())
    }

    /// The restricted (REML) drift parameters: fixed-point iterations of the M-step whose
    /// second moments of each joint's drift include what the uncertainty of the θ offsets adds
    /// to them, `Σ_k (C̃_k V C̃_kᵀ)_jj` ([`restricted_moments`]): maximum likelihood fixes the
    /// offsets at their estimate, which absorbs the slowest part of the drift, so its τ and σ
    /// come out low when τ is not small against the session. Each iteration: the information
    /// (the offsets' covariance `V`, an exact static step, the rate bias's intensities), the
    /// sensitivity pass, one filter + smoother pass, the corrected M-step.
    fn restricted(&mut self, ws: &mut [DriftSlot<N>]) -> Result<(), CalibError> {
        let floor = self.floor();
        for _ in 0..REML_ITERATIONS {
            let ks = self.ks;
            let par = self.z.params(floor);
            // The information at every iteration: held for even a 5% move of τ and σ, it left
            // slow drift (τ 10 s) stating 1.08 / 1.32 of what it reached instead of 0.85 / 1.06.
            let (_, info) = information(
                &mut ws[..ks],
                &self.z.x,
                &par,
                self.opts.rate_bias && self.prior.iter().any(|v| *v > 0.0),
                None,
                &mut self.prior,
                &mut self.statistic,
                self.opts.rank_tolerance,
            )?;
            self.information_passes += 1;
            let (dx, t) = info.step();
            self.z = self.z.with_static(core::array::from_fn(|p| self.z.x[p] + dx[p]), t);
            let v = drift_visible_covariance(&ws[..ks], &par, &info);
            let extra = restricted_moments(&mut ws[..ks], &par, &v)?;
            let (_, mut st, _, _) = self.smooth_at_iterate(ws)?;
            self.iterations += 1;
            for j in 0..N {
                st.e0[j] += extra.e0[j];
                st.s00[j] += extra.s00[j];
                st.s10[j] += extra.s10[j];
                st.s11[j] += extra.s11[j];
            }
            let new = m_step(&st, &par, ks, floor, true);
            let next = Iterate::new(self.z.x, self.z.t, &new);
            // Converged when τ and σ settle (the pose noise creeps on noise-free data, where the
            // likelihood is flat along it).
            let change = (0..N).fold(0.0f64, |m, j| {
                m.max((next.lphi[j] - self.z.lphi[j]).abs())
                    .max((next.lq[j] - self.z.lq[j]).abs())
            });
            self.z = next;
            if change < self.opts.param_tolerance {
                break;
            }
        }
        Ok(())
    }
}

/// The covariance of the static geometry's error as the drift sees it: `Π V Πᵀ` (N × N), with
/// `V` the geometry's covariance and `Π = (Σ Jᵀ R⁻¹ J)⁻¹ Σ Jᵀ R⁻¹ H` the least-squares map of a
/// parameter change to the constant drift that explains the same pose errors (`Π` is the
/// identity on the θ offsets). A θ offset that is poorly determined because it trades off
/// against other parameters moves the drift much less than its own variance says: the other
/// parameters' share of the same error compensates. [`Iteration::restricted`] pushes this
/// through the smoother's exact sensitivity to the θ offsets.
fn drift_visible_covariance<const N: usize, const P: usize>(
    slots: &[DriftSlot<N>],
    par: &Params<N>,
    info: &Info<N, P>,
) -> [[f64; N]; N] {
    let mut jj = [[0.0; N]; N];
    let mut jh = [[0.0; P]; N];
    for slot in slots {
        for i in 0..6 {
            let w = slot.w / par.r[i];
            let h = &slot.h[i][3];
            let row = slot.h[i].as_flattened();
            for a in 0..N {
                let ha = w * h[a];
                for (x, hb) in jj[a].iter_mut().zip(h) {
                    *x += ha * hb;
                }
                for (x, hp) in jh[a].iter_mut().zip(row) {
                    *x += ha * hp;
                }
            }
        }
    }
    // Π = JJ⁻¹ JH by Cholesky, column by column of JH.
    let Some(chol) = cholesky(&jj) else {
        return [[0.0; N]; N];
    };
    let mut pi = [[0.0; P]; N];
    for p in 0..P {
        let col = cholesky_solve(&chol, &core::array::from_fn(|a| jh[a][p]));
        for a in 0..N {
            pi[a][p] = col[a];
        }
    }
    // Π V Πᵀ: V Πᵀ column a is the geometry covariance times Π's row a.
    let mut out = [[0.0; N]; N];
    for a in 0..N {
        let (vpa, _) = info.solve(&pi[a], &[[0.0; M]; N]);
        for b in 0..N {
            out[b][a] = pi[b].iter().zip(&vpa).map(|(x, y)| x * y).sum();
        }
    }
    out
}

/// Lower Cholesky factor of a small symmetric positive definite matrix.
fn cholesky<const K: usize>(a: &[[f64; K]; K]) -> Option<[[f64; K]; K]> {
    let mut l = [[0.0; K]; K];
    for i in 0..K {
        for j in 0..=i {
            let s = a[i][j] - l[i][..j].iter().zip(&l[j][..j]).map(|(x, y)| x * y).sum::<f64>();
            if i == j {
                if !(s > 0.0 && s.is_finite()) {
                    return None;
                }
                l[i][i] = libm::sqrt(s);
            } else {
                l[i][j] = s / l[j][j];
            }
        }
    }
    Some(l)
}

/// `A⁻¹ b` from [`cholesky`]'s factor.
fn cholesky_solve<const K: usize>(l: &[[f64; K]; K], b: &[f64; K]) -> [f64; K] {
    let mut z = *b;
    for i in 0..K {
        for k in 0..i {
            z[i] -= l[i][k] * z[k];
        }
        z[i] /= l[i][i];
    }
    for i in (0..K).rev() {
        for k in i + 1..K {
            z[i] -= l[k][i] * z[k];
        }
        z[i] /= l[i][i];
    }
    z
}

fn add_trend<const N: usize>(a: &Trend<N>, b: &Trend<N>) -> Trend<N> {
    core::array::from_fn(|j| core::array::from_fn(|m| a[j][m] + b[j][m]))
}

/// Runs our EM from the geometry `start` (normally the LS result).
///
/// `workspace` needs one slot per sample; on return it holds the smoothed drift trajectory.
/// `P` must be `4N` (checked at compile time).
pub fn em_drift<const N: usize, const P: usize>(
    start: &DhTable<N>,
    samples: &[Sample<N>],
    opts: &DriftEmOptions<N>,
    workspace: &mut [DriftSlot<N>],
) -> Result<DriftEmResult<N>, CalibError> {
    const { assert!(P == 4 * N, "P must be 4N") };
    if !start.is_finite() {
        return Err(CalibError::InvalidInput { what: "starting table" });
    }
    let valid = positive(opts.dt)
        && positive(opts.tolerance)
        && positive(opts.param_tolerance)
        && positive(opts.se_tolerance)
        && positive(opts.initial_tau)
        && positive(opts.initial_drift_std)
        && positive(opts.initial_noise_std)
        && positive(opts.noise_floor)
        && positive(opts.rank_tolerance)
        && positive(opts.max_discounted_share)
        && positive(opts.max_inconsistency)
        && positive(opts.max_jump)
        && opts.max_stride > 0
        && opts.max_iterations > 0
        && opts.max_iterations < MAX_EM_ITERATIONS;
    if !valid {
        return Err(CalibError::InvalidInput { what: "DriftEmOptions" });
    }
    validate_samples(samples, &opts.checks)?;
    if samples.len() < 2 {
        return Err(CalibError::TooFewSamples {
            got: samples.len(),
            need: 2,
        });
    }
    if workspace.len() < samples.len() {
        return Err(CalibError::WorkspaceTooSmall {
            got: workspace.len(),
            need: samples.len(),
        });
    }
    let kn = samples.len();
    let stride = (kn / MIN_ITERATION_SAMPLES).clamp(1, opts.max_stride);
    let dt_s = opts.dt * stride as f64;
    let phi0 = libm::exp(-dt_s / opts.initial_tau);
    let par0 = Params {
        phi: [phi0; N],
        q: [opts.initial_drift_std * opts.initial_drift_std * (1.0 - phi0 * phi0); N],
        r: [opts.initial_noise_std * opts.initial_noise_std; 6],
    };
    for slot in workspace[..kn].iter_mut() {
        slot.w = 1.0;
        slot.mean = [0.0; N];
    }
    let seconds = (kn - 1) as f64 * opts.dt;
    let floor_prior: TrendPrior = if opts.rate_bias {
        opts.rate_bias_spec.intensities(seconds)
    } else {
        [0.0; M]
    };
    let mut it = Iteration::<N, P> {
        samples,
        opts,
        kn,
        stride,
        ks: kn.div_ceil(stride),
        g_ref: *start,
        // The rate-bias model is fitted first, from a rate bias as large as the starting drift:
        // started from none, the drift's τ and σ grow to absorb a ramp before the intensities
        // are ever refitted, and the model never sees it.
        prior: if opts.rate_bias {
            let spec = floor_prior;
            core::array::from_fn(|m| spec[m].max(opts.initial_drift_std * opts.initial_drift_std))
        } else {
            [0.0; M]
        },
        statistic: f64::NAN,
        fitting: opts.rate_bias,
        floor_prior,
        z: Iterate::new([0.0; P], [[0.0; M]; N], &par0),
        history: heapless::Vec::new(),
        objectives: heapless::Vec::new(),
        iterations: 0,
        information_passes: 0,
        converged: false,
        cols: [[Vector6::zeros(); N]; 4],
    };

    // 1–4 (the rate bias's intensities refitted at every information pass), then the
    // reference's weights and the re-linearisation, each followed by the iteration again when it
    // changed something.
    it.linearise(workspace, false);
    let mut dof = f64::INFINITY;
    let mut reweights = 0;
    let mut relinearisations = 0;
    loop {
        it.run(workspace)?;
        let mut again = false;
        let relinearise = relinearisations < opts.relinearisations && it.iterations < opts.max_iterations;
        if opts.robust && !dof.is_finite() {
            // The first weights from the robust filter (a glitch discounted before it moves the
            // drift), then the smoother's.
            let par = it.z.params(it.floor());
            let sub = &mut workspace[..it.ks];
            filter_robust(sub, &it.z.x, &it.z.t, &par, DOF_START)?;
            smooth::<N, P>(sub, &par)?;
            // The iteration ran at weight 1: the change is measured from there.
            for s in sub.iter_mut() {
                s.w = 1.0;
            }
            it.iterations += 1;
        } else if opts.robust || relinearise {
            it.smooth_at_iterate(workspace)?;
            it.iterations += 1;
        }
        if opts.robust {
            dof = fit_dof(&workspace[..it.ks]);
            reweights += 1;
            if reweight(&mut workspace[..it.ks], dof) > REWEIGHT_TOLERANCE && reweights < MAX_REWEIGHTS {
                again = true;
            }
        }
        if relinearise {
            relinearisations += 1;
            if it.relinearise(workspace) > 1e-3 {
                again = true;
            }
        }
        if !again || it.iterations >= opts.max_iterations {
            break;
        }
    }
    if it.fitting {
        // The model choice: the rate bias stays when the data support it, else the drift is the
        // paper's Gauss-Markov and its parameters are fitted again without it.
        it.fitting = false;
        let spec = it.floor_prior.iter().any(|v| *v > 0.0);
        let supported = it.statistic > threshold_of(kn, &it.prior) && it.prior.iter().any(|v| *v > 0.0);
        if !spec && !supported {
            let had = it.prior.iter().any(|v| *v > 0.0);
            it.prior = [0.0; M];
            it.z = it.z.with_static(it.z.x, [[0.0; M]; N]);
            if had {
                it.run(workspace)?;
            }
        }
    }
    if opts.restricted {
        it.restricted(workspace)?;
    }
    let converged = it.converged;
    if !converged && opts.require_convergence {
        let h = it.last_objective();
        let last = h.last().copied().unwrap_or(0.0);
        let prev = h.iter().rev().nth(1).copied().unwrap_or(last);
        return Err(CalibError::NotConverged {
            iterations: it.iterations,
            last_change: (last - prev).abs() / last.abs().max(1.0),
        });
    }
    finish(it, workspace, dof, relinearisations)
}

/// Step 5: every sample, at the iterated geometry and drift parameters (at the step Δt),
/// linearised at the smoothed drift; the final table, its bound, the model choice's and the
/// consistency's share of the stated error, the discounted samples and the refusals.
fn finish<const N: usize, const P: usize>(
    it: Iteration<'_, N, P>,
    workspace: &mut [DriftSlot<N>],
    dof: f64,
    relinearisations: usize,
) -> Result<DriftEmResult<N>, CalibError> {
    let (opts, samples, kn, stride) = (it.opts, it.samples, it.kn, it.stride);
    let mut cols = it.cols;
    let par = restride(&it.z.params(opts.noise_floor), stride, 1);
    let g1 = it.g_ref.perturbed(&it.z.x);
    let t = it.z.t;
    let last = (kn - 1).max(1) as f64;
    let prepared = g1.prepare();
    let relinearised = relinearisations > 0;
    // Linearise every sample at the iterated samples' smoothed drift (interpolated) and the
    // rate bias: from the last sample down, so that the iterated slots a sample needs (its own
    // index divided by the stride, and the next) are read before they are overwritten.
    for k in (0..kn).rev() {
        let s = k as f64 / last;
        let offset: Option<[f64; N]> = relinearised.then(|| {
            let (i, f) = (k / stride, (k % stride) as f64 / stride as f64);
            let a = workspace[i].mean;
            let b = if f > 0.0 && i + 1 < it.ks { workspace[i + 1].mean } else { a };
            let c = rate_bias(&t, s);
            core::array::from_fn(|j| (1.0 - f) * a[j] + f * b[j] + c[j])
        });
        let slot = &mut workspace[k];
        slot.s = s;
        slot.w = 1.0;
        linearise_at(&prepared, &samples[k], offset.as_ref(), &mut cols, slot);
    }
    let ws = &mut workspace[..kn];
    let x0 = [0.0; P];
    // A reference the iteration found Gaussian (ν at the top of its range: no glitch among the
    // iterated samples) keeps weight 1 on every sample.
    let robust = opts.robust && dof < GAUSSIAN_DOF;
    if robust || relinearised {
        // Every sample's weight (the robust filter's, then the smoother's), and its own smoothed
        // drift to re-linearise at.
        if robust {
            filter_robust(ws, &x0, &t, &par, dof)?;
        } else {
            filter(ws, &x0, &t, &par)?;
        }
        smooth::<N, P>(ws, &par)?;
        if robust {
            reweight(ws, dof);
        }
        if relinearised {
            for (k, slot) in ws.iter_mut().enumerate() {
                let c = rate_bias(&t, slot.s);
                let a: [f64; N] = core::array::from_fn(|j| slot.mean[j] + c[j]);
                let mut fresh = *slot;
                linearise_at(&prepared, &samples[k], Some(&a), &mut cols, &mut fresh);
                // The pseudo-measurement is relative to the reported angles: keep `e`, `h` of the
                // new point, the weight and time of the old.
                slot.e = fresh.e;
                slot.h = fresh.h;
            }
        }
    }
    // The final information at the static parameters (0, 0), the rate bias's columns
    // accumulated: the step is the absolute rate bias. Its intensities and `2 Δ ln L` are
    // refitted on every sample, and the model chosen again.
    let zero_t = [[0.0; M]; N];
    // The rate bias's columns where its model is in or could be (its weight as the other model
    // at least 1%): where the session's 2 Δ ln L was far below the threshold, the paper's model
    // is kept without them.
    let trend = opts.rate_bias && (it.prior.iter().any(|v| *v > 0.0) || it.statistic > rate_bias_threshold(kn, 1) - 9.2);
    // The consider allowance needs the rate bias's columns too (accumulated, not fitted).
    let considered = opts.consider.intensities(last * opts.dt);
    let considering = considered.iter().any(|v| *v > 0.0);
    let (_, acc) = accumulate(ws, &x0, &zero_t, &par, trend || considering)?;
    let spec = it.floor_prior.iter().any(|v| *v > 0.0);
    let ln_k = libm::log(kn.max(2) as f64);
    let (fitted, statistic) = match trend
        .then(|| acc.choose_prior(opts.rank_tolerance, &it.floor_prior, ln_k))
        .flatten()
    {
        Some((v, lr)) => (v, lr),
        None => ([0.0; M], if opts.rate_bias { it.statistic } else { f64::NAN }),
    };
    let threshold = threshold_of(kn, &fitted);
    let rich = (spec || statistic > threshold) && fitted.iter().any(|v| *v > 0.0);
    let prior = if rich { fitted } else { [0.0; M] };
    let info = match acc.analyse(&prior, opts.rank_tolerance) {
        Some(a) => a,
        None => qr_information(ws, &par, opts.rank_tolerance)?,
    };
    let rich = info.prior().iter().any(|v| *v > 0.0);
    let (step, rate) = info.step();
    let table = g1.perturbed(&step);
    let final_ll = filter(ws, &step, &rate, &par)?;
    smooth::<N, P>(ws, &par)?;
    let (check_ll, inn) = consistency(ws, &par)?;
    debug_assert!(check_ll == final_ll || !check_ll.is_finite());

    // Model choice: the other model's weight, and its table and covariance where it matters.
    let (crb_x, _) = info.std_errors();
    let other_weight = if statistic.is_finite() && !spec {
        let w = rich_weight(statistic, threshold);
        if rich {
            1.0 - w
        } else {
            w
        }
    } else {
        0.0
    };
    let mut alternative: Option<(f64, Info<N, P>, [f64; P])> = None;
    if other_weight > 1e-3 && fitted.iter().any(|v| *v > 0.0) {
        let other = if rich { [0.0; M] } else { fitted };
        if let Some(alt) = acc.analyse(&other, opts.rank_tolerance) {
            let (s_alt, _) = alt.step();
            let dx: [f64; P] = core::array::from_fn(|p| s_alt[p] - step[p]);
            alternative = Some((other_weight, alt, dx));
        }
    }
    let duration = last * opts.dt;
    let models: [JointDrift; N] = core::array::from_fn(|j| {
        let mut m = JointDrift {
            model: DriftModel::GaussMarkov,
            statistic,
            threshold,
            by_spec: spec && rich,
            other_weight,
            rate: [0.0; 2],
            angle: 0.0,
            angle_se: 0.0,
        };
        if rich {
            m.model = DriftModel::RateBias;
            // c(s) = t1 s + t2 s²: rate c'(s)/T at s = 0 and 1.
            m.rate = [rate[j][0] / duration, (rate[j][0] + 2.0 * rate[j][1]) / duration];
            m.angle = rate[j][0] + rate[j][1];
            let v = info.trend_covariance(j);
            m.angle_se = libm::sqrt(v.as_flattened().iter().sum::<f64>().max(0.0));
        }
        m
    });

    // Consistency: per joint, its normalised drift innovations' long-run variance and largest
    // value; per pose component, its standardised innovations'.
    let joints: [JointConsistency; N] = core::array::from_fn(|j| {
        let JointInnovations {
            long_run,
            lag1,
            largest,
            at,
        } = inn.joints[j];
        JointConsistency {
            long_run,
            lag1,
            largest,
            at,
        }
    });
    let consistency = Consistency {
        joints,
        pose_nis: inn.pose_nis,
        pose_long_run: inn.pose_long_run,
        blocks: inn.blocks,
    };

    let poses = || opts.error_poses.of(samples);
    let expected_error = expected_table_error::<N, P>(&table, poses(), |u| info.an.variance_along(u));
    // The consider allowance, where the chosen model leaves the rate bias out (at that model's
    // weight where the other one is mixed in).
    let keep = 1.0 - alternative.as_ref().map_or(0.0, |(w, _, _)| *w);
    let allowance = expected_table_error::<N, P>(&table, poses(), |u| {
        if rich || !considering {
            0.0
        } else {
            keep * acc.consider_variance(&info.an, u, &considered)
        }
    });
    let stated_error = expected_table_error::<N, P>(&table, poses(), |u| {
        let v0 = info.an.variance_along(u);
        let mut v = v0;
        if let Some((w, alt, dx)) = &alternative {
            let d: f64 = u.iter().zip(dx).map(|(a, b)| a * b).sum();
            v += w * (alt.an.variance_along(u) - v0) + w * (1.0 - w) * d * d;
        }
        v
    });

    // Discounted samples, in runs.
    let mut discounted = Discounted {
        count: 0,
        samples: kn,
        runs: heapless::Vec::new(),
        more_runs: false,
        dof: if opts.robust { dof } else { f64::INFINITY },
    };
    for k in discounted_samples(ws) {
        discounted.count += 1;
        match discounted.runs.last_mut() {
            Some(run) if run.1 + 1 == k => run.1 = k,
            _ => {
                if discounted.runs.push((k, k)).is_err() {
                    discounted.more_runs = true;
                }
            }
        }
    }
    let mut refusals: heapless::Vec<Refusal, MAX_REFUSALS> = heapless::Vec::new();
    if discounted.share() > opts.max_discounted_share {
        let _ = refusals.push(Refusal::TooManyDiscounted {
            count: discounted.count,
            samples: kn,
            limit: opts.max_discounted_share,
        });
    }
    for (j, c) in joints.iter().enumerate() {
        if c.largest > opts.max_jump {
            let _ = refusals.push(Refusal::Jump {
                joint: j,
                sample: c.at,
                sigma: c.largest,
            });
        }
        if c.long_run > opts.max_inconsistency {
            let _ = refusals.push(Refusal::Inconsistent {
                joint: j,
                long_run: c.long_run,
                limit: opts.max_inconsistency,
            });
        }
    }

    let t_total = kn as f64 * opts.dt;
    let drift: [DriftParams; N] = core::array::from_fn(|j| DriftParams::from_discrete(par.phi[j], par.q[j], opts.dt));
    Ok(DriftEmResult {
        table,
        phi: par.phi,
        process_variance: par.q,
        drift,
        measurement_variance: par.r,
        separability: core::array::from_fn(|j| drift[j].stationary_sigma * libm::sqrt(2.0 * drift[j].tau / t_total)),
        log_likelihood: it.history,
        objectives: it.objectives,
        final_log_likelihood: final_ll,
        stride,
        iterations: it.iterations,
        information_passes: it.information_passes,
        relinearisations,
        converged: it.converged,
        rank: info.an.rank,
        std_errors: core::array::from_fn(|k| core::array::from_fn(|j| crb_x[k * N + j])),
        expected_error,
        stated_error,
        allowance,
        models,
        rate_bias: rate,
        discounted,
        consistency,
        refusals,
    })
}

/// The Cramér-Rao bound of the `4N` geometric parameters at a *known* table, drift and noise
/// (e.g. the truth of a simulation): the exact Fisher information with the drift trajectory
/// integrated out (the two-stage filter of [`em_drift`], O(K)), as an [`Analysis`] whose
/// [`Analysis::variance_along`] / [`Analysis::std_errors`]`(1.0)` give the bound. Per joint the
/// drift is `φ_j = e^{−Δt/τ_j}` with process variance `q_j`; `r` is the pose-noise variance
/// per component (m², rad²), floored at `noise_floor` (a noise-free pose keeps a finite bound).
pub fn cramer_rao<const N: usize, const P: usize>(
    table: &DhTable<N>,
    samples: &[Sample<N>],
    phi: [f64; N],
    q: [f64; N],
    r: [f64; 6],
    noise_floor: f64,
) -> Result<Analysis<P>, CalibError> {
    const { assert!(P == 4 * N, "P must be 4N") };
    let valid = phi.iter().all(|p| (0.0..1.0).contains(p)) && q.iter().all(|v| positive(*v)) && r.iter().all(|v| *v >= 0.0);
    if !(valid && positive(noise_floor) && table.is_finite()) {
        return Err(CalibError::InvalidInput {
            what: "cramer_rao drift or noise",
        });
    }
    let par = Params {
        phi,
        q,
        r: r.map(|v| v.max(noise_floor)),
    };
    let prepared = table.prepare();
    let mut cols = [[Vector6::zeros(); N]; 4];
    let mut slot = DriftSlot::<N>::default();
    let mut gram = crate::linalg::GramAccumulator::<P>::new();
    let mut ts = TwoStage::<N, P>::new(&par, false);
    for s in samples {
        crate::kalman::linearise_into(&prepared, s, &mut cols, &mut slot);
        ts.absorb(&slot.e, &slot.h, 0.0, 1.0, &par, &mut |rows, _, rhs| {
            gram.add_rows(rows, rhs, 0)
        })?;
    }
    if let Some(analysis) = gram.analyse(1e-12) {
        return Ok(analysis);
    }
    let mut qr = QrAccumulator::<P>::new();
    let mut ts = TwoStage::<N, P>::new(&par, false);
    for s in samples {
        crate::kalman::linearise_into(&prepared, s, &mut cols, &mut slot);
        ts.absorb(&slot.e, &slot.h, 0.0, 1.0, &par, &mut |rows, _, rhs| {
            for (row, y) in rows.iter().zip(rhs) {
                qr.add_row(row, *y);
            }
        })?;
    }
    Ok(qr.analyse(1e-12))
}

/// [`em_drift`] with an allocated workspace; returns the result and the smoothed drift.
#[cfg(any(test, feature = "std"))]
pub fn em_drift_vec<const N: usize, const P: usize>(
    start: &DhTable<N>,
    samples: &[Sample<N>],
    opts: &DriftEmOptions<N>,
) -> Result<(DriftEmResult<N>, std::vec::Vec<[f64; N]>), CalibError> {
    let mut ws = std::vec![DriftSlot::default(); samples.len()];
    let r = em_drift::<N, P>(start, samples, opts, &mut ws)?;
    Ok((r, ws.iter().take(samples.len()).map(DriftSlot::drift).collect()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ls::{identify_ls, LsOptions};
    use crate::metrics::{objective_y, objective_y_corrected, ParamErrors};
    use crate::sim::{Scenario, ScenarioConfig, SimSample};

    fn session(seed: u64, k: usize) -> std::vec::Vec<SimSample<7>> {
        Scenario::new(ScenarioConfig::paper(), seed).take(k).collect()
    }

    #[test]
    fn likelihood_never_decreases_and_drift_is_tracked() {
        let sim = session(21, 1500);
        let samples: std::vec::Vec<_> = sim.iter().map(|s| s.sample).collect();
        let ls = identify_ls::<7, 28>(&DhTable::paper_nominal(), &samples, &LsOptions::paper()).unwrap();
        let opts = DriftEmOptions {
            max_iterations: 25,
            ..DriftEmOptions::new(0.01)
        };
        let (r, drift) = em_drift_vec::<7, 28>(&ls.table, &samples, &opts).unwrap();
        for w in r.last_objective().windows(2) {
            assert!(w[1] >= w[0] - 1e-9 * w[0].abs(), "{} -> {}", w[0], w[1]);
        }
        let y_ls = objective_y(&ls.table, &samples);
        let y_em = objective_y_corrected(&r.table, &samples, |k| drift[k]);
        assert!(y_em < 0.1 * y_ls, "in-sample y: LS {y_ls}, EM {y_em}");
        // The smoothed drift follows the true one. Not exactly: a 7-joint arm seen through a
        // 6-vector pose has a one-dimensional self-motion at every sample, which only the
        // Gauss-Markov prior constrains.
        let err: f64 = sim
            .iter()
            .zip(&drift)
            .map(|(s, d)| (0..7).map(|j| (s.drift[j] - d[j]).powi(2)).sum::<f64>())
            .sum();
        let tot: f64 = sim.iter().map(|s| s.drift.iter().map(|d| d * d).sum::<f64>()).sum();
        assert!(err < 0.4 * tot, "drift tracking error {err} of {tot}");
        let pe = ParamErrors::between(&r.table, &DhTable::paper_actual());
        let pl = ParamErrors::between(&ls.table, &DhTable::paper_actual());
        assert!(pe.a < pl.a && pe.alpha < pl.alpha, "EM {pe:?} vs LS {pl:?}");
        for j in 0..7 {
            assert!(r.separability[j] > 0.0 && r.drift[j].tau > 0.0);
        }
    }

    #[test]
    fn recovers_tau_sigma_and_noise_of_an_exact_gauss_markov_drift() {
        // Exact discretisation, τ = 0.5 s, σ = 10 mrad, with 0.5 mm / 1 mrad pose noise, 40 s.
        let mut cfg = ScenarioConfig::paper();
        cfg.drift = crate::GaussMarkov {
            tau: 0.5,
            sigma: 0.01,
            discretisation: crate::Discretisation::Exact,
            ..cfg.drift
        };
        cfg.position_noise = 5e-4;
        cfg.rotation_noise = 1e-3;
        let samples: std::vec::Vec<_> = Scenario::new(cfg, 77).take(4000).map(|s| s.sample).collect();
        let ls = identify_ls::<7, 28>(&DhTable::paper_nominal(), &samples, &LsOptions::paper()).unwrap();
        let (r, _) = em_drift_vec::<7, 28>(&ls.table, &samples, &DriftEmOptions::new(0.01)).unwrap();
        let mean = |f: &dyn Fn(&DriftParams) -> f64| r.drift.iter().map(f).sum::<f64>() / 7.0;
        let (tau, sigma) = (mean(&|d| d.tau), mean(&|d| d.stationary_sigma));
        assert!((tau - 0.5).abs() < 0.15, "τ {tau}");
        assert!((sigma - 0.01).abs() < 0.002, "σ {sigma}");
        let v = r.measurement_variance;
        for i in 0..3 {
            assert!(
                (v[i].sqrt() - 5e-4).abs() < 1e-4 && (v[i + 3].sqrt() - 1e-3).abs() < 2e-4,
                "noise {v:?}"
            );
        }
    }

    #[test]
    fn bad_inputs_are_typed_errors() {
        let samples: std::vec::Vec<_> = session(1, 200).iter().map(|s| s.sample).collect();
        let start = DhTable::paper_nominal();
        let opts = DriftEmOptions::new(0.01);
        let mut ws = std::vec![DriftSlot::default(); 100];
        assert_eq!(
            em_drift::<7, 28>(&start, &samples, &opts, &mut ws).unwrap_err(),
            CalibError::WorkspaceTooSmall { got: 100, need: 200 }
        );
        for bad in [
            DriftEmOptions { dt: 0.0, ..opts },
            DriftEmOptions {
                initial_tau: f64::NAN,
                ..opts
            },
            DriftEmOptions {
                noise_floor: -1.0,
                ..opts
            },
            DriftEmOptions {
                max_iterations: MAX_EM_ITERATIONS,
                ..opts
            },
        ] {
            assert_eq!(
                em_drift_vec::<7, 28>(&start, &samples, &bad).unwrap_err(),
                CalibError::InvalidInput { what: "DriftEmOptions" }
            );
        }
        let mut nan_start = start;
        nan_start.rows[3].alpha = f64::NAN;
        assert!(matches!(
            em_drift_vec::<7, 28>(&nan_start, &samples, &opts),
            Err(CalibError::InvalidInput { .. })
        ));
        let mut nan = samples.clone();
        nan[9].joints[0] = f64::NAN;
        assert_eq!(
            em_drift_vec::<7, 28>(&start, &nan, &opts).unwrap_err(),
            CalibError::NonFinite { sample: 9 }
        );
        assert!(matches!(
            em_drift_vec::<7, 28>(&start, &samples[..3], &opts),
            Err(CalibError::TooFewSamples { .. })
        ));
        let still: std::vec::Vec<_> = (0..50).map(|_| samples[0]).collect();
        assert!(matches!(
            em_drift_vec::<7, 28>(&start, &still, &opts),
            Err(CalibError::NoExcitation { .. })
        ));
        let strict = DriftEmOptions {
            max_iterations: 1,
            require_convergence: true,
            ..opts
        };
        assert!(matches!(
            em_drift_vec::<7, 28>(&start, &samples, &strict),
            Err(CalibError::NotConverged { .. })
        ));
    }
}

#[cfg(test)]
mod cost {
    use super::*;
    use crate::ls::{identify_ls, LsOptions};
    use crate::sim::{Scenario, ScenarioConfig};

    /// Seconds since an arbitrary start (wall clock: on a shared machine, take the best of
    /// several runs).
    fn cpu_seconds() -> f64 {
        use std::sync::OnceLock;
        static START: OnceLock<std::time::Instant> = OnceLock::new();
        START.get_or_init(std::time::Instant::now).elapsed().as_secs_f64()
    }

    /// LS + our EM at K = 6,000 (the paper scenario, seed 1, 60 s), the paper's model alone and
    /// the full one, best of 5 (print only: `cargo test -p calib-core
    /// --release em_cost_at_k_6000 -- --ignored --nocapture`).
    #[test]
    #[ignore]
    fn em_cost_at_k_6000() {
        let samples: std::vec::Vec<_> = Scenario::new(ScenarioConfig::paper(), 1)
            .take(6000)
            .map(|s| s.sample)
            .collect();
        for (name, opts) in [
            ("plain", DriftEmOptions::plain(0.01)),
            ("issue 30", DriftEmOptions::new(0.01)),
        ] {
            let (mut ls_best, mut em_best) = (f64::INFINITY, f64::INFINITY);
            let mut ws = std::vec![DriftSlot::default(); samples.len()];
            let mut last = None;
            for _ in 0..5 {
                let t0 = cpu_seconds();
                let ls = identify_ls::<7, 28>(&DhTable::paper_nominal(), &samples, &LsOptions::paper()).unwrap();
                let t1 = cpu_seconds();
                let em = em_drift::<7, 28>(&ls.table, &samples, &opts, &mut ws).unwrap();
                let t2 = cpu_seconds();
                ls_best = ls_best.min(t1 - t0);
                em_best = em_best.min(t2 - t1);
                last = Some(em);
            }
            let em = last.unwrap();
            std::eprintln!(
                "{name}: LS {:.1} ms, EM {:.1} ms ({} maps, {} informations, stride {})",
                ls_best * 1e3,
                em_best * 1e3,
                em.iterations,
                em.information_passes,
                em.stride
            );
        }
    }
}
