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

    /// Absorbs the rows collected in `panel` with one blocked Householder QR of `[R; panel]`
    /// (a reflection per column over all the panel's rows instead of a Givens rotation per row
    /// and column), and empties the panel. Mathematically the same as [`QrAccumulator::add_row`]
    /// on every row; `R` keeps a non-negative diagonal.
    pub fn absorb<const M: usize>(&mut self, panel: &mut QrPanel<P, M>) {
        let (nf, nt) = (panel.nf, panel.nt);
        let mut w = [0.0; P];
        for j in 0..P {
            // Tail rows are zero in the first `split` columns: their reflections skip them.
            let nt_j = if j >= panel.split { nt } else { 0 };
            let (full, tail) = (&mut panel.full[..nf], &mut panel.tail[..nt_j]);
            let sigma = sum_sq_col(full, j) + sum_sq_col(tail, j);
            if sigma == 0.0 {
                continue;
            }
            // Reflection H = I − τ v vᵀ, v = [1; x / v0], mapping [r_jj; x] to [μ; 0], μ ≥ 0
            // (v0 = r_jj − μ without cancellation, Golub & Van Loan Alg. 5.1.1).
            let a = self.r[j][j];
            let mu = libm::sqrt(a * a + sigma);
            let v0 = if a <= 0.0 { a - mu } else { -sigma / (a + mu) };
            let tau = 2.0 * v0 * v0 / (sigma + v0 * v0);
            let inv = 1.0 / v0;
            self.r[j][j] = mu;
            // w = τ (r_j,k + Σ_i v_i x_ik) for k > j, and the same for the right-hand side.
            let wr = &mut w[j + 1..];
            wr.copy_from_slice(&self.r[j][j + 1..]);
            let mut wy = self.z[j];
            wy += project(full, &panel.full_y[..nf], j, inv, wr);
            wy += project(tail, &panel.tail_y[..nt_j], j, inv, wr);
            for wk in wr.iter_mut() {
                *wk *= tau;
            }
            wy *= tau;
            for (rk, wk) in self.r[j][j + 1..].iter_mut().zip(wr.iter()) {
                *rk -= wk;
            }
            self.z[j] -= wy;
            reflect(full, &mut panel.full_y[..nf], j, wr, wy);
            reflect(tail, &mut panel.tail_y[..nt_j], j, wr, wy);
        }
        self.rss += panel.full_y[..nf]
            .iter()
            .chain(&panel.tail_y[..nt])
            .map(|y| y * y)
            .sum::<f64>();
        self.rows += nf + nt;
        panel.nf = 0;
        panel.nt = 0;
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
        let scale = column_scale(&norms, self.rows);
        // Columns of the scaled R.
        let mut a: [[f64; P]; P] = core::array::from_fn(|j| core::array::from_fn(|i| self.r[i][j] / scale[j]));
        Analysis::of_triangle(&mut a, &self.z, scale, self.rows, self.rss, rel_tol)
    }
}

/// Column scales making every column of norm `√rows` (zero columns are left alone).
fn column_scale<const P: usize>(norms: &[f64; P], rows: usize) -> [f64; P] {
    let target = libm::sqrt(rows.max(1) as f64);
    core::array::from_fn(|j| if norms[j] > 0.0 { norms[j] / target } else { 1.0 })
}

/// Streaming normal equations of `min ‖H x − y‖²`: `HᵀH` (upper triangle), `Hᵀy`, `yᵀy`.
///
/// Half the work per row of the blocked Householder QR, at the price of squaring the condition
/// number: [`GramAccumulator::analyse`] declines (returns `None`) unless the column-scaled
/// problem is well conditioned, and the caller then uses a [`QrAccumulator`].
#[derive(Clone, Debug)]
pub struct GramAccumulator<const P: usize> {
    g: [[f64; P]; P],
    b: [f64; P],
    yy: f64,
    rows: usize,
}

impl<const P: usize> Default for GramAccumulator<P> {
    fn default() -> Self {
        Self::new()
    }
}

