//! Exit statuses, after BSD's sysexits(3), and the daemon's top-level error.
//!
//! Contract: every way `exocald` can fail maps to one [`DaemonError`] variant, and every variant
//! to one documented exit status, so that systemd, scripts and tests can tell "bad config" (78)
//! from "calibration refused" (65) from "interrupted" (75) without parsing logs.

use std::fmt;

use crate::config::ConfigError;

/// sysexits(3) statuses used by exocald.
pub mod code {
    /// Success: the table was pushed (or, for `check-config`, the file is valid).
    pub const OK: u8 = 0;
    /// EX_USAGE: the command line is wrong.
    pub const USAGE: u8 = 64;
    /// EX_DATAERR: the calibration failed validation; nothing was pushed. For `offline`, also:
    /// the input file does not parse.
    pub const DATAERR: u8 = 65;
    /// EX_NOINPUT: the session ended without enough motion or samples to calibrate.
    pub const NOINPUT: u8 = 66;
    /// EX_UNAVAILABLE: the CAN interface is missing, or a node could not be reached.
    pub const UNAVAILABLE: u8 = 69;
    /// EX_SOFTWARE: an internal error (a bug).
    pub const SOFTWARE: u8 = 70;
    /// EX_IOERR: reading CAN or writing the log failed.
    pub const IOERR: u8 = 74;
    /// EX_TEMPFAIL: interrupted (SIGTERM/SIGINT) before pushing; nothing was pushed.
    pub const TEMPFAIL: u8 = 75;
    /// EX_CONFIG: the configuration is invalid.
    pub const CONFIG: u8 = 78;
}

/// Why the daemon stopped unsuccessfully.
#[derive(Debug)]
pub enum DaemonError {
    /// Bad configuration (78).
    Config(ConfigError),
    /// The CAN interface does not exist or cannot be opened (69).
    Interface { name: String, reason: String },
    /// A node did not accept the table (69); the report says which.
    Push(String),
    /// Not enough motion/samples before the session's maximum duration (66).
    Session(String),
    /// The calibration was refused by validation (65): the reasons.
    Validation(Vec<String>),
    /// I/O failure (74): what was being done, and the error.
    Io {
        what: String,
        source: std::io::Error,
    },
    /// Interrupted by a signal before anything was pushed (75).
    Interrupted,
    /// A feature this build cannot perform (70).
    Unsupported(String),
    /// An offline input that does not parse (65): the file, the line, the problem.
    Input(String),
    /// Options that do not go together (64).
    Usage(String),
}

impl DaemonError {
    /// The process exit status for this error.
    pub fn exit_code(&self) -> u8 {
        match self {
            DaemonError::Config(_) => code::CONFIG,
            DaemonError::Interface { .. } | DaemonError::Push(_) => code::UNAVAILABLE,
            DaemonError::Session(_) => code::NOINPUT,
            DaemonError::Validation(_) => code::DATAERR,
            DaemonError::Io { .. } => code::IOERR,
            DaemonError::Interrupted => code::TEMPFAIL,
            DaemonError::Unsupported(_) => code::SOFTWARE,
            DaemonError::Input(_) => code::DATAERR,
            DaemonError::Usage(_) => code::USAGE,
        }
    }
}

impl fmt::Display for DaemonError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            DaemonError::Config(e) => write!(f, "bad configuration: {e}"),
            DaemonError::Interface { name, reason } => {
                write!(f, "CAN interface `{name}`: {reason}")
            }
            DaemonError::Push(why) => write!(f, "push failed: {why}"),
            DaemonError::Session(why) => write!(f, "session incomplete: {why}"),
            DaemonError::Validation(reasons) => {
                write!(
                    f,
                    "calibration refused, nothing pushed: {}",
                    reasons.join("; ")
                )
            }
            DaemonError::Io { what, source } => write!(f, "{what}: {source}"),
            DaemonError::Interrupted => write!(f, "interrupted before pushing; nothing pushed"),
            DaemonError::Unsupported(what) => write!(f, "not supported by this build: {what}"),
            DaemonError::Input(what) => write!(f, "bad input: {what}"),
            DaemonError::Usage(what) => write!(f, "usage: {what}"),
        }
    }
}

impl std::error::Error for DaemonError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            DaemonError::Config(e) => Some(e),
            DaemonError::Io { source, .. } => Some(source),
            _ => None,
        }
    }
}

impl From<ConfigError> for DaemonError {
    fn from(e: ConfigError) -> Self {
        DaemonError::Config(e)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_failure_has_its_own_status() {
        let cfg = crate::config::Config::parse("x = 1").unwrap_err();
        let errors = [
            DaemonError::Config(cfg),
            DaemonError::Interface {
                name: "can9".into(),
                reason: "no such device".into(),
            },
            DaemonError::Session("joint 3 covered 10% of its range".into()),
            DaemonError::Validation(vec!["a".into()]),
            DaemonError::Io {
                what: "writing log".into(),
                source: std::io::Error::other("disk full"),
            },
            DaemonError::Interrupted,
            DaemonError::Unsupported("x".into()),
            DaemonError::Input("s.csv: CSV samples, line 3: bad".into()),
            DaemonError::Usage("x".into()),
        ];
        let codes: Vec<u8> = errors.iter().map(DaemonError::exit_code).collect();
        assert_eq!(codes, [78, 69, 66, 65, 74, 75, 70, 65, 64]);
        assert!(errors[1].to_string().contains("can9"));
    }
}
