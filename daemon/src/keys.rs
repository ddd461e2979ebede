//! The node and trigger keys: from the systemd credential `exocal-keys`, never from
//! `exocald.toml`, the logs or the report.
//!
//! Contract:
//! - [`load`] reads `$CREDENTIALS_DIRECTORY/exocal-keys` (systemd's `LoadCredential=` or
//!   `LoadCredentialEncrypted=`, which work with `DynamicUser=`): a key file as
//!   [`KeySet::parse`] reads it (`Joint1 <32 hex digits>` … `Joint7`, `Trigger`);
//! - every joint node the configuration names must have a key, and so must the trigger when
//!   `exocald run` needs it; anything missing is a [`KeyError`] naming what and where, which
//!   `exocald` maps to exit 78 at start-up, before it touches the bus;
//! - a key never appears in an error, a log line or the session report ([`KeySet`]'s `Debug`
//!   names nodes, not keys); a key file with an all-zero key or one key for two names is
//!   refused ([`KeySet::parse`]); keys are zeroised when dropped
//!   ([`exocal_dbc::auth::Key`]), and the shipped units set `LimitCORE=0` (no core dump holds
//!   them);
//! - outside systemd (no `$INVOCATION_ID`: a credentials directory made by hand), a key file
//!   that group or others may read or write is loaded with a warning ([`permission_warning`]);
//!   under systemd the credential is the service's own, whatever the source file's mode.

use std::fmt;
use std::path::{Path, PathBuf};

use exocal_dbc::auth::{KeyFileError, KeySet};
use exocal_dbc::NodeId;

/// The name of the systemd credential holding the keys.
pub const CREDENTIAL: &str = "exocal-keys";

/// How to provision the keys, for error messages.
const HOW: &str = "provision it as a systemd credential (systemd/README.md, \"Keys\": a key file \
                   in /etc/credstore/exocal-keys, mode 0600, read by the shipped unit's \
                   LoadCredential=), or, on a bench without keys, set `[push] authenticate = \
                   false` in the configuration";

/// Why the keys could not be loaded.
#[derive(Debug)]
pub enum KeyError {
    /// No credential: `$CREDENTIALS_DIRECTORY` is unset, or it has no `exocal-keys`.
    Missing {
        /// Where the credential was looked for (`None`: `$CREDENTIALS_DIRECTORY` is unset).
        looked: Option<PathBuf>,
    },
    /// The credential could not be read.
    Io {
        /// The credential file.
        path: PathBuf,
        /// The read error.
        source: std::io::Error,
    },
    /// The credential is not a key file.
    File {
        /// The credential file.
        path: PathBuf,
        /// Why it does not parse.
        source: KeyFileError,
    },
    /// The key file has no key for this node (or `Trigger`).
    NoKey {
        /// The credential file.
        path: PathBuf,
        /// The node (`Joint1` … `Joint7`) or `Trigger` it has no key for.
        name: &'static str,
    },
    /// No state directory (`$STATE_DIRECTORY` unset): the counters that refuse replays would
    /// not survive the run.
    NoState,
}

impl fmt::Display for KeyError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            KeyError::Missing { looked: None } => write!(
                f,
                "no keys: $CREDENTIALS_DIRECTORY is not set, so the credential `{CREDENTIAL}` \
                 was not passed; {HOW}"
            ),
            KeyError::Missing { looked: Some(p) } => write!(
                f,
                "no keys: the credential `{CREDENTIAL}` is missing ({} does not exist); {HOW}",
                p.display()
            ),
            KeyError::Io { path, source } => {
                write!(f, "cannot read the keys in {}: {source}", path.display())
            }
            KeyError::File { path, source } => write!(
                f,
                "the key file {} is not valid: {source} (a line is `Joint1` … `Joint7` or \
                 `Trigger`, a space, and 32 hexadecimal digits)",
                path.display()
            ),
            KeyError::NoKey { path, name } => write!(
                f,
                "the key file {} has no key for {name}; {HOW}",
                path.display()
            ),
            KeyError::NoState => f.write_str(
                "no state directory: $STATE_DIRECTORY is not set, and authenticated transfers \
                 keep the nodes' freshness counters and the trigger counter there between runs; \
                 run under the shipped unit (StateDirectory=exocald), or set STATE_DIRECTORY to \
                 a directory only exocald may write",
            ),
        }
    }
}

