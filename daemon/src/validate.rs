//! Validation of a calibration before it may be pushed.
//!
//! Contract: [`validate`] checks a candidate table and returns a [`Verdict`] listing *every*
//! reason to refuse it (not just the first), so the log says everything that is wrong:
//! - every parameter finite;
//! - within the anatomical bounds of the configuration: `a_i`, `d_i` in their intervals (Table 2
//!   for `a_1..a_4`), `α_i` and the joint offset within the allowed deviation of nominal;
//! - the condition number of the identification problem at most `max_condition_number`;
//! - on the held-out slice (the end of the session, never fitted on) the mean pose error of the
//!   candidate is at least `min_improvement` (a fraction) below that of the nominal table.
//!
//! Pose error is calib-core's tool-frame 6-vector (position m, rotation vector rad); its norm,
//! averaged over the held-out samples, is the paper's objective y divided by their count.

use calib_core::{objective_y, pose_error, DhTable, Sample};
use serde::Serialize;

use crate::config::{Config, DhRow, JOINTS};

/// Fewest held-out samples a verdict may rest on.
pub const MIN_HELDOUT: usize = 50;

/// Held-out accuracy of one table.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Accuracy {
    /// Mean ‖6-vector pose error‖ (paper's y / K).
    pub mean_error: f64,
    /// Mean position error (m).
    pub mean_position_m: f64,
    /// Mean orientation error (rad).
    pub mean_rotation_rad: f64,
}

/// The outcome of [`validate`].
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Verdict {
    /// Every reason to refuse; empty when the table may be pushed.
    pub reasons: Vec<String>,
    pub condition_number: f64,
    pub heldout_samples: usize,
    pub nominal: Accuracy,
    pub candidate: Accuracy,
    /// `1 − candidate / nominal` mean error on the held-out slice.
    pub improvement: f64,
}

impl Verdict {
    /// Whether the table may be pushed.
    pub fn accepted(&self) -> bool {
        self.reasons.is_empty()
    }
}

/// The nominal table of the configuration, as calib-core's type.
pub fn table_from_rows(rows: &[DhRow; JOINTS]) -> DhTable<JOINTS> {
    DhTable {
        rows: rows.map(|r| calib_core::DhRow {
            a: r.a,
            alpha: r.alpha,
            d: r.d,
            theta_offset: r.offset,
        }),
    }
}

/// Splits time-ordered samples into (fit, held-out): the last `fraction` is held out.
pub fn split_holdout<T>(samples: &[T], fraction: f64) -> (&[T], &[T]) {
    let held = ((samples.len() as f64) * fraction.clamp(0.0, 1.0)).round() as usize;
    samples.split_at(samples.len() - held.min(samples.len()))
}

/// Held-out accuracy of `table` on `samples` (zeros when there are none).
pub fn accuracy(table: &DhTable<JOINTS>, samples: &[Sample<JOINTS>]) -> Accuracy {
    if samples.is_empty() {
        return Accuracy {
            mean_error: 0.0,
            mean_position_m: 0.0,
            mean_rotation_rad: 0.0,
        };
    }
    let n = samples.len() as f64;
    let (mut pos, mut rot) = (0.0, 0.0);
    for s in samples {
        let e = pose_error(&table.fk(&s.joints), &s.pose);
        pos += e.fixed_rows::<3>(0).norm();
        rot += e.fixed_rows::<3>(3).norm();
    }
    Accuracy {
        mean_error: objective_y(table, samples) / n,
        mean_position_m: pos / n,
        mean_rotation_rad: rot / n,
    }
}

/// Wraps an angle difference into (−π, π].
fn angle_diff(a: f64, b: f64) -> f64 {
    let tau = std::f64::consts::TAU;
    let d = (a - b).rem_euclid(tau);
    if d > std::f64::consts::PI {
        d - tau
    } else {
        d
    }
}

