//! The per-sample kernels of our EM ([`crate::em_drift`]): the drift filter with scalar
//! (sequential) measurement updates, its Rauch-Tung-Striebel smoother with the M-step's
//! sufficient statistics, and the two-stage (Friedland) filter that carries the static
//! geometry as an affine function of the drift mean.
//!
//! # Model (linearised at a reference geometry)
//! Sample k has the pose error `e_k` and the `6 × 4N` residual Jacobian `H_k` at the reference
//! geometry; at a geometry offset `x` its residual is `y_k = e_k − H_k x = J_k δ_k + v_k`,
//! with `J_k` the θ block of `H_k`, `v_k ~ N(0, diag(r))` and, per joint j,
//! `δ_{k+1,j} = φ_j δ_{k,j} + N(0, q_j)`, `δ_{0,j} ~ N(0, q_j / (1 − φ_j²))`.
//!
//! Two extensions, both static in the filter's sense:
//! * **a rate bias integrated into the angle** ([`crate::drift_em`]'s richer drift model): joint
//!   j's angle error is `δ_{k,j} + Σ_m t_{j,m} s_k^m` (m = 1..[`RATE_BIAS_TERMS`]), with `s_k`
//!   the sample's time as a fraction of the session ([`DriftSlot::time`]); the coefficients `t`
//!   are static parameters beside the geometry offset `x`, so the residual is
//!   `y_k = e_k − H_k x − J_k c_k(t)`;
//! * **a per-sample weight** `w_k` ([`DriftSlot::weight`]): sample k's pose noise is
//!   `diag(r) / w_k` (the heavy-tailed reference: a Student-t is a Gaussian with a random
//!   precision, and the EM's E-step gives its weight).
//!
//! # Cost (N = 7)
//! The six pose components are processed one at a time (the noise is diagonal), so there is
//! no 6 × 6 factorisation: about 800 multiply-adds per sample for the filter, 1,600 for the
//! smoother and its statistics, 5,000 for the two-stage pass (dominated by its `4N + 1`
//! columns). No allocation: the caller's [`DriftSlot`] per sample holds the linearisation and the
//! filter moments.

use nalgebra::Vector6;

use crate::error::CalibError;
use crate::linalg::dot;
use crate::model::{error_jacobian, pose_error, PreparedTable, Sample};

pub(crate) const LN_2PI: f64 = 1.837_877_066_409_345_3;

/// Terms of the integrated rate bias: `s` and `s²` of the session's time fraction `s` (a
/// ramp, and a rate bias that changes linearly; see [`crate::drift_em`]).
pub const RATE_BIAS_TERMS: usize = 2;

/// Coefficients of the integrated rate bias per joint (rad): `t[j][m]` multiplies `s^(m+1)`.
pub type Trend<const N: usize> = [[f64; RATE_BIAS_TERMS]; N];

/// The basis of the integrated rate bias at the time fraction `s`: `[s, s²]`.
#[inline]
pub(crate) fn basis(s: f64) -> [f64; RATE_BIAS_TERMS] {
    [s, s * s]
}

/// Per-sample storage of [`crate::em_drift`]: the sample's linearisation, its residual and its
/// drift moments (filtered, then smoothed). One slot per sample: fixed memory, no allocation;
/// 288 `f64` for N = 7.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DriftSlot<const N: usize> {
    /// Pose error at the reference geometry (and drift, once relinearised).
    pub(crate) e: [f64; 6],
    /// Residual Jacobian `H`, row by row, each row in parameter order (`kind`, `joint`); the
    /// θ block `h[i][3]` is the drift Jacobian.
    pub(crate) h: [[[f64; N]; 4]; 6],
    /// Residual `e − H x − J c(t)` at the static parameters of the last filter pass.
    pub(crate) y: [f64; 6],
    /// Drift mean.
    pub(crate) mean: [f64; N],
    /// Drift covariance.
    pub(crate) cov: [[f64; N]; N],
    /// Weight of the sample's pose (its noise is `r / w`).
    pub(crate) w: f64,
    /// `Σ_i E[(y − Jδ)_i²] / r_i` after the last smoother pass (the sample's squared
    /// Mahalanobis distance, which the weight is updated from).
    pub(crate) m2: f64,
    /// The sample's time as a fraction of the session, in [0, 1].
    pub(crate) s: f64,
    /// Sensitivity of the drift mean to the θ offsets (filtered, then smoothed), for the
    /// restricted drift parameters ([`restricted_moments`]).
    pub(crate) sens: [[f64; N]; N],
}

impl<const N: usize> DriftSlot<N> {
    /// Smoothed drift estimate E[δ_k | all data] (rad) after [`crate::em_drift`]: the
    /// Gauss-Markov part; [`crate::DriftEmResult::rate_bias_at`] gives the integrated rate bias.
    pub fn drift(&self) -> [f64; N] {
        self.mean
    }

