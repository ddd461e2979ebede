//! calib-core: D-H kinematics, least-squares identification and EM drift calibration for the
//! exocal 7-DoF upper-limb exoskeleton (after Qin et al. 2024, with the corrections of docs/paper.md).
//!
//! `no_std` without the default `std` feature, no `unsafe`, no allocation: every buffer is a
//! const-generic array or a caller-provided slice. All arithmetic is `f64`.
//!
//! # API overview
//!
//! | what | where |
//! |---|---|
//! | D-H table, Table 1 / Table 4, FK, Jacobians | [`DhTable`], [`DhTable::paper_nominal`], [`DhTable::fk`], [`DhTable::fk_jacobian`] |
//! | pose error (tool frame: position, rotation vector) | [`pose_error`] |
//! | anatomical bounds (Table 2) and ranges (Table 3) | [`Bounds::paper`], [`check_bounds`], [`JointRanges::paper`] |
//! | a calibration sample | [`Sample`] `{ joints: [f64; N], pose: Frame }` |
//! | Gauss-Markov drift, rate bias, and the seeded session simulator (drift in the arm or the reading, reading noise, glitches, slips) | [`GaussMarkov`], [`RateBias`], [`Scenario`], [`ScenarioConfig`], [`DriftSite`], [`Outliers`], [`Slip`] |
//! | least squares | [`identify_ls`]`::<N, P>(&start, &samples, &LsOptions) -> Result<LsResult, CalibError>` |
//! | least squares with the per-sample work split by the caller (e.g. over cores) | [`identify_ls_with`], [`Linearise`], [`normal_equations`], [`GramAccumulator::merge`] |
//! | least squares with base and tool frames (`P = 4N + 12`; feature `research`) | [`identify_ls_frames`] |
//! | the paper's EM (eqs. 33–36; feature `research`) | [`paper_em()`] |
//! | the drift's rough part out of the readings, before LS and the EM | [`separate()`], [`SeparationSlot`] |
//! | our EM (Kalman + RTS smoother over the drift; drift model per joint, Student-t reference, REML drift, stated error, refusals: the contract is in [`drift_em`]) | [`em_drift()`], [`DriftEmResult::stated_error`], [`JointDrift`], [`Discounted`], [`Consistency`], [`Refusal`] |
//! | what LS alone is worth when the EM gives no figure | [`ls_white_expected_error`] |
//! | confidence intervals of its τ, σ per joint | [`drift_confidence()`], [`DriftConfidence`] |
//! | which joint's motion would most reduce the expected table error (guidance while collecting) | [`guidance()`], [`Guidance`] |
//! | objective y (eq. 10) and parameter errors | [`objective_y`], [`ParamErrors`] |
//! | table error, expected table error, the Cramér-Rao bound | [`table_error`], [`DriftEmResult::expected_error`], [`cramer_rao()`] |
//! | the accuracy sweep and its field cells (feature `research`) | `sweep` |
//!
//! # Quick start
//! ```
//! use calib_core::*;
//!
//! // A simulated 10 s session of the paper's Section 4 (use real samples in the daemon).
//! let cfg = ScenarioConfig::paper();
//! let samples: Vec<Sample<7>> = Scenario::new(cfg, 7).take(1000).map(|s| s.sample).collect();
//!
//! let nominal = DhTable::paper_nominal();
//! let ls = identify_ls::<7, SUIT_PARAMS>(&nominal, &samples, &LsOptions::paper())?;
//! assert!(objective_y(&ls.table, &samples) < 0.2 * objective_y(&nominal, &samples));
//! assert_eq!(ls.rank, SUIT_PARAMS); // every D-H error is identifiable from full poses
//!
//! let opts = DriftEmOptions { max_iterations: 10, ..DriftEmOptions::new(cfg.drift.dt) };
//! let mut workspace = vec![DriftSlot::default(); samples.len()];
//! let em = em_drift::<7, SUIT_PARAMS>(&ls.table, &samples, &opts, &mut workspace)?;
//! let drift_of_sample_0: [f64; 7] = workspace[0].drift();
//! assert!(check_bounds(&em.table, &Bounds::paper()).is_ok());
//! # let _ = drift_of_sample_0;
//! # Ok::<(), CalibError>(())
//! ```
//!
//! Generic functions take the joint count `N` and the parameter count `P = 4N` separately
//! (stable Rust cannot write `4 * N` in a type); `P == 4N` is checked at compile time. For the
//! suit: `N = `[`SUIT_JOINTS`]` = 7`, `P = `[`SUIT_PARAMS`]` = 28`.
//!
//! # f32?
//! Everything is `f64`. `f32` would not do for identification: the pose errors to resolve are
//! ~1e-4 of the arm length while the Jacobian is accumulated over thousands of samples and
//! the column-scaled condition number is ~10²–10³, so f32's 6e-8 relative precision leaves
//! 3–4 significant digits at best, and the noise-free 1e-9 recovery target is far below f32
//! resolution (6e-8 m on a 0.7 m arm). Cortex-M4F has only a single-precision FPU, so f64 is
//! emulated in software there: correct, ~10× slower (an LS iteration at K = 6,000 is then
//! seconds, acceptable for a one-off calibration). FK alone at runtime could use f32.
#![cfg_attr(not(any(test, feature = "std")), no_std)]
#![deny(unsafe_code)]
#![warn(missing_docs)]