/// Largest scaled condition number [`GramAccumulator::analyse`] accepts: the normal equations
/// then lose at most `1e6 · ε ≈ 2e-10` relative in the step and the singular values.
pub const GRAM_MAX_CONDITION: f64 = 1e3;

/// Rows of `HᵀH` updated together by [`GramAccumulator`] (see `update_rows`). Two rows share
/// the loads of `h` and give the core independent sums: 234 → 203 ns per sample of the LS
/// (x86-64, baseline SSE2, CPU clock). Four rows, or four columns per step, hold more
/// broadcast factors than the 16 SSE registers and spill: 231 and 235 ns.
const GRAM_BLOCK: usize = 2;

impl<const P: usize> GramAccumulator<P> {
    /// An empty accumulator.
    pub fn new() -> Self {
        GramAccumulator {
            g: [[0.0; P]; P],
            b: [0.0; P],
            yy: 0.0,
            rows: 0,
        }
    }

    /// Number of rows absorbed.
    pub fn rows(&self) -> usize {
        self.rows
    }

    /// Empties the accumulator (in place).
    pub fn clear(&mut self) {
        for row in self.g.iter_mut() {
            row.fill(0.0);
        }
        self.b.fill(0.0);
        self.yy = 0.0;
        self.rows = 0;
    }

    /// Adds the rows absorbed by `other` (e.g. another block of the same session, accumulated
    /// on another core): the accumulator of both sets of rows.
    pub fn merge(&mut self, other: &Self) {
        for (row, orow) in self.g.iter_mut().zip(&other.g) {
            for (x, y) in row.iter_mut().zip(orow) {
                *x += y;
            }
        }
        for (x, y) in self.b.iter_mut().zip(&other.b) {
            *x += y;
        }
        self.yy += other.yy;
        self.rows += other.rows;
    }

    /// Subtracts a rank-deficient outer product from the accumulated problem: `HᵀH[p][q] −=
    /// g(p, q)` (upper triangle), `Hᵀy[p] −= b(p)`, `yᵀy −= yy`: the Schur complement of
    /// columns eliminated elsewhere (`g = ZᵀZ`, `b = Zᵀζ`, `yy = ζᵀζ`).
    pub(crate) fn subtract_outer(&mut self, g: impl Fn(usize, usize) -> f64, b: impl Fn(usize) -> f64, yy: f64) {
        for p in 0..P {
            for q in p..P {
                self.g[p][q] -= g(p, q);
            }
            self.b[p] -= b(p);
        }
        self.yy -= yy;
    }

    /// `vᵀ (HᵀH) v`, from the upper triangle the accumulator keeps.
    pub fn quadratic_form(&self, v: &[f64; P]) -> f64 {
        let mut sum = 0.0;
        for (i, (g, vi)) in self.g.iter().zip(v).enumerate() {
            let row: f64 = g[i + 1..].iter().zip(&v[i + 1..]).map(|(a, b)| a * b).sum();
            sum += vi * (g[i] * vi + 2.0 * row);
        }
        sum
    }

    /// Adds the `R` rows `h[r] · x ≈ y[r]`, which must be zero in the columns `0..first`.
    pub fn add_rows<const R: usize>(&mut self, h: &[[f64; P]; R], y: &[f64; R], first: usize) {
        self.update(core::array::from_fn(|r| &h[r]), y, first, P);
        self.yy += y.iter().map(|v| v * v).sum::<f64>();
        self.rows += R;
    }

    /// Adds three rows `full` (any columns) and three rows `tail` (zero in the columns
    /// `0..split`): the same as two [`GramAccumulator::add_rows`], with one pass over the rows of
    /// `HᵀH` from `split` on instead of two.
    pub fn add_rows_3_3(&mut self, full: &[[f64; P]; 3], yf: &[f64; 3], tail: &[[f64; P]; 3], yt: &[f64; 3], split: usize) {
        let split = split.min(P);
        self.update([&full[0], &full[1], &full[2]], yf, 0, split);
        let h = [&full[0], &full[1], &full[2], &tail[0], &tail[1], &tail[2]];
        self.update(h, &[yf[0], yf[1], yf[2], yt[0], yt[1], yt[2]], split, P);
        self.yy += yf.iter().chain(yt).map(|v| v * v).sum::<f64>();
        self.rows += 6;
    }

