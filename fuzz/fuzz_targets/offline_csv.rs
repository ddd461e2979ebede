//! `exocald offline`'s reading of CSV samples (issue 34, item 5): arbitrary bytes, and
//! the seeds (samples, and samples spanning more than a session: 200,000 rows once took
//! 573 MiB), read line by line under the default configuration's
//! budget. Invariant: a recording, or bad input (exit 65) naming the file — never a panic, an
//! abort or another error.
#![no_main]

use std::path::Path;

use exocald::cmd::offline::{read_input, Format};
use exocald::config::Config;
use exocald::exit::DaemonError;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let rules = Config::default_config().calibration.window;
    match read_input(Path::new("fuzz.csv"), data, Format::Csv, &rules) {
        Ok(_) => {}
        Err(DaemonError::Input(what)) => assert!(what.starts_with("fuzz.csv: "), "{what}"),
        Err(e) => panic!("not bad input: {e}"),
    }
});
