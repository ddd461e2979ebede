//! One live session and what it needs around the data path: the session loop (`runner`), its
//! outputs (`io`: the log, systemd, the console) and the lines each step writes (`lines`), the
//! stream nonces, the fan-out of its records, systemd notification, signals, the printed
//! summary and the HTML report file.

pub mod html_report;
pub mod io;
pub mod lines;
pub mod notify;
pub mod runner;
pub mod shutdown;
pub mod stream_nonce;
pub mod summary;
pub mod tee;
pub mod throttle;
