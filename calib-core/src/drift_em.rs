//! Our EM: the drift as a time series (Kalman filter + Rauch-Tung-Striebel smoother).
//!
//! # Model
//! Linearised at the current geometry G, the pose error of sample k is
//! `e_k = H_k Δg + J_k δ_k + v_k`, with H_k the `6 × 4N` residual Jacobian, J_k its θ block,
//! `v_k ~ N(0, diag(r))` and, per joint j, the Gauss-Markov drift
//! `δ_{k+1,j} = φ_j δ_{k,j} + ρ`, `ρ ~ N(0, q_j)`, `δ_{0,j} ~ N(0, q_j / (1 − φ_j²))`.
//! The estimate is the maximum of the exact likelihood `p(e_1..K | G, φ, q, r)` (the drift
//! integrated out); the per-sample kernels are in the private `kalman` module.
//!
//! # Iteration
//! 1. **Iterate on every `stride`-th sample** (at most [`DriftEmOptions::max_stride`], and at
//!    least [`MIN_ITERATION_SAMPLES`] of them): the drift of a decimated session is the same
//!    Gauss-Markov process at the step `stride·Δt`, so φ, q and r are estimated from it at a
//!    fraction of the cost; the table is fitted on every sample at the end (5.). The iterated
//!    samples are linearised once; the geometry is an offset `x` from that linearisation. A
//!    drift faster than [`TAU_STEPS`] iterated steps is hard to tell from white pose noise on
//!    decimated samples: when the iteration converges with such a τ, it goes on at a smaller
//!    stride (from where it is).
//! 2. **ECME map.** One filter + smoother pass at `(x, φ, q, r)` gives the likelihood, the
//!    M-step of φ and q (per joint, a 1-D profile search of the expected complete-data
//!    log-likelihood with the stationary prior of δ_0), the noise update and the exact
//!    gradient of the log-likelihood in `x`, `Hᵀ R⁻¹ (y − J E[δ])`. The noise update is EM's
//!    `r = Σ E[(y − Jδ)²] / K` corrected for the leverage of the drift, `r = Σ res² / (K − Σ
//!    Var[Jδ] / r)`: the same fixed point, reached at once where EM creeps (with small noise
//!    the drift absorbs nearly all of each sample's residual). The geometry step is the
//!    gradient times the inverse of the exact information `Hᵀ Σ⁻¹ H` from the two-stage
//!    (Friedland) filter that carries `x` in the drift mean; that information is recomputed,
//!    with an exact step, whenever a drift parameter has moved by more than a factor
//!    `1 + `[`REFRESH`] since, or a map lowered the likelihood.
//! 3. **SQUAREM** (Varadhan & Roland 2008) extrapolates two maps at a time along the slow
//!    directions, in coordinates scaled by standard errors (`x`) and logarithms (φ, q, r). Every
//!    iterate is accepted only if its likelihood is no lower than the last accepted one
//!    (otherwise the iteration returns to it with fresh information and a plain EM update), so
//!    the recorded likelihood never decreases.
//! 4. **Stops** when, between accepted iterates, the geometry moved less than
//!    [`DriftEmOptions::se_tolerance`] of its standard errors and either every τ, q, r changed
//!    by less than [`DriftEmOptions::param_tolerance`] (relative) or the likelihood rose by less
//!    than [`DriftEmOptions::tolerance`].
//! 5. **All samples, once.** The drift parameters are converted to the step Δt, every sample
//!    is linearised at the iterated geometry and one two-stage pass gives the exact geometry
//!    step (the final table), the Fisher information of the geometry with the drift integrated
//!    out (`std_errors`, `expected_error`) and the likelihood. A filter and smoother pass at the
//!    final table (on the same linearisation) leaves the smoothed drift trajectory in the
//!    workspace ([`DriftSlot::drift`]).
//!
//! On the paper's scenario (K = 6,000) that is about 14 maps on 1,500 samples, 4 exact
//! informations and one pass over all samples (`cargo run -p calib-core --release --example
//! paper` prints the counts).
//!
//! A static θ offset and a slow drift are separable only to about `σ·√(2τ/T)` for a session of
//! length T (the standard error of the mean of a Gauss-Markov process); the result reports this
//! per joint as [`DriftEmResult::separability`].