    /// Its posterior standard deviation per joint (rad).
    pub fn drift_std(&self) -> [f64; N] {
        core::array::from_fn(|j| libm::sqrt(self.cov[j][j].max(0.0)))
    }

    /// The weight the EM gave the sample's pose (1 for a Gaussian reference; near 0 for a
    /// sample it discounted as a glitch).
    pub fn weight(&self) -> f64 {
        self.w
    }

    /// The sample's time as a fraction of the session (0 at the first sample, 1 at the last).
    pub fn time(&self) -> f64 {
        self.s
    }
}

impl<const N: usize> Default for DriftSlot<N> {
    fn default() -> Self {
        DriftSlot {
            e: [0.0; 6],
            h: [[[0.0; N]; 4]; 6],
            y: [0.0; 6],
            mean: [0.0; N],
            cov: [[0.0; N]; N],
            w: 1.0,
            m2: 0.0,
            s: 0.0,
            sens: [[0.0; N]; N],
        }
    }
}

/// Linearises sample `s` at `table` into `slot.e`, `slot.h` (the exact residual Jacobian
/// `M(e)·J` of [`crate::model::error_jacobian`]; `a` and `d` rows of rotation are zero).
pub(crate) fn linearise_into<const N: usize>(
    table: &PreparedTable<N>,
    s: &Sample<N>,
    cols: &mut [[Vector6<f64>; N]; 4],
    slot: &mut DriftSlot<N>,
) {
    linearise_at(table, s, None, cols, slot);
}

/// [`linearise_into`] at the joint angles `θ_k + a` (the estimated angle error `a`: drift and
/// integrated rate bias), re-expressed at `θ_k`: `H` at `θ_k + a`, and the pose error
/// `e(θ_k + a) + J a`, so that the residual model `y = H x + J (δ + c) + v` keeps its meaning to
/// second order in the drift (`None`: at `θ_k`).
pub(crate) fn linearise_at<const N: usize>(
    table: &PreparedTable<N>,
    s: &Sample<N>,
    offset: Option<&[f64; N]>,
    cols: &mut [[Vector6<f64>; N]; 4],
    slot: &mut DriftSlot<N>,
) {
    let joints: [f64; N] = match offset {
        Some(a) => core::array::from_fn(|j| s.joints[j] + a[j]),
        None => s.joints,
    };
    let t = table.fk_jacobian_into(&joints, cols);
    let e = pose_error(&t, &s.pose);
    let m = error_jacobian(&e);
    let (ex, ey, ez) = (e[0], e[1], e[2]);
    for (kind, kcols) in cols.iter().enumerate() {
        for (j, c) in kcols.iter().enumerate() {
            if kind < 2 {
                // Pure translations: M·c = c.
                for r in 0..3 {
                    slot.h[r][kind][j] = c[r];
                    slot.h[r + 3][kind][j] = 0.0;
                }
            } else {
                let (w0, w1, w2) = (c[3], c[4], c[5]);
                // v + ω × e_p, and J_l⁻¹ ω.
                slot.h[0][kind][j] = c[0] + w1 * ez - w2 * ey;
                slot.h[1][kind][j] = c[1] + w2 * ex - w0 * ez;
                slot.h[2][kind][j] = c[2] + w0 * ey - w1 * ex;
                for r in 0..3 {
                    slot.h[r + 3][kind][j] = m[(r + 3, 3)] * w0 + m[(r + 3, 4)] * w1 + m[(r + 3, 5)] * w2;
                }
            }
        }
    }
    slot.e = e.into();
    if let Some(a) = offset {
        for i in 0..6 {
            slot.e[i] += dot(&slot.h[i][3], a);
        }
    }
}

/// The residual `e − H x − J c(t)` of a slot at the static parameters `(x, t)`.
#[inline]
pub(crate) fn residual<const N: usize, const P: usize>(slot: &DriftSlot<N>, x: &[f64; P], t: &Trend<N>) -> [f64; 6] {
    let c = rate_bias(t, slot.s);
    core::array::from_fn(|i| slot.e[i] - row_dot(&slot.h[i], x) - dot(&slot.h[i][3], &c))
}

/// The integrated rate bias `c(s)` of every joint at the time fraction `s`.
#[inline]
pub(crate) fn rate_bias<const N: usize>(t: &Trend<N>, s: f64) -> [f64; N] {
    let b = basis(s);
    core::array::from_fn(|j| t[j].iter().zip(&b).map(|(c, v)| c * v).sum())
}

/// `Σ_p row[p]·x[p]` over a residual-Jacobian row in parameter order.
#[inline]
pub(crate) fn row_dot<const N: usize, const P: usize>(row: &[[f64; N]; 4], x: &[f64; P]) -> f64 {
    dot_slices(row.as_flattened(), x)
}