    /// `HᵀH += hᵀh` and `Hᵀy += hᵀy` in the rows `rows_from..rows_to` of `HᵀH` (upper triangle),
    /// [`GRAM_BLOCK`] rows at a time.
    #[inline]
    fn update<const R: usize>(&mut self, h: [&[f64; P]; R], y: &[f64; R], rows_from: usize, rows_to: usize) {
        const { assert!(R > 0, "at least one row") };
        let mut i = rows_from;
        while !i.is_multiple_of(GRAM_BLOCK) && i < rows_to {
            self.update_rows::<R, 1>(h, y, i);
            i += 1;
        }
        // Aligned blocks: their rows start at the same even column.
        while i + GRAM_BLOCK <= rows_to {
            self.update_rows::<R, GRAM_BLOCK>(h, y, i);
            i += GRAM_BLOCK;
        }
        while i < rows_to {
            self.update_rows::<R, 1>(h, y, i);
            i += 1;
        }
    }

    /// [`GramAccumulator::update`] of the `B` rows `i..i + B` of `HᵀH`, from column `i & !1`
    /// (an even column, so that every row splits into pairs of columns: vectorised, without a
    /// scalar remainder when `P` is even). The entries left of the diagonal that this adds to
    /// (`g[i + j][i & !1 .. i + j]`) are never read. Each entry gets the same sum, in the same
    /// order, as with `B = 1`: the result does not depend on `B`; the `B` rows share the loads
    /// of `h` and give the core `2B` independent sums per pair of columns.
    #[inline(always)]
    fn update_rows<const R: usize, const B: usize>(&mut self, h: [&[f64; P]; R], y: &[f64; R], i: usize) {
        let hi: [[f64; R]; B] = core::array::from_fn(|j| core::array::from_fn(|r| h[r][i + j]));
        let start = i & !1;
        let rows = &mut self.g[i..i + B];
        let mut k = start;
        while k + 2 <= P {
            // From the first product, not from 0.0 + it: the same sum (up to the sign of a
            // zero) for one addition fewer.
            let mut s: [[f64; 2]; B] = core::array::from_fn(|j| [hi[j][0] * h[0][k], hi[j][0] * h[0][k + 1]]);
            for r in 1..R {
                let (h0, h1) = (h[r][k], h[r][k + 1]);
                for (sj, hj) in s.iter_mut().zip(&hi) {
                    sj[0] += hj[r] * h0;
                    sj[1] += hj[r] * h1;
                }
            }
            for (row, sj) in rows.iter_mut().zip(&s) {
                row[k] += sj[0];
                row[k + 1] += sj[1];
            }
            k += 2;
        }
        if k < P {
            for (row, hj) in rows.iter_mut().zip(&hi) {
                let mut sum = hj[0] * h[0][k];
                for r in 1..R {
                    sum += hj[r] * h[r][k];
                }
                row[k] += sum;
            }
        }
        for (j, hj) in hi.iter().enumerate() {
            let mut sum = hj[0] * y[0];
            for r in 1..R {
                sum += hj[r] * y[r];
            }
            self.b[i + j] += sum;
        }
    }

    /// The same [`Analysis`] as [`QrAccumulator::analyse`] of the same rows, from the Cholesky
    /// factor of the column-scaled `HᵀH` (which is the scaled `R` of the QR). `None` when the
    /// factorisation fails or the scaled condition number exceeds [`GRAM_MAX_CONDITION`].
    pub fn analyse(&self, rel_tol: f64) -> Option<Analysis<P>> {
        self.analyse_from(rel_tol, None)
    }