impl std::error::Error for KeyError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            KeyError::Io { source, .. } => Some(source),
            KeyError::File { source, .. } => Some(source),
            _ => None,
        }
    }
}

/// Loads the keys from the credentials directory `dir` (`$CREDENTIALS_DIRECTORY`, `None` when
/// unset) and checks there is one for each of `nodes`, and for the trigger if `trigger`.
pub fn load(dir: Option<PathBuf>, nodes: &[NodeId], trigger: bool) -> Result<KeySet, KeyError> {
    let Some(path) = dir.map(|d| d.join(CREDENTIAL)) else {
        return Err(KeyError::Missing { looked: None });
    };
    let text = match std::fs::read_to_string(&path) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            return Err(KeyError::Missing { looked: Some(path) })
        }
        Err(source) => return Err(KeyError::Io { path, source }),
    };
    let keys = KeySet::parse(&text).map_err(|source| KeyError::File {
        path: path.clone(),
        source,
    })?;
    if let Some(node) = nodes.iter().find(|&&n| keys.node(n).is_none()) {
        return Err(KeyError::NoKey {
            path,
            name: node.name(),
        });
    }
    if trigger && keys.trigger().is_none() {
        return Err(KeyError::NoKey {
            path,
            name: "Trigger",
        });
    }
    Ok(keys)
}

/// [`load`] from `$CREDENTIALS_DIRECTORY`.
pub fn load_credential(nodes: &[NodeId], trigger: bool) -> Result<KeySet, KeyError> {
    load(credentials_dir(), nodes, trigger)
}

fn credentials_dir() -> Option<PathBuf> {
    std::env::var_os("CREDENTIALS_DIRECTORY").map(PathBuf::from)
}

/// The keys from `$CREDENTIALS_DIRECTORY` if the credential is there (`None` if it is not:
/// a command that can do without, like `exocald nodes`, then reads unauthenticated).
pub fn load_if_present(nodes: &[NodeId]) -> Result<Option<KeySet>, KeyError> {
    match load_credential(nodes, false) {
        Ok(keys) => Ok(Some(keys)),
        Err(KeyError::Missing { .. }) => Ok(None),
        Err(e) => Err(e),
    }
}

/// A warning for a key file in `dir` (the credentials directory) that group or others may
/// read or write, when not `under_systemd` (whose credentials are the service's own); `None`
/// when the file is private, absent, or systemd passed it.
pub fn permission_warning(dir: Option<&Path>, under_systemd: bool) -> Option<String> {
    use std::os::unix::fs::PermissionsExt;
    if under_systemd {
        return None;
    }
    let path = dir?.join(CREDENTIAL);
    let mode = std::fs::metadata(&path).ok()?.permissions().mode() & 0o777;
    (mode & 0o077 != 0).then(|| {
        format!(
            "WARNING: the key file {} has mode {mode:04o}: other users may read the node keys \
             (chmod 600 it, or pass it as a systemd credential)",
            path.display()
        )
    })
}

/// [`permission_warning`] for `$CREDENTIALS_DIRECTORY`, outside systemd when `$INVOCATION_ID`
/// is unset.
pub fn credential_warning() -> Option<String> {
    let under_systemd = std::env::var_os("INVOCATION_ID").is_some();
    permission_warning(credentials_dir().as_deref(), under_systemd)
}

#[cfg(test)]
mod tests {
    use super::*;

    const K: &str = "000102030405060708090a0b0c0d0e0f";