#[inline]
fn dot_slices(a: &[f64], b: &[f64]) -> f64 {
    // Four partial sums: independent chains the compiler can keep in vector registers.
    let mut acc = [0.0; 4];
    let mut ca = a.chunks_exact(4);
    let mut cb = b.chunks_exact(4);
    for (x, y) in (&mut ca).zip(&mut cb) {
        for i in 0..4 {
            acc[i] += x[i] * y[i];
        }
    }
    for (x, y) in ca.remainder().iter().zip(cb.remainder()) {
        acc[0] += x * y;
    }
    (acc[0] + acc[1]) + (acc[2] + acc[3])
}

/// Drift parameters at the filter's step: per joint φ, q, per pose component r.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Params<const N: usize> {
    pub phi: [f64; N],
    pub q: [f64; N],
    pub r: [f64; 6],
}

/// Filtered drift moments.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Filter<const N: usize> {
    pub m: [f64; N],
    pub p: [[f64; N]; N],
}

impl<const N: usize> Filter<N> {
    /// The stationary prior of `δ_0`.
    pub fn start(par: &Params<N>) -> Self {
        let mut p = [[0.0; N]; N];
        for (j, row) in p.iter_mut().enumerate() {
            row[j] = par.q[j] / (1.0 - par.phi[j] * par.phi[j]);
        }
        Filter { m: [0.0; N], p }
    }

    /// Time update (diagonal transition).
    #[inline]
    pub fn predict(&mut self, par: &Params<N>) {
        for a in 0..N {
            self.m[a] *= par.phi[a];
            for b in 0..N {
                self.p[a][b] *= par.phi[a] * par.phi[b];
            }
            self.p[a][a] += par.q[a];
        }
    }

    /// `P h`.
    #[inline]
    fn ph(&self, h: &[f64; N]) -> [f64; N] {
        let mut out = [0.0; N];
        for (row, hb) in self.p.iter().zip(h) {
            for (o, pab) in out.iter_mut().zip(row) {
                *o += pab * hb;
            }
        }
        out
    }

    /// Scalar measurement update `y = h·δ + N(0, r)`; returns the innovation, its variance and
    /// the gain times that variance (`P h` before the update).
    #[inline]
    pub fn observe(&mut self, h: &[f64; N], y: f64, r: f64) -> Result<(f64, f64, [f64; N]), CalibError> {
        let ph = self.ph(h);
        let s = dot(h, &ph) + r;
        if !(s > 0.0 && s.is_finite()) {
            return Err(CalibError::InvalidInput {
                what: "innovation variance not positive",
            });
        }
        let nu = y - dot(h, &self.m);
        let inv = 1.0 / s;
        let g = nu * inv;
        for (m, k) in self.m.iter_mut().zip(&ph) {
            *m += k * g;
        }
        for (row, ka) in self.p.iter_mut().zip(&ph) {
            let ka = ka * inv;
            for (pab, kb) in row.iter_mut().zip(&ph) {
                *pab -= ka * kb;
            }
        }
        Ok((nu, s, ph))
    }
}

/// Kalman filter over stored linearisations at the static parameters `(x, t)`: stores each
/// sample's residual and filtered moments, returns the log-likelihood `ln p(y_1..K)`.
pub(crate) fn filter<const N: usize, const P: usize>(
    slots: &mut [DriftSlot<N>],
    x: &[f64; P],
    t: &Trend<N>,
    par: &Params<N>,
) -> Result<f64, CalibError> {
    filter_weighting(slots, x, t, par, None)
}

/// [`filter`], and with `robust_dof` [`filter_robust`]'s weights set before each update.
#[inline(always)]
fn filter_weighting<const N: usize, const P: usize>(
    slots: &mut [DriftSlot<N>],
    x: &[f64; P],
    t: &Trend<N>,
    par: &Params<N>,
    robust_dof: Option<f64>,
) -> Result<f64, CalibError> {
    let mut f = Filter::start(par);
    let mut ll = 0.0;
    for (k, slot) in slots.iter_mut().enumerate() {
        if k > 0 {
            f.predict(par);
        }
        slot.y = residual(slot, x, t);
        if let Some(dof) = robust_dof {
            let mut probe = f;
            let mut m = 0.0;
            for i in 0..6 {
                let (nu, s, _) = probe.observe(&slot.h[i][3], slot.y[i], par.r[i])?;
                m += nu * nu / s;
            }
            slot.w = (dof + 6.0) / (dof + m);
        }
        observe_sample(&mut f, slot, par, &mut ll, None)?;
        slot.mean = f.m;
        slot.cov = f.p;
    }
    Ok(ll)
}

