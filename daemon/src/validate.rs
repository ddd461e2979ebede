//! Validation of a calibration before it may be pushed.
//!
//! Contract: [`validate`] checks a candidate table and returns a [`Verdict`] listing *every*
//! reason to refuse it (not just the first), so the log says everything that is wrong:
//! - every parameter finite;
//! - within the anatomical bounds of the configuration: `a_i`, `d_i` in their intervals (Table 2
//!   for `a_1..a_4`), `α_i` and the joint offset within the allowed deviation of nominal;
//! - the condition number of the identification problem at most `max_condition_number`;
//! - its **expected table error** (1σ, from the drift EM's Cramér-Rao bound: calib-core's
//!   `DriftEmResult::expected_error`) within `max_expected_position_error_mm` and
//!   `max_expected_rotation_error_mrad`; a table without one (the EM failed) is refused;
//! - on the held-out slice (the end of the session, never fitted on) the candidate is **not
//!   significantly worse than nominal**: a paired one-sided t-test of the per-sample difference
//!   of pose-error norms, over [`HELDOUT_BATCHES`] contiguous batch means (the drift correlates
//!   neighbouring samples; batch means are close to independent), refused above
//!   [`HELDOUT_T_REFUSE`].
//!
//! The held-out slice does not have to show a fixed improvement: its error is dominated by that
//! slice's own drift, so a suit close to nominal shows little improvement there although its
//! table error drops several-fold. Whether the table is accurate is what the expected table
//! error says; the held-out test catches a table that is wrong in a way the model did not see.
//!
//! Pose error is calib-core's tool-frame 6-vector (position m, rotation vector rad); its norm,
//! averaged over the held-out samples, is the paper's objective y divided by their count.

use calib_core::{objective_y, pose_error, DhTable, Sample, TableError};
use serde::Serialize;

use crate::config::{Config, DhRow, JOINTS};

/// Fewest held-out samples a verdict may rest on.
pub const MIN_HELDOUT: usize = 50;

/// Contiguous batches the held-out slice is cut into for the paired test.
pub const HELDOUT_BATCHES: usize = 10;

/// Refuse when the held-out t statistic (candidate minus nominal) exceeds this: the one-sided
/// 1% point of Student's t with `HELDOUT_BATCHES − 1` = 9 degrees of freedom.
pub const HELDOUT_T_REFUSE: f64 = 2.821;

/// A table's expected accuracy (1σ table error, see calib-core's `metrics`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Expected {
    /// RMS position error (mm).
    pub position_mm: f64,
    /// RMS rotation error (mrad).
    pub rotation_mrad: f64,
}

impl From<TableError> for Expected {
    fn from(e: TableError) -> Self {
        Expected {
            position_mm: e.position_m * 1e3,
            rotation_mrad: e.rotation_rad * 1e3,
        }
    }
}

impl std::fmt::Display for Expected {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "±{:.2} mm, ±{:.2} mrad (1σ)",
            self.position_mm, self.rotation_mrad
        )
    }
}

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
    /// `1 − candidate / nominal` mean error on the held-out slice (reported, not a criterion).
    pub improvement: f64,
    /// Paired t statistic of candidate minus nominal pose error on the held-out slice
    /// (negative: the candidate is better); NaN without enough held-out samples.
    pub heldout_t: f64,
    /// The table's expected accuracy; `None` when the EM did not provide one.
    pub expected: Option<Expected>,
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

/// Paired t statistic over [`HELDOUT_BATCHES`] batch means of `candidate − nominal` pose-error
/// norms (`+∞` when every batch is worse by the same amount, 0 when none differs).
fn paired_t(
    candidate: &DhTable<JOINTS>,
    nominal: &DhTable<JOINTS>,
    heldout: &[Sample<JOINTS>],
) -> f64 {
    let b = HELDOUT_BATCHES;
    let means: Vec<f64> = (0..b)
        .map(|i| {
            let batch = &heldout[i * heldout.len() / b..(i + 1) * heldout.len() / b];
            let sum: f64 = batch
                .iter()
                .map(|s| {
                    pose_error(&candidate.fk(&s.joints), &s.pose).norm()
                        - pose_error(&nominal.fk(&s.joints), &s.pose).norm()
                })
                .sum();
            sum / batch.len() as f64
        })
        .collect();
    let mean = means.iter().sum::<f64>() / b as f64;
    let var = means.iter().map(|m| (m - mean) * (m - mean)).sum::<f64>() / (b - 1) as f64;
    let se = (var / b as f64).sqrt();
    if se > 0.0 {
        mean / se
    } else if mean > 0.0 {
        f64::INFINITY
    } else if mean < 0.0 {
        f64::NEG_INFINITY
    } else if mean == 0.0 {
        0.0
    } else {
        f64::NAN
    }
}

