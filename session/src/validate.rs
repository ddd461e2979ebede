//! Validation of a calibration before it may be pushed.
//!
//! Contract: [`validate`] checks a candidate table and returns a [`Verdict`] listing *every*
//! reason to refuse it (not just the first), so the log says everything that is wrong:
//! - every parameter finite;
//! - within the anatomical bounds of the configuration: `a_i`, `d_i` in their intervals (Table 2
//!   for `a_1..a_4`), `α_i` and the joint offset within the allowed deviation of nominal. A
//!   parameter estimated outside by at most [`BOUND_SLACK_SIGMAS`] of its own standard error is
//!   not evidence that the arm is: [`onto_bounds`] moves it onto the bound before validation (the
//!   table pushed is inside the bounds either way) and its stated error grows by the move;
//! - the condition number of the identification problem at most `max_condition_number`;
//! - its **expected table error** (1σ, from the drift EM's Cramér-Rao bound: calib-core's
//!   `DriftEmResult::expected_error`) within `max_expected_position_error_mm` and
//!   `max_expected_rotation_error_mrad`; a table without one (the EM failed) is refused;
//! - on the held-out slice (the end of the session) the table fitted without it — the candidate,
//!   or the table the candidate was refitted from on every sample ([`HeldOut`]) — is **not
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

use calib_core::{
    bound_violations, objective_y, pose_error, DhTable, ParamKind, Sample, TableError,
};
use std::fmt;

use serde::Serialize;

use crate::{Settings, MAX_JOINTS};

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

/// One reason to refuse a table: what a summary, the log and the report state, and what a
/// test matches. [`fmt::Display`] gives the line (the serialised form is that line too).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Refusal {
    /// A parameter of joint `joint` (1-based) is not finite.
    NonFinite {
        /// 1-based joint.
        joint: usize,
        /// Its a, d, α, θ offset.
        values: [f64; 4],
    },
    /// A parameter outside the anatomical bounds.
    Bound(calib_core::BoundViolation),
    /// The identification problem is too ill-conditioned.
    Conditioning {
        /// Its condition number.
        condition: f64,
        /// The largest allowed.
        max: f64,
    },
    /// The calibration produced no expected accuracy (the EM failed and LS's normal equations
    /// were too ill-conditioned to give one).
    NoExpectedAccuracy,
    /// The expected table error in position is above the limit.
    ExpectedPosition {
        /// 1σ, mm.
        mm: f64,
        /// The limit, mm.
        max: f64,
    },
    /// The expected table error in rotation is above the limit.
    ExpectedRotation {
        /// 1σ, mrad.
        mrad: f64,
        /// The limit, mrad.
        max: f64,
    },
    /// Too few held-out samples to judge the table.
    TooFewHeldOut {
        /// Held-out samples.
        have: usize,
    },
    /// The data contradict the drift EM's model (calib-core's reason: a joint's sensor that
    /// jumped, too many reference glitches, a drift grossly off its model).
    Model {
        /// calib-core's reason, naming the joint or the share.
        why: calib_core::Refusal,
        /// When it happened (s since the session's start), where there is a moment.
        at_s: Option<f64>,
    },
    /// Joints whose reading integrates its gyro unaided (`[sensors] unaided_joints`), and the
    /// suit never still long enough to measure the gyros' bias: their heading, which a session
    /// cannot tell from the geometry, is unmeasured.
    NeverStill {
        /// The unaided joints.
        joints: [bool; MAX_JOINTS],
    },
    /// On the held-out slice the judged table is significantly worse than nominal.
    WorseThanNominal {
        /// Mean pose error of the judged table.
        candidate: f64,
        /// Mean pose error of nominal.
        nominal: f64,
        /// The paired t statistic.
        t: f64,
    },
}