/// The six scalar updates of one sample from its stored residual `slot.y` at noise `r / w`,
/// its likelihood term subtracted from `ll` (with unit weights, in the order [`filter`] always
/// used: the same bits); the standardised innovations go to `innovations` if given.
#[inline(always)]
fn observe_sample<const N: usize>(
    f: &mut Filter<N>,
    slot: &DriftSlot<N>,
    par: &Params<N>,
    ll: &mut f64,
    mut standardised: Option<&mut [f64; 6]>,
) -> Result<(), CalibError> {
    let mut det = 1.0;
    let w = slot.w;
    for i in 0..6 {
        let r = if w == 1.0 { par.r[i] } else { par.r[i] / w };
        let (nu, s, _) = f.observe(&slot.h[i][3], slot.y[i], r)?;
        *ll -= 0.5 * nu * nu / s;
        det *= s;
        if let Some(z) = standardised.as_deref_mut() {
            z[i] = nu / libm::sqrt(s);
        }
    }
    *ll -= 0.5 * (libm::log(det) + 6.0 * LN_2PI);
    Ok(())
}

/// [`filter`] from the residuals the slots hold (`slot.y`, those of the last filter pass),
/// read-only: the log-likelihood `ln p(y_1..K)` at other drift and noise parameters, leaving the
/// slots (e.g. the smoothed drift after [`crate::em_drift`]) untouched.
pub(crate) fn log_likelihood<const N: usize>(slots: &[DriftSlot<N>], par: &Params<N>) -> Result<f64, CalibError> {
    let mut f = Filter::start(par);
    let mut ll = 0.0;
    for (k, slot) in slots.iter().enumerate() {
        if k > 0 {
            f.predict(par);
        }
        observe_sample(&mut f, slot, par, &mut ll, None)?;
    }
    Ok(ll)
}

/// [`filter`] that first sets every sample's weight from its predicted innovation: `w = (ν + 6)
/// / (ν + m)` with `m` the squared Mahalanobis distance of the six innovations at the noise `r`
/// (a robust filter: a glitch of the reference is discounted before it moves the drift, so the
/// samples around it are not).
pub(crate) fn filter_robust<const N: usize, const P: usize>(
    slots: &mut [DriftSlot<N>],
    x: &[f64; P],
    t: &Trend<N>,
    par: &Params<N>,
    dof: f64,
) -> Result<f64, CalibError> {
    filter_weighting(slots, x, t, par, Some(dof))
}

/// Per joint: the long-run variance (batch means) and the lag-one autocorrelation of its
/// normalised drift innovations.
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct JointInnovations {
    pub long_run: f64,
    pub lag1: f64,
    /// The largest |normalised innovation| and its sample.
    pub largest: f64,
    pub at: usize,
}

/// What [`consistency`] measures.
#[derive(Clone, Copy, Debug)]
pub(crate) struct InnovationStats<const N: usize> {
    pub joints: [JointInnovations; N],
    pub pose_nis: [f64; 6],
    pub pose_long_run: [f64; 6],
    pub blocks: usize,
}

/// Batch means of a unit-variance white sequence: block sums, their mean square over the
/// block length, the sum of squares and of lag-one products.
#[derive(Clone, Copy, Debug, Default)]
struct Batch {
    block: f64,
    blocks: f64,
    sum2: f64,
    lag1: f64,
    last: f64,
}

impl Batch {
    fn add(&mut self, u: f64, close: bool, len: f64) {
        self.block += u;
        self.sum2 += u * u;
        self.lag1 += u * self.last;
        self.last = u;
        if close {
            self.blocks += self.block * self.block / len;
            self.block = 0.0;
        }
    }
}

/// [`log_likelihood`] (read-only, the same bits) that also measures how well the data follow
/// the model: per joint, the normalised drift innovations `(m⁺ − m⁻)_j / √(P⁻ − P⁺)_jj` (the
/// filter's update of the joint's drift over its variance: white, unit variance under the
/// model), and per pose component the standardised innovations; of each, the long-run variance
/// by batch means (blocks of `max(10, √K)` samples) and the lag-one autocorrelation.
pub(crate) fn consistency<const N: usize>(
    slots: &[DriftSlot<N>],
    par: &Params<N>,
) -> Result<(f64, InnovationStats<N>), CalibError> {
    let kn = slots.len();
    let len = libm::round(libm::sqrt(kn as f64).max(10.0)) as usize;
    let blocks = kn / len.max(1);
    let used = blocks * len;
    let mut f = Filter::start(par);
    let mut ll = 0.0;
    let mut joint = [Batch::default(); N];
    let mut largest = [(0.0f64, 0usize); N];
    let mut pose = [Batch::default(); 6];
    let mut z = [0.0; 6];
    for (k, slot) in slots.iter().enumerate() {
        if k > 0 {
            f.predict(par);
        }
        let (m0, p0) = (f.m, core::array::from_fn::<f64, N, _>(|j| f.p[j][j]));
        observe_sample(&mut f, slot, par, &mut ll, Some(&mut z))?;
        let close = (k + 1) % len == 0 && k < used;
        for j in 0..N {
            let v = p0[j] - f.p[j][j];
            let u = if v > 0.0 { (f.m[j] - m0[j]) / libm::sqrt(v) } else { 0.0 };
            if u.abs() > largest[j].0 {
                largest[j] = (u.abs(), k);
            }
            if k < used {
                joint[j].add(u, close, len as f64);
            }
        }
        if k >= used {
            continue;
        }
        for i in 0..6 {
            pose[i].add(z[i], close, len as f64);
        }
    }
    let b = blocks.max(1) as f64;
    let lag = |x: &Batch| if x.sum2 > 0.0 { x.lag1 / x.sum2 } else { 0.0 };
    Ok((
        ll,
        InnovationStats {
            joints: core::array::from_fn(|j| JointInnovations {
                long_run: joint[j].blocks / b,
                lag1: lag(&joint[j]),
                largest: largest[j].0,
                at: largest[j].1,
            }),
            pose_nis: core::array::from_fn(|i| pose[i].sum2 / used.max(1) as f64),
            pose_long_run: core::array::from_fn(|i| pose[i].blocks / b),
            blocks,
        },
    ))
}

