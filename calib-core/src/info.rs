//! The information of the static parameters of [`crate::em_drift`]: the geometry offset `x`
//! (`P = 4N`) and the rate-bias coefficients `t` (`RATE_BIAS_TERMS` per joint), as the two-stage
//! filter's whitened rows give it.
//!
//! The geometry has a flat prior; the rate-bias coefficients are random effects: term m of every
//! joint is `N(0, v_m)`, with the intensities `v` shared by the joints (the suit's sensors are
//! of one kind) and estimated by maximising the marginal likelihood ([`InfoAcc::choose_prior`]).
//! `v_m = 0` takes the term out of the model; `v = 0` is the paper's Gauss-Markov drift.
//!
//! The geometry keeps its normal equations ([`GramAccumulator`], analysed by SVD as in LS); the
//! rate-bias columns are eliminated by their Schur complement: with `C' = C + diag(1/v)`,
//! `S = A − B C'⁻¹ Bᵀ` is the geometry's information with the rate bias integrated out, `S⁻¹`
//! its covariance, and `C'⁻¹ (r_t − Bᵀ x)` the rate bias's posterior mean at a geometry `x`. The
//! rows must be accumulated at `t = 0` (the prior's centre), so that the step gives the absolute
//! rate bias.

use crate::kalman::{Trend, TrendRows, RATE_BIAS_TERMS};
use crate::linalg::{Analysis, GramAccumulator};

const M: usize = RATE_BIAS_TERMS;

/// Intensities of the rate bias's terms (rad²): the prior variance of every joint's
/// coefficient of each term; 0 takes the term out of the model.
pub(crate) type TrendPrior = [f64; M];

/// Largest intensity searched (rad²): a rate bias worth a radian over the session.
const PRIOR_MAX: f64 = 1.0;
/// Smallest intensity searched (rad²) before a term is taken out.
const PRIOR_MIN: f64 = 1e-14;

/// Whitened rows of the geometry and the rate bias, accumulated.
#[derive(Clone, Debug)]
pub(crate) struct InfoAcc<const N: usize, const P: usize> {
    pub gram: GramAccumulator<P>,
    /// `Σ d_x[p] d_t`: per geometry column, the cross products with the rate-bias columns.
    bt: [Trend<N>; P],
    /// `Σ d_t d_tᵀ`, indexed `[j][m][j'][m']`.
    ct: [[Trend<N>; M]; N],
    /// `Σ d_t ν`.
    rt: Trend<N>,
    /// Whether the rate-bias columns are accumulated.
    pub trend: bool,
}

/// A symmetric matrix over the rate-bias columns, `[j][m][j'][m']`.
type TrendMatrix<const N: usize> = [[Trend<N>; M]; N];

fn get<const N: usize>(a: &TrendMatrix<N>, r: usize, c: usize) -> f64 {
    a[r / M][r % M][c / M][c % M]
}

fn set<const N: usize>(a: &mut TrendMatrix<N>, r: usize, c: usize, v: f64) {
    a[r / M][r % M][c / M][c % M] = v;
}

impl<const N: usize, const P: usize> InfoAcc<N, P> {
    pub fn new(trend: bool) -> Self {
        InfoAcc {
            gram: GramAccumulator::new(),
            bt: [[[0.0; M]; N]; P],
            ct: [[[[0.0; M]; N]; M]; N],
            rt: [[0.0; M]; N],
            trend,
        }
    }

    /// Adds one sample's six rows.
    #[inline]
    pub fn add(&mut self, rows: &[[f64; P]; 6], trows: &TrendRows<N>, rhs: &[f64; 6]) {
        self.gram.add_rows(rows, rhs, 0);
        if !self.trend {
            return;
        }
        for ((row, trow), y) in rows.iter().zip(trows).zip(rhs) {
            let t = trow.as_flattened();
            for (b, dx) in self.bt.iter_mut().zip(row) {
                for (bv, tv) in b.as_flattened_mut().iter_mut().zip(t) {
                    *bv += dx * tv;
                }
            }
            for (a, ta) in t.iter().enumerate() {
                let crow = self.ct[a / M][a % M].as_flattened_mut();
                for (c, tb) in crow.iter_mut().zip(t) {
                    *c += ta * tb;
                }
            }
            for (r, tv) in self.rt.as_flattened_mut().iter_mut().zip(t) {
                *r += tv * y;
            }
        }
    }

