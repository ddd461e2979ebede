//! The session log: what a session records (once), the MCAP writer, and the recovery of a log
//! cut short.

pub mod mcaplog;
pub mod records;
pub mod recover;
