//! The paper's objective y (eq. 10) and parameter errors against a known truth.
//!
//! `y = Σ_k ‖e_k‖₂` over the 6-vector pose error of [`crate::pose_error`] (position in metres
//! and rotation vector in radians, summed as the paper does). Its value does not depend on the
//! frame the error is expressed in.

use crate::model::{pose_error, DhTable, ParamKind, Sample};

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
}
