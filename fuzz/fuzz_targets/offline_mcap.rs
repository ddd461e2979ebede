//! `exocald offline`'s reading of an MCAP session log (issue 34, item 5): arbitrary bytes, and
//! the damaged logs of the seed corpus (bit flips, truncations, insertions, lengths of 2^62, a
//! chunk claiming 1 TB once decompressed), read as a stream under the default configuration's
//! budget. Invariant: a recording, or bad input (exit 65) naming the log — never a panic, an
//! abort or another error.
#![no_main]

use std::path::Path;

use exocald::cmd::offline::{read_input, Format};
use exocald::config::Config;
use exocald::exit::DaemonError;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let rules = Config::default_config().calibration.window;
    match read_input(Path::new("fuzz.mcap"), data, Format::Mcap, &rules) {
        Ok(_) => {}
        Err(DaemonError::Input(what)) => assert!(what.starts_with("fuzz.mcap: "), "{what}"),
        Err(e) => panic!("not bad input: {e}"),
    }
});