    /// The analysis with the rate bias under `prior` (none in the model when every intensity is
    /// 0, or when the columns were not accumulated). `None` when the normal equations decline
    /// (see [`GramAccumulator::analyse`]).
    pub fn analyse(&self, prior: &TrendPrior, rel_tol: f64) -> Option<Info<N, P>> {
        if !self.trend || prior.iter().all(|v| *v <= 0.0) {
            return Some(Info::geometry(self.gram.analyse(rel_tol)?));
        }
        let factor = TrendFactor::new(&self.ct, prior)?;
        // Z = L⁻¹ Bᵀ (per geometry column), ζ = L⁻¹ r_t: S = A − ZᵀZ, b_S = b − Zᵀζ.
        let mut z = self.bt;
        for zp in z.iter_mut() {
            *zp = factor.masked(zp);
            factor.forward(zp);
        }
        let mut zeta = factor.masked(&self.rt);
        factor.forward(&mut zeta);
        let mut s = self.gram.clone();
        s.subtract_outer(|p, q| dot_t(&z[p], &z[q]), |p| dot_t(&z[p], &zeta), dot_t(&zeta, &zeta));
        Some(Info {
            an: s.analyse(rel_tol)?,
            trend: Some((factor, self.bt, self.rt)),
        })
    }

    /// `uᵀ A⁻¹ B Λ Bᵀ A⁻¹ u` with `Λ` the intensities `prior` per joint: the variance along `u`
    /// that rate-bias coefficients of those intensities add to the geometry estimated without
    /// them (`an`, the analysis of `A`; Schmidt's consider covariance). 0 without the columns.
    pub fn consider_variance(&self, an: &Analysis<P>, u: &[f64; P], prior: &TrendPrior) -> f64 {
        if !self.trend {
            return 0.0;
        }
        let a = an.solve(u);
        let mut v = 0.0;
        for j in 0..N {
            for (m, lambda) in prior.iter().enumerate() {
                let d: f64 = (0..P).map(|p| self.bt[p][j][m] * a[p]).sum();
                v += lambda * d * d;
            }
        }
        v
    }

    /// The intensities BIC prefers, and their `2 Δ ln L` against `v = 0` (the Gauss-Markov
    /// model): of every term fitted and the first alone (a steady rate bias, the rest at their
    /// floor; only where the floor allows them 0), the one whose `2 Δ ln L` less `terms · ln_k`
    /// is larger (`terms` its intensities that are not 0, `ln_k` the log of the sample count).
    /// Each maximises the marginal likelihood (the rate bias integrated out, the geometry
    /// profiled, the drift parameters fixed), searched per term in ln v (golden section over
    /// [max(1e-14, floor), 1] rad², two rounds) against the floor (0: the term out). `None`
    /// without rate-bias columns or when `A` declines.
    pub fn choose_prior(&self, rel_tol: f64, floor: &TrendPrior, ln_k: f64) -> Option<(TrendPrior, f64)> {
        let every = self.fit_terms(rel_tol, floor, [true; M])?;
        if floor[1..].iter().any(|v| *v > 0.0) {
            return Some(every);
        }
        let steady = self.fit_terms(rel_tol, floor, core::array::from_fn(|m| m == 0))?;
        let score = |(v, lr): &(TrendPrior, f64)| lr - v.iter().filter(|x| **x > 0.0).count().max(1) as f64 * ln_k;
        Some(if score(&steady) >= score(&every) { steady } else { every })
    }

    /// Those of the `active` terms searched (the others at their floor) and their `2 Δ ln L`.
    fn fit_terms(&self, rel_tol: f64, floor: &TrendPrior, active: [bool; M]) -> Option<(TrendPrior, f64)> {
        if !self.trend {
            return None;
        }
        let marginal = Marginal::new(self, rel_tol)?;
        let ll0 = marginal.log_likelihood(&[0.0; M])?;
        let mut best = *floor;
        let mut best_ll = marginal.log_likelihood(&best)?;
        for _ in 0..2 {
            for m in (0..M).filter(|m| active[*m]) {
                let at = |v: f64| {
                    let mut p = best;
                    p[m] = v;
                    marginal.log_likelihood(&p).unwrap_or(f64::NEG_INFINITY)
                };
                let (mut lo, mut hi) = (libm::log(PRIOR_MIN.max(floor[m])), libm::log(PRIOR_MAX.max(floor[m])));
                let gr = 0.618_033_988_749_894_9;
                let (mut a, mut b) = (hi - gr * (hi - lo), lo + gr * (hi - lo));
                let (mut fa, mut fb) = (at(libm::exp(a)), at(libm::exp(b)));
                for _ in 0..36 {
                    if fa >= fb {
                        hi = b;
                        (b, fb) = (a, fa);
                        a = hi - gr * (hi - lo);
                        fa = at(libm::exp(a));
                    } else {
                        lo = a;
                        (a, fa) = (b, fb);
                        b = lo + gr * (hi - lo);
                        fb = at(libm::exp(b));
                    }
                }
                let v = libm::exp(0.5 * (lo + hi));
                let (lv, l0) = (at(v), at(floor[m]));
                if lv > l0 && lv >= best_ll {
                    best[m] = v;
                    best_ll = lv;
                } else if l0 >= best_ll {
                    best[m] = floor[m];
                    best_ll = l0;
                }
            }
        }
        Some((best, 2.0 * (best_ll - ll0)))
    }
}

