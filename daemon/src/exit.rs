//! Exit statuses, after BSD's sysexits(3), and the daemon's top-level error.
//!
//! Contract: every way `exocald` can fail maps to one [`DaemonError`] variant, and every variant
//! to one documented exit status, so that systemd, scripts and tests can tell "bad config" (78)
//! from "calibration refused" (65) from "interrupted" (75) without parsing logs.

use std::fmt;

use crate::config::ConfigError;
use crate::keys::KeyError;
use exocal_bus::BusError;
use exocal_log::write::LogError;
use exocal_session::pipeline::CalibrateError;
use exocal_session::validate::Refusal;
use exocal_session::window::Shortfall;

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
    /// EX_UNAVAILABLE: the CAN interface is missing, or a node could not be reached (for
    /// `nodes`: some node did not answer).
    pub const UNAVAILABLE: u8 = 69;
    /// EX_SOFTWARE: an internal error (a bug).
    pub const SOFTWARE: u8 = 70;
    /// EX_IOERR: reading CAN or writing the log failed.
    pub const IOERR: u8 = 74;
    /// EX_TEMPFAIL: interrupted (SIGTERM/SIGINT) before pushing; nothing was pushed.
    pub const TEMPFAIL: u8 = 75;
    /// EX_CONFIG: the configuration is invalid, or its keys are missing.
    pub const CONFIG: u8 = 78;
}

/// Why the daemon stopped unsuccessfully.
#[derive(Debug)]
pub enum DaemonError {
    /// Bad configuration (78).
    Config(ConfigError),
    /// Authentication is on but the keys are missing or invalid (78).
    Keys(KeyError),
    /// The CAN interface does not exist or cannot be opened (69).
    Interface {
        /// The interface's name.
        name: String,
        /// Why it cannot be used, with a hint.
        reason: String,
    },
    /// A node did not accept the table (69); the report says which.
    Push(String),
    /// Not enough motion/samples before the session's maximum duration (66): what was missing.
    Session(Vec<Shortfall>),
    /// The samples could not be calibrated at all (66): too few, or calib-core's reason.
    Calibration(CalibrateError),
    /// The calibration was refused by validation (65): the reasons.
    Validation(Vec<Refusal>),
    /// A validated table cannot be pushed (65): it does not fit the protocol's table
    /// (the row of `joint`, 1-based, and why).
    Unpushable(String),
    /// I/O failure (74): what was being done, and the error.
    Io {
        /// What was being done.
        what: String,
        /// The I/O error.
        source: std::io::Error,
    },
    /// The CAN bus failed (74): what was being done, and the error.
    Bus {
        /// What was being done.
        what: String,
        /// The bus error.
        source: BusError,
    },
    /// The session log could not be written (74).
    Log {
        /// What was being done.
        what: String,
        /// The log error.
        source: LogError,
    },
    /// Interrupted by a signal before anything was pushed (75).
    Interrupted,
    /// A bug (70): a task panicked or was cancelled; what it was doing, and the runtime's error.
    Internal {
        /// What the task was doing.
        what: String,
        /// The runtime's error.
        source: Box<dyn std::error::Error + Send + Sync>,
    },
    /// An offline input that does not parse (65): the file, the line, the problem.
    Input(String),
    /// Options that do not go together (64).
    Usage(String),
    /// Nodes that did not answer (69), by name.
    NoAnswer(Vec<String>),
}

impl From<crate::live::LiveError> for DaemonError {
    /// The live view is I/O (74): its socket or its runtime.
    fn from(e: crate::live::LiveError) -> Self {
        DaemonError::Io {
            what: e.what,
            source: e.source,
        }
    }
}

impl DaemonError {
    /// The process exit status for this error.
    pub fn exit_code(&self) -> u8 {
        match self {
            DaemonError::Config(_) | DaemonError::Keys(_) => code::CONFIG,
            DaemonError::Interface { .. } | DaemonError::Push(_) | DaemonError::NoAnswer(_) => {
                code::UNAVAILABLE
            }
            // Frames on a node's identifiers that the node did not sign: hostile input.
            DaemonError::Session(why)
                if why
                    .iter()
                    .any(|s| matches!(s, Shortfall::SecondSender { .. })) =>
            {
                code::DATAERR
            }
            DaemonError::Session(_) | DaemonError::Calibration(_) => code::NOINPUT,
            DaemonError::Validation(_) | DaemonError::Unpushable(_) => code::DATAERR,
            DaemonError::Io { .. } | DaemonError::Bus { .. } | DaemonError::Log { .. } => {
                code::IOERR
            }
            DaemonError::Interrupted => code::TEMPFAIL,
            DaemonError::Internal { .. } => code::SOFTWARE,
            DaemonError::Input(_) => code::DATAERR,
            DaemonError::Usage(_) => code::USAGE,
        }
    }
}

/// Every item's line, separated by `; `.
fn lines<T: fmt::Display>(items: &[T]) -> String {
    let all: Vec<String> = items.iter().map(T::to_string).collect();
    all.join("; ")
}

