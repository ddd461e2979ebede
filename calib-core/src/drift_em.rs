//! Our EM: the drift as a time series (Kalman filter + Rauch-Tung-Striebel smoother).
//!
//! # Model
//! Linearised at the current geometry G, the pose error of sample k is
//! `e_k = H_k Δg + J_k δ_k + v_k`, with H_k the `6 × 4N` residual Jacobian, J_k its θ block,
//! `v_k ~ N(0, diag(r))` and, per joint j, the Gauss-Markov drift
//! `δ_{k+1,j} = φ_j δ_{k,j} + ρ`, `ρ ~ N(0, q_j)`, `δ_{0,j} ~ N(0, q_j / (1 − φ_j²))`.
//!
//! # Iteration (an ECME algorithm: every step raises the likelihood)
//! 1. **Geometry.** The static errors Δg are carried in the filter state with zero process
//!    noise, in the two-stage (Friedland) form: the filtered drift mean is kept affine in Δg,
//!    `a_k + B_k Δg`, so one forward pass yields the exact likelihood as a quadratic in Δg,
//!    whose whitened rows go into the same streaming QR as the LS. Its maximiser is the
//!    geometry step (backtracked on the exact likelihood at the re-linearised geometry).
//!    Updating the static offsets only in an M-step against the smoothed drift converges very
//!    slowly (the drift absorbs them); carried in the state they converge in a few iterations.
//! 2. **E-step.** Kalman filter and RTS smoother of δ at the new geometry (the caller's
//!    workspace stores one [`DriftSlot`] per sample: fixed memory, no allocation).
//! 3. **M-step.** Per joint, φ_j and q_j maximise the expected complete-data log-likelihood
//!    (including the stationary prior of δ_0; a 1-D profile search, kept only if it improves),
//!    and `r_i = mean E[(e − Jδ)_i²]`, floored at `noise_floor`.
//!
//! The log-likelihood `ln p(e_1..K | G, φ, q, r)` (from the filter innovations) is recorded at
//! the start of every iteration and never decreases. After the last iteration the workspace
//! holds the smoothed drift trajectory ([`DriftSlot::drift`]).
//!
//! A static θ offset and a slow drift are separable only to about `σ·√(2τ/T)` for a session of
//! length T (the standard error of the mean of a Gauss-Markov process); the result reports this
//! per joint as [`DriftEmResult::separability`].

use nalgebra::{Cholesky, Const, SMatrix, SVector, Vector6};

use crate::drift::DriftParams;
use crate::error::CalibError;
use crate::linalg::{Analysis, QrAccumulator};
use crate::ls::{positive, validate_samples, InputChecks};
use crate::metrics::{expected_table_error, TableError};
use crate::model::{error_jacobian, pose_error, DhTable, Sample};
use crate::paper_em::MAX_EM_ITERATIONS;

const LN_2PI: f64 = 1.837_877_066_409_345_3;

/// Per-sample storage of the E-step (filtered, then smoothed, drift moments and the sample's
/// linearisation). One slot per sample; 104 `f64` for N = 7.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DriftSlot<const N: usize> {
    mean: SVector<f64, N>,
    cov: SMatrix<f64, N, N>,
    e: Vector6<f64>,
    jt: SMatrix<f64, 6, N>,
}

impl<const N: usize> Default for DriftSlot<N> {
    fn default() -> Self {
        DriftSlot {
            mean: SVector::zeros(),
            cov: SMatrix::zeros(),
            e: Vector6::zeros(),
            jt: SMatrix::zeros(),
        }
    }
}

impl<const N: usize> DriftSlot<N> {
    /// Smoothed drift estimate E[δ_k | all data] (rad) after [`em_drift`].
    pub fn drift(&self) -> [f64; N] {
        self.mean.into()
    }

    /// Its posterior standard deviation per joint (rad).
    pub fn drift_std(&self) -> [f64; N] {
        core::array::from_fn(|j| libm::sqrt(self.cov[(j, j)].max(0.0)))
    }
}

/// Options of [`em_drift`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DriftEmOptions<const N: usize> {
    /// Sample period Δt (s).
    pub dt: f64,
    /// Iteration limit (below [`MAX_EM_ITERATIONS`]).
    pub max_iterations: usize,
    /// Converged when the log-likelihood changes by less than this (relative).
    pub tolerance: f64,
    /// Also converged when, in one iteration, the geometry moved less than
    /// `geometry_tolerance` and every τ_j and q_j changed by less than `param_tolerance`
    /// (relative). The likelihood is a poor stopping signal on noise-free data: the noise
    /// variance creeps towards `noise_floor` for hundreds of iterations (EM's linear rate) while
    /// the geometry stays put to 1e-6.
    pub param_tolerance: f64,
    /// See `param_tolerance` (m, rad).
    pub geometry_tolerance: f64,
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
            tolerance: 1e-9,
            param_tolerance: 2e-3,
            geometry_tolerance: 1e-5,
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
    /// Log-likelihood at the start of every iteration, then at the final parameters.
    pub log_likelihood: heapless::Vec<f64, MAX_EM_ITERATIONS>,
    /// Iterations run.
    pub iterations: usize,
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