impl fmt::Display for Refusal {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            Refusal::NonFinite { joint, values } => {
                write!(f, "joint {joint}: non-finite parameter {values:?}")
            }
            Refusal::Bound(v) => f.write_str(&bound_reason(&v)),
            Refusal::Conditioning { condition, max } => write!(
                f,
                "condition number {condition:.3e} above {max:.3e}: the motion did not excite every parameter"
            ),
            Refusal::NoExpectedAccuracy => {
                f.write_str("no expected accuracy: neither the drift EM nor least squares could state one")
            }
            Refusal::ExpectedPosition { mm, max } => write!(
                f,
                "expected table error ±{mm:.2} mm (1σ) above the {max} mm allowed: more varied motion or a longer session would lower it"
            ),
            Refusal::ExpectedRotation { mrad, max } => write!(
                f,
                "expected table error ±{mrad:.2} mrad (1σ) above the {max} mrad allowed: more varied motion or a longer session would lower it"
            ),
            Refusal::Model { why, at_s: None } => write!(f, "{why}"),
            Refusal::Model {
                why,
                at_s: Some(t),
            } => write!(f, "{why} ({t:.2} s into the session)"),
            Refusal::NeverStill { joints } => {
                write!(
                    f,
                    "joints {} integrate their gyro unaided and the suit was never still for {} s: \
                     their heading is not measured (stand still for a few seconds at the start)",
                    crate::rules::joint_list(&joints),
                    calib_core::rest::MIN_REST_S
                )
            }
            Refusal::TooFewHeldOut { have } => write!(
                f,
                "only {have} held-out samples, at least {MIN_HELDOUT} needed"
            ),
            Refusal::WorseThanNominal {
                candidate,
                nominal,
                t,
            } => write!(
                f,
                "held-out pose error {candidate:.3e} vs nominal {nominal:.3e}: significantly worse than nominal \
                 (paired t = {t:.2} over {HELDOUT_BATCHES} batches, refused above {HELDOUT_T_REFUSE})"
            ),
        }
    }
}

impl Serialize for Refusal {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.collect_str(self)
    }
}

/// The outcome of [`validate`].
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Verdict {
    /// Every reason to refuse; empty when the table may be pushed.
    pub reasons: Vec<Refusal>,
    /// Condition number of the (column-scaled) identification problem.
    pub condition_number: f64,
    /// Samples in the held-out slice.
    pub heldout_samples: usize,
    /// Accuracy of the nominal table on the held-out slice.
    pub nominal: Accuracy,
    /// Accuracy of the judged table (fitted without the slice) on it.
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

/// Splits time-ordered samples into (fit, held-out): the last `fraction` is held out.
pub fn split_holdout<T>(samples: &[T], fraction: f64) -> (&[T], &[T]) {
    let held = ((samples.len() as f64) * fraction.clamp(0.0, 1.0)).round() as usize;
    samples.split_at(samples.len() - held.min(samples.len()))
}

/// Held-out accuracy of `table` on `samples` (zeros when there are none).
pub fn accuracy(table: &DhTable<MAX_JOINTS>, samples: &[Sample<MAX_JOINTS>]) -> Accuracy {
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

/// Paired t statistic over [`HELDOUT_BATCHES`] batch means of `candidate − nominal` pose-error
/// norms (`+∞` when every batch is worse by the same amount, 0 when none differs).
fn paired_t(
    candidate: &DhTable<MAX_JOINTS>,
    nominal: &DhTable<MAX_JOINTS>,
    heldout: &[Sample<MAX_JOINTS>],
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

/// How far outside its anatomical bound (in its own standard errors, 1σ) a parameter may be
/// estimated and be moved onto the bound instead of refusing the table ([`onto_bounds`]). An arm
/// a few mm inside a bound (the paper's `a_4` is 3 mm below its 267 mm) is estimated outside it
/// by chance in a few sessions in a hundred; one estimated outside by more is refused.
pub const BOUND_SLACK_SIGMAS: f64 = 1.0;

/// How far inside its bound [`onto_bounds`] puts a parameter (m or rad): nothing physical.
const ONTO_INSIDE: f64 = 1e-12;

/// A parameter estimated just outside its bound and moved onto it ([`onto_bounds`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OntoBound {
    /// The bound it was outside, with the estimated value.
    pub violation: calib_core::BoundViolation,
    /// The value it was moved to (on the bound).
    pub to: f64,
    /// How far outside it was, in its standard errors.
    pub sigmas: f64,
}

impl OntoBound {
    /// The move as the summary and the session log tell it.
    pub fn line(&self) -> String {
        format!("onto its bound: {self} (the expected table error includes the move)")
    }
}

impl fmt::Display for OntoBound {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let v = &self.violation;
        let j = v.joint + 1;
        let name = v.kind.name();
        let s = self.sigmas;
        if v.kind.is_angle() {
            let (from, to) = (v.value.to_degrees(), self.to.to_degrees());
            write!(
                f,
                "joint {j}: {name} {from:.3}° outside its bound by {s:.2}σ, moved onto it ({to:.3}°)"
            )
        } else {
            write!(
                f,
                "{} by {s:.2}σ, moved onto it ({:.4} m)",
                bound_reason(v),
                self.to
            )
        }
    }
}

impl Serialize for OntoBound {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.collect_str(self)
    }
}