/// Checks `candidate`, whose expected table error is `expected` (see the module docs).
pub fn validate(
    candidate: &DhTable<JOINTS>,
    condition_number: f64,
    expected: Option<TableError>,
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
    let rules = &config.validation;
    let expected = expected.map(Expected::from);
    match expected {
        None => reasons.push("no expected accuracy: the drift EM did not produce one".to_string()),
        Some(e) => {
            if e.position_mm.is_nan() || e.position_mm > rules.max_expected_position_error_mm {
                reasons.push(format!(
                    "expected table error ±{:.2} mm (1σ) above the {} mm allowed: more varied motion or a longer session would lower it",
                    e.position_mm, rules.max_expected_position_error_mm
                ));
            }
            if e.rotation_mrad.is_nan() || e.rotation_mrad > rules.max_expected_rotation_error_mrad
            {
                reasons.push(format!(
                    "expected table error ±{:.2} mrad (1σ) above the {} mrad allowed: more varied motion or a longer session would lower it",
                    e.rotation_mrad, rules.max_expected_rotation_error_mrad
                ));
            }
        }
    }
    let nominal_table = table_from_rows(&config.nominal);
    let nominal = accuracy(&nominal_table, heldout);
    let cand = accuracy(candidate, heldout);
    let improvement = if nominal.mean_error > 0.0 {
        1.0 - cand.mean_error / nominal.mean_error
    } else {
        0.0
    };
    let mut heldout_t = f64::NAN;
    if heldout.len() < MIN_HELDOUT {
        reasons.push(format!(
            "only {} held-out samples, at least {MIN_HELDOUT} needed",
            heldout.len()
        ));
    } else {
        heldout_t = paired_t(candidate, &nominal_table, heldout);
        if heldout_t.is_nan() || heldout_t > HELDOUT_T_REFUSE {
            reasons.push(format!(
                "held-out pose error {:.3e} vs nominal {:.3e}: significantly worse than nominal \
                 (paired t = {heldout_t:.2} over {HELDOUT_BATCHES} batches, refused above {HELDOUT_T_REFUSE})",
                cand.mean_error, nominal.mean_error,
            ));
        }
    }
    Verdict {
        reasons,
        condition_number,
        heldout_samples: heldout.len(),
        nominal,
        candidate: cand,
        improvement,
        heldout_t,
        expected,
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

    /// An expected accuracy well within the default limits.
    fn good() -> Option<TableError> {
        Some(TableError {
            position_m: 1e-3,
            rotation_rad: 3e-3,
        })
    }

    #[test]
    fn the_true_table_passes_and_a_table_worse_than_nominal_is_refused() {
        let config = Config::default_config();
        let held = samples(200);
        let truth = DhTable::paper_actual();
        let v = validate(&truth, 50.0, good(), &held, &config);
        assert!(v.accepted(), "{:?}", v.reasons);
        assert!(v.improvement > 0.999_999, "{}", v.improvement);
        assert!(v.heldout_t < -HELDOUT_T_REFUSE, "{}", v.heldout_t);
        assert!(v.nominal.mean_position_m > 0.01, "{:?}", v.nominal);
        assert_eq!(v.heldout_samples, 200);
        assert_eq!(v.expected.unwrap().to_string(), "±1.00 mm, ±3.00 mrad (1σ)");

        // Nominal itself is not worse than nominal.
        let nominal = table_from_rows(&config.nominal);
        let v = validate(&nominal, 50.0, good(), &held, &config);
        assert!(v.accepted(), "{:?}", v.reasons);
        assert_eq!((v.improvement, v.heldout_t), (0.0, 0.0));

        // Nominal with a 3° error at the shoulder is worse, everywhere on the held-out slice.
        let mut worse = nominal;
        worse.rows[1].theta_offset += 3f64.to_radians();
        let v = validate(&worse, 50.0, good(), &held, &config);
        assert_eq!(v.reasons.len(), 1, "{:?}", v.reasons);
        assert!(
            v.reasons[0].contains("significantly worse than nominal"),
            "{:?}",
            v.reasons
        );
        assert!(
            v.heldout_t > HELDOUT_T_REFUSE && v.improvement < 0.0,
            "{v:?}"
        );
    }

    #[test]
    fn the_expected_accuracy_must_be_known_and_within_the_limits() {
        let config = Config::default_config();
        let held = samples(200);
        let truth = DhTable::paper_actual();
        let v = validate(&truth, 50.0, None, &held, &config);
        assert_eq!(
            v.reasons,
            ["no expected accuracy: the drift EM did not produce one"]
        );
        let coarse = TableError {
            position_m: 4e-3,
            rotation_rad: 2e-3,
        };
        let v = validate(&truth, 50.0, Some(coarse), &held, &config);
        assert_eq!(v.reasons.len(), 1, "{:?}", v.reasons);
        assert!(
            v.reasons[0].starts_with("expected table error ±4.00 mm (1σ) above the 3 mm allowed"),
            "{:?}",
            v.reasons
        );
        let twisted = TableError {
            position_m: 1e-3,
            rotation_rad: 0.02,
        };
        let v = validate(&truth, 50.0, Some(twisted), &held, &config);
        assert!(
            v.reasons[0]
                .starts_with("expected table error ±20.00 mrad (1σ) above the 10 mrad allowed"),
            "{:?}",
            v.reasons
        );
    }

    #[test]
    fn every_reason_is_listed() {
        let config = Config::default_config();
        let mut t = DhTable::paper_actual();
        t.rows[2].a = 0.6; // outside Table 2
        t.rows[4].d = 0.2;
        t.rows[1].alpha += 0.5; // ~28.6° off
        t.rows[6].theta_offset -= 1.0;
        let v = validate(
            &t,
            1e9,
            Some(TableError {
                position_m: 0.1,
                rotation_rad: 0.1,
            }),
            &samples(10),
            &config,
        );
        let all = v.reasons.join("\n");
        for needle in [
            "joint 3: a = 0.6000",
            "joint 5: d = 0.2000",
            "joint 2: alpha",
            "joint 7: joint offset",
            "condition number",
            "±100.00 mm (1σ) above",
            "±100.00 mrad (1σ) above",
            "only 10 held-out samples",
        ] {
            assert!(all.contains(needle), "missing {needle} in\n{all}");
        }
        assert_eq!(v.reasons.len(), 8, "{all}");
    }

    #[test]
    fn non_finite_tables_and_conditions_are_refused() {
        let config = Config::default_config();
        let mut t = DhTable::paper_actual();
        t.rows[0].a = f64::NAN;
        let v = validate(&t, f64::NAN, good(), &samples(100), &config);
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
