//! Small fixed-size dense linear algebra that must stay generic over a `const P`:
//! a streaming square-root-information accumulator (Givens QR) and a one-sided Jacobi SVD
//! of its column-scaled triangle. Memory is `O(P²)` whatever the number of rows.

/// Streaming least squares `min ‖H x − y‖²` kept as `R x = z` (R upper triangular, `P × P`)
/// plus the residual sum of squares not explained by any `x`.
#[derive(Clone, Debug)]
pub struct QrAccumulator<const P: usize> {
    /// `r[i][j]`, row-major, upper triangle used.
    r: [[f64; P]; P],
    z: [f64; P],
    rss: f64,
    rows: usize,
}

impl<const P: usize> Default for QrAccumulator<P> {
    fn default() -> Self {
        Self::new()
    }
}

impl<const P: usize> QrAccumulator<P> {
    /// An empty accumulator.
    pub fn new() -> Self {
        QrAccumulator {
            r: [[0.0; P]; P],
            z: [0.0; P],
            rss: 0.0,
            rows: 0,
        }
    }

    /// Number of rows absorbed.
    pub fn rows(&self) -> usize {
        self.rows
    }

    /// Residual sum of squares at the least-squares solution (of all rows absorbed).
    pub fn residual_ss(&self) -> f64 {
        self.rss
    }

    /// Absorbs one row `h·x ≈ y` with Givens rotations.
    pub fn add_row(&mut self, h: &[f64; P], y: f64) {
        let mut h = *h;
        let mut y = y;
        for j in 0..P {
            if h[j] == 0.0 {
                continue;
            }
            let a = self.r[j][j];
            // `hypot` guards against overflow and underflow of the squares, at several times
            // the cost of the plain formula; only fall back to it outside the safe range.
            let ss = a * a + h[j] * h[j];
            let rr = if (1e-290..1e290).contains(&ss) {
                libm::sqrt(ss)
            } else {
                libm::hypot(a, h[j])
            };
            let (c, s) = (a / rr, h[j] / rr);
            self.r[j][j] = rr;
            let row = &mut self.r[j];
            for k in j + 1..P {
                let (rk, hk) = (row[k], h[k]);
                row[k] = c * rk + s * hk;
                h[k] = c * hk - s * rk;
            }
            let zj = self.z[j];
            self.z[j] = c * zj + s * y;
            y = c * y - s * zj;
        }
        self.rss += y * y;
        self.rows += 1;
    }

    /// Column norms of the stacked `H` (equal to those of `R`).
    pub fn column_norms(&self) -> [f64; P] {
        core::array::from_fn(|j| libm::sqrt((0..=j).map(|i| self.r[i][j] * self.r[i][j]).sum::<f64>()))
    }

    /// Column-scales `R` (columns to norm `√rows`, so that singular values are per-sample
    /// RMS sensitivities) and takes its SVD. `rel_tol` decides the numerical rank:
    /// singular values below `rel_tol · σ_max` are treated as zero.
    pub fn analyse(&self, rel_tol: f64) -> Analysis<P> {
        let norms = self.column_norms();
        let target = libm::sqrt(self.rows.max(1) as f64);
        let scale: [f64; P] = core::array::from_fn(|j| if norms[j] > 0.0 { norms[j] / target } else { 1.0 });
        // Columns of the scaled R.
        let mut a: [[f64; P]; P] = core::array::from_fn(|j| core::array::from_fn(|i| self.r[i][j] / scale[j]));
        let mut v: [[f64; P]; P] = core::array::from_fn(|j| core::array::from_fn(|i| if i == j { 1.0 } else { 0.0 }));
        jacobi_svd(&mut a, &mut v);
        let sigma: [f64; P] = core::array::from_fn(|i| libm::sqrt(dot(&a[i], &a[i])));
        // a_iᵀ z = σ_i u_iᵀ z.
        let az: [f64; P] = core::array::from_fn(|i| dot(&a[i], &self.z));
        let mut order: [usize; P] = core::array::from_fn(|i| i);
        order.sort_unstable_by(|&x, &y| sigma[y].total_cmp(&sigma[x]));
        let smax = if P > 0 { sigma[order[0]] } else { 0.0 };
        let tol = rel_tol * smax;
        let rank = order.iter().filter(|&&i| sigma[i] > tol && sigma[i] > 0.0).count();
        Analysis {
            singular: core::array::from_fn(|k| sigma[order[k]]),
            v: core::array::from_fn(|k| v[order[k]]),
            az: core::array::from_fn(|k| az[order[k]]),
            scale,
            rank,
            rows: self.rows,
            rss: self.rss,
        }
    }
}