    /// [`GramAccumulator::analyse`], with the SVD started from the right singular vectors of
    /// `warm` (typically the analysis of the previous iterate: the same result in fewer sweeps).
    #[inline(never)]
    pub fn analyse_from(&self, rel_tol: f64, warm: Option<&Analysis<P>>) -> Option<Analysis<P>> {
        let norms: [f64; P] = core::array::from_fn(|j| libm::sqrt(self.g[j][j]));
        let scale = column_scale(&norms, self.rows);
        // Upper Cholesky factor R of D⁻¹ HᵀH D⁻¹, kept by columns (`a[k][j] = R[j][k]`, the
        // layout of the SVD, so no second P × P array is needed on a small target's stack).
        let mut a = [[0.0; P]; P];
        for j in 0..P {
            let mut d = self.g[j][j] / (scale[j] * scale[j]);
            for x in &a[j][..j] {
                d -= x * x;
            }
            if !(d > 0.0 && d.is_finite()) {
                return None;
            }
            let rjj = libm::sqrt(d);
            a[j][j] = rjj;
            for k in j + 1..P {
                let mut x = self.g[j][k] / (scale[j] * scale[k]);
                x -= dot_prefix(&a[j], &a[k], j);
                a[k][j] = x / rjj;
            }
        }
        // z = R⁻ᵀ D⁻¹ Hᵀy (= Qᵀy of the QR), forward substitution.
        let mut z = [0.0; P];
        for j in 0..P {
            let x = self.b[j] / scale[j] - dot_prefix(&a[j], &z, j);
            z[j] = x / a[j][j];
        }
        let rss = (self.yy - dot(&z, &z)).max(0.0);
        // `of_triangle` scales by columns: hand it R with unit scales, then restore them.
        let mut an = Analysis::of_triangle_from(&mut a, &z, [1.0; P], self.rows, rss, rel_tol, warm.map(|w| &w.v));
        an.scale = scale;
        if an.condition() > GRAM_MAX_CONDITION {
            return None;
        }
        Some(an)
    }
}

/// Scales column `j` of `rows` by `inv` (it becomes the reflection vector `v`), adds
/// `Σ_i v_i rows[i][j+1..]` to `w` and returns `Σ_i v_i y_i`. Two rows at a time, so that `w`
/// is loaded and stored once per pair.
fn project<const P: usize>(rows: &mut [[f64; P]], y: &[f64], j: usize, inv: f64, w: &mut [f64]) -> f64 {
    let mut wy = 0.0;
    let mut pairs = rows.chunks_exact_mut(2);
    let mut ys = y.chunks_exact(2);
    for (pair, yy) in (&mut pairs).zip(&mut ys) {
        let (a, b) = pair.split_at_mut(1);
        let (a, b) = (&mut a[0], &mut b[0]);
        let (va, vb) = (a[j] * inv, b[j] * inv);
        a[j] = va;
        b[j] = vb;
        for ((wk, xa), xb) in w.iter_mut().zip(&a[j + 1..]).zip(&b[j + 1..]) {
            *wk += va * xa + vb * xb;
        }
        wy += va * yy[0] + vb * yy[1];
    }
    for (row, yy) in pairs.into_remainder().iter_mut().zip(ys.remainder()) {
        let v = row[j] * inv;
        row[j] = v;
        for (wk, xk) in w.iter_mut().zip(&row[j + 1..]) {
            *wk += v * xk;
        }
        wy += v * yy;
    }
    wy
}

/// Applies the reflection to the panel rows: `rows[i][j+1..] −= v_i w`, `y_i −= v_i w_y`.
fn reflect<const P: usize>(rows: &mut [[f64; P]], y: &mut [f64], j: usize, w: &[f64], wy: f64) {
    for (row, yi) in rows.iter_mut().zip(y) {
        let v = row[j];
        for (xk, wk) in row[j + 1..].iter_mut().zip(w) {
            *xk -= v * wk;
        }
        *yi -= v * wy;
    }
}

/// Σ_i rows[i][j]², with four partial sums (a single chain of dependent additions is slow).
fn sum_sq_col<const P: usize>(rows: &[[f64; P]], j: usize) -> f64 {
    let mut acc = [0.0; 4];
    let mut chunks = rows.chunks_exact(4);
    for c in &mut chunks {
        for (a, row) in acc.iter_mut().zip(c) {
            *a += row[j] * row[j];
        }
    }
    for (a, row) in acc.iter_mut().zip(chunks.remainder()) {
        *a += row[j] * row[j];
    }
    (acc[0] + acc[1]) + (acc[2] + acc[3])
}

