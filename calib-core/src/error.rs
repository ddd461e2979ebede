//! Typed errors of every fallible entry point.

use core::fmt;

use crate::model::ParamKind;

/// Why a calibration input or run was rejected. Small and `Copy`; joints are 0-based.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum CalibError {
    /// Fewer samples than the method needs.
    TooFewSamples {
        /// Samples given.
        got: usize,
        /// Samples required.
        need: usize,
    },
    /// A joint angle or pose entry of a sample is NaN or infinite.
    NonFinite {
        /// Index of the offending sample.
        sample: usize,
    },
    /// A starting table or option value is NaN, infinite or out of its domain.
    InvalidInput {
        /// Which input.
        what: &'static str,
    },
    /// A joint barely moved during the session (the arm was held still).
    NoExcitation {
        /// The joint.
        joint: usize,
        /// Its range of motion in the data (rad).
        range: f64,
    },
    /// A reported joint angle is far outside its anatomical range (Table 3).
    JointOutOfRange {
        /// Index of the offending sample.
        sample: usize,
        /// The joint.
        joint: usize,
        /// The angle (rad).
        value: f64,
    },
    /// The iteration did not converge within its budget.
    NotConverged {
        /// Iterations run.
        iterations: usize,
        /// Last relative step or likelihood change.
        last_change: f64,
    },
    /// The identified table breaks the anatomical bounds (Table 2) and the policy is `Reject`.
    OutOfBounds {
        /// Which parameter.
        kind: ParamKind,
        /// The joint.
        joint: usize,
        /// The identified value.
        value: f64,
    },
    /// A caller-provided workspace is shorter than the number of samples.
    WorkspaceTooSmall {
        /// Slots given.
        got: usize,
        /// Slots needed.
        need: usize,
    },
}

impl fmt::Display for CalibError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            CalibError::TooFewSamples { got, need } => write!(f, "too few samples: got {got}, need at least {need}"),
            CalibError::NonFinite { sample } => write!(f, "sample {sample} contains NaN or infinity"),
            CalibError::InvalidInput { what } => write!(f, "invalid input: {what}"),
            CalibError::NoExcitation { joint, range } => {
                write!(
                    f,
                    "joint {} barely moved ({:.3} deg range): the arm must move every joint",
                    joint + 1,
                    range.to_degrees()
                )
            }
            CalibError::JointOutOfRange { sample, joint, value } => {
                write!(
                    f,
                    "sample {sample}: joint {} at {:.1} deg is far outside its anatomical range",
                    joint + 1,
                    value.to_degrees()
                )
            }
            CalibError::NotConverged { iterations, last_change } => {
                write!(
                    f,
                    "no convergence after {iterations} iterations (last change {last_change:.3e})"
                )
            }
            CalibError::OutOfBounds { kind, joint, value } => {
                write!(
                    f,
                    "identified {}{} = {value:.5} is outside the anatomical bounds",
                    kind.name(),
                    joint + 1
                )
            }
            CalibError::WorkspaceTooSmall { got, need } => write!(f, "workspace has {got} slots, {need} needed"),
        }
    }
}

impl core::error::Error for CalibError {}

#[cfg(test)]
mod tests {
    use super::*;
    use std::string::ToString;

    #[test]
    fn every_variant_has_a_message_naming_the_problem() {
        let cases = [
            (CalibError::TooFewSamples { got: 3, need: 28 }, "got 3, need at least 28"),
            (CalibError::NonFinite { sample: 4 }, "sample 4"),
            (
                CalibError::InvalidInput {
                    what: "LsOptions tolerances",
                },
                "LsOptions tolerances",
            ),
            (CalibError::NoExcitation { joint: 2, range: 0.0 }, "joint 3 barely moved"),
            (
                CalibError::JointOutOfRange {
                    sample: 1,
                    joint: 0,
                    value: 3.0,
                },
                "joint 1 at 171.9 deg",
            ),
            (
                CalibError::NotConverged {
                    iterations: 5,
                    last_change: 1e-3,
                },
                "after 5 iterations",
            ),
            (
                CalibError::OutOfBounds {
                    kind: ParamKind::A,
                    joint: 2,
                    value: 0.5,
                },
                "a3 = 0.50000",
            ),
            (CalibError::WorkspaceTooSmall { got: 1, need: 2 }, "1 slots, 2 needed"),
        ];
        for (e, needle) in cases {
            let msg = e.to_string();
            assert!(msg.contains(needle), "{msg:?} lacks {needle:?}");
        }
    }
}
