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
//!   names nodes, not keys); a key file with a key that cannot be random (all zero, a few
//!   repeated bytes, counting byte by byte), or with one key for two names or two keys a few
//!   hex digits apart, is refused ([`KeySet::parse`]); keys, and the key file's text, are
//!   zeroised when dropped ([`exocal_dbc::auth::Key`]), and the shipped units set
//!   `LimitCORE=0` (no core dump holds them);
//! - a key file that group or others may read or write is loaded with a warning
//!   ([`permission_warning`]), whatever the environment: the credential as the daemon sees it,
//!   and its source `/etc/credstore/exocal-keys` where the daemon can see it (as root; a
//!   `DynamicUser=` service cannot look into `/etc/credstore`, mode 0700).

use std::fmt;
use std::path::PathBuf;

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
    // The key file's text is wiped when dropped, as the keys are.
    let text = match std::fs::read_to_string(&path) {
        Ok(t) => zeroize::Zeroizing::new(t),
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

/// Where the shipped units load the credential from (`LoadCredential=`).
pub const CREDENTIAL_SOURCE: &str = "/etc/credstore/exocal-keys";

/// A warning for the first of `files` (key files) that group or others may read or write;
/// `None` when each is private, absent, or out of sight.
pub fn permission_warning(files: &[PathBuf]) -> Option<String> {
    use std::os::unix::fs::PermissionsExt;
    files.iter().find_map(|path| {
        let mode = std::fs::metadata(path).ok()?.permissions().mode() & 0o777;
        (mode & 0o077 != 0).then(|| {
            format!(
                "WARNING: the key file {} has mode {mode:04o}: other users may read the node keys \
                 (chmod 600 it, or pass it as a systemd credential)",
                path.display()
            )
        })
    })
}

/// [`permission_warning`] for the credential in `$CREDENTIALS_DIRECTORY` and its source,
/// [`CREDENTIAL_SOURCE`].
pub fn credential_warning() -> Option<String> {
    let mut files: Vec<PathBuf> = credentials_dir()
        .map(|d| d.join(CREDENTIAL))
        .into_iter()
        .collect();
    files.push(PathBuf::from(CREDENTIAL_SOURCE));
    permission_warning(&files)
}

/// A seed for the transfer and readback nonces ([`exocal_dbc::auth::nonce`]) from the OS random
/// source: the clock alone repeats across boots of a controller without a real-time clock, so a
/// recorded answer would verify again. Should the OS source fail, std's randomly keyed hasher
/// over the time stands in (its keys come from the OS too).
pub fn nonce_seed() -> u64 {
    getrandom::u64().unwrap_or_else(|_| {
        use std::hash::BuildHasher;
        std::collections::hash_map::RandomState::new().hash_one(std::time::SystemTime::now())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Random keys, as `openssl rand -hex 16` makes them: Joint1 … Joint7, then the trigger.
    const KEYS: [&str; 8] = [
        "d2fe1afeaf1a7f865abffce7e70bc40f",
        "f8cdd3372ffdf62dd6e41bb3ca8305df",
        "83b0061fafc8061321dd9c86f166f1a9",
        "803141d6acbe79035aa51970f73b2a20",
        "4e8f6a2f12becd4cc10408154b93d44f",
        "8c093a86240c2d004be100a8d84da4cb",
        "892048930dc0381aae120438d77217d5",
        "6ef94891acfe2c5f0906f9eb19e38475",
    ];

    fn dir(name: &str, text: Option<&str>) -> PathBuf {
        let d = std::env::temp_dir().join(format!("exocald-keys-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        if let Some(t) = text {
            std::fs::write(d.join(CREDENTIAL), t).unwrap();
        }
        d
    }

    /// A key per name ([`KEYS`]).
    fn all(trigger: bool) -> String {
        let mut t: String = NodeId::JOINTS
            .iter()
            .zip(KEYS)
            .map(|(n, k)| format!("{} {k}\n", n.name()))
            .collect();
        if trigger {
            t.push_str(&format!("Trigger {}\n", KEYS[7]));
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
        let d4 = dir("bad", Some(&all(true).replace("Joint3 83", "Joint3 zz")));
        let e = load(Some(d4.clone()), &NodeId::JOINTS, true).unwrap_err();
        let shown = e.to_string();
        assert!(
            shown.contains("line 3") && !shown.contains(&KEYS[2][2..]),
            "{shown}"
        );
        for d in [d, d2, d3, d4] {
            let _ = std::fs::remove_dir_all(&d);
        }
    }

    /// A shared, all-zero, patterned or nearly shared key is refused, naming the line and not
    /// the key.
    #[test]
    fn a_shared_or_all_zero_key_is_refused() {
        let with = |joint: usize, key: &str| all(true).replace(KEYS[joint - 1], key);
        let nearly = format!("{}{}", &KEYS[2][..31], "0");
        for (name, text, line, said) in [
            ("shared", with(5, KEYS[2]), "line 5", "same key"),
            ("nearly", with(5, &nearly), "line 5", "nearly the same key"),
            ("zero", with(2, &"0".repeat(32)), "line 2", "all-zero"),
            (
                "counting",
                with(4, "00112233445566778899aabbccddeeff"),
                "line 4",
                "counting",
            ),
            (
                "repeated",
                with(6, &"c0ffee".repeat(6)[..32]),
                "line 6",
                "repeated bytes",
            ),
        ] {
            let d = dir(name, Some(&text));
            let e = load(Some(d.clone()), &NodeId::JOINTS, true)
                .unwrap_err()
                .to_string();
            assert!(e.contains(line) && e.contains(said), "{name}: {e}");
            assert!(KEYS.iter().all(|k| !e.contains(&k[..12])), "{e}");
            let _ = std::fs::remove_dir_all(&d);
        }
    }

    /// A key file others may read is said whatever the environment (under systemd too, so a
    /// world-readable source in /etc/credstore is not left unsaid); a private one, or one out
    /// of sight, is not.
    #[test]
    fn a_key_file_readable_by_others_is_warned_about() {
        use std::os::unix::fs::PermissionsExt;
        let d = dir("mode", Some(&all(true)));
        let file = d.join(CREDENTIAL);
        let source = d.join("credstore-exocal-keys");
        std::fs::write(&source, all(true)).unwrap();
        std::fs::set_permissions(&file, std::fs::Permissions::from_mode(0o600)).unwrap();
        std::fs::set_permissions(&source, std::fs::Permissions::from_mode(0o644)).unwrap();
        let w = permission_warning(&[file.clone(), source.clone()]).expect("a warning");
        assert!(
            w.contains("0644") && w.contains("credstore-exocal-keys"),
            "{w}"
        );
        assert!(KEYS.iter().all(|k| !w.contains(&k[..12])), "{w}");
        std::fs::set_permissions(&source, std::fs::Permissions::from_mode(0o600)).unwrap();
        assert_eq!(permission_warning(&[file, source]), None);
        assert_eq!(permission_warning(&[d.join("absent")]), None);
        let _ = std::fs::remove_dir_all(&d);
    }
}
