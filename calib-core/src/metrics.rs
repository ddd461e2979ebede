//! The paper's objective y (eq. 10), parameter errors against a known truth, and the table
//! error — how we judge a calibrated table.
//!
//! **Table error** ([`table_error`]): RMS over drift-free poses of the position (m) and the
//! rotation (rad, rotation-vector norm) of [`crate::pose_error`] between FK with one table and
//! FK with another (normally the calibrated and the true table). Unlike y on held-out motion,
//! it does not contain that motion's own drift. [`expected_table_error`] is its expectation
//! (1σ) for a parameter covariance, e.g. the Cramér-Rao bound of [`crate::em_drift`].
//!
//! `y = Σ_k ‖e_k‖₂` over the 6-vector pose error of [`crate::pose_error`] (position in metres
//! and rotation vector in radians, summed as the paper does). Its value does not depend on the
//! frame the error is expressed in.

use core::borrow::Borrow;

use crate::linalg::GramAccumulator;
use crate::model::{pose_error, DhTable, JointRanges, ParamKind, Sample};

/// RMS position and rotation difference between two tables' FK over a set of poses (see the
/// module docs), or its expectation.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct TableError {
    /// RMS position difference (m).
    pub position_m: f64,
    /// RMS rotation difference (rad).
    pub rotation_rad: f64,
}

/// Table error of `table` against `truth` over `poses` (joint angles, rad). Zero for no poses.
pub fn table_error<const N: usize>(
    table: &DhTable<N>,
    truth: &DhTable<N>,
    poses: impl IntoIterator<Item = impl Borrow<[f64; N]>>,
) -> TableError {
    let (mut pos, mut rot, mut n) = (0.0, 0.0, 0usize);
    for q in poses {
        let q = q.borrow();
        let e = pose_error(&table.fk(q), &truth.fk(q));
        pos += e.fixed_rows::<3>(0).norm_squared();
        rot += e.fixed_rows::<3>(3).norm_squared();
        n += 1;
    }
    rms(pos, rot, n)
}

/// Expected table error (1σ, RMS over `poses`) of a table near `table` whose parameter error
/// has covariance `C`, given as `variance(u) = uᵀ C u` over the `P = 4N` parameters in
/// [`DhTable::param`] order (e.g. [`crate::linalg::Analysis::variance_along`]). Linearised:
/// the FK difference at pose q is `J(q) Δ` with `J` the tool-frame FK Jacobian.
pub fn expected_table_error<const N: usize, const P: usize>(
    table: &DhTable<N>,
    poses: impl IntoIterator<Item = impl Borrow<[f64; N]>>,
    variance: impl Fn(&[f64; P]) -> f64,
) -> TableError {
    const { assert!(P == 4 * N, "P must be 4N") };
    let (mut pos, mut rot, mut n) = (0.0, 0.0, 0usize);
    for q in poses {
        let (_, cols) = table.fk_jacobian(q.borrow());
        // Row r of the 6 × P FK Jacobian: one output (position x, y, z, rotation x, y, z).
        let rows: [[f64; P]; 6] = core::array::from_fn(|r| core::array::from_fn(|p| cols[p / N][p % N][r]));
        for (r, u) in rows.iter().enumerate() {
            let v = variance(u).max(0.0);
            if r < 3 {
                pos += v;
            } else {
                rot += v;
            }
        }
        n += 1;
    }
    rms(pos, rot, n)
}