fn dot<const P: usize>(x: &[f64; P], y: &[f64; P]) -> f64 {
    x.iter().zip(y).map(|(a, b)| a * b).sum()
}

/// One-sided Jacobi SVD: orthogonalises the columns `a` in place, accumulating the rotations
/// in `v` (columns). On return `a = U Σ` column by column.
fn jacobi_svd<const P: usize>(a: &mut [[f64; P]; P], v: &mut [[f64; P]; P]) {
    for _sweep in 0..80 {
        let mut rotated = false;
        for i in 0..P {
            for j in i + 1..P {
                let alpha = dot(&a[i], &a[i]);
                let beta = dot(&a[j], &a[j]);
                let gamma = dot(&a[i], &a[j]);
                if gamma == 0.0 || gamma.abs() <= 1e-15 * libm::sqrt(alpha * beta) {
                    continue;
                }
                rotated = true;
                let zeta = (beta - alpha) / (2.0 * gamma);
                let t = zeta.signum() / (zeta.abs() + libm::sqrt(1.0 + zeta * zeta));
                let c = 1.0 / libm::sqrt(1.0 + t * t);
                let s = c * t;
                for m in [&mut *a, &mut *v] {
                    let (lo, hi) = m.split_at_mut(j);
                    let (ci, cj) = (&mut lo[i], &mut hi[0]);
                    for k in 0..P {
                        let (x, y) = (ci[k], cj[k]);
                        ci[k] = c * x - s * y;
                        cj[k] = s * x + c * y;
                    }
                }
            }
        }
        if !rotated {
            break;
        }
    }
}

/// The SVD of a column-scaled least-squares problem, sorted by decreasing singular value.
#[derive(Clone, Debug)]
pub struct Analysis<const P: usize> {
    /// Singular values of the scaled Jacobian (columns of RMS 1 per row), descending.
    pub singular: [f64; P],
    /// Right singular vectors (in scaled coordinates), `v[k]` belongs to `singular[k]`.
    pub v: [[f64; P]; P],
    az: [f64; P],
    /// Column scales: `x_physical = x_scaled / scale`.
    pub scale: [f64; P],
    /// Numerical rank.
    pub rank: usize,
    rows: usize,
    rss: f64,
}

impl<const P: usize> Analysis<P> {
    /// Damped minimum-norm step (`lambda = 0`: Gauss-Newton, truncated to the rank).
    pub fn step(&self, lambda: f64) -> [f64; P] {
        let mut xs = [0.0; P];
        for k in 0..self.rank {
            let w = self.az[k] / (self.singular[k] * self.singular[k] + lambda);
            for (x, vk) in xs.iter_mut().zip(&self.v[k]) {
                *x += w * vk;
            }
        }
        core::array::from_fn(|p| xs[p] / self.scale[p])
    }

    /// Condition number `σ_max / σ_min` of the scaled Jacobian (infinite if rank-deficient).
    pub fn condition(&self) -> f64 {
        match (self.singular.first(), self.singular.last()) {
            (Some(&hi), Some(&lo)) if lo > 0.0 => hi / lo,
            _ => f64::INFINITY,
        }
    }

    /// Rows of the problem.
    pub fn rows(&self) -> usize {
        self.rows
    }

    /// Residual variance per row, `rss / (rows − rank)`.
    pub fn noise_variance(&self) -> f64 {
        self.rss / (self.rows.saturating_sub(self.rank).max(1)) as f64
    }

