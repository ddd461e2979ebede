//! `exocald offline`'s reading of an MCAP session log: arbitrary bytes, and the damaged logs
//! of the seed corpus (bit flips, truncations, insertions, lengths of 2^62, a chunk claiming
//! 1 TB once decompressed), read as a stream under the default configuration's budget.
//! Invariant: a recording, or bad input (exit 65) naming the log — never a panic, an abort or
//! another error.
#![no_main]

use exocald::cmd::offline::Format;
use libfuzzer_sys::fuzz_target;

#[path = "common/offline.rs"]
mod offline;

fuzz_target!(|data: &[u8]| offline::read_as(data, "fuzz.mcap", Format::Mcap));