/// Sufficient statistics of the M-step, summed over the samples.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Stats<const N: usize> {
    /// `E[δ_0²]`.
    pub e0: [f64; N],
    /// `Σ_{k<K−1} E[δ_k²]`.
    pub s00: [f64; N],
    /// `Σ_{k>0} E[δ_k δ_{k−1}]`.
    pub s10: [f64; N],
    /// `Σ_{k>0} E[δ_k²]`.
    pub s11: [f64; N],
    /// `Σ_k (y_k − J_k E[δ_k])_i²`.
    pub res: [f64; 6],
    /// `Σ_k Var[(J_k δ_k)_i]` (so that `res + var = Σ_k E[(y_k − J_k δ_k)_i²]`).
    pub var: [f64; 6],
}

impl<const N: usize> Stats<N> {
    /// Nothing summed yet.
    const ZERO: Self = Stats {
        e0: [0.0; N],
        s00: [0.0; N],
        s10: [0.0; N],
        s11: [0.0; N],
        res: [0.0; 6],
        var: [0.0; 6],
    };

    /// Joint `j`'s second moment `x` at sample `k` of `kn`: the first sample's, and into the
    /// sums over all but the last (`s00`) and all but the first (`s11`).
    #[inline(always)]
    fn add_moment(&mut self, k: usize, kn: usize, j: usize, x: f64) {
        if k == 0 {
            self.e0[j] = x;
        }
        if k + 1 < kn {
            self.s00[j] += x;
        }
        if k > 0 {
            self.s11[j] += x;
        }
    }
}

/// `Σ_b x[b]·rows[b]` (a vector-matrix product as a sum of scaled rows: vectorises).
#[inline(always)]
fn combo<const N: usize>(x: &[f64; N], rows: &[[f64; N]; N]) -> [f64; N] {
    let mut out = [0.0; N];
    for (xb, row) in x.iter().zip(rows) {
        for (o, v) in out.iter_mut().zip(row) {
            *o += xb * v;
        }
    }
    out
}

/// Solves `A X = B` for a symmetric positive definite `A` (Cholesky, row-oriented so that
/// every inner loop runs over the `N` right-hand sides); `b` is overwritten by `X`.
#[inline(always)]
fn spd_solve<const N: usize>(a: &[[f64; N]; N], b: &mut [[f64; N]; N]) -> Result<(), CalibError> {
    let mut l = [[0.0; N]; N];
    let mut inv = [0.0; N];
    for j in 0..N {
        let mut d = a[j][j];
        for x in &l[j][..j] {
            d -= x * x;
        }
        if !(d > 0.0 && d.is_finite()) {
            return Err(CalibError::InvalidInput {
                what: "predicted drift covariance not positive definite",
            });
        }
        let ljj = libm::sqrt(d);
        inv[j] = 1.0 / ljj;
        l[j][j] = ljj;
        for i in j + 1..N {
            let mut s = a[i][j];
            for (x, y) in l[i][..j].iter().zip(&l[j][..j]) {
                s -= x * y;
            }
            l[i][j] = s * inv[j];
        }
    }
    // Forward: L Z = B, row by row.
    for i in 0..N {
        let mut row = b[i];
        for k in 0..i {
            let lik = l[i][k];
            for (r, z) in row.iter_mut().zip(&b[k]) {
                *r -= lik * z;
            }
        }
        for r in row.iter_mut() {
            *r *= inv[i];
        }
        b[i] = row;
    }
    // Backward: Lᵀ X = Z.
    for i in (0..N).rev() {
        let mut row = b[i];
        for k in i + 1..N {
            let lki = l[k][i];
            for (r, x) in row.iter_mut().zip(&b[k]) {
                *r -= lki * x;
            }
        }
        for r in row.iter_mut() {
            *r *= inv[i];
        }
        b[i] = row;
    }
    Ok(())
}

/// An `N × N` matrix, row by row.
type Square<const N: usize> = [[f64; N]; N];

