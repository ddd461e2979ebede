//! `exocald offline`'s reading of a candump log (issue 34, item 5): arbitrary bytes, and
//! the seeds (a log whose first lines are at time 0, which once sized the alignment grid at
//! 1.4 TB), read line by line under the default configuration's
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
    match read_input(Path::new("fuzz.log"), data, Format::Candump, &rules) {
        Ok(_) => {}
        Err(DaemonError::Input(what)) => assert!(what.starts_with("fuzz.log: "), "{what}"),
        Err(e) => panic!("not bad input: {e}"),
    }
});
