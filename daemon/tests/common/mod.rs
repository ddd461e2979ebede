//! Helpers shared by the integration tests (each test file that needs them says `mod common;`).
// Not every test file uses every helper.
#![allow(dead_code)]

use std::path::Path;

use exocald::config::Config;
use exocald::exit::DaemonError;
use exocald::shell::summary::{SessionError, SessionSummary};

/// One live session of the paper scenario with `seed`, as `exocald demo` runs it (the emulated
/// suit and the daemon on the in-process bus, on simulated time, as fast as the machine
/// goes), with 20 s of collection, logging to `dir`. A refused table or a failed push still
/// leaves a calibration to look at: their summary is returned too.
pub fn live_session(dir: &Path, seed: u64) -> (Config, SessionSummary) {
    live_session_with(dir, seed, |_| {})
}

/// [`live_session`] with its configuration changed by `adjust` first.
pub fn live_session_with(
    dir: &Path,
    seed: u64,
    adjust: impl FnOnce(&mut Config),
) -> (Config, SessionSummary) {
    let opts = exocald::cmd::demo::DemoOptions {
        seed,
        speed: 1e6,
        output: dir.to_path_buf(),
        hold: false,
        quiet: false,
        wearer: Default::default(),
        drift: Default::default(),
    };
    let mut config = exocald::cmd::demo::demo_config(Config::default_config(), dir, 1.0);
    config.calibration.window.min_duration_s = 20.0;
    adjust(&mut config);
    let summary = match exocald::cmd::demo::run(&config, &opts).map_err(|e| *e) {
        Ok(r) => r.summary,
        Err(SessionError {
            error: DaemonError::Validation(_) | DaemonError::Push(_),
            summary: Some(s),
        }) => s,
        Err(SessionError { error, summary }) => panic!("{error}\n{summary:#?}"),
    };
    (config, summary)
}