/// Rows collected for one blocked Householder update of a [`QrAccumulator`]
/// ([`QrAccumulator::absorb`]), row-major: up to `M` "full" rows that may be non-zero in every
/// column, and up to `M` "tail" rows that are exactly zero in the first `split` columns (in LS,
/// the rotation rows vanish in the `a` and `d` columns), whose reflections then skip them.
#[derive(Clone, Debug)]
pub struct QrPanel<const P: usize, const M: usize> {
    full: [[f64; P]; M],
    full_y: [f64; M],
    nf: usize,
    tail: [[f64; P]; M],
    tail_y: [f64; M],
    nt: usize,
    split: usize,
}

impl<const P: usize, const M: usize> QrPanel<P, M> {
    /// An empty panel whose tail rows are zero in columns `0..split`.
    pub fn new(split: usize) -> Self {
        QrPanel {
            full: [[0.0; P]; M],
            full_y: [0.0; M],
            nf: 0,
            tail: [[0.0; P]; M],
            tail_y: [0.0; M],
            nt: 0,
            split,
        }
    }

    /// Room for `f` more full rows and `t` more tail rows.
    pub fn has_room(&self, f: usize, t: usize) -> bool {
        self.nf + f <= M && self.nt + t <= M
    }

    /// Appends a full row (`h · x ≈ y`); the caller checks [`QrPanel::has_room`].
    pub fn push_full(&mut self) -> (&mut [f64; P], &mut f64) {
        let i = self.nf;
        self.nf += 1;
        (&mut self.full[i], &mut self.full_y[i])
    }

    /// Appends a tail row; only its columns `split..` are read (the rest must be zero).
    pub fn push_tail(&mut self) -> (&mut [f64; P], &mut f64) {
        let i = self.nt;
        self.nt += 1;
        (&mut self.tail[i], &mut self.tail_y[i])
    }
}

/// `Σ_{i<n} x_i y_i`.
fn dot_prefix<const P: usize>(x: &[f64; P], y: &[f64; P], n: usize) -> f64 {
    x[..n].iter().zip(&y[..n]).map(|(a, b)| a * b).sum()
}