/// Expected table error (1σ, RMS over `poses`) of the plain least-squares table `table` (its
/// optimum on `samples`, consecutive at the drift's step) when the joint angles drift as
/// independent stationary AR(1) processes — coefficient `phi[j]` per sample, stationary variance
/// `drift_var[j]` (rad²) — and every pose component carries white noise of variance
/// `noise_var` (m², rad²): what LS alone is worth on such a session, beside the Cramér-Rao bound
/// that our EM reaches ([`crate::DriftEmResult::expected_error`]).
///
/// LS weighs every residual as white, so its error covariance is the sandwich `A⁻¹ B A⁻¹`, with
/// `A = Σₜ JₜᵀJₜ` and `B = Σₜₛ Jₜᵀ Cov(eₜ, eₛ) Jₛ`. A joint's drift enters the pose as its θ
/// offset does (the column `gₜⱼ = JₜᵀJₜ e_θⱼ`), so its share of `B` is
/// `σⱼ² Σₜₛ φⱼ^|t−s| gₜⱼ gₛⱼᵀ`, summed in one pass with `hₜ = φ (hₜ₋₁ + gₜ₋₁)` as
/// `(g + h)(g + h)ᵀ − h hᵀ` per sample. `None` if `A` is too ill-conditioned for its normal
/// equations (see [`GramAccumulator::analyse`]).
pub fn ls_expected_table_error<const N: usize, const P: usize>(
    table: &DhTable<N>,
    samples: &[Sample<N>],
    phi: &[f64; N],
    drift_var: &[f64; N],
    noise_var: &[f64; 6],
    poses: impl IntoIterator<Item = impl Borrow<[f64; N]>>,
) -> Option<TableError> {
    const { assert!(P == 4 * N, "P must be 4N") };
    let prepared = table.prepare();
    let theta = ParamKind::Theta as usize * N;
    let (mut a, mut plus, mut minus) = (
        GramAccumulator::<P>::new(),
        GramAccumulator::<P>::new(),
        GramAccumulator::<P>::new(),
    );
    let mut h = [[0.0; P]; N];
    let mut g_prev = [[0.0; P]; N];
    let noise_sd = noise_var.map(libm::sqrt);
    let drift_sd = drift_var.map(libm::sqrt);
    for s in samples {
        let (_, cols) = prepared.fk_jacobian(&s.joints);
        let rows: [[f64; P]; 6] = core::array::from_fn(|r| core::array::from_fn(|p| cols[p / N][p % N][r]));
        a.add_rows(&rows, &[0.0; 6], 0);
        plus.add_rows(&core::array::from_fn(|r| rows[r].map(|x| x * noise_sd[r])), &[0.0; 6], 0);
        // Per joint: hₜ = φ (hₜ₋₁ + gₜ₋₁), then gₜ = JₜᵀJₜ e_θⱼ; the rows σ(g + h) and σh.
        let mut up = [[0.0; P]; N];
        let mut down = [[0.0; P]; N];
        for j in 0..N {
            let g: [f64; P] = core::array::from_fn(|p| (0..6).map(|r| rows[r][p] * rows[r][theta + j]).sum());
            for p in 0..P {
                h[j][p] = phi[j] * (h[j][p] + g_prev[j][p]);
                up[j][p] = drift_sd[j] * (g[p] + h[j][p]);
                down[j][p] = drift_sd[j] * h[j][p];
            }
            g_prev[j] = g;
        }
        plus.add_rows(&up, &[0.0; N], 0);
        minus.add_rows(&down, &[0.0; N], 0);
    }
    let analysis = a.analyse(1e-9)?;
    Some(expected_table_error::<N, P>(table, poses, |u| {
        let v = analysis.solve(u);
        plus.quadratic_form(&v) - minus.quadratic_form(&v)
    }))
}

/// What an angle error `offset(k)` on every sample `k` moves a least-squares table by (in
/// [`DhTable::param`] order, linearised at `table`): `A⁻¹ Σₖ Jₖᵀ Jₖ^θ offset(k)`, with `A` as in
/// [`ls_expected_table_error`]. An angle error enters the pose as the joint's θ offset does, so
/// LS takes a constant one into the offsets exactly and a ramp partly into the rest of the
/// table: for the EM's fitted rate bias, what LS's table is expected to be off by, beside the
/// noise [`ls_expected_table_error`] states. `None` as for [`ls_expected_table_error`].
pub fn ls_response<const N: usize, const P: usize>(
    table: &DhTable<N>,
    samples: &[Sample<N>],
    offset: impl Fn(usize) -> [f64; N],
) -> Option<[f64; P]> {
    const { assert!(P == 4 * N, "P must be 4N") };
    let prepared = table.prepare();
    let theta = ParamKind::Theta as usize * N;
    let mut a = GramAccumulator::<P>::new();
    let mut b = [0.0; P];
    for (k, s) in samples.iter().enumerate() {
        let (_, cols) = prepared.fk_jacobian(&s.joints);
        let rows: [[f64; P]; 6] = core::array::from_fn(|r| core::array::from_fn(|p| cols[p / N][p % N][r]));
        a.add_rows(&rows, &[0.0; 6], 0);
        let c = offset(k);
        for row in &rows {
            let y: f64 = (0..N).map(|j| row[theta + j] * c[j]).sum();
            for (bp, h) in b.iter_mut().zip(row) {
                *bp += h * y;
            }
        }
    }
    Some(a.analyse(1e-9)?.solve(&b))
}

