//! `exocald offline`'s reading of CSV samples: arbitrary bytes, and the seeds (samples, and
//! samples spanning more than a session: 200,000 rows would take 573 MiB without the budget),
//! read line by line under the default configuration's budget. Invariant: a recording, or bad
//! input (exit 65) naming the file — never a panic, an abort or another error.
#![no_main]

use exocald::cmd::offline::Format;
use libfuzzer_sys::fuzz_target;

#[path = "common/offline.rs"]
mod offline;

fuzz_target!(|data: &[u8]| offline::read_as(data, "fuzz.csv", Format::Csv));
