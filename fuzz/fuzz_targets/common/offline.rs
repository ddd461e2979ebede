//! What the `offline_*` targets share: `exocald offline`'s reading of one input format.

use std::path::Path;

use exocald::cmd::offline::{read_input, Format};
use exocald::config::Config;
use exocald::exit::DaemonError;

/// Reads `data` as the file `name` in `format` under the default configuration's budget. The
/// invariant: a recording, or bad input (exit 65) naming the file; anything else panics.
pub fn read_as(data: &[u8], name: &str, format: Format) {
    let settings = Config::default_config().calibration;
    match read_input(Path::new(name), data, format, &settings) {
        Ok(_) => {}
        Err(DaemonError::Input(what)) => assert!(
            what.strip_prefix(name).is_some_and(|r| r.starts_with(": ")),
            "{what}"
        ),
        Err(e) => panic!("not bad input: {e}"),
    }
}