fn dot_t<const N: usize>(a: &Trend<N>, b: &Trend<N>) -> f64 {
    a.as_flattened().iter().zip(b.as_flattened()).map(|(x, y)| x * y).sum()
}

/// The marginal likelihood of the intensities from one accumulation: with `A⁻¹` applied once,
/// each evaluation is two Cholesky factorisations of the rate-bias block.
struct Marginal<const N: usize> {
    /// `C − Bᵀ A⁻¹ B`.
    c_schur: TrendMatrix<N>,
    /// `C`.
    c: TrendMatrix<N>,
    /// `r_t − Bᵀ A⁻¹ b`.
    r: Trend<N>,
}

impl<const N: usize> Marginal<N> {
    fn new<const P: usize>(acc: &InfoAcc<N, P>, rel_tol: f64) -> Option<Self> {
        let an = acc.gram.analyse(rel_tol)?;
        let ab = an.step(0.0);
        let nt = N * M;
        let mut c_schur = acc.ct;
        let mut r = acc.rt;
        for a in 0..nt {
            let col: [f64; P] = core::array::from_fn(|p| acc.bt[p][a / M][a % M]);
            let ainv = an.solve(&col);
            for b in a..nt {
                let v: f64 = (0..P).map(|p| ainv[p] * acc.bt[p][b / M][b % M]).sum();
                set(&mut c_schur, a, b, get(&acc.ct, a, b) - v);
                set(&mut c_schur, b, a, get(&acc.ct, a, b) - v);
            }
            r[a / M][a % M] -= (0..P).map(|p| col[p] * ab[p]).sum::<f64>();
        }
        Some(Marginal { c_schur, c: acc.ct, r })
    }

    /// `ln p(y | v)` up to a constant: `−½ [−r″ᵀ C″⁻¹ r″ + ln det Λ + ln det(Λ⁻¹ + C)]` on the
    /// terms with `v_m > 0`, `C″ = C − BᵀA⁻¹B + Λ⁻¹`.
    fn log_likelihood(&self, prior: &TrendPrior) -> Option<f64> {
        if prior.iter().all(|v| *v <= 0.0) {
            return Some(0.0);
        }
        let f2 = TrendFactor::new(&self.c_schur, prior)?;
        let mut u = f2.masked(&self.r);
        f2.forward(&mut u);
        let quad = dot_t(&u, &u);
        let f1 = TrendFactor::new(&self.c, prior)?;
        let mut logdet = f1.log_det();
        for (m, v) in prior.iter().enumerate() {
            if *v > 0.0 {
                let _ = m;
                logdet += N as f64 * libm::log(*v);
            }
        }
        Some(0.5 * quad - 0.5 * logdet)
    }
}

/// The Cholesky factor of `C + diag(1/v)` on the active terms (`v_m > 0`; the others: identity,
/// no cross terms).
#[derive(Clone, Debug)]
pub(crate) struct TrendFactor<const N: usize> {
    l: TrendMatrix<N>,
    prior: TrendPrior,
}

impl<const N: usize> TrendFactor<N> {
    fn new(c: &TrendMatrix<N>, prior: &TrendPrior) -> Option<Self> {
        let active = |a: usize| prior[a % M] > 0.0;
        let nt = N * M;
        let mut l = [[[[0.0; M]; N]; M]; N];
        for a in 0..nt {
            if !active(a) {
                set(&mut l, a, a, 1.0);
                continue;
            }
            let mut d = get(c, a, a) + 1.0 / prior[a % M];
            for k in 0..a {
                d -= get(&l, a, k) * get(&l, a, k);
            }
            if !(d > 0.0 && d.is_finite()) {
                return None;
            }
            let laa = libm::sqrt(d);
            set(&mut l, a, a, laa);
            for b in a + 1..nt {
                if !active(b) {
                    continue;
                }
                let mut x = get(c, a, b);
                for k in 0..a {
                    x -= get(&l, b, k) * get(&l, a, k);
                }
                set(&mut l, b, a, x / laa);
            }
        }
        Some(TrendFactor { l, prior: *prior })
    }