use nalgebra::Vector6;

use crate::drift::DriftParams;
use crate::error::CalibError;
pub use crate::kalman::DriftSlot;
use crate::kalman::{filter, linearise_into, smooth, Params, Stats, TwoStage};
use crate::linalg::{Analysis, GramAccumulator, QrAccumulator};
use crate::ls::{positive, validate_samples, InputChecks};
use crate::metrics::{expected_table_error, TableError};
use crate::model::{DhTable, Sample};
use crate::paper_em::MAX_EM_ITERATIONS;

/// The iteration runs on at least this many samples (fewer only if the session is shorter).
pub const MIN_ITERATION_SAMPLES: usize = 1000;

/// The iteration moves to a smaller stride when a joint's estimated correlation time is below
/// this many iterated steps.
pub const TAU_STEPS: f64 = 10.0;

/// The geometry step's information is recomputed when a drift parameter has changed by more
/// than a factor `1 + REFRESH` since it was (measured: a stale information still gives steps
/// that raise the likelihood at a factor of 4; a refresh costs about two maps).
pub const REFRESH: f64 = 3.0;

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
}

impl<const N: usize> DriftEmOptions<N> {
    /// Defaults for a sample period `dt`. The starting values are deliberately not the
    /// simulator's truth: τ = 3 s, 0.02 rad drift, 1 mm / 1 mrad noise.
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
            initial_drift_std: 0.02,
            initial_noise_std: 1e-3,
            noise_floor: 1e-14,
            rank_tolerance: 1e-9,
            checks: InputChecks::new(None),
        }
    }
}

/// Result of [`em_drift`]. The drift trajectory is in the workspace.
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
    /// Measurement-noise variance per pose component (m², rad²).
    pub measurement_variance: [f64; 6],
    /// Per joint `σ·√(2τ/T)`: how well a static θ offset can be told from the drift (rad).
    pub separability: [f64; N],
    /// Log-likelihood of the iterated samples (every `stride`-th, at the final stride) at every
    /// accepted iterate. It never decreases.
    pub log_likelihood: heapless::Vec<f64, MAX_EM_ITERATIONS>,
    /// Log-likelihood of all samples at the final table and drift parameters (linearised at
    /// the iterated geometry).
    pub final_log_likelihood: f64,
    /// The iteration ended on every `stride`-th sample.
    pub stride: usize,
    /// ECME maps (filter + smoother passes over the iterated samples).
    pub iterations: usize,
    /// Exact geometry informations (two-stage passes over the iterated samples).
    pub information_passes: usize,
    /// Whether the tolerance was reached.
    pub converged: bool,
    /// Numerical rank of the last geometry step.
    pub rank: usize,
    /// Cramér-Rao bound (1σ) of every geometric parameter under the fitted drift and noise
    /// model, `std_errors[kind][joint]` (m, rad): the inverse of the exact Fisher information
    /// of the static parameters with the drift integrated out (from the two-stage filter).
    pub std_errors: [[f64; N]; 4],
    /// Expected table error (1σ) of [`DriftEmResult::table`] under that bound: the RMS over the
    /// session's own poses (at most [`EXPECTED_ERROR_POSES`], evenly spread) of the position and
    /// rotation error its FK would have against the true table ([`crate::metrics`]).
    pub expected_error: TableError,
}

/// Most poses of the session [`DriftEmResult::expected_error`] is averaged over.
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

/// The iterate of the ECME map: the geometry offset and the drift parameters, the latter as
/// logarithms (`ln(−ln φ)`, `ln q`, `ln r`) so that any extrapolation stays admissible.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Iterate<const N: usize, const P: usize> {
    x: [f64; P],
    lphi: [f64; N],
    lq: [f64; N],
    lr: [f64; 6],
}