pub mod drift;
pub mod drift_conf;
pub mod drift_em;
pub mod error;
#[cfg(any(test, feature = "research"))]
pub mod frames;
pub mod guidance;
mod info;
mod kalman;
pub mod linalg;
pub mod ls;
pub mod metrics;
pub mod model;
#[cfg(any(test, feature = "research"))]
pub mod paper_em;
pub mod reading;
pub mod rest;
pub mod rng;
#[cfg(test)]
mod scenario_tests;
pub mod sim;
#[cfg(any(test, feature = "research"))]
pub mod sweep;
pub mod versus_ls;

pub use drift::{Discretisation, DriftParams, GaussMarkov, RateBias};
pub use drift_conf::{drift_confidence, DriftConfidence};
#[cfg(any(test, feature = "std"))]
pub use drift_em::em_drift_vec;
pub use drift_em::{
    cramer_rao, discounted_samples, em_drift, Consistency, Discounted, DriftEmOptions, DriftEmResult, DriftModel, DriftSlot,
    JointConsistency, JointDrift, Refusal, Trend, EXPECTED_ERROR_POSES, MAX_EM_ITERATIONS, RATE_BIAS_TERMS,
};
pub use error::CalibError;
#[cfg(any(test, feature = "research"))]
pub use frames::{identify_ls_frames, LsFramesResult, Mounting, Param, FRAME_PARAMS};
pub use guidance::{guidance, Guidance, GUIDANCE_CONFIGS, GUIDANCE_POSES, PRIOR_SD};
pub use linalg::{GramAccumulator, Observability, QrAccumulator, QrPanel, GRAM_MAX_CONDITION};
pub use ls::{
    identify_ls, identify_ls_with, normal_equations, validate_samples, BoundsOutcome, BoundsPolicy, InputChecks, Linearise,
    LsOptions, LsResult, NullDirection, Sequential,
};
pub use metrics::{
    expected_table_error, ls_expected_table_error, ls_response, ls_white_expected_error, median, objective_y,
    objective_y_corrected, table_error, ErrorPoses, ParamErrors, TableError,
};
pub use model::{
    bound_violations, check_bounds, clamp_to_bounds, pose_error, BoundViolation, Bounds, DhRow, DhTable, Frame, JointRanges,
    ParamKind, PreparedTable, Sample, SUIT_JOINTS, SUIT_PARAMS,
};
#[cfg(any(test, feature = "research"))]
pub use paper_em::{paper_em, PaperEmForm, PaperEmOptions, PaperEmResult};
pub use reading::{separate, JointSeparation, SeparationSlot};
pub use rest::{GyroAtRest, GyroBias};
pub use rng::Rng;
pub use sim::{DriftSite, Motion, Outliers, Scenario, ScenarioConfig, SimSample, Slip};
pub use versus_ls::{em_versus_ls, EmVersusLs, TableChoice, MAX_EM_LS_STATISTIC};