/// The expected table error (1σ, RMS over `poses`) of the least-squares table `table` on
/// `samples` when its residuals are white: [`ls_expected_table_error`] with no drift and each
/// pose component's noise variance taken as its residual variance at `table`. What LS alone is
/// worth where the drift EM has no figure to give (it failed, or the session has no drift to
/// speak of): honest for white residuals, optimistic by the drift's colour otherwise. `None` as
/// for [`ls_expected_table_error`].
pub fn ls_white_expected_error<const N: usize, const P: usize>(
    table: &DhTable<N>,
    samples: &[Sample<N>],
    poses: &ErrorPoses<N>,
) -> Option<TableError> {
    let mut var = [0.0; 6];
    for s in samples {
        let e = pose_error(&table.fk(&s.joints), &s.pose);
        for (v, x) in var.iter_mut().zip(e.iter()) {
            *v += x * x;
        }
    }
    let dof = samples.len().saturating_sub(P / 6 + 1).max(1) as f64;
    let var = var.map(|v| v / dof);
    ls_expected_table_error::<N, P>(table, samples, &[0.0; N], &[0.0; N], &var, poses.of(samples))
}

/// The poses an expected table error is averaged over (RMS): [`crate::EXPECTED_ERROR_POSES`] of
/// them.
///
/// A table is used over the joints' whole ranges, not only where its session went: a session
/// whose wrist moved through a third of its range identifies the wrist's parameters well
/// there and poorly at the ends, and its error over its own poses says nothing of the ends.
/// [`ErrorPoses::Ranges`] states what the table is worth over the ranges, whatever the session
/// covered; [`ErrorPoses::Session`] what it is worth where the session went. The two are close
/// when the session swept every joint's range; the even spread weighs the ends of the ranges
/// more than a wearer's motion does, so it is the more cautious of the two there.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum ErrorPoses<const N: usize> {
    /// The session's own poses, evenly spread over it.
    Session,
    /// Poses spread evenly over the joint ranges ([`JointRanges::spread`]): the same set for
    /// every session with these ranges.
    Ranges(JointRanges<N>),
}

impl<const N: usize> ErrorPoses<N> {
    /// The poses, for a session of `samples`.
    pub fn of<'a>(&self, samples: &'a [Sample<N>]) -> impl Iterator<Item = [f64; N]> + 'a {
        let (session, spread) = match *self {
            ErrorPoses::Session => {
                let stride = samples.len().div_ceil(crate::EXPECTED_ERROR_POSES).max(1);
                (Some(samples.iter().step_by(stride).map(|s| s.joints)), None)
            }
            ErrorPoses::Ranges(ranges) => (None, Some((0..crate::EXPECTED_ERROR_POSES).map(move |i| ranges.spread(i)))),
        };
        session.into_iter().flatten().chain(spread.into_iter().flatten())
    }
}

/// The median of `v` (sorted in place, by `f64::total_cmp`; the mean of the middle two for an
/// even count), NaN for none.
pub fn median(v: &mut [f64]) -> f64 {
    v.sort_unstable_by(f64::total_cmp);
    let n = v.len();
    match n {
        0 => f64::NAN,
        _ if n % 2 == 1 => v[n / 2],
        _ => 0.5 * (v[n / 2 - 1] + v[n / 2]),
    }
}

fn rms(pos: f64, rot: f64, n: usize) -> TableError {
    if n == 0 {
        return TableError::default();
    }
    TableError {
        position_m: libm::sqrt(pos / n as f64),
        rotation_rad: libm::sqrt(rot / n as f64),
    }
}

/// y (eq. 10) of `table` on `samples`, using the reported joint angles.
pub fn objective_y<const N: usize>(table: &DhTable<N>, samples: &[Sample<N>]) -> f64 {
    samples.iter().map(|s| pose_error(&table.fk(&s.joints), &s.pose).norm()).sum()
}