/// Checks `candidate` (see the module docs).
pub fn validate(
    candidate: &DhTable<JOINTS>,
    condition_number: f64,
    heldout: &[Sample<JOINTS>],
    config: &Config,
) -> Verdict {
    let mut reasons = Vec::new();
    let b = &config.bounds;
    for (i, (row, nom)) in candidate.rows.iter().zip(&config.nominal).enumerate() {
        let j = i + 1;
        let values = [row.a, row.d, row.alpha, row.theta_offset];
        if values.iter().any(|v| !v.is_finite()) {
            reasons.push(format!("joint {j}: non-finite parameter {values:?}"));
            continue;
        }
        if !b.a[i].contains(row.a) {
            reasons.push(format!(
                "joint {j}: a = {:.4} m outside [{}, {}]",
                row.a, b.a[i].min, b.a[i].max
            ));
        }
        if !b.d[i].contains(row.d) {
            reasons.push(format!(
                "joint {j}: d = {:.4} m outside [{}, {}]",
                row.d, b.d[i].min, b.d[i].max
            ));
        }
        let dalpha = angle_diff(row.alpha, nom.alpha);
        if dalpha.abs() > b.alpha_deviation {
            reasons.push(format!(
                "joint {j}: alpha is {:.2}° from nominal, at most {:.2}° allowed",
                dalpha.to_degrees(),
                b.alpha_deviation.to_degrees()
            ));
        }
        let doff = angle_diff(row.theta_offset, nom.offset);
        if doff.abs() > b.offset_deviation {
            reasons.push(format!(
                "joint {j}: joint offset is {:.2}° from nominal, at most {:.2}° allowed",
                doff.to_degrees(),
                b.offset_deviation.to_degrees()
            ));
        }
    }
    let max_k = config.validation.max_condition_number;
    if !(condition_number.is_finite() && condition_number <= max_k) {
        reasons.push(format!(
            "condition number {condition_number:.3e} above {max_k:.3e}: the motion did not excite every parameter"
        ));
    }
    let nominal_table = table_from_rows(&config.nominal);
    let nominal = accuracy(&nominal_table, heldout);
    let cand = accuracy(candidate, heldout);
    let improvement = if nominal.mean_error > 0.0 {
        1.0 - cand.mean_error / nominal.mean_error
    } else {
        0.0
    };
    if heldout.len() < MIN_HELDOUT {
        reasons.push(format!(
            "only {} held-out samples, at least {MIN_HELDOUT} needed",
            heldout.len()
        ));
    } else if improvement.is_nan() || improvement < config.validation.min_improvement {
        reasons.push(format!(
            "held-out pose error {:.3e} vs nominal {:.3e}: {:.1}% better, {:.1}% required",
            cand.mean_error,
            nominal.mean_error,
            improvement * 100.0,
            config.validation.min_improvement * 100.0
        ));
    }
    Verdict {
        reasons,
        condition_number,
        heldout_samples: heldout.len(),
        nominal,
        candidate: cand,
        improvement,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Samples of the paper's "actual" arm (Table 4) along a deterministic sweep, exact poses.
    fn samples(n: usize) -> Vec<Sample<JOINTS>> {
        let actual = DhTable::paper_actual();
        let ranges = Config::default_config().bounds.joint_range;
        (0..n)
            .map(|k| {
                let joints: [f64; JOINTS] = std::array::from_fn(|j| {
                    let u = 0.5 + 0.45 * ((k as f64) * 0.013 * (j as f64 + 1.0) + j as f64).sin();
                    ranges[j].min + u * ranges[j].width()
                });
                Sample {
                    joints,
                    pose: actual.fk(&joints),
                }
            })
            .collect()
    }

    #[test]
    fn the_true_table_passes_and_the_nominal_fails() {
        let config = Config::default_config();
        let held = samples(200);
        let truth = DhTable::paper_actual();
        let v = validate(&truth, 50.0, &held, &config);
        assert!(v.accepted(), "{:?}", v.reasons);
        assert!(v.improvement > 0.999_999, "{}", v.improvement);
        assert!(v.nominal.mean_position_m > 0.01, "{:?}", v.nominal);
        assert_eq!(v.heldout_samples, 200);

        let nominal = table_from_rows(&config.nominal);
        let v = validate(&nominal, 50.0, &held, &config);
        assert_eq!(v.improvement, 0.0);
        assert_eq!(v.reasons.len(), 1, "{:?}", v.reasons);
        assert!(v.reasons[0].contains("0.0% better"), "{:?}", v.reasons);
    }

    #[test]
    fn every_reason_is_listed() {
        let config = Config::default_config();
        let mut t = DhTable::paper_actual();
        t.rows[2].a = 0.6; // outside Table 2
        t.rows[4].d = 0.2;
        t.rows[1].alpha += 0.5; // ~28.6° off
        t.rows[6].theta_offset -= 1.0;
        let v = validate(&t, 1e9, &samples(10), &config);
        let all = v.reasons.join("\n");
        for needle in [
            "joint 3: a = 0.6000",
            "joint 5: d = 0.2000",
            "joint 2: alpha",
            "joint 7: joint offset",
            "condition number",
            "only 10 held-out samples",
        ] {
            assert!(all.contains(needle), "missing {needle} in\n{all}");
        }
        assert_eq!(v.reasons.len(), 6, "{all}");
    }

    #[test]
    fn non_finite_tables_and_conditions_are_refused() {
        let config = Config::default_config();
        let mut t = DhTable::paper_actual();
        t.rows[0].a = f64::NAN;
        let v = validate(&t, f64::NAN, &samples(100), &config);
        assert!(!v.accepted());
        assert!(v.reasons.iter().any(|r| r.contains("non-finite")));
        assert!(v.reasons.iter().any(|r| r.contains("condition number")));
        // The NaN table has NaN accuracy: that is a refusal too, not a pass.
        assert!(v.reasons.iter().any(|r| r.contains("held-out")));
    }

    #[test]
    fn angle_deviation_wraps() {
        assert!((angle_diff(3.1, -3.1) - (6.2 - std::f64::consts::TAU)).abs() < 1e-12);
        let half_pi = std::f64::consts::FRAC_PI_2;
        assert!(angle_diff(-half_pi, 3.0 * half_pi).abs() < 1e-12);
    }

    #[test]
    fn holdout_is_the_end_of_the_session() {
        let v: Vec<u32> = (0..10).collect();
        let (fit, held) = split_holdout(&v, 0.2);
        assert_eq!((fit.len(), held), (8, &[8, 9][..]));
        assert_eq!(split_holdout(&v, 0.0).1.len(), 0);
        assert_eq!(split_holdout(&v, 1.0).0.len(), 0);
    }
}