impl fmt::Display for DaemonError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            DaemonError::Config(e) => write!(f, "bad configuration: {e}"),
            DaemonError::Keys(e) => write!(f, "bad configuration: {e}"),
            DaemonError::Interface { name, reason } => {
                write!(f, "CAN interface `{name}`: {reason}")
            }
            DaemonError::Push(why) => write!(f, "push failed: {why}"),
            DaemonError::Session(why) => write!(f, "session incomplete: {}", lines(why)),
            DaemonError::Calibration(e) => write!(f, "session incomplete: {e}"),
            DaemonError::Validation(reasons) => {
                write!(f, "calibration refused, nothing pushed: {}", lines(reasons))
            }
            DaemonError::Unpushable(why) => write!(f, "calibration refused, nothing pushed: {why}"),
            DaemonError::Io { what, source } => write!(f, "{what}: {source}"),
            DaemonError::Bus { what, source } => write!(f, "{what}: {source}"),
            DaemonError::Log { what, source } => write!(f, "{what}: {source}"),
            DaemonError::Interrupted => write!(f, "interrupted before pushing; nothing pushed"),
            DaemonError::Internal { what, source } => {
                write!(
                    f,
                    "internal error (a bug; please report it) {what}: {source}"
                )
            }
            DaemonError::Input(what) => write!(f, "bad input: {what}"),
            DaemonError::Usage(what) => write!(f, "usage: {what}"),
            DaemonError::NoAnswer(nodes) => write!(f, "no answer from {}", nodes.join(", ")),
        }
    }
}

impl std::error::Error for DaemonError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            DaemonError::Config(e) => Some(e),
            DaemonError::Keys(e) => Some(e),
            DaemonError::Calibration(e) => Some(e),
            DaemonError::Io { source, .. } => Some(source),
            DaemonError::Bus { source, .. } => Some(source),
            DaemonError::Log { source, .. } => Some(source),
            DaemonError::Internal { source, .. } => Some(source.as_ref()),
            _ => None,
        }
    }
}

impl From<crate::push::PushError> for DaemonError {
    fn from(e: crate::push::PushError) -> Self {
        use crate::push::PushError;
        match e {
            PushError::Incomplete(failed) => DaemonError::Push(failed),
            PushError::Bus(source) => DaemonError::Bus {
                what: "pushing tables (what each node was sent and holds is in the log)".into(),
                source,
            },
        }
    }
}

impl From<crate::state::StateError> for DaemonError {
    fn from(e: crate::state::StateError) -> Self {
        DaemonError::Io {
            what: format!("{} {}", e.doing, e.path.display()),
            source: e.source,
        }
    }
}

impl From<ConfigError> for DaemonError {
    fn from(e: ConfigError) -> Self {
        DaemonError::Config(e)
    }
}

impl From<KeyError> for DaemonError {
    fn from(e: KeyError) -> Self {
        DaemonError::Keys(e)
    }
}

impl From<CalibrateError> for DaemonError {
    fn from(e: CalibrateError) -> Self {
        DaemonError::Calibration(e)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_push_that_ends_short_is_a_push_failure_and_a_bus_that_fails_a_bus_error() {
        use crate::push::PushError;
        let incomplete = DaemonError::from(PushError::Incomplete("joint 2: Old".into()));
        assert!(matches!(&incomplete, DaemonError::Push(why) if why == "joint 2: Old"));
        assert_eq!(incomplete.to_string(), "push failed: joint 2: Old");
        let bus = DaemonError::from(PushError::Bus(exocal_bus::BusError::Closed));
        let DaemonError::Bus { what, .. } = &bus else {
            panic!("{bus:?}")
        };
        assert!(what.starts_with("pushing tables"), "{what}");
        assert_eq!(bus.exit_code(), code::IOERR);
        assert_eq!(incomplete.exit_code(), code::UNAVAILABLE);
    }

    #[test]
    fn each_failure_has_its_own_status() {
        let cfg = crate::config::Config::parse("x = 1").unwrap_err();
        let errors = [
            DaemonError::Config(cfg),
            DaemonError::Interface {
                name: "can9".into(),
                reason: "no such device".into(),
            },
            DaemonError::Session(vec![Shortfall::Samples { have: 3, need: 9 }]),
            DaemonError::Validation(vec![Refusal::NoExpectedAccuracy]),
            DaemonError::Io {
                what: "writing log".into(),
                source: std::io::Error::other("disk full"),
            },
            DaemonError::Interrupted,
            DaemonError::Internal {
                what: "calibrating".into(),
                source: "task panicked".into(),
            },
            DaemonError::Input("s.csv: CSV samples, line 3: bad".into()),
            DaemonError::Usage("x".into()),
            DaemonError::Bus {
                what: "receiving CAN".into(),
                source: BusError::Closed,
            },
            DaemonError::Calibration(CalibrateError::TooFewSamples { have: 3, need: 5 }),
            DaemonError::Log {
                what: "writing the log".into(),
                source: LogError::Io(std::io::Error::other("disk full")),
            },
            DaemonError::NoAnswer(vec!["Joint4".into(), "Joint6".into()]),
            DaemonError::Keys(KeyError::Missing { looked: None }),
        ];
        let codes: Vec<u8> = errors.iter().map(DaemonError::exit_code).collect();
        assert_eq!(
            codes,
            [78, 69, 66, 65, 74, 75, 70, 65, 64, 74, 66, 74, 69, 78]
        );
        assert_eq!(errors[12].to_string(), "no answer from Joint4, Joint6");
        assert!(errors[1].to_string().contains("can9"));
        // The causes are kept, not flattened to strings: a caller can walk to the root.
        use std::error::Error as _;
        let io = errors[11]
            .source()
            .and_then(|e| e.source())
            .expect("the io error");
        assert_eq!(io.to_string(), "disk full");
        let calib = DaemonError::from(CalibrateError::Ls(calib_core::CalibError::NoExcitation {
            joint: 3,
            range: 0.0,
        }));
        assert!(calib.source().and_then(|e| e.source()).is_some());
    }
}
