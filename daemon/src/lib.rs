//! exocald: the SocketCAN service that aligns, calibrates, logs and pushes.
//!
//! | module | contract |
//! |---|---|
//! | [`align`] | per-node clock models, resampling onto one grid |
//! | [`ingest`] | frames → decoded messages → per-node streams; counts unknown/malformed |
//! | [`config`] | strict TOML configuration; errors name key and line |
//! | [`cli`] | the command line (clap) |
//! | [`mcaplog`] | the per-session MCAP log (zstd chunks, flushed on an interval, Foxglove schemas) |
//! | [`session`] | the collection window: coverage, sample counts, ready/failed |
//! | [`report`] | progress bar / systemd `STATUS=` / plain lines; READY and WATCHDOG |
//! | [`calibrate`] | LS, then drift EM, then validation, on aligned samples (pure) |
//! | [`validate`] | bounds, condition number and held-out accuracy before any push |
//! | [`push`] | table transfer to every node: retries, backoff, CRC readback, per-node report |
//! | [`keys`] | the node and trigger keys, from the systemd credential `exocal-keys` |
//! | [`serve`] | `exocald run`: which `Trigger` frames start a session (authenticated, cooldown) |
//! | [`runner`] | one session on any transport: collect, align, calibrate, validate, push, log |
//! | `demo` | exocal-hil and the daemon in one process on the in-process bus (feature `demo`, on by default) |
//! | [`offline`] | recalibration from a recorded MCAP, candump or CSV file, through the same pipeline |
//! | [`calreport`] | the HTML calibration report of a session (live or offline) |
//! | [`exit`] | [`exit::DaemonError`] and its sysexits status |
//! | [`shutdown`] | SIGTERM/SIGINT as a flag a session waits on |
//! | [`app`] | what each subcommand does |

pub mod align;
pub mod app;
pub mod calibrate;
pub mod calreport;
pub mod cli;
pub mod config;
#[cfg(feature = "demo")]
pub mod demo;
pub mod exit;
pub mod ingest;
pub mod keys;
pub mod mcaplog;
pub mod offline;
pub mod push;
pub mod report;
pub mod runner;
pub mod serve;
pub mod session;
pub mod shutdown;
pub mod validate;