/// `table` with every parameter that lies outside its bound by at most [`BOUND_SLACK_SIGMAS`]
/// of its standard error (`std_errors`, in [`DhTable::param`] order) moved onto the bound, and
/// the moves. Parameters further outside, or without a finite standard error, are left for
/// [`validate`] to refuse. The move is along that parameter alone: the caller adds the table
/// error it makes to the stated error (it is systematic, so added, not in quadrature).
pub fn onto_bounds(
    table: &DhTable<MAX_JOINTS>,
    std_errors: &[f64; crate::MAX_PARAMS],
    settings: &Settings,
) -> (DhTable<MAX_JOINTS>, Vec<OntoBound>) {
    let bounds = settings.bounds.table(&settings.nominal, settings.joints);
    let mut moved = *table;
    let mut moves = Vec::new();
    for v in bound_violations(table, &bounds).filter(|v| v.value.is_finite()) {
        let sigma = std_errors[v.kind.index(v.joint, MAX_JOINTS)];
        // Angles as bounds compare them: within π of the interval's centre.
        let centre = 0.5 * (v.min + v.max);
        let compared = if v.kind.is_angle() {
            centre + wrap_angle(v.value - centre)
        } else {
            v.value
        };
        // Onto the bound, a hair inside it: the bound check recomputes the angle's wrap.
        let on = compared.clamp(v.min + ONTO_INSIDE, v.max - ONTO_INSIDE);
        let sigmas = (compared - on).abs() / sigma;
        if sigma > 0.0 && sigma.is_finite() && sigmas <= BOUND_SLACK_SIGMAS {
            let to = v.value + (on - compared);
            *moved.rows[v.joint].get_mut(v.kind) = to;
            moves.push(OntoBound {
                violation: v,
                to,
                sigmas,
            });
        }
    }
    (moved, moves)
}

/// The refusal line of one bound violation: lengths against their interval, angles as their
/// deviation from nominal (the interval's centre).
fn bound_reason(v: &calib_core::BoundViolation) -> String {
    let j = v.joint + 1;
    let centre = 0.5 * (v.min + v.max);
    let off = wrap_angle(v.value - centre).to_degrees();
    let allowed = (0.5 * (v.max - v.min)).to_degrees();
    match v.kind {
        ParamKind::A | ParamKind::D => format!(
            "joint {j}: {} = {:.4} m outside [{}, {}]",
            v.kind.name(),
            v.value,
            v.min,
            v.max
        ),
        ParamKind::Alpha => {
            format!("joint {j}: alpha is {off:.2}° from nominal, at most {allowed:.2}° allowed")
        }
        ParamKind::Theta => format!(
            "joint {j}: joint offset is {off:.2}° from nominal, at most {allowed:.2}° allowed"
        ),
    }
}

/// `x` wrapped into [−π, π].
fn wrap_angle(x: f64) -> f64 {
    let tau = std::f64::consts::TAU;
    x - tau * (x / tau).round()
}

/// The held-out slice and the table it judges: one fitted without that slice — the candidate
/// itself, or the table the candidate was refitted from on every sample.
#[derive(Debug, Clone, Copy)]
pub struct HeldOut<'a> {
    /// The table fitted without the slice.
    pub table: &'a DhTable<MAX_JOINTS>,
    /// The held-out samples.
    pub samples: &'a [Sample<MAX_JOINTS>],
}