#[derive(Clone, Copy, Debug)]
struct Params<const N: usize> {
    phi: [f64; N],
    q: [f64; N],
    r: [f64; 6],
}

impl<const N: usize> Params<N> {
    fn p0(&self) -> SMatrix<f64, N, N> {
        SMatrix::from_fn(|i, j| {
            if i == j {
                self.q[i] / (1.0 - self.phi[i] * self.phi[i])
            } else {
                0.0
            }
        })
    }

    fn predict(&self, cov: &mut SMatrix<f64, N, N>) {
        for i in 0..N {
            for j in 0..N {
                cov[(i, j)] *= self.phi[i] * self.phi[j];
            }
            cov[(i, i)] += self.q[i];
        }
    }
}

fn degenerate(what: &'static str) -> CalibError {
    CalibError::InvalidInput { what }
}

/// Residual and its Jacobians at `g`: (e, H (6 × P), J (θ block, 6 × N)).
fn linearise<const N: usize, const P: usize>(
    g: &DhTable<N>,
    s: &Sample<N>,
) -> (Vector6<f64>, SMatrix<f64, 6, P>, SMatrix<f64, 6, N>) {
    let (t, cols) = g.fk_jacobian(&s.joints);
    let e = pose_error(&t, &s.pose);
    let m = error_jacobian(&e);
    let h = SMatrix::<f64, 6, P>::from_fn(|r, p| (m * cols[p / N][p % N])[r]);
    let jt = SMatrix::<f64, 6, N>::from_fn(|r, j| h[(r, 3 * N + j)]);
    (e, h, jt)
}

fn innovation_cov<const N: usize>(
    jt: &SMatrix<f64, 6, N>,
    cov: &SMatrix<f64, N, N>,
    r: &[f64; 6],
) -> Result<Cholesky<f64, Const<6>>, CalibError> {
    let mut s = jt * cov * jt.transpose();
    for i in 0..6 {
        s[(i, i)] += r[i];
    }
    Cholesky::new(0.5 * (s + s.transpose())).ok_or(degenerate("innovation covariance not positive definite"))
}

fn log_det(ch: &Cholesky<f64, Const<6>>) -> f64 {
    2.0 * (0..6).map(|i| libm::log(ch.l_dirty()[(i, i)])).sum::<f64>()
}

/// Forward pass of the two-stage filter: likelihood at Δg = 0 and the whitened Δg rows.
fn geometry_pass<const N: usize, const P: usize>(
    g: &DhTable<N>,
    samples: &[Sample<N>],
    par: &Params<N>,
) -> Result<(f64, QrAccumulator<P>), CalibError> {
    let mut acc = QrAccumulator::<P>::new();
    let mut a = SVector::<f64, N>::zeros();
    let mut b = SMatrix::<f64, N, P>::zeros();
    let mut cov = par.p0();
    let mut ll = 0.0;
    for (k, s) in samples.iter().enumerate() {
        if k > 0 {
            for i in 0..N {
                a[i] *= par.phi[i];
                b.row_mut(i).scale_mut(par.phi[i]);
            }
            par.predict(&mut cov);
        }
        let (e, h, jt) = linearise::<N, P>(g, s);
        let c = e - jt * a;
        let d = h + jt * b;
        let ch = innovation_cov(&jt, &cov, &par.r)?;
        let sinv_c = ch.solve(&c);
        ll -= 0.5 * (c.dot(&sinv_c) + log_det(&ch) + 6.0 * LN_2PI);
        let l = ch.l();
        let wd = l.solve_lower_triangular(&d).ok_or(degenerate("singular innovation factor"))?;
        let wc = l.solve_lower_triangular(&c).ok_or(degenerate("singular innovation factor"))?;
        for r in 0..6 {
            let row: [f64; P] = core::array::from_fn(|p| wd[(r, p)]);
            acc.add_row(&row, wc[r]);
        }
        // Gain K = P Jᵀ S⁻¹ (N × 6).
        let kg = ch.solve(&(jt * cov)).transpose();
        a += kg * c;
        b -= kg * d;
        cov -= kg * jt * cov;
        cov = 0.5 * (cov + cov.transpose());
    }
    Ok((ll, acc))
}