    fn dir(name: &str, text: Option<&str>) -> PathBuf {
        let d = std::env::temp_dir().join(format!("exocald-keys-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        if let Some(t) = text {
            std::fs::write(d.join(CREDENTIAL), t).unwrap();
        }
        d
    }

    /// A distinct key per name: `K` with its last digit the node's id (`f` for the trigger).
    fn all(trigger: bool) -> String {
        let key = |last: char| format!("{}{last}", &K[..31]);
        let mut t: String = NodeId::JOINTS
            .iter()
            .map(|n| format!("{} {}\n", n.name(), key(char::from(b'0' + n.raw()))))
            .collect();
        if trigger {
            t.push_str(&format!("Trigger {}\n", key('f')));
        }
        t
    }

    #[test]
    fn a_complete_credential_loads() {
        let d = dir("ok", Some(&all(true)));
        let keys = load(Some(d.clone()), &NodeId::JOINTS, true).unwrap();
        assert!(keys.trigger().is_some());
        let _ = std::fs::remove_dir_all(&d);
    }

    #[test]
    fn what_is_missing_is_named_and_no_key_is_shown() {
        let e = load(None, &NodeId::JOINTS, false).unwrap_err();
        assert!(
            e.to_string().contains("CREDENTIALS_DIRECTORY is not set"),
            "{e}"
        );
        let d = dir("none", None);
        let e = load(Some(d.clone()), &NodeId::JOINTS, false).unwrap_err();
        assert!(e.to_string().contains("exocal-keys` is missing"), "{e}");
        assert!(e.to_string().contains("authenticate = false"), "{e}");
        let d2 = dir("no-trigger", Some(&all(false)));
        let e = load(Some(d2.clone()), &NodeId::JOINTS, true).unwrap_err();
        assert!(e.to_string().contains("no key for Trigger"), "{e}");
        assert!(load(Some(d2.clone()), &NodeId::JOINTS, false).is_ok());
        let d3 = dir("no-joint5", Some(&all(true).replace("Joint5", "# Joint5")));
        let e = load(Some(d3.clone()), &NodeId::JOINTS, true).unwrap_err();
        assert!(e.to_string().contains("no key for Joint5"), "{e}");
        let d4 = dir("bad", Some(&all(true).replace("Joint3 00", "Joint3 zz")));
        let e = load(Some(d4.clone()), &NodeId::JOINTS, true).unwrap_err();
        let shown = e.to_string();
        assert!(shown.contains("line 3") && !shown.contains(K), "{shown}");
        for d in [d, d2, d3, d4] {
            let _ = std::fs::remove_dir_all(&d);
        }
    }

    /// Issue 34, item 8: a shared or all-zero key is refused, naming the line and not the key.
    #[test]
    fn a_shared_or_all_zero_key_is_refused() {
        let shared = all(true).replace(
            &format!("Joint5 {}5", &K[..31]),
            &format!("Joint5 {}3", &K[..31]),
        );
        let d = dir("shared", Some(&shared));
        let e = load(Some(d.clone()), &NodeId::JOINTS, true)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("line 5") && e.contains("same key") && !e.contains(&K[..20]),
            "{e}"
        );
        let zero = all(true).replace(&format!("{}2", &K[..31]), &"0".repeat(32));
        let d2 = dir("zero", Some(&zero));
        let e = load(Some(d2.clone()), &NodeId::JOINTS, true)
            .unwrap_err()
            .to_string();
        assert!(e.contains("line 2") && e.contains("all-zero"), "{e}");
        for d in [d, d2] {
            let _ = std::fs::remove_dir_all(&d);
        }
    }

    /// Issue 34, item 8: outside systemd, a key file others may read is said; a private one,
    /// or one systemd passed, is not.
    #[test]
    fn a_key_file_readable_by_others_is_warned_about_outside_systemd() {
        use std::os::unix::fs::PermissionsExt;
        let d = dir("mode", Some(&all(true)));
        let file = d.join(CREDENTIAL);
        std::fs::set_permissions(&file, std::fs::Permissions::from_mode(0o644)).unwrap();
        let w = permission_warning(Some(&d), false).expect("a warning");
        assert!(w.contains("0644") && w.contains("exocal-keys"), "{w}");
        assert!(!w.contains(&K[..20]), "{w}");
        assert_eq!(permission_warning(Some(&d), true), None);
        std::fs::set_permissions(&file, std::fs::Permissions::from_mode(0o600)).unwrap();
        assert_eq!(permission_warning(Some(&d), false), None);
        assert_eq!(permission_warning(None, false), None);
        let _ = std::fs::remove_dir_all(&d);
    }
}
