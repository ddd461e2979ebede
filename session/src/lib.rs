//! exocal-session: the data path of a calibration session, sans I/O.
//!
//! Frames with their receive time in; aligned samples, their quality and a judged calibration
//! out. The daemon feeds it from the bus, `exocald offline` from a recording, the tests from
//! the emulated suit: the same frames give the same outcome, bit for bit. Nothing here reads a
//! clock, a file or a socket (time is always an argument), so the same code runs live, in a
//! replay and in a test at any speed.
//!
//! One module per stage, data flowing one way:
//!
//! | module | stage |
//! |---|---|
//! | [`arm`] | an arm of 1–7 joints in fixed-size arrays: the padding, and calib-core at the arm's length |
//! | [`rules`] | what the data path reads: node ids, nominal table, bounds, window and validation rules |
//! | [`stream`] | the streams a session takes in, declared once: source node, message, column, log topic |
//! | [`gate`] | the stream gate (authentication): a node's data frames pass only once the digest covering them verifies |
//! | [`ingest`] | frames → decoded messages → per-node streams; counts unknown/malformed frames |
//! | [`align`] | per-node clock models, resampling onto one grid |
//! | [`window`] | the collection window: coverage, sample counts, ready/failed and why |
//! | [`collect`] | frames → aligned samples and their data quality, live or replayed |
//! | [`session`] | the [`Session`]: frames and ticks in; progress, phase, estimate jobs out; their results back |
//! | [`estimate`] | the in-collection estimates: condition number, expected table error so far |
//! | [`pipeline`] | aligned samples → split, LS, drift EM, validation, node rows, report detail |
//! | [`formats`] | the text formats of recorded sessions: `candump -L` logs, CSV samples |
//! | [`parallel`] | the LS linearisation in sample blocks on several cores (std scoped threads) |
//! | [`replay`] | a recorded session (frames or samples) through the same stages, judged by the same rules |
//! | [`validate`] | bounds, condition number and held-out accuracy before any push; typed refusals |
//! | [`detail`] | the calibration's detail every consumer reads (LS, EM, correlations, data quality) |

#![warn(missing_docs)]

pub mod align;
pub mod arm;
pub mod collect;
pub mod detail;
pub mod estimate;
pub mod formats;
pub mod gate;
pub mod ingest;
pub mod parallel;
pub mod pipeline;
pub mod replay;
pub mod rules;
pub mod session;
pub mod stream;
pub mod validate;
pub mod window;

pub use rules::{Bounds, SensorSpec, Settings, ValidationRules, WindowRules};
pub use session::{CalibrationJob, Session};

/// The most joints an arm has (the paper's suit, calib-core's `SUIT_JOINTS`): the length of
/// every per-joint array of the data path; an arm of fewer uses the first
/// [`Settings::joints`] ([`arm`]).
pub const MAX_JOINTS: usize = calib_core::SUIT_JOINTS;
/// D-H parameters of the longest arm (`4 × MAX_JOINTS`), indexed `kind·MAX_JOINTS + joint`
/// (kinds a, d, α, θ).
pub const MAX_PARAMS: usize = calib_core::SUIT_PARAMS;

// The protocol's joint nodes (from exocal.dbc) are the longest arm's joints.
const _: () = assert!(exocal_dbc::NodeId::JOINTS.len() == MAX_JOINTS);
