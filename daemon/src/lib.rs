//! exocald: the SocketCAN service that aligns, calibrates, logs and pushes.
//!
//! | module | contract |
//! |---|---|
//! | [`config`] | strict TOML configuration; errors name key and line |
//! | [`cli`] | the command line (clap) |
//! | [`record`] | what a session records, once: the records and their content (frames, arm, calibration) |
//! | [`recorder`] | every record to every observer: the log, the live view |
//! | [`mcaplog`] | the per-session MCAP log (zstd chunks, flushed on an interval, protobuf with Foxglove's schemas) |
//! | [`live`] | the live view: the session over the Foxglove WebSocket protocol (`[live]`) |
//! | [`report`] | progress bar / systemd `STATUS=` / plain lines; READY and WATCHDOG |
//! | [`push`] | table transfer to every node: retries, backoff, CRC readback, per-node report |
//! | [`keys`] | the node and trigger keys, from the systemd credential `exocal-keys` |
//! | [`serve`] | `exocald run`: which `Trigger` frames start a session (authenticated, cooldown) |
//! | [`runner`] | one session on any transport: collect, align, calibrate, validate, push, log |
//! | [`summary`] | a session's summary as printed on stdout |
//! | `demo` | exocal-hil and the daemon in one process on the in-process bus (feature `demo`, on by default) |
//! | [`offline`] | recalibration from a recorded MCAP, candump or CSV file, through the same pipeline |
//! | [`calreport`] | the HTML report of a session (live or offline), from what the pipeline computed |
//! | [`nodes`] | `exocald nodes`: every joint node's table, read over the bus, against the last push |
//! | [`recover`] | a session log cut short (kill -9, power loss) read record by record and rewritten complete |
//! | [`exit`] | [`exit::DaemonError`] and its sysexits status |
//! | [`shutdown`] | SIGTERM/SIGINT as a flag a session waits on |
//! | [`app`] | what each subcommand does |

#![warn(missing_docs)]

pub mod app;
pub mod calreport;
pub mod cli;
pub mod config;
#[cfg(feature = "demo")]
pub mod demo;
pub mod exit;
pub mod keys;
pub mod live;
pub mod mcaplog;
pub mod nodes;
pub mod offline;
pub mod push;
pub mod record;
pub mod recorder;
pub mod recover;
pub mod report;
pub mod runner;
pub mod serve;
pub mod shutdown;
pub mod summary;
