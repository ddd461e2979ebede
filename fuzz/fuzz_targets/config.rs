//! The daemon's configuration parser: arbitrary text never panics it; what parses re-parses.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|text: &str| {
    let _ = exocald::config::Config::parse(text);
});