    fn masked(&self, v: &Trend<N>) -> Trend<N> {
        core::array::from_fn(|j| core::array::from_fn(|m| if self.prior[m] > 0.0 { v[j][m] } else { 0.0 }))
    }

    fn log_det(&self) -> f64 {
        (0..N * M)
            .filter(|a| self.prior[a % M] > 0.0)
            .map(|a| 2.0 * libm::log(get(&self.l, a, a)))
            .sum()
    }

    /// `v ← L⁻¹ v`.
    fn forward(&self, v: &mut Trend<N>) {
        let f = v.as_flattened_mut();
        for a in 0..f.len() {
            let mut x = f[a];
            for (c, fc) in f[..a].iter().enumerate() {
                x -= get(&self.l, a, c) * fc;
            }
            f[a] = x / get(&self.l, a, a);
        }
    }

    /// `v ← L⁻ᵀ v`.
    fn backward(&self, v: &mut Trend<N>) {
        let f = v.as_flattened_mut();
        for a in (0..f.len()).rev() {
            let mut x = f[a];
            for (c, fc) in f.iter().enumerate().skip(a + 1) {
                x -= get(&self.l, c, a) * fc;
            }
            f[a] = x / get(&self.l, a, a);
        }
    }

    /// `C'⁻¹ v` on the active terms (0 on the others).
    fn solve(&self, v: &Trend<N>) -> Trend<N> {
        let mut u = self.masked(v);
        self.forward(&mut u);
        self.backward(&mut u);
        self.masked(&u)
    }
}

/// The analysis of the static parameters (see the module docs).
#[derive(Clone, Debug)]
pub(crate) struct Info<const N: usize, const P: usize> {
    /// The geometry's information with the rate bias integrated out.
    pub an: Analysis<P>,
    /// The rate-bias block's factor, `B` and `r_t`, when the model has a rate bias.
    trend: Option<(TrendFactor<N>, [Trend<N>; P], Trend<N>)>,
}

impl<const N: usize, const P: usize> Info<N, P> {
    /// The geometry alone.
    pub fn geometry(an: Analysis<P>) -> Self {
        Info { an, trend: None }
    }

    /// The intensities of the rate bias in the model (0: none).
    pub fn prior(&self) -> TrendPrior {
        self.trend.as_ref().map_or([0.0; M], |(f, _, _)| f.prior)
    }

    /// The Gauss-Newton step of the accumulated problem (rows at `t = 0`): the geometry
    /// (rank-truncated) and the rate bias's posterior mean at that geometry.
    pub fn step(&self) -> ([f64; P], Trend<N>) {
        let dx = self.an.step(0.0);
        let t = match &self.trend {
            Some((_, _, rt)) => self.trend_at(&dx, rt),
            None => [[0.0; M]; N],
        };
        (dx, t)
    }

    /// `C'⁻¹ (g_t − Bᵀ dx)`.
    fn trend_at(&self, dx: &[f64; P], gt: &Trend<N>) -> Trend<N> {
        let Some((f, bt, _)) = &self.trend else {
            return [[0.0; M]; N];
        };
        let mut v = *gt;
        for (bp, x) in bt.iter().zip(dx) {
            for (vv, b) in v.as_flattened_mut().iter_mut().zip(bp.as_flattened()) {
                *vv -= b * x;
            }
        }
        f.solve(&v)
    }

    /// The penalised problem's inverse information times `(g_x, g_t)` (rank-truncated in the
    /// geometry); `g_t` is the gradient of the log-likelihood plus the prior's, `−t / v`.
    pub fn solve(&self, gx: &[f64; P], gt: &Trend<N>) -> ([f64; P], Trend<N>) {
        let Some((f, bt, _)) = &self.trend else {
            return (self.an.solve(gx), [[0.0; M]; N]);
        };
        let u = f.solve(gt);
        let g: [f64; P] = core::array::from_fn(|p| gx[p] - dot_t(&bt[p], &u));
        let dx = self.an.solve(&g);
        (dx, self.trend_at(&dx, gt))
    }

