//! exocal-report: renders what a session computed; computes nothing.
//!
//! | module | contract |
//! |---|---|
//! | [`input`] | [`ReportInput`]: the session crate's outcome, with a title and a source line |
//! | [`plot`] | SVG charts (plotters), returned as strings |
//! | [`html`] | [`html::render`]: one self-contained HTML file, no external resources |
//! | [`export`] | the calibrated table as URDF |
//!
//! Nothing here knows about CAN, files, the daemon or its configuration keys, and nothing here
//! calibrates: the session crate's pipeline computes the calibration (LS, EM, validation,
//! correlations) and its data quality, and hands them here to render.

#![warn(missing_docs)]

pub mod export;
pub mod html;
pub mod input;
pub mod plot;

pub use input::{
    Calibration, Correlation, EmDetail, LsDetail, NodePush, Quality, ReportInput, SessionInput,
    StreamQuality, TimedSample, VerdictSummary, MAX_JOINTS, MAX_PARAMS,
};