/// Checks `candidate`, whose expected table error is `expected` and whose identification has
/// `condition_number`, and judges `heldout` (see the module docs).
pub fn validate(
    candidate: &DhTable<MAX_JOINTS>,
    condition_number: f64,
    expected: Option<TableError>,
    heldout: HeldOut<'_>,
    settings: &Settings,
) -> Verdict {
    let mut reasons = Vec::new();
    for (i, row) in candidate.rows.iter().enumerate() {
        let values = [row.a, row.d, row.alpha, row.theta_offset];
        if values.iter().any(|v| !v.is_finite()) {
            reasons.push(Refusal::NonFinite {
                joint: i + 1,
                values,
            });
        }
    }
    let bounds = settings.bounds.table(&settings.nominal, settings.joints);
    for v in bound_violations(candidate, &bounds).filter(|v| v.value.is_finite()) {
        reasons.push(Refusal::Bound(v));
    }
    let max_k = settings.validation.max_condition_number;
    if !(condition_number.is_finite() && condition_number <= max_k) {
        reasons.push(Refusal::Conditioning {
            condition: condition_number,
            max: max_k,
        });
    }
    let rules = &settings.validation;
    let expected = expected.map(Expected::from);
    match expected {
        None => reasons.push(Refusal::NoExpectedAccuracy),
        Some(e) => {
            if e.position_mm.is_nan() || e.position_mm > rules.max_expected_position_error_mm {
                reasons.push(Refusal::ExpectedPosition {
                    mm: e.position_mm,
                    max: rules.max_expected_position_error_mm,
                });
            }
            if e.rotation_mrad.is_nan() || e.rotation_mrad > rules.max_expected_rotation_error_mrad
            {
                reasons.push(Refusal::ExpectedRotation {
                    mrad: e.rotation_mrad,
                    max: rules.max_expected_rotation_error_mrad,
                });
            }
        }
    }
    let HeldOut {
        table: judged,
        samples: heldout,
    } = heldout;
    let nominal_table = settings.nominal;
    let nominal = accuracy(&nominal_table, heldout);
    let cand = accuracy(judged, heldout);
    let improvement = if nominal.mean_error > 0.0 {
        1.0 - cand.mean_error / nominal.mean_error
    } else {
        0.0
    };
    let mut heldout_t = f64::NAN;
    if heldout.len() < MIN_HELDOUT {
        reasons.push(Refusal::TooFewHeldOut {
            have: heldout.len(),
        });
    } else {
        heldout_t = paired_t(judged, &nominal_table, heldout);
        if heldout_t.is_nan() || heldout_t > HELDOUT_T_REFUSE {
            reasons.push(Refusal::WorseThanNominal {
                candidate: cand.mean_error,
                nominal: nominal.mean_error,
                t: heldout_t,
            });
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
    fn samples(n: usize) -> Vec<Sample<MAX_JOINTS>> {
        let actual = DhTable::paper_actual();
        let ranges = Settings::suit_default().bounds.joint_range.limits;
        (0..n)
            .map(|k| {
                let joints: [f64; MAX_JOINTS] = std::array::from_fn(|j| {
                    let u = 0.5 + 0.45 * ((k as f64) * 0.013 * (j as f64 + 1.0) + j as f64).sin();
                    let (min, max) = ranges[j];
                    min + u * (max - min)
                });
                Sample {
                    joints,
                    pose: actual.fk(&joints),
                }
            })
            .collect()
    }

    /// An expected accuracy well within the default limits.
    /// The held-out slice `samples`, judging `table` itself.
    fn judging<'a>(
        table: &'a DhTable<MAX_JOINTS>,
        samples: &'a [Sample<MAX_JOINTS>],
    ) -> HeldOut<'a> {
        HeldOut { table, samples }
    }

    fn good() -> Option<TableError> {
        Some(TableError {
            position_m: 1e-3,
            rotation_rad: 3e-3,
        })
    }

    #[test]
    fn the_true_table_passes_and_a_table_worse_than_nominal_is_refused() {
        let config = Settings::suit_default();
        let held = samples(200);
        let truth = DhTable::paper_actual();
        let v = validate(&truth, 50.0, good(), judging(&truth, &held), &config);
        assert!(v.accepted(), "{:?}", v.reasons);
        assert!(v.improvement > 0.999_999, "{}", v.improvement);
        assert!(v.heldout_t < -HELDOUT_T_REFUSE, "{}", v.heldout_t);
        assert!(v.nominal.mean_position_m > 0.01, "{:?}", v.nominal);
        assert_eq!(v.heldout_samples, 200);
        assert_eq!(v.expected.unwrap().to_string(), "±1.00 mm, ±3.00 mrad (1σ)");

        // Nominal itself is not worse than nominal.
        let nominal = config.nominal;
        let v = validate(&nominal, 50.0, good(), judging(&nominal, &held), &config);
        assert!(v.accepted(), "{:?}", v.reasons);
        assert_eq!((v.improvement, v.heldout_t), (0.0, 0.0));

        // Nominal with a 3° error at the shoulder is worse, everywhere on the held-out slice.
        let mut worse = nominal;
        worse.rows[1].theta_offset += 3f64.to_radians();
        let v = validate(&worse, 50.0, good(), judging(&worse, &held), &config);
        assert!(
            matches!(v.reasons[..], [Refusal::WorseThanNominal { .. }]),
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
        let config = Settings::suit_default();
        let held = samples(200);
        let truth = DhTable::paper_actual();
        let v = validate(&truth, 50.0, None, judging(&truth, &held), &config);
        assert_eq!(v.reasons, [Refusal::NoExpectedAccuracy]);
        assert_eq!(
            v.reasons[0].to_string(),
            "no expected accuracy: neither the drift EM nor least squares could state one"
        );
        let coarse = TableError {
            position_m: 4e-3,
            rotation_rad: 2e-3,
        };
        let v = validate(&truth, 50.0, Some(coarse), judging(&truth, &held), &config);
        assert_eq!(v.reasons, [Refusal::ExpectedPosition { mm: 4.0, max: 3.0 }]);
        assert!(v.reasons[0]
            .to_string()
            .starts_with("expected table error ±4.00 mm (1σ) above the 3 mm allowed"));
        let twisted = TableError {
            position_m: 1e-3,
            rotation_rad: 0.02,
        };
        let v = validate(&truth, 50.0, Some(twisted), judging(&truth, &held), &config);
        assert_eq!(
            v.reasons,
            [Refusal::ExpectedRotation {
                mrad: 20.0,
                max: 10.0
            }]
        );
    }

    #[test]
    fn the_held_out_slice_judges_the_table_fitted_without_it() {
        // A refitted candidate is judged for bounds and accuracy itself, on the held-out slice
        // through the table it was refitted from.
        let config = Settings::suit_default();
        let held = samples(200);
        let truth = DhTable::paper_actual();
        let mut worse = config.nominal;
        worse.rows[1].theta_offset += 3f64.to_radians();
        let v = validate(&truth, 50.0, good(), judging(&worse, &held), &config);
        assert!(
            matches!(v.reasons[..], [Refusal::WorseThanNominal { .. }]),
            "{:?}",
            v.reasons
        );
        let v = validate(&worse, 50.0, good(), judging(&truth, &held), &config);
        assert!(v.accepted(), "{:?}", v.reasons);
    }

    #[test]
    fn a_parameter_just_outside_its_bound_goes_onto_it_and_one_further_out_is_refused() {
        let config = Settings::suit_default();
        let held = samples(200);
        let sigma = 1.5e-3;
        let std_errors = [sigma; crate::MAX_PARAMS];
        let (a4_max, alpha_dev) = (config.bounds.a[3].1, config.bounds.alpha_deviation);
        // The paper's a_4 estimated 0.2 mm above its 267 mm (the power-up test's refused
        // session), α_2 0.5σ beyond its allowed deviation the negative way, d_5 2σ out.
        let mut t = DhTable::paper_actual();
        t.rows[3].a = a4_max + 0.2e-3;
        t.rows[1].alpha = config.nominal.rows[1].alpha - alpha_dev - 0.5 * sigma;
        t.rows[4].d = config.bounds.d[4].1 + 2.0 * sigma;
        let (moved, onto) = onto_bounds(&t, &std_errors, &config);
        let lines: Vec<String> = onto.iter().map(ToString::to_string).collect();
        assert_eq!(onto.len(), 2, "{lines:?}");
        assert!(
            (moved.rows[3].a - a4_max).abs() < 1e-9,
            "{}",
            moved.rows[3].a
        );
        let alpha_min = config.nominal.rows[1].alpha - alpha_dev;
        assert!((moved.rows[1].alpha - alpha_min).abs() < 1e-9);
        assert_eq!(moved.rows[4].d, t.rows[4].d, "2σ out stays for validate");
        // Nothing else moved.
        for p in (0..crate::MAX_PARAMS)
            .filter(|&p| ![3, 2 * MAX_JOINTS + 1, MAX_JOINTS + 4].contains(&p))
        {
            assert_eq!(moved.param(p), t.param(p), "parameter {p}");
        }
        assert!(lines[0].starts_with("joint 4: a = 0.2672 m outside [0.211, 0.267] by 0.13σ"));
        assert!(lines[1].contains("joint 2: alpha") && lines[1].contains("by 0.50σ"));
        // Validation then refuses d_5 alone: the moved ones are inside, to the bit.
        let truth = DhTable::paper_actual();
        let v = validate(&moved, 50.0, good(), judging(&truth, &held), &config);
        let reasons: Vec<String> = v.reasons.iter().map(ToString::to_string).collect();
        assert_eq!(reasons.len(), 1, "{reasons:?}");
        assert!(reasons[0].starts_with("joint 5: d = "), "{reasons:?}");
        // A parameter without a standard error is never moved.
        let (_, onto) = onto_bounds(&t, &[f64::NAN; crate::MAX_PARAMS], &config);
        assert!(onto.is_empty());
        // A table inside its bounds is left as it is.
        assert_eq!(
            onto_bounds(&truth, &std_errors, &config),
            (truth, Vec::new())
        );
    }

    #[test]
    fn every_reason_is_listed() {
        let config = Settings::suit_default();
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
            judging(&t, &samples(10)),
            &config,
        );
        let all: Vec<String> = v.reasons.iter().map(Refusal::to_string).collect();
        let all = all.join("\n");
        let bound = |joint, kind| {
            v.reasons
                .iter()
                .any(|r| matches!(r, Refusal::Bound(b) if b.joint == joint && b.kind == kind))
        };
        assert!(bound(2, ParamKind::A) && bound(4, ParamKind::D), "{all}");
        assert!(
            bound(1, ParamKind::Alpha) && bound(6, ParamKind::Theta),
            "{all}"
        );
        assert!(v
            .reasons
            .iter()
            .any(|r| matches!(r, Refusal::Conditioning { .. })));
        assert!(v.reasons.contains(&Refusal::ExpectedPosition {
            mm: 100.0,
            max: 3.0
        }));
        assert!(v.reasons.contains(&Refusal::ExpectedRotation {
            mrad: 100.0,
            max: 10.0
        }));
        assert!(v.reasons.contains(&Refusal::TooFewHeldOut { have: 10 }));
        // And each says it in words.
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
        let config = Settings::suit_default();
        let mut t = DhTable::paper_actual();
        t.rows[0].a = f64::NAN;
        let v = validate(&t, f64::NAN, good(), judging(&t, &samples(100)), &config);
        assert!(!v.accepted());
        assert!(v
            .reasons
            .iter()
            .any(|r| matches!(r, Refusal::NonFinite { joint: 1, .. })));
        assert!(v
            .reasons
            .iter()
            .any(|r| matches!(r, Refusal::Conditioning { .. })));
        // The NaN table has NaN accuracy: that is a refusal too, not a pass.
        assert!(v
            .reasons
            .iter()
            .any(|r| matches!(r, Refusal::WorseThanNominal { .. })));
    }

    #[test]
    fn angle_deviations_wrap() {
        let mut config = Settings::suit_default();
        // Nominal α1 = -90°; 270° is the same twist, 3° off is 3° off whichever way it is written.
        let mut t = config.nominal;
        t.rows[0].alpha = 270f64.to_radians();
        let v = validate(&t, 50.0, good(), judging(&t, &samples(100)), &config);
        assert!(v.accepted(), "{:?}", v.reasons);
        t.rows[0].alpha = 273f64.to_radians();
        config.bounds.alpha_deviation = 1f64.to_radians();
        let v = validate(&t, 50.0, good(), judging(&t, &samples(100)), &config);
        assert!(
            v.reasons.iter().any(|r| matches!(r, Refusal::Bound(b)
                if b.joint == 0 && b.kind == ParamKind::Alpha)
                && r.to_string() == "joint 1: alpha is 3.00° from nominal, at most 1.00° allowed"),
            "{:?}",
            v.reasons
        );
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