pub(crate) fn dot<const P: usize>(x: &[f64; P], y: &[f64; P]) -> f64 {
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
    /// SVD of the scaled triangle given by its columns `a` (with `R x_scaled = z`).
    fn of_triangle(a: &mut [[f64; P]; P], z: &[f64; P], scale: [f64; P], rows: usize, rss: f64, rel_tol: f64) -> Self {
        Self::of_triangle_from(a, z, scale, rows, rss, rel_tol, None)
    }

    /// [`Analysis::of_triangle`], with the Jacobi iteration started from the right singular
    /// vectors `warm` (any orthogonal matrix gives the same SVD; a nearby one, e.g. of the
    /// previous Gauss-Newton iterate, needs a fraction of the sweeps).
    #[inline(never)]
    fn of_triangle_from(
        a: &mut [[f64; P]; P],
        z: &[f64; P],
        scale: [f64; P],
        rows: usize,
        rss: f64,
        rel_tol: f64,
        warm: Option<&[[f64; P]; P]>,
    ) -> Self {
        let mut v: [[f64; P]; P] = match warm {
            Some(v0) => {
                // A ← A·V0, row by row in place: (A V0)[i][k] = Σ_j A[i][j] v0[k][j], with
                // A[i][j] = a[j][i].
                for i in 0..P {
                    let row: [f64; P] = core::array::from_fn(|k| (0..P).map(|j| a[j][i] * v0[k][j]).sum());
                    for (ak, x) in a.iter_mut().zip(row) {
                        ak[i] = x;
                    }
                }
                *v0
            }
            None => core::array::from_fn(|j| core::array::from_fn(|i| if i == j { 1.0 } else { 0.0 })),
        };
        jacobi_svd(a, &mut v);
        let sigma: [f64; P] = core::array::from_fn(|i| libm::sqrt(dot(&a[i], &a[i])));
        // a_iᵀ z = σ_i u_iᵀ z.
        let az: [f64; P] = core::array::from_fn(|i| dot(&a[i], z));
        let mut order: [usize; P] = core::array::from_fn(|i| i);
        order.sort_unstable_by(|&x, &y| sigma[y].total_cmp(&sigma[x]));
        let smax = if P > 0 { sigma[order[0]] } else { 0.0 };
        let tol = rel_tol * smax;
        let rank = order.iter().filter(|&&i| sigma[i] > tol && sigma[i] > 0.0).count();
        // Sort v in place (following the permutation's cycles: no second P × P array).
        let mut done = [false; P];
        for start in 0..P {
            let mut k = start;
            while !done[k] {
                done[k] = true;
                let next = order[k];
                if next != start {
                    v.swap(k, next);
                }
                k = next;
            }
        }
        Analysis {
            singular: core::array::from_fn(|k| sigma[order[k]]),
            v,
            az: core::array::from_fn(|k| az[order[k]]),
            scale,
            rank,
            rows,
            rss,
        }
    }

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

    /// `C g` for the parameter covariance `C` (physical units, row noise variance 1): the
    /// Gauss-Newton step of this problem for another gradient `g = Hᵀ(y − H x)`, truncated to
    /// the numerical rank like [`Analysis::step`] (`solve(Hᵀy) = step(0.0)`).
    pub fn solve(&self, g: &[f64; P]) -> [f64; P] {
        let gs: [f64; P] = core::array::from_fn(|p| g[p] / self.scale[p]);
        let mut xs = [0.0; P];
        for k in 0..self.rank {
            let w = dot(&self.v[k], &gs) / (self.singular[k] * self.singular[k]);
            for (x, vk) in xs.iter_mut().zip(&self.v[k]) {
                *x += w * vk;
            }
        }
        core::array::from_fn(|p| xs[p] / self.scale[p])
    }

    /// The decrease of the residual sum of squares that the Gauss-Newton step
    /// ([`Analysis::step`]`(0.0)`) predicts: the squared projection of the right-hand side on
    /// the identifiable directions.
    pub fn predicted_decrease(&self) -> f64 {
        (0..self.rank)
            .map(|k| {
                let c = self.az[k] / self.singular[k];
                c * c
            })
            .sum()
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

    /// `uᵀ C u` for the covariance `C` of the parameters (physical units) at row noise variance
    /// 1: the variance of the linear functional `u · Δx`, e.g. one output of the FK Jacobian.
    /// Directions outside the numerical rank are excluded, as in [`Analysis::std_errors`]
    /// (`variance_along(e_p) = std_errors(1.0)[p]²`).
    pub fn variance_along(&self, u: &[f64; P]) -> f64 {
        (0..self.rank)
            .map(|k| {
                let c: f64 = (0..P).map(|p| self.v[k][p] * u[p] / self.scale[p]).sum();
                c * c / (self.singular[k] * self.singular[k])
            })
            .sum()
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
    fn quadratic_form_is_v_hth_v() {
        let h = [[1.0, 2.0, -1.0], [0.5, -3.0, 2.0]];
        let mut g = GramAccumulator::<3>::new();
        g.add_rows(&h, &[0.0, 0.0], 0);
        let v = [0.3, -1.2, 2.5];
        let direct: f64 = h
            .iter()
            .map(|r| r.iter().zip(&v).map(|(a, b)| a * b).sum::<f64>().powi(2))
            .sum();
        assert!(
            (g.quadratic_form(&v) - direct).abs() < 1e-12 * direct.abs(),
            "{} vs {direct}",
            g.quadratic_form(&v)
        );
    }

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
    fn householder_panels_match_givens_rows() {
        let mut rng = Rng::new(7);
        let mut givens = QrAccumulator::<6>::new();
        let mut blocked = QrAccumulator::<6>::new();
        let mut panel = QrPanel::<6, 5>::new(2);
        for k in 0..37 {
            // Every other row is zero in the first two columns (a "tail" row).
            let tail = k % 2 == 1;
            let h: [f64; 6] = core::array::from_fn(|j| if tail && j < 2 { 0.0 } else { rng.normal() * (1 + j) as f64 });
            let y = rng.normal();
            givens.add_row(&h, y);
            if !panel.has_room(usize::from(!tail), usize::from(tail)) {
                blocked.absorb(&mut panel);
            }
            let (row, yy) = if tail { panel.push_tail() } else { panel.push_full() };
            *row = h;
            *yy = y;
        }
        blocked.absorb(&mut panel);
        assert_eq!(blocked.rows(), 37);
        assert!((blocked.residual_ss() - givens.residual_ss()).abs() < 1e-12 * givens.residual_ss());
        for i in 0..6 {
            for j in 0..6 {
                assert!(
                    (blocked.r[i][j] - givens.r[i][j]).abs() < 1e-12 * givens.r[i][i],
                    "R[{i}][{j}]"
                );
            }
            assert!((blocked.z[i] - givens.z[i]).abs() < 1e-12 * givens.r[i][i]);
        }
    }

    #[test]
    fn normal_equations_match_qr_when_well_conditioned_and_decline_otherwise() {
        let mut rng = Rng::new(8);
        let mut qr = QrAccumulator::<5>::new();
        let mut gram = GramAccumulator::<5>::new();
        for _ in 0..60 {
            // Badly scaled but well-conditioned after column scaling; rows zero in column 0
            // half of the time (the `first` argument).
            let h: [f64; 5] = core::array::from_fn(|j| rng.normal() * libm::pow(10.0, j as f64 - 2.0));
            let y = rng.normal();
            qr.add_row(&h, y);
            gram.add_rows(&[h], &[y], 0);
            let mut t = h;
            t[0] = 0.0;
            let y = rng.normal();
            qr.add_row(&t, y);
            gram.add_rows(&[t], &[y], 1);
        }
        let (a, b) = (qr.analyse(1e-9), gram.analyse(1e-9).expect("well conditioned"));
        assert_eq!((a.rank, a.rows()), (b.rank, b.rows()));
        for (x, y) in a.scale.iter().zip(&b.scale) {
            assert!((x - y).abs() < 1e-14 * x);
        }
        for k in 0..5 {
            assert!((a.singular[k] - b.singular[k]).abs() < 1e-12 * a.singular[0]);
        }
        for (x, y) in a.step(0.0).iter().zip(&b.step(0.0)) {
            assert!((x - y).abs() < 1e-12 * x.abs().max(1e-3), "{x} vs {y}");
        }
        assert!((a.noise_variance() - b.noise_variance()).abs() < 1e-12 * a.noise_variance());
        // Two identical columns: the normal equations decline.
        let mut gram = GramAccumulator::<2>::new();
        for _ in 0..10 {
            let u = rng.normal();
            gram.add_rows(&[[u, u]], &[u], 0);
        }
        assert!(gram.analyse(1e-9).is_none());
    }

    /// The update, entry by entry and in the plainest order: each entry's products summed over
    /// the rows in order, then added (indices, as in the formula).
    #[allow(clippy::needless_range_loop)]
    fn reference_update<const P: usize, const R: usize>(
        g: &mut [[f64; P]; P],
        b: &mut [f64; P],
        h: &[[f64; P]; R],
        y: &[f64; R],
        first: usize,
    ) {
        for i in first..P {
            for k in i..P {
                let mut s = h[0][i] * h[0][k];
                for r in 1..R {
                    s += h[r][i] * h[r][k];
                }
                g[i][k] += s;
            }
            let mut s = h[0][i] * y[0];
            for r in 1..R {
                s += h[r][i] * y[r];
            }
            b[i] += s;
        }
    }

    fn random_rows<const P: usize, const R: usize>(rng: &mut Rng, first: usize) -> [[f64; P]; R] {
        core::array::from_fn(|_| core::array::from_fn(|j| if j < first { 0.0 } else { rng.normal() }))
    }

    /// The blocked update gives every entry of the upper triangle the same sum, in the same
    /// order, as the plain one: bit for bit, for even and odd sizes and first rows.
    #[allow(clippy::needless_range_loop)]
    fn blocked_update_is_bit_identical<const P: usize>(firsts: &[usize]) {
        let mut rng = Rng::new(P as u64);
        let mut acc = GramAccumulator::<P>::new();
        let (mut g, mut b) = ([[0.0; P]; P], [0.0; P]);
        for round in 0..20 {
            let first = firsts[round % firsts.len()];
            let h3 = random_rows::<P, 3>(&mut rng, first);
            let y3 = [rng.normal(), rng.normal(), rng.normal()];
            acc.add_rows(&h3, &y3, first);
            reference_update(&mut g, &mut b, &h3, &y3, first);
            let full = random_rows::<P, 3>(&mut rng, 0);
            let tail = random_rows::<P, 3>(&mut rng, first);
            let (yf, yt) = (
                [rng.normal(), rng.normal(), rng.normal()],
                [rng.normal(), rng.normal(), rng.normal()],
            );
            acc.add_rows_3_3(&full, &yf, &tail, &yt, first);
            // The same 6 rows, full ones first: zero in the tail's leading columns.
            let six = [full[0], full[1], full[2], tail[0], tail[1], tail[2]];
            let y6 = [yf[0], yf[1], yf[2], yt[0], yt[1], yt[2]];
            let mut g_lead = [[0.0; P]; P];
            let mut b_lead = [0.0; P];
            // Rows 0..first of HᵀH see only the full rows; the reference adds them separately.
            reference_update(&mut g_lead, &mut b_lead, &full, &yf, 0);
            for i in 0..first.min(P) {
                for k in i..P {
                    g[i][k] += g_lead[i][k];
                }
                b[i] += b_lead[i];
            }
            let (mut g_tail, mut b_tail) = ([[0.0; P]; P], [0.0; P]);
            reference_update(&mut g_tail, &mut b_tail, &six, &y6, first.min(P));
            for i in first.min(P)..P {
                for k in i..P {
                    g[i][k] += g_tail[i][k];
                }
                b[i] += b_tail[i];
            }
            for i in 0..P {
                assert_eq!(acc.b[i].to_bits(), b[i].to_bits(), "P = {P}, b[{i}]");
                for k in i..P {
                    assert_eq!(acc.g[i][k].to_bits(), g[i][k].to_bits(), "P = {P}, g[{i}][{k}]");
                }
            }
        }
    }

    #[test]
    fn blocked_update_equals_the_plain_one_bit_for_bit() {
        blocked_update_is_bit_identical::<28>(&[0, 14, 3, 27]);
        blocked_update_is_bit_identical::<7>(&[0, 1, 2, 5, 6]);
        blocked_update_is_bit_identical::<8>(&[0, 3, 4, 7]);
        blocked_update_is_bit_identical::<1>(&[0]);
    }

    #[test]
    fn three_and_three_rows_equal_two_row_groups() {
        let mut rng = Rng::new(9);
        let (mut one, mut two) = (GramAccumulator::<7>::new(), GramAccumulator::<7>::new());
        for _ in 0..10 {
            let full: [[f64; 7]; 3] = core::array::from_fn(|_| core::array::from_fn(|_| rng.normal()));
            let tail: [[f64; 7]; 3] = core::array::from_fn(|_| core::array::from_fn(|j| if j < 3 { 0.0 } else { rng.normal() }));
            let (yf, yt) = (
                [rng.normal(), rng.normal(), rng.normal()],
                [rng.normal(), rng.normal(), rng.normal()],
            );
            one.add_rows_3_3(&full, &yf, &tail, &yt, 3);
            two.add_rows(&full, &yf, 0);
            two.add_rows(&tail, &yt, 3);
        }
        assert_eq!(one.rows(), two.rows());
        assert!((one.yy - two.yy).abs() < 1e-12 * two.yy);
        for i in 0..7 {
            assert!((one.b[i] - two.b[i]).abs() < 1e-12);
            for k in i..7 {
                assert!((one.g[i][k] - two.g[i][k]).abs() < 1e-12, "g[{i}][{k}]");
            }
        }
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