/// The Rauch-Tung-Striebel gain at a step whose filtered covariance is `cov`: the predicted
/// covariance `P⁻ = Φ P Φ + Q` and `Gᵀ = (P⁻)⁻¹ Φ P` (so `gt[b][a] = G[a][b]`).
#[inline(always)]
fn rts_gain<const N: usize>(cov: &Square<N>, par: &Params<N>) -> Result<(Square<N>, Square<N>), CalibError> {
    let mut fp = *cov;
    let mut pred = *cov;
    for a in 0..N {
        for b in 0..N {
            fp[a][b] *= par.phi[a];
            pred[a][b] = fp[a][b] * par.phi[b];
        }
        pred[a][a] += par.q[a];
    }
    let mut gt = fp;
    spd_solve(&pred, &mut gt)?;
    Ok((pred, gt))
}

/// `m += G D`, `G` given by `gt` as [`rts_gain`] returns it (row `a` of `G D` is
/// `Σ_b gt[b][a] D[b]`).
#[inline(always)]
fn add_gain_times<const N: usize>(m: &mut Square<N>, gt: &Square<N>, d: &Square<N>) {
    for (a, row) in m.iter_mut().enumerate() {
        let ga: [f64; N] = core::array::from_fn(|b| gt[b][a]);
        let add = combo(&ga, d);
        for (x, y) in row.iter_mut().zip(&add) {
            *x += y;
        }
    }
}

/// RTS smoother over the filtered slots (in place: the slots then hold the smoothed moments,
/// and each its `m2`), the M-step statistics (weighted: `res` and `var` sum `w_k`-scaled terms)
/// and the gradient of the log-likelihood in the static parameters,
/// `Σ_k H_kᵀ w_k R⁻¹ (y_k − J_k E[δ_k])` in `x` and the same with the rate-bias columns
/// `J_k s_k^m` in `t` (= `Hᵀ Σ⁻¹ y`, Σ the covariance of all residuals).
pub(crate) fn smooth<const N: usize, const P: usize>(
    slots: &mut [DriftSlot<N>],
    par: &Params<N>,
) -> Result<(Stats<N>, [f64; P], Trend<N>), CalibError> {
    let kn = slots.len();
    let mut st = Stats::ZERO;
    let mut grad = [0.0; P];
    let mut grad_t = [[0.0; RATE_BIAS_TERMS]; N];
    let rinv: [f64; 6] = core::array::from_fn(|i| 1.0 / par.r[i]);
    let mut add = |k: usize, slot: &mut DriftSlot<N>, st: &mut Stats<N>| {
        for j in 0..N {
            st.add_moment(k, kn, j, slot.mean[j] * slot.mean[j] + slot.cov[j][j]);
        }
        let w = slot.w;
        let b = basis(slot.s);
        let mut m2 = 0.0;
        for (i, ri) in rinv.iter().enumerate() {
            let h = &slot.h[i][3];
            let res = slot.y[i] - dot(h, &slot.mean);
            let ph = combo(h, &slot.cov);
            let var = dot(h, &ph);
            m2 += (res * res + var) * ri;
            st.res[i] += w * res * res;
            st.var[i] += w * var;
            let g = w * res * ri;
            for (gp, hp) in grad.iter_mut().zip(slot.h[i].as_flattened()) {
                *gp += hp * g;
            }
            for (gt, hj) in grad_t.iter_mut().zip(h) {
                for (gm, bm) in gt.iter_mut().zip(&b) {
                    *gm += hj * bm * g;
                }
            }
        }
        slot.m2 = m2;
    };
    add(kn - 1, &mut slots[kn - 1], &mut st);
    for k in (0..kn - 1).rev() {
        let (lo, hi) = slots.split_at_mut(k + 1);
        let (cur, next) = (&mut lo[k], &hi[0]);
        let (pred, gt) = rts_gain(&cur.cov, par)?;
        // Mean: m_s = m + G (m_s' − Φ m).
        let dm: [f64; N] = core::array::from_fn(|b| next.mean[b] - par.phi[b] * cur.mean[b]);
        let gdm = combo(&dm, &gt);
        for (m, d) in cur.mean.iter_mut().zip(&gdm) {
            *m += d;
        }
        // Covariance: P_s = P + G (P_s' − P⁻) Gᵀ; with D = P_s' − P⁻, (D Gᵀ) row b is
        // Σ_c D[b][c] gt[c], and G (D Gᵀ) row a is Σ_b gt[b][a] (D Gᵀ)[b].
        let mut dgt = [[0.0; N]; N];
        for b in 0..N {
            let drow: [f64; N] = core::array::from_fn(|c| next.cov[b][c] - pred[b][c]);
            dgt[b] = combo(&drow, &gt);
        }
        add_gain_times(&mut cur.cov, &gt, &dgt);
        // Symmetric up to rounding: make it exactly so.
        for a in 0..N {
            for c in a + 1..N {
                let v = 0.5 * (cur.cov[a][c] + cur.cov[c][a]);
                cur.cov[a][c] = v;
                cur.cov[c][a] = v;
            }
        }
        // Lag-one covariance diagonal: (P_s' Gᵀ)_jj.
        for (j, s10) in st.s10.iter_mut().enumerate() {
            let lag: f64 = next.cov[j].iter().zip(&gt).map(|(c, g)| c * g[j]).sum();
            *s10 += next.mean[j] * cur.mean[j] + lag;
        }
        add(k, cur, &mut st);
    }
    Ok((st, grad, grad_t))
}