/// Kalman filter at fixed geometry, storing every sample in `ws`; returns the likelihood.
fn filter_pass<const N: usize, const P: usize>(
    g: &DhTable<N>,
    samples: &[Sample<N>],
    par: &Params<N>,
    ws: &mut [DriftSlot<N>],
) -> Result<f64, CalibError> {
    let mut m = SVector::<f64, N>::zeros();
    let mut cov = par.p0();
    let mut ll = 0.0;
    for (k, (s, slot)) in samples.iter().zip(ws.iter_mut()).enumerate() {
        if k > 0 {
            for i in 0..N {
                m[i] *= par.phi[i];
            }
            par.predict(&mut cov);
        }
        let (e, _h, jt) = linearise::<N, P>(g, s);
        let nu = e - jt * m;
        let ch = innovation_cov(&jt, &cov, &par.r)?;
        ll -= 0.5 * (nu.dot(&ch.solve(&nu)) + log_det(&ch) + 6.0 * LN_2PI);
        let kg = ch.solve(&(jt * cov)).transpose();
        m += kg * nu;
        cov -= kg * jt * cov;
        cov = 0.5 * (cov + cov.transpose());
        *slot = DriftSlot { mean: m, cov, e, jt };
    }
    Ok(ll)
}

/// Sufficient statistics of the M-step.
struct Stats<const N: usize> {
    e0: [f64; N],
    s00: [f64; N],
    s10: [f64; N],
    s11: [f64; N],
    r: [f64; 6],
}

/// RTS smoother over the filtered workspace (in place) and the M-step statistics.
fn smooth<const N: usize>(ws: &mut [DriftSlot<N>], par: &Params<N>) -> Result<Stats<N>, CalibError> {
    let kn = ws.len();
    let mut st = Stats {
        e0: [0.0; N],
        s00: [0.0; N],
        s10: [0.0; N],
        s11: [0.0; N],
        r: [0.0; 6],
    };
    let mut add = |k: usize, slot: &DriftSlot<N>| {
        for j in 0..N {
            let ex = slot.mean[j] * slot.mean[j] + slot.cov[(j, j)];
            if k == 0 {
                st.e0[j] = ex;
            }
            if k + 1 < kn {
                st.s00[j] += ex;
            }
            if k > 0 {
                st.s11[j] += ex;
            }
        }
        let res = slot.e - slot.jt * slot.mean;
        let jpj = slot.jt * slot.cov * slot.jt.transpose();
        for i in 0..6 {
            st.r[i] += res[i] * res[i] + jpj[(i, i)];
        }
    };
    add(kn - 1, &ws[kn - 1]);
    let mut s10 = [0.0; N];
    for k in (0..kn - 1).rev() {
        let (lo, hi) = ws.split_at_mut(k + 1);
        let (cur, next) = (&mut lo[k], &hi[0]);
        let mut pred = cur.cov;
        par.predict(&mut pred);
        let fp = SMatrix::<f64, N, N>::from_fn(|i, j| par.phi[i] * cur.cov[(i, j)]);
        let ch = Cholesky::new(0.5 * (pred + pred.transpose())).ok_or(degenerate("predicted drift covariance"))?;
        // Smoother gain G = P_k F P⁻¹_{k+1} = (P⁻¹ F P_k)ᵀ.
        let gain = ch.solve(&fp).transpose();
        let fm = SVector::<f64, N>::from_fn(|i, _| par.phi[i] * cur.mean[i]);
        let mean = cur.mean + gain * (next.mean - fm);
        let cov = cur.cov + gain * (next.cov - pred) * gain.transpose();
        let lag = next.cov * gain.transpose();
        for j in 0..N {
            s10[j] += next.mean[j] * mean[j] + lag[(j, j)];
        }
        cur.mean = mean;
        cur.cov = 0.5 * (cov + cov.transpose());
        add(k, cur);
    }
    st.s10 = s10;
    Ok(st)
}

/// Expected complete-data log-likelihood of one joint's drift (constants dropped).
fn q_joint(phi: f64, q: f64, k: f64, e0: f64, s00: f64, s10: f64, s11: f64) -> f64 {
    let p0 = q / (1.0 - phi * phi);
    -0.5 * (libm::log(p0) + e0 / p0 + (k - 1.0) * libm::log(q) + (s11 - 2.0 * phi * s10 + phi * phi * s00) / q)
}

