//! exocal-report: the calibration report, the exports, and the offline session readers.
//!
//! | module | contract |
//! |---|---|
//! | [`input`] | [`ReportInput`]: plain data a live session and an offline run fill alike |
//! | [`plot`] | SVG charts (plotters), returned as strings |
//! | [`html`] | [`html::render`]: one self-contained HTML file, no external resources |
//! | [`export`] | the calibrated table as the daemon's TOML and as URDF; frames as `candump -L` |
//! | [`readers`] | offline inputs: `candump -L` logs, the daemon's MCAP logs, CSV samples |
//!
//! Nothing here knows about CAN sockets or the daemon, and nothing here calibrates: the
//! daemon's pipeline computes the calibration (LS, EM, validation, correlations) and hands it
//! here to render; its `offline` command replays recorded frames through its own ingest and
//! alignment.

#![warn(missing_docs)]

pub mod export;
pub mod html;
pub mod input;
pub mod plot;
pub mod readers;

pub use input::{
    Calibration, Correlation, EmDetail, LsDetail, Quality, ReportInput, SessionInput,
    StreamQuality, TimedSample, VerdictSummary, JOINTS, PARAMS,
};
pub use readers::{McapSession, ReadError, RecordedFrame};