/// What the uncertainty of the θ offsets adds to the M-step's second moments of each joint's
/// drift, `Σ_k (C̃_k V C̃_kᵀ)_jj` (and its lag-one and first-sample terms), with `C̃_k` the
/// sensitivity of the smoothed drift mean to the θ offsets and `V` their covariance: the
/// E-step of the restricted (REML) likelihood, in which the offsets are integrated out instead
/// of fixed at their estimate. `C̃` does not depend on the data: a forward pass carries the
/// filtered sensitivity `C_k` (the θ columns of the two-stage filter), a backward pass
/// smooths it with the Rauch-Tung-Striebel gains. The slots' `cov` and `sens` are overwritten.
pub(crate) fn restricted_moments<const N: usize>(
    slots: &mut [DriftSlot<N>],
    par: &Params<N>,
    v: &[[f64; N]; N],
) -> Result<Stats<N>, CalibError> {
    let kn = slots.len();
    let mut f = Filter::start(par);
    let mut c = [[0.0; N]; N];
    for (k, slot) in slots.iter_mut().enumerate() {
        if k > 0 {
            f.predict(par);
            for (row, phi) in c.iter_mut().zip(&par.phi) {
                for x in row.iter_mut() {
                    *x *= phi;
                }
            }
        }
        for i in 0..6 {
            let h = &slot.h[i][3];
            // d = h + hᵀ C (the θ columns of the two-stage row), then the update.
            let mut d = *h;
            for (ha, crow) in h.iter().zip(&c) {
                for (dl, cl) in d.iter_mut().zip(crow) {
                    *dl += ha * cl;
                }
            }
            let r = if slot.w == 1.0 { par.r[i] } else { par.r[i] / slot.w };
            let (_, s, ph) = f.observe(h, 0.0, r)?;
            let inv = 1.0 / s;
            for (crow, ka) in c.iter_mut().zip(&ph) {
                let ka = ka * inv;
                for (cl, dl) in crow.iter_mut().zip(&d) {
                    *cl -= ka * dl;
                }
            }
        }
        slot.cov = f.p;
        slot.sens = c;
    }
    let mut st = Stats::ZERO;
    // (C V Cᵀ)_jj and (A V Bᵀ)_jj.
    let quad = |a: &[f64; N], b: &[f64; N]| -> f64 {
        let vb = combo(b, v);
        dot(a, &vb)
    };
    let add = |k: usize, cur: &[[f64; N]; N], st: &mut Stats<N>| {
        for (j, row) in cur.iter().enumerate() {
            st.add_moment(k, kn, j, quad(row, row));
        }
    };
    add(kn - 1, &slots[kn - 1].sens, &mut st);
    for k in (0..kn - 1).rev() {
        let (lo, hi) = slots.split_at_mut(k + 1);
        let (cur, next) = (&mut lo[k], &hi[0]);
        let (_, gt) = rts_gain(&cur.cov, par)?;
        // C̃_k = C_k + G (C̃_{k+1} − Φ C_k).
        let d: [[f64; N]; N] = core::array::from_fn(|b| core::array::from_fn(|l| next.sens[b][l] - par.phi[b] * cur.sens[b][l]));
        add_gain_times(&mut cur.sens, &gt, &d);
        for j in 0..N {
            st.s10[j] += quad(&next.sens[j], &cur.sens[j]);
        }
        add(k, &cur.sens, &mut st);
    }
    Ok(st)
}

/// The two-stage filter: the drift mean is kept as `m + C x + C_t t`, affine in the static
/// parameters (the geometry offset `x` and, when `trend` is on, the rate-bias coefficients `t`),
/// so that one pass yields the exact likelihood as a quadratic in them: its whitened rows
/// (`d·x + d_t·t ≈ ν`, six per sample) go to the caller's accumulator.
pub(crate) struct TwoStage<const N: usize, const P: usize> {
    f: Filter<N>,
    c: [[f64; P]; N],
    ct: [Trend<N>; N],
    trend: bool,
    started: bool,
    /// Log-likelihood at `x = 0`, `t = 0`.
    pub ll: f64,
}

/// The whitened rows of one sample's six pose components in the rate-bias coefficients.
pub(crate) type TrendRows<const N: usize> = [Trend<N>; 6];

impl<const N: usize, const P: usize> TwoStage<N, P> {
    /// A pass without (`trend = false`) or with the rate-bias columns.
    pub fn new(par: &Params<N>, trend: bool) -> Self {
        TwoStage {
            f: Filter::start(par),
            c: [[0.0; P]; N],
            ct: [[[0.0; RATE_BIAS_TERMS]; N]; N],
            trend,
            started: false,
            ll: 0.0,
        }
    }

