//! `exocald offline`'s reading of a candump log: arbitrary bytes, and the seeds (a log whose
//! first lines are at time 0, which without the budget would size the alignment grid at
//! 1.4 TB), read line by line under the default configuration's budget. Invariant: a
//! recording, or bad input (exit 65) naming the file — never a panic, an abort or another
//! error.
#![no_main]

use exocald::cmd::offline::Format;
use libfuzzer_sys::fuzz_target;

#[path = "common/offline.rs"]
mod offline;

fuzz_target!(|data: &[u8]| offline::read_as(data, "fuzz.log", Format::Candump));