fn m_step<const N: usize>(st: &Stats<N>, par: &Params<N>, kn: usize, noise_floor: f64) -> Params<N> {
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
        out.r[i] = (st.r[i] / k).max(noise_floor);
    }
    out
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
        && positive(opts.geometry_tolerance)
        && positive(opts.initial_tau)
        && positive(opts.initial_drift_std)
        && positive(opts.initial_noise_std)
        && positive(opts.noise_floor)
        && positive(opts.rank_tolerance)
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
    let ws = &mut workspace[..samples.len()];
    let phi0 = libm::exp(-opts.dt / opts.initial_tau);
    let mut par = Params {
        phi: [phi0; N],
        q: [opts.initial_drift_std * opts.initial_drift_std * (1.0 - phi0 * phi0); N],
        r: [opts.initial_noise_std * opts.initial_noise_std; 6],
    };
    let mut g = *start;
    let mut history: heapless::Vec<f64, MAX_EM_ITERATIONS> = heapless::Vec::new();
    let mut converged = false;
    let mut rank = 0;
    let mut iterations = 0;
    let mut settled = false;
    while iterations < opts.max_iterations {
        let (ll, acc) = geometry_pass::<N, P>(&g, samples, &par)?;
        if let Some(&prev) = history.last() {
            if settled || (ll - prev).abs() <= opts.tolerance * ll.abs().max(1.0) {
                converged = true;
            }
        }
        // Capacity MAX_EM_ITERATIONS exceeds max_iterations + 1.
        let _ = history.push(ll);
        if converged {
            break;
        }
        iterations += 1;
        let analysis = acc.analyse(opts.rank_tolerance);
        rank = analysis.rank;
        let step = analysis.step(0.0);
        let mut accepted = false;
        let mut t = 1.0;
        let mut moved = 0.0f64;
        for _ in 0..12 {
            let delta: [f64; P] = core::array::from_fn(|p| t * step[p]);
            moved = delta.iter().fold(0.0, |m, d| m.max(d.abs()));
            let candidate = g.perturbed(&delta);
            if let Ok(ll_c) = filter_pass::<N, P>(&candidate, samples, &par, ws) {
                if ll_c >= ll - 1e-12 * ll.abs() {
                    g = candidate;
                    accepted = true;
                    break;
                }
            }
            t *= 0.5;
        }
        if !accepted {
            moved = 0.0;
            filter_pass::<N, P>(&g, samples, &par, ws)?;
        }
        let st = smooth(ws, &par)?;
        let new = m_step(&st, &par, samples.len(), opts.noise_floor);
        let rel = |a: f64, b: f64| (a - b).abs() / b.abs().max(1e-300);
        settled = moved < opts.geometry_tolerance
            && (0..N).all(|j| {
                rel(new.phi[j], par.phi[j]) < opts.param_tolerance * (1.0 - par.phi[j])
                    && rel(new.q[j], par.q[j]) < opts.param_tolerance
            });
        par = new;
    }
    let (ll, acc) = geometry_pass::<N, P>(&g, samples, &par)?;
    let analysis = acc.analyse(opts.rank_tolerance);
    let crb = analysis.std_errors(1.0);
    let stride = samples.len().div_ceil(EXPECTED_ERROR_POSES);
    let expected_error = expected_table_error::<N, P>(&g, samples.iter().step_by(stride).map(|s| &s.joints), |u| {
        analysis.variance_along(u)
    });
    filter_pass::<N, P>(&g, samples, &par, ws)?;
    smooth(ws, &par)?;
    if !converged {
        let _ = history.push(ll);
        if opts.require_convergence {
            let prev = history.iter().rev().nth(1).copied().unwrap_or(ll);
            return Err(CalibError::NotConverged {
                iterations,
                last_change: (ll - prev).abs() / ll.abs().max(1.0),
            });
        }
    }
    let t_total = samples.len() as f64 * opts.dt;
    let drift: [DriftParams; N] = core::array::from_fn(|j| DriftParams::from_discrete(par.phi[j], par.q[j], opts.dt));
    Ok(DriftEmResult {
        table: g,
        phi: par.phi,
        process_variance: par.q,
        drift,
        measurement_variance: par.r,
        separability: core::array::from_fn(|j| drift[j].stationary_sigma * libm::sqrt(2.0 * drift[j].tau / t_total)),
        log_likelihood: history,
        iterations,
        converged,
        rank,
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
    let (_, acc) = geometry_pass::<N, P>(table, samples, &par)?;
    Ok(acc.analyse(1e-12))
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
    Ok((r, ws.iter().map(DriftSlot::drift).collect()))
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