    /// Absorbs the next sample (its residual `y` at the static parameters the rows are relative
    /// to, Jacobian rows `h`, time fraction `s`, weight `w`); `sink` receives its six whitened
    /// rows (geometry, rate bias: zero without `trend`) and right-hand sides.
    #[inline]
    #[allow(clippy::too_many_arguments)]
    pub fn absorb(
        &mut self,
        y: &[f64; 6],
        h: &[[[f64; N]; 4]; 6],
        s: f64,
        w: f64,
        par: &Params<N>,
        sink: &mut impl FnMut(&[[f64; P]; 6], &TrendRows<N>, &[f64; 6]),
    ) -> Result<(), CalibError> {
        if self.started {
            self.f.predict(par);
            for ((crow, ctrow), phi) in self.c.iter_mut().zip(self.ct.iter_mut()).zip(&par.phi) {
                for v in crow.iter_mut() {
                    *v *= phi;
                }
                if self.trend {
                    for v in ctrow.as_flattened_mut() {
                        *v *= phi;
                    }
                }
            }
        }
        self.started = true;
        let mut rows = [[0.0; P]; 6];
        let mut trows = [[[0.0; RATE_BIAS_TERMS]; N]; 6];
        let mut rhs = [0.0; 6];
        let mut det = 1.0;
        let b = basis(s);
        for i in 0..6 {
            let hj = &h[i][3];
            // d = H_i + hᵀ C.
            let d = &mut rows[i];
            for (dp, hp) in d.iter_mut().zip(h[i].as_flattened()) {
                *dp = *hp;
            }
            for (ha, crow) in hj.iter().zip(&self.c) {
                for (dp, cp) in d.iter_mut().zip(crow) {
                    *dp += ha * cp;
                }
            }
            let dt = &mut trows[i];
            if self.trend {
                // d_t = h ⊗ basis + hᵀ C_t.
                for (dj, hjj) in dt.iter_mut().zip(hj) {
                    for (dm, bm) in dj.iter_mut().zip(&b) {
                        *dm = hjj * bm;
                    }
                }
                for (ha, ctrow) in hj.iter().zip(&self.ct) {
                    for (dv, cv) in dt.as_flattened_mut().iter_mut().zip(ctrow.as_flattened()) {
                        *dv += ha * cv;
                    }
                }
            }
            let r = if w == 1.0 { par.r[i] } else { par.r[i] / w };
            let (nu, s, ph) = self.f.observe(hj, y[i], r)?;
            let inv = 1.0 / s;
            for ((crow, ctrow), ka) in self.c.iter_mut().zip(self.ct.iter_mut()).zip(&ph) {
                let ka = ka * inv;
                for (cp, dp) in crow.iter_mut().zip(d.iter()) {
                    *cp -= ka * dp;
                }
                if self.trend {
                    for (cv, dv) in ctrow.as_flattened_mut().iter_mut().zip(dt.as_flattened()) {
                        *cv -= ka * dv;
                    }
                }
            }
            let sq = libm::sqrt(inv);
            for dp in d.iter_mut() {
                *dp *= sq;
            }
            if self.trend {
                for dv in dt.as_flattened_mut() {
                    *dv *= sq;
                }
            }
            rhs[i] = nu * sq;
            self.ll -= 0.5 * nu * nu * inv;
            det *= s;
        }
        self.ll -= 0.5 * (libm::log(det) + 6.0 * LN_2PI);
        sink(&rows, &trows, &rhs);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::DhTable;
    use crate::sim::{Scenario, ScenarioConfig};

    /// Linearised at the angle error `a`, the pseudo-measurement `e(θ + a) + J a` is the pose
    /// error at `θ` to second order in `a`, and `H` moves by first order.
    #[test]
    fn relinearising_at_an_angle_error_keeps_the_pose_error_to_second_order() {
        let table = DhTable::paper_nominal().prepare();
        let s = Scenario::new(ScenarioConfig::paper(), 3).nth(50).unwrap().sample;
        let mut cols = [[nalgebra::Vector6::zeros(); 7]; 4];
        let mut plain = DriftSlot::<7>::default();
        linearise_into(&table, &s, &mut cols, &mut plain);
        for scale in [1e-3, 1e-2] {
            let a: [f64; 7] = core::array::from_fn(|j| scale * (1.0 + j as f64) / 7.0);
            let mut moved = DriftSlot::<7>::default();
            linearise_at(&table, &s, Some(&a), &mut cols, &mut moved);
            let err = (0..6).map(|i| (moved.e[i] - plain.e[i]).abs()).fold(0.0, f64::max);
            let size = (0..6).map(|i| dot(&plain.h[i][3], &a).abs()).fold(0.0, f64::max);
            assert!(
                err < 2.0 * scale * size,
                "scale {scale}: {err:e} against a first-order {size:e}"
            );
        }
    }
}