impl<const N: usize, const P: usize> Iterate<N, P> {
    fn new(x: [f64; P], par: &Params<N>) -> Self {
        Iterate {
            x,
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

    /// `self + a·u + b·w` (componentwise).
    fn combine(&self, a: f64, u: &Self, b: f64, w: &Self) -> Self {
        fn mix<const M: usize>(s: &[f64; M], a: f64, u: &[f64; M], b: f64, w: &[f64; M]) -> [f64; M] {
            core::array::from_fn(|i| s[i] + a * u[i] + b * w[i])
        }
        Iterate {
            x: mix(&self.x, a, &u.x, b, &w.x),
            lphi: mix(&self.lphi, a, &u.lphi, b, &w.lphi),
            lq: mix(&self.lq, a, &u.lq, b, &w.lq),
            lr: mix(&self.lr, a, &u.lr, b, &w.lr),
        }
    }

    /// `self − other`.
    fn minus(&self, other: &Self) -> Self {
        self.combine(-1.0, other, 0.0, other)
    }

    /// Squared norm with the geometry in units of `se`.
    fn norm2(&self, se: &[f64; P]) -> f64 {
        let g: f64 = self.x.iter().zip(se).map(|(x, s)| (x / s) * (x / s)).sum();
        let d: f64 = self.lphi.iter().chain(&self.lq).chain(&self.lr).map(|v| v * v).sum();
        g + d
    }

    /// Largest geometry change in units of `se`, and largest change of a drift parameter's
    /// logarithm, from `other` to `self`.
    fn change(&self, other: &Self, se: &[f64; P]) -> (f64, f64) {
        let g = (0..P).fold(0.0f64, |m, p| m.max(((self.x[p] - other.x[p]) / se[p]).abs()));
        let tau = (0..N).fold(0.0f64, |m, j| m.max((self.lphi[j] - other.lphi[j]).abs()));
        let q = (0..N).fold(0.0f64, |m, j| m.max((self.lq[j] - other.lq[j]).abs()));
        let r = (0..6).fold(0.0f64, |m, i| m.max((self.lr[i] - other.lr[i]).abs()));
        (g, tau.max(q).max(r))
    }

    fn is_finite(&self) -> bool {
        self.x
            .iter()
            .chain(&self.lphi)
            .chain(&self.lq)
            .chain(&self.lr)
            .all(|v| v.is_finite())
    }
}

/// One exact two-stage pass over stored linearisations at offset `x`: the likelihood and the
/// analysis of the geometry step (normal equations, or the QR when they are ill-conditioned).
fn information<const N: usize, const P: usize>(
    slots: &mut [DriftSlot<N>],
    x: &[f64; P],
    par: &Params<N>,
    rank_tolerance: f64,
) -> Result<(f64, Analysis<P>), CalibError> {
    for slot in slots.iter_mut() {
        for i in 0..6 {
            slot.y[i] = slot.e[i] - crate::kalman::row_dot(&slot.h[i], x);
        }
    }
    let mut gram = GramAccumulator::<P>::new();
    let mut ts = TwoStage::<N, P>::new(par);
    for slot in slots.iter() {
        ts.absorb(&slot.y, &slot.h, par, &mut |rows, rhs| gram.add_rows(rows, rhs, 0))?;
    }
    let analysis = match gram.analyse(rank_tolerance) {
        Some(a) => a,
        None => qr_information(slots, par, rank_tolerance)?,
    };
    Ok((ts.ll, analysis))
}

/// [`information`] through the QR (rank-deficient or ill-conditioned geometry), from the
/// residuals the slots hold.
#[inline(never)]
fn qr_information<const N: usize, const P: usize>(
    slots: &[DriftSlot<N>],
    par: &Params<N>,
    rank_tolerance: f64,
) -> Result<Analysis<P>, CalibError> {
    let mut qr = QrAccumulator::<P>::new();
    let mut ts = TwoStage::<N, P>::new(par);
    for slot in slots {
        ts.absorb(&slot.y, &slot.h, par, &mut |rows, rhs| {
            for (row, y) in rows.iter().zip(rhs) {
                qr.add_row(row, *y);
            }
        })?;
    }
    Ok(qr.analyse(rank_tolerance))
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
    let mut stride = (kn / MIN_ITERATION_SAMPLES).clamp(1, opts.max_stride);
    let mut ks = kn.div_ceil(stride);
    let floor = opts.noise_floor;

    // 1. The iterated samples, linearised at the start.
    let mut g_ref = *start;
    let mut cols = [[Vector6::zeros(); N]; 4];
    let mut linearise_subset = |g: &DhTable<N>, stride: usize, ws: &mut [DriftSlot<N>]| {
        let prepared = g.prepare();
        for (slot, s) in ws.iter_mut().zip(samples.iter().step_by(stride)) {
            linearise_into(&prepared, s, &mut cols, slot);
        }
    };
    linearise_subset(&g_ref, stride, &mut workspace[..ks]);
    let dt_s = opts.dt * stride as f64;
    let phi0 = libm::exp(-dt_s / opts.initial_tau);
    let par0 = Params {
        phi: [phi0; N],
        q: [opts.initial_drift_std * opts.initial_drift_std * (1.0 - phi0 * phi0); N],
        r: [opts.initial_noise_std * opts.initial_noise_std; 6],
    };

    // 2-4. ECME maps, accelerated. `best` is the last accepted iterate (its likelihood known);
    // `z` the next candidate, accepted when the filter pass that starts its map finds its
    // likelihood no lower.
    let mut history: heapless::Vec<f64, MAX_EM_ITERATIONS> = heapless::Vec::new();
    let mut iterations = 0;
    let mut information_passes = 0;
    let mut z = Iterate::<N, P>::new([0.0; P], &par0);
    let mut best: Option<(f64, Iterate<N, P>)> = None;
    let mut pre: Option<(Analysis<P>, Iterate<N, P>, [f64; P])> = None;
    let mut step_max = STEP_MAX0;
    let mut converged = false;
    // After a rejected candidate: plain EM updates (monotone) for one map.
    let mut safe = false;
    let stale = |z: &Iterate<N, P>, pre: &Option<(Analysis<P>, Iterate<N, P>, [f64; P])>| match pre {
        None => true,
        Some((_, at, _)) => z.change(at, &[1.0; P]).1 > libm::log(1.0 + REFRESH),
    };
    while iterations < opts.max_iterations {
        let sub = &mut workspace[..ks];
        if stale(&z, &pre) {
            // The exact information at the current drift parameters, and an exact step.
            let par = z.params(floor);
            let (_, analysis) = information(sub, &z.x, &par, opts.rank_tolerance)?;
            information_passes += 1;
            let step = analysis.step(0.0);
            for (x, s) in z.x.iter_mut().zip(&step) {
                *x += s;
            }
            let se = analysis
                .std_errors(1.0)
                .map(|s| if s > 0.0 && s.is_finite() { s } else { 1.0 });
            pre = Some((analysis, z, se));
        }
        let Some((pre_an, _, se)) = &pre else {
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
                None => filter(sub, &z.x, &par)?,
            };
            let (st, grad) = smooth::<N, P>(sub, &par)?;
            let new = m_step(&st, &par, ks, floor, !safe);
            let dx = pre_an.solve(&grad);
            Ok((ll, Iterate::new(core::array::from_fn(|p| z.x[p] + dx[p]), &new)))
        };
        let (ll0, z1) = map(&z, sub, None, safe)?;
        iterations += 1;
        if let Some((ll_b, z_b)) = best {
            if ll0 < ll_b {
                z = z_b;
                pre = None;
                safe = true;
                continue;
            }
            let (dg, dp) = z.change(&z_b, se);
            if dg < opts.se_tolerance && (dp < opts.param_tolerance || ll0 - ll_b <= opts.tolerance) {
                // A drift faster than TAU_STEPS iterated steps is poorly told from white noise on the
                // decimated samples: iterate on more of them (from the current estimate).
                let par = z.params(floor);
                let tau_steps = par.phi.iter().fold(f64::INFINITY, |m, p| m.min(-1.0 / libm::log(*p)));
                if stride > 1 && tau_steps < TAU_STEPS {
                    let finer = ((tau_steps * stride as f64 / (1.5 * TAU_STEPS)) as usize).clamp(1, stride - 1);
                    g_ref = g_ref.perturbed(&z.x);
                    let par = restride(&par, stride, finer);
                    stride = finer;
                    ks = kn.div_ceil(stride);
                    linearise_subset(&g_ref, stride, &mut workspace[..ks]);
                    z = Iterate::new([0.0; P], &par);
                    best = None;
                    pre = None;
                    history.clear();
                    continue;
                }
                let _ = history.push(ll0);
                best = Some((ll0, z));
                converged = true;
                break;
            }
        }
        let _ = history.push(ll0);
        best = Some((ll0, z));
        if safe || stale(&z1, &pre) || iterations + 2 > opts.max_iterations {
            // Warming up (the drift parameters still move fast), or recovering: plain maps.
            safe = false;
            z = z1;
            continue;
        }
        let (ll1, z2) = map(&z1, sub, None, false)?;
        iterations += 1;
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
                if let Ok(ll_c) = filter(sub, &cand.x, &par) {
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
        let (_, z_new) = map(&cand, sub, ll_c, false)?;
        iterations += 1;
        z = z_new;
    }
    let (ll_z, z) = best.ok_or(degenerate("no iteration"))?;
    if !converged && opts.require_convergence {
        let prev = history.iter().rev().nth(1).copied().unwrap_or(ll_z);
        return Err(CalibError::NotConverged {
            iterations,
            last_change: (ll_z - prev).abs() / ll_z.abs().max(1.0),
        });
    }

    // 5. Every sample, at the iterated geometry and the drift parameters at the step Δt.
    let par = restride(&z.params(floor), stride, 1);
    let g1 = g_ref.perturbed(&z.x);
    let ws = &mut workspace[..kn];
    let prepared = g1.prepare();
    let mut gram = GramAccumulator::<P>::new();
    let mut ts = TwoStage::<N, P>::new(&par);
    for (slot, s) in ws.iter_mut().zip(samples) {
        linearise_into(&prepared, s, &mut cols, slot);
        slot.y = slot.e;
        ts.absorb(&slot.y, &slot.h, &par, &mut |rows, rhs| gram.add_rows(rows, rhs, 0))?;
    }
    let analysis = match gram.analyse(opts.rank_tolerance) {
        Some(a) => a,
        None => qr_information(ws, &par, opts.rank_tolerance)?,
    };
    let step = analysis.step(0.0);
    let final_ll = filter(ws, &step, &par)?;
    smooth::<N, P>(ws, &par)?;
    let table = g1.perturbed(&step);
    let crb = analysis.std_errors(1.0);
    let pose_stride = kn.div_ceil(EXPECTED_ERROR_POSES);
    let expected_error = expected_table_error::<N, P>(&table, samples.iter().step_by(pose_stride).map(|s| &s.joints), |u| {
        analysis.variance_along(u)
    });
    let t_total = kn as f64 * opts.dt;
    let drift: [DriftParams; N] = core::array::from_fn(|j| DriftParams::from_discrete(par.phi[j], par.q[j], opts.dt));
    Ok(DriftEmResult {
        table,
        phi: par.phi,
        process_variance: par.q,
        drift,
        measurement_variance: par.r,
        separability: core::array::from_fn(|j| drift[j].stationary_sigma * libm::sqrt(2.0 * drift[j].tau / t_total)),
        log_likelihood: history,
        final_log_likelihood: final_ll,
        stride,
        iterations,
        information_passes,
        converged,
        rank: analysis.rank,
        std_errors: core::array::from_fn(|k| core::array::from_fn(|j| crb[k * N + j])),
        expected_error,
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
    let mut gram = GramAccumulator::<P>::new();
    let mut ts = TwoStage::<N, P>::new(&par);
    for s in samples {
        linearise_into(&prepared, s, &mut cols, &mut slot);
        ts.absorb(&slot.e, &slot.h, &par, &mut |rows, rhs| gram.add_rows(rows, rhs, 0))?;
    }
    if let Some(analysis) = gram.analyse(1e-12) {
        return Ok(analysis);
    }
    let mut qr = QrAccumulator::<P>::new();
    let mut ts = TwoStage::<N, P>::new(&par);
    for s in samples {
        linearise_into(&prepared, s, &mut cols, &mut slot);
        ts.absorb(&slot.e, &slot.h, &par, &mut |rows, rhs| {
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
        for w in r.log_likelihood.windows(2) {
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
