//! The session's records built from the daemon's types (the outcome, the push, the arm), for
//! the log (`exocal_log`: schema, records, writer, readers, recovery) and the live view.

pub mod records;