    /// The gradient of the rate bias's prior at `t`, `−t / v` (0 off the model).
    pub fn prior_gradient(&self, t: &Trend<N>) -> Trend<N> {
        let prior = self.prior();
        core::array::from_fn(|j| core::array::from_fn(|m| if prior[m] > 0.0 { -t[j][m] / prior[m] } else { 0.0 }))
    }

    /// Posterior standard errors of the geometry and of the rate-bias coefficients (0 where
    /// not in the model).
    pub fn std_errors(&self) -> ([f64; P], Trend<N>) {
        let sx = self.an.std_errors(1.0);
        let prior = self.prior();
        let st = core::array::from_fn(|j| {
            core::array::from_fn(|m| {
                if prior[m] <= 0.0 {
                    return 0.0;
                }
                let mut e = [[0.0; M]; N];
                e[j][m] = 1.0;
                let (_, t) = self.solve(&[0.0; P], &e);
                libm::sqrt(t[j][m].max(0.0))
            })
        });
        (sx, st)
    }

    /// The posterior covariance of joint `j`'s rate-bias coefficients (`M × M`, 0 off the
    /// model).
    pub fn trend_covariance(&self, j: usize) -> [[f64; M]; M] {
        let prior = self.prior();
        core::array::from_fn(|a| {
            if prior[a] <= 0.0 {
                return [0.0; M];
            }
            let mut e = [[0.0; M]; N];
            e[j][a] = 1.0;
            let (_, t) = self.solve(&[0.0; P], &e);
            core::array::from_fn(|m| t[j][m])
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    /// Whitened rows `ν = D_x x + D_t t + N(0, 1)` with random `D`, `x` and the rate bias `t`
    /// drawn from its prior: the fitted intensities find it, the step recovers `x` and `t`.
    #[test]
    fn the_rate_bias_intensity_and_coefficients_are_recovered_from_their_rows() {
        const N: usize = 7;
        const P: usize = 28;
        let mut rng = Rng::new(5);
        let truth_v = [4.0, 1.0];
        let x: [f64; P] = core::array::from_fn(|_| rng.normal());
        let t: Trend<N> = core::array::from_fn(|_| core::array::from_fn(|m| libm::sqrt(truth_v[m]) * rng.normal()));
        let mut acc = InfoAcc::<N, P>::new(true);
        let mut plain = InfoAcc::<N, P>::new(true);
        for _ in 0..400 {
            let rows: [[f64; P]; 6] = core::array::from_fn(|_| core::array::from_fn(|_| rng.normal()));
            let trows: TrendRows<N> =
                core::array::from_fn(|_| core::array::from_fn(|_| core::array::from_fn(|_| 0.3 * rng.normal())));
            let rhs: [f64; 6] = core::array::from_fn(|i| {
                let a: f64 = rows[i].iter().zip(&x).map(|(r, v)| r * v).sum();
                let b: f64 = trows[i].as_flattened().iter().zip(t.as_flattened()).map(|(r, v)| r * v).sum();
                a + b + rng.normal()
            });
            acc.add(&rows, &trows, &rhs);
            let rhs0: [f64; 6] = core::array::from_fn(|i| {
                rhs[i]
                    - trows[i]
                        .as_flattened()
                        .iter()
                        .zip(t.as_flattened())
                        .map(|(r, v)| r * v)
                        .sum::<f64>()
            });
            plain.add(&rows, &trows, &rhs0);
        }
        let (v, lr) = acc.fit_terms(1e-9, &[0.0; M], [true; M]).unwrap();
        assert!(lr > 20.0, "2ΔlnL {lr}");
        for m in 0..M {
            assert!(v[m] > 0.2 * truth_v[m] && v[m] < 5.0 * truth_v[m], "{v:?}");
        }
        let info = acc.analyse(&v, 1e-9).unwrap();
        let (dx, tt) = info.step();
        let err_t = tt
            .as_flattened()
            .iter()
            .zip(t.as_flattened())
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        let err_x = dx.iter().zip(&x).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
        assert!(err_t < 1.0 && err_x < 0.3, "t {err_t}, x {err_x}");
        // Without a rate bias in the rows, the intensities stay at (or near) zero.
        let (v0, lr0) = plain.fit_terms(1e-9, &[0.0; M], [true; M]).unwrap();
        assert!(lr0 < 6.0, "{v0:?} {lr0}");
    }
}
