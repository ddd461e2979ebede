//! exocald: the shell around the session crate — sockets, timers, signals, systemd, the push,
//! the log and the live view. The data path itself (ingest, alignment, the window, LS, EM,
//! validation) is `exocal_session`'s; nothing here re-implements math, codecs or the data path.
//!
//! | module | role |
//! |---|---|
//! | [`cli`] | the command line (clap) |
//! | [`config`] | strict TOML configuration; errors name key and line; the one writer of its keys |
//! | [`exit`] | [`exit::DaemonError`] and its sysexits status |
//! | [`cmd`] | one module per subcommand: what each does (`calibrate` in [`cmd`] itself) |
//! | [`cmd::serve`] | `exocald run`: which `Trigger` frames start a session (authenticated, cooldown) |
//! | [`cmd::offline`] | recalibration from a recorded MCAP, candump or CSV file, through the same data path |
//! | [`cmd::nodes`] | `exocald nodes`: every joint node's table, read over the bus, against the last push |
//! | `cmd::demo` | exocal-hil and the daemon in one process on the in-process bus (feature `demo`, on by default) |
//! | [`shell`] | one live session and what it needs around the data path |
//! | [`shell::runner`] | one session on any transport: the loop that drives the `Session`, runs its jobs off the loop, pushes and reports |
//! | [`shell::io`] | the loop's outputs in one place: the log (opened and finished on every path), systemd, the console |
//! | [`shell::lines`] | what each step says in the log, as lines (renderers, no decisions) |
//! | [`shell::stream_nonce`] | the controller's side of stream authentication: the nonces, signed per node |
//! | [`push`] | table transfer to every node: retries, backoff, CRC readback, per-node report |
//! | [`keys`] | the node and trigger keys, from the systemd credential `exocal-keys` |
//! | [`state`] | the state directory: the nodes' proved and signed freshness counters, the trigger counter (fsynced) |
//! | [`shell::notify`] | progress bar / systemd `STATUS=` / plain lines; READY and WATCHDOG |
//! | [`shell::shutdown`] | SIGTERM/SIGINT as a flag a session waits on |
//! | [`shell::summary`] | what a session did (`SessionSummary`), and how it is printed on stdout |
//! | [`shell::tee`] | every record to every observer: the log, the live view |
//! | [`shell::html_report`] | the HTML report of a session (live or offline), rendered from what the session computed |
//! | [`log`] | the session's records from the daemon's types, for the log (`exocal_log`) and the live view |
//! | [`log::records`] | the session's records built from the daemon's types (frames, arm, calibration, push); the log itself — schema, records, writer, readers, recovery — is `exocal_log`'s |
//! | [`live`] | the live view: the session over the Foxglove WebSocket protocol (`[live]`) |

#![warn(missing_docs)]

pub mod cli;
pub mod cmd;
pub mod config;
pub mod exit;
pub mod keys;
pub mod live;
pub mod log;
pub mod push;
pub mod shell;
pub mod state;