/// y with a per-sample joint correction: the model pose of sample `k` is
/// `FK(table, θ_k + correction(k))` (e.g. the smoothed drift of [`crate::em_drift`]).
pub fn objective_y_corrected<const N: usize>(
    table: &DhTable<N>,
    samples: &[Sample<N>],
    correction: impl Fn(usize) -> [f64; N],
) -> f64 {
    samples
        .iter()
        .enumerate()
        .map(|(k, s)| {
            let c = correction(k);
            let q: [f64; N] = core::array::from_fn(|j| s.joints[j] + c[j]);
            pose_error(&table.fk(&q), &s.pose).norm()
        })
        .sum()
}

/// Largest absolute error of each parameter kind against a truth (m for a, d; rad for α, θ).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ParamErrors {
    /// max |Δa| (m).
    pub a: f64,
    /// max |Δd| (m).
    pub d: f64,
    /// max |Δα| (rad).
    pub alpha: f64,
    /// max |Δθ offset| (rad).
    pub theta: f64,
}

impl ParamErrors {
    /// Errors of `estimate` against `truth`.
    pub fn between<const N: usize>(estimate: &DhTable<N>, truth: &DhTable<N>) -> Self {
        let max = |kind: ParamKind| {
            (0..N)
                .map(|j| (estimate.rows[j].get(kind) - truth.rows[j].get(kind)).abs())
                .fold(0.0, f64::max)
        };
        ParamErrors {
            a: max(ParamKind::A),
            d: max(ParamKind::D),
            alpha: max(ParamKind::Alpha),
            theta: max(ParamKind::Theta),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::{Scenario, ScenarioConfig};

    #[test]
    fn the_median_is_the_middle_or_the_mean_of_the_middle_two() {
        assert_eq!(median(&mut [3.0, -1.0, 2.0]), 2.0);
        assert_eq!(median(&mut [4.0, 1.0, 3.0, 2.0]), 2.5);
        assert!(median(&mut []).is_nan());
    }

    #[test]
    fn y_is_zero_for_the_truth_and_positive_for_nominal() {
        let mut cfg = ScenarioConfig::paper();
        cfg.drift.sigma = 0.0;
        let s: std::vec::Vec<_> = Scenario::new(cfg, 1).take(50).map(|s| s.sample).collect();
        assert!(objective_y(&DhTable::paper_actual(), &s) < 1e-12);
        let y = objective_y(&DhTable::paper_nominal(), &s);
        assert!(y > 50.0 * 0.01, "{y}");
        // A correction equal to the truth's offset difference is honoured.
        let shifted = DhTable::paper_actual().with_theta_offsets(&[0.01; 7]);
        assert!(objective_y(&shifted, &s) > 0.1);
        assert!(objective_y_corrected(&shifted, &s, |_| [-0.01; 7]) < 1e-12);
        let e = ParamErrors::between(&DhTable::paper_nominal(), &DhTable::paper_actual());
        assert!(
            (e.a - 0.03).abs() < 1e-12
                && (e.d - 0.03).abs() < 1e-12
                && (e.alpha - 5f64.to_radians()).abs() < 1e-12
                && e.theta == 0.0
        );
    }

    #[test]
    fn table_error_is_zero_for_the_same_table_and_matches_its_expectation_for_a_known_shift() {
        let poses: std::vec::Vec<[f64; 7]> = Scenario::new(ScenarioConfig::paper(), 3)
            .take(200)
            .map(|s| s.sample.joints)
            .collect();
        let truth = DhTable::paper_actual();
        assert_eq!(table_error(&truth, &truth, &poses), TableError::default());
        // A 1 mm shift of d_1 moves every pose by 1 mm, rotating nothing.
        let mut t = truth;
        t.rows[0].d += 1e-3;
        let e = table_error(&t, &truth, &poses);
        assert!((e.position_m - 1e-3).abs() < 1e-9 && e.rotation_rad < 1e-12, "{e:?}");
        // The expectation for a covariance concentrated on d_1 with variance (1 mm)² agrees.
        let d1 = ParamKind::D as usize * 7; // d_1
        let exp = expected_table_error::<7, 28>(&truth, &poses, |u| (1e-3 * u[d1]) * (1e-3 * u[d1]));
        assert!((exp.position_m - 1e-3).abs() < 1e-9 && exp.rotation_rad < 1e-12, "{exp:?}");
        // A joint-offset error rotates the tool: its rotation error is the offset.
        let mut t = truth;
        t.rows[6].theta_offset += 2e-3;
        let e = table_error(&t, &truth, &poses);
        assert!((e.rotation_rad - 2e-3).abs() < 1e-9, "{e:?}");
    }
}
