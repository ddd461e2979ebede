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

/// Per-sample storage of [`crate::em_drift`]: the sample's linearisation, its residual and its
/// drift moments (filtered, then smoothed). One slot per sample: fixed memory, no allocation;
/// 230 `f64` for N = 7.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DriftSlot<const N: usize> {
    /// Pose error at the reference geometry.
    pub(crate) e: [f64; 6],
    /// Residual Jacobian `H`, row by row, each row in parameter order (`kind`, `joint`); the
    /// θ block `h[i][3]` is the drift Jacobian.
    pub(crate) h: [[[f64; N]; 4]; 6],
    /// Residual `e − H x` at the offset of the last filter pass.
    pub(crate) y: [f64; 6],
    /// Drift mean.
    pub(crate) mean: [f64; N],
    /// Drift covariance.
    pub(crate) cov: [[f64; N]; N],
}

impl<const N: usize> DriftSlot<N> {
    /// Smoothed drift estimate E[δ_k | all data] (rad) after [`crate::em_drift`].
    pub fn drift(&self) -> [f64; N] {
        self.mean
    }

    /// Its posterior standard deviation per joint (rad).
    pub fn drift_std(&self) -> [f64; N] {
        core::array::from_fn(|j| libm::sqrt(self.cov[j][j].max(0.0)))
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
    let t = table.fk_jacobian_into(&s.joints, cols);
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

/// Kalman filter over stored linearisations at the offset `x`: stores each sample's residual
/// and filtered moments, returns the log-likelihood `ln p(y_1..K)`.
pub(crate) fn filter<const N: usize, const P: usize>(
    slots: &mut [DriftSlot<N>],
    x: &[f64; P],
    par: &Params<N>,
) -> Result<f64, CalibError> {
    let mut f = Filter::start(par);
    let mut ll = 0.0;
    for (k, slot) in slots.iter_mut().enumerate() {
        if k > 0 {
            f.predict(par);
        }
        for i in 0..6 {
            slot.y[i] = slot.e[i] - row_dot(&slot.h[i], x);
        }
        observe_sample(&mut f, slot, par, &mut ll)?;
        slot.mean = f.m;
        slot.cov = f.p;
    }
    Ok(ll)
}

/// The six scalar updates of one sample from its stored residual `slot.y`, its likelihood
/// term subtracted from `ll` (in the order [`filter`] always used: the same bits).
#[inline(always)]
fn observe_sample<const N: usize>(
    f: &mut Filter<N>,
    slot: &DriftSlot<N>,
    par: &Params<N>,
    ll: &mut f64,
) -> Result<(), CalibError> {
    let mut det = 1.0;
    for i in 0..6 {
        let (nu, s, _) = f.observe(&slot.h[i][3], slot.y[i], par.r[i])?;
        *ll -= 0.5 * nu * nu / s;
        det *= s;
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
        observe_sample(&mut f, slot, par, &mut ll)?;
    }
    Ok(ll)
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

/// RTS smoother over the filtered slots (in place: the slots then hold the smoothed moments),
/// the M-step statistics and the gradient of the log-likelihood in the offset,
/// `Σ_k H_kᵀ R⁻¹ (y_k − J_k E[δ_k])` (= `Hᵀ Σ⁻¹ y`, Σ the covariance of all residuals).
pub(crate) fn smooth<const N: usize, const P: usize>(
    slots: &mut [DriftSlot<N>],
    par: &Params<N>,
) -> Result<(Stats<N>, [f64; P]), CalibError> {
    let kn = slots.len();
    let mut st = Stats {
        e0: [0.0; N],
        s00: [0.0; N],
        s10: [0.0; N],
        s11: [0.0; N],
        res: [0.0; 6],
        var: [0.0; 6],
    };
    let mut grad = [0.0; P];
    let rinv: [f64; 6] = core::array::from_fn(|i| 1.0 / par.r[i]);
    let mut add = |k: usize, slot: &DriftSlot<N>, st: &mut Stats<N>| {
        for j in 0..N {
            let ex = slot.mean[j] * slot.mean[j] + slot.cov[j][j];
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
        for (i, ri) in rinv.iter().enumerate() {
            let h = &slot.h[i][3];
            let res = slot.y[i] - dot(h, &slot.mean);
            let ph = combo(h, &slot.cov);
            st.res[i] += res * res;
            st.var[i] += dot(h, &ph);
            let w = res * ri;
            for (g, hp) in grad.iter_mut().zip(slot.h[i].as_flattened()) {
                *g += hp * w;
            }
        }
    };
    add(kn - 1, &slots[kn - 1], &mut st);
    for k in (0..kn - 1).rev() {
        let (lo, hi) = slots.split_at_mut(k + 1);
        let (cur, next) = (&mut lo[k], &hi[0]);
        // Predicted covariance P⁻ = Φ P Φ + Q and Φ P.
        let mut fp = cur.cov;
        let mut pred = cur.cov;
        for a in 0..N {
            for b in 0..N {
                fp[a][b] *= par.phi[a];
                pred[a][b] = fp[a][b] * par.phi[b];
            }
            pred[a][a] += par.q[a];
        }
        // Smoother gain Gᵀ = (P⁻)⁻¹ Φ P (so gt[b][a] = G[a][b]).
        let mut gt = fp;
        spd_solve(&pred, &mut gt)?;
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
        for (a, row) in cur.cov.iter_mut().enumerate() {
            let ga: [f64; N] = core::array::from_fn(|b| gt[b][a]);
            let add = combo(&ga, &dgt);
            for (c, v) in row.iter_mut().zip(&add) {
                *c += v;
            }
        }
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
    Ok((st, grad))
}

/// The two-stage filter: the drift mean is kept as `m + C x`, affine in the geometry offset,
/// so that one pass yields the exact likelihood as a quadratic in `x`: its whitened rows
/// (`d·x ≈ ν`, six per sample) go to the caller's accumulator.
pub(crate) struct TwoStage<const N: usize, const P: usize> {
    f: Filter<N>,
    c: [[f64; P]; N],
    started: bool,
    /// Log-likelihood at `x = 0`.
    pub ll: f64,
}

impl<const N: usize, const P: usize> TwoStage<N, P> {
    pub fn new(par: &Params<N>) -> Self {
        TwoStage {
            f: Filter::start(par),
            c: [[0.0; P]; N],
            started: false,
            ll: 0.0,
        }
    }

    /// Absorbs the next sample (residual `y`, Jacobian rows `h`); `sink` receives its six
    /// whitened rows and right-hand sides.
    #[inline]
    pub fn absorb(
        &mut self,
        y: &[f64; 6],
        h: &[[[f64; N]; 4]; 6],
        par: &Params<N>,
        sink: &mut impl FnMut(&[[f64; P]; 6], &[f64; 6]),
    ) -> Result<(), CalibError> {
        if self.started {
            self.f.predict(par);
            for (crow, phi) in self.c.iter_mut().zip(&par.phi) {
                for v in crow.iter_mut() {
                    *v *= phi;
                }
            }
        }
        self.started = true;
        let mut rows = [[0.0; P]; 6];
        let mut rhs = [0.0; 6];
        let mut det = 1.0;
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
            let (nu, s, ph) = self.f.observe(hj, y[i], par.r[i])?;
            let inv = 1.0 / s;
            for (crow, ka) in self.c.iter_mut().zip(&ph) {
                let ka = ka * inv;
                for (cp, dp) in crow.iter_mut().zip(d.iter()) {
                    *cp -= ka * dp;
                }
            }
            let w = libm::sqrt(inv);
            for dp in d.iter_mut() {
                *dp *= w;
            }
            rhs[i] = nu * w;
            self.ll -= 0.5 * nu * nu * inv;
            det *= s;
        }
        self.ll -= 0.5 * (libm::log(det) + 6.0 * LN_2PI);
        sink(&rows, &rhs);
        Ok(())
    }
}