    /// Standard deviation of each parameter (physical units) from the information matrix, for a
    /// row noise variance `noise_var` — the Cramér-Rao bound of the linearised problem.
    /// Directions outside the numerical rank are excluded (reported as unidentifiable).
    pub fn std_errors(&self, noise_var: f64) -> [f64; P] {
        core::array::from_fn(|p| {
            let var_s: f64 = (0..self.rank)
                .map(|k| self.v[k][p] * self.v[k][p] / (self.singular[k] * self.singular[k]))
                .sum();
            libm::sqrt(noise_var * var_s) / self.scale[p]
        })
    }

    /// Observability indices of the scaled Jacobian (see [`Observability`]).
    pub fn observability(&self) -> Observability {
        let m = P as f64;
        let rows = self.rows.max(1) as f64;
        let smax = self.singular.first().copied().unwrap_or(0.0);
        let smin = self.singular.last().copied().unwrap_or(0.0);
        let o1 = if smin > 0.0 {
            libm::exp(self.singular.iter().map(|s| libm::log(*s)).sum::<f64>() / m) / libm::sqrt(rows)
        } else {
            0.0
        };
        Observability {
            o1,
            o2: if smax > 0.0 { smin / smax } else { 0.0 },
            o3: smin,
            o4: if smax > 0.0 { smin * smin / smax } else { 0.0 },
        }
    }
}

/// Observability indices of an identification Jacobian (columns scaled to RMS 1 per row).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Observability {
    /// O1 (Borm & Menq): `(σ_1 ⋯ σ_m)^{1/m} / √rows`.
    pub o1: f64,
    /// O2: inverse condition number `σ_min / σ_max`.
    pub o2: f64,
    /// O3: minimum singular value `σ_min`.
    pub o3: f64,
    /// O4 (noise amplification): `σ_min² / σ_max`.
    pub o4: f64,
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    #[test]
    fn streaming_qr_solves_an_overdetermined_system() {
        let mut rng = Rng::new(5);
        let x_true = [1.0, -2.0, 1e-3, 50.0];
        let mut acc = QrAccumulator::<4>::new();
        for _ in 0..40 {
            // Badly scaled columns on purpose.
            let h = [rng.normal(), 1e-3 * rng.normal(), 1e3 * rng.normal(), rng.normal()];
            let y: f64 = h.iter().zip(&x_true).map(|(a, b)| a * b).sum();
            acc.add_row(&h, y);
        }
        let an = acc.analyse(1e-12);
        assert_eq!(an.rank, 4);
        let x = an.step(0.0);
        for (a, b) in x.iter().zip(&x_true) {
            assert!((a - b).abs() < 1e-9 * (1.0 + b.abs()), "{x:?}");
        }
        assert!(acc.residual_ss() < 1e-18);
        assert!(an.condition() < 10.0, "scaling failed: {}", an.condition());
    }

    #[test]
    fn rank_deficiency_is_detected_and_min_norm_step_returned() {
        let mut rng = Rng::new(6);
        let mut acc = QrAccumulator::<3>::new();
        for _ in 0..20 {
            let (u, w) = (rng.normal(), rng.normal());
            // Columns 0 and 1 identical: only x0 + x1 is identifiable.
            acc.add_row(&[u, u, w], 2.0 * u + 3.0 * w);
        }
        let an = acc.analyse(1e-10);
        assert_eq!(an.rank, 2);
        let null = an.v[2];
        assert!((null[0] + null[1]).abs() < 1e-9 && null[2].abs() < 1e-9);
        let x = an.step(0.0);
        assert!((x[0] + x[1] - 2.0).abs() < 1e-9 && (x[0] - x[1]).abs() < 1e-9 && (x[2] - 3.0).abs() < 1e-9);
        assert!(an.condition().is_infinite() || an.condition() > 1e10);
        assert_eq!(an.observability().o3, an.singular[2]);
    }
}
