//! The state directory: what the daemon keeps between runs so that nothing recorded on the bus
//! can be replayed to it or through it — per node the freshness counters of its authenticated
//! transfers, and the last trigger counter accepted.
//!
//! Contract:
//! - the directory is systemd's `StateDirectory=` (`$STATE_DIRECTORY`: `/var/lib/exocald` in the
//!   shipped unit, beside the keys' credential), never `output.directory`: `--output` chooses
//!   where logs go and resets nothing;
//! - every write goes to a temporary file in the directory, is fsynced, renamed over the old
//!   file, and the directory fsynced: after a power loss the file holds the old or the new
//!   content, never a mix or nothing;
//! - `node-counters` ([`NodeCounters`]): one line per node, `NAME KEYID VERIFIED SIGNED`
//!   (`Joint3 1a2b3c4d 41 42`): the highest freshness counter the node proved (in an answer to
//!   Begin whose MAC verified), the highest this controller signed a `CommitAuth` for, and the
//!   id of the key both were made with ([`exocal_dbc::auth::Key::id`]; a node given a new key
//!   starts afresh). A push accepts a node's counter only within
//!   [`NodeCounters::window`] — from the last verified to the highest signed — and records a
//!   counter it signs **before** the `CommitAuth` goes out, so a power loss mid-push never
//!   makes the node's genuine counter look like a jump;
//! - `trigger-counter`: the last trigger counter accepted (decimal);
//! - `stream-nonce`: the last stream nonce sent (decimal, [`next_stream_nonce`]). A node takes
//!   only a `StreamNonce` above the one it holds, so each nonce is above every one sent before:
//!   this controller's next nonce always wins over a replayed one;
//! - a file that does not read is an error naming it, never a silent reset (a reset would
//!   reopen every recorded transfer or trigger to replay).

use std::collections::BTreeMap;
use std::fmt;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::{SystemTime, UNIX_EPOCH};

use exocal_dbc::auth::Key;
use exocal_dbc::NodeId;

/// The file of the nodes' counters.
pub const NODE_COUNTERS: &str = "node-counters";
/// The file of the last accepted trigger counter.
pub const TRIGGER_COUNTER: &str = "trigger-counter";
/// The file of the last stream nonce sent.
pub const STREAM_NONCE: &str = "stream-nonce";
/// The wall clock's part in a stream nonce: tenths of a second since this Unix time
/// (2026-01-01 00:00:00 UTC; 2³² tenths last 13.6 years).
pub const STREAM_NONCE_EPOCH_S: u64 = 1_767_225_600;

/// A state file that could not be read or written.
#[derive(Debug)]
pub struct StateError {
    /// `reading` or `writing`.
    pub doing: &'static str,
    /// The file.
    pub path: PathBuf,
    /// What went wrong.
    pub source: std::io::Error,
}

impl fmt::Display for StateError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{} {}: {}", self.doing, self.path.display(), self.source)
    }
}

impl std::error::Error for StateError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        Some(&self.source)
    }
}

fn invalid(what: String) -> std::io::Error {
    std::io::Error::new(std::io::ErrorKind::InvalidData, what)
}

/// Reads `dir/name`: `None` if it does not exist.
fn read(dir: &Path, name: &str) -> Result<Option<String>, StateError> {
    let path = dir.join(name);
    match std::fs::read_to_string(&path) {
        Ok(text) => Ok(Some(text)),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        Err(source) => Err(StateError {
            doing: "reading",
            path,
            source,
        }),
    }
}

/// Replaces `dir/name` with `text`: temporary file, fsync, rename, fsync of the directory.
fn write(dir: &Path, name: &str, text: &str) -> Result<(), StateError> {
    let path = dir.join(name);
    let tmp = dir.join(format!("{name}.tmp"));
    let io = |source| StateError {
        doing: "writing",
        path: path.clone(),
        source,
    };
    std::fs::create_dir_all(dir).map_err(io)?;
    let mut f = std::fs::File::create(&tmp).map_err(io)?;
    f.write_all(text.as_bytes()).map_err(io)?;
    f.sync_all().map_err(io)?;
    drop(f);
    std::fs::rename(&tmp, &path).map_err(io)?;
    std::fs::File::open(dir)
        .and_then(|d| d.sync_all())
        .map_err(io)
}

/// What the daemon knows of one node's freshness counter.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct NodeRecord {
    /// The id of the key the counters below were made with.
    pub key_id: u32,
    /// The highest counter the node proved (an answer to Begin whose MAC verified).
    pub verified: u32,
    /// The highest counter this controller signed a `CommitAuth` for.
    pub signed: u32,
}

/// The nodes' counters (`node-counters`, see the module docs).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct NodeCounters {
    records: BTreeMap<NodeId, NodeRecord>,
}

impl NodeCounters {
    /// Reads `dir`'s `node-counters` (none yet: empty).
    pub fn load(dir: &Path) -> Result<NodeCounters, StateError> {
        let mut out = NodeCounters::default();
        let Some(text) = read(dir, NODE_COUNTERS)? else {
            return Ok(out);
        };
        for (i, line) in text.lines().enumerate() {
            let bad = |why: &str| StateError {
                doing: "reading",
                path: dir.join(NODE_COUNTERS),
                source: invalid(format!(
                    "line {}: {why} (expected `Joint1 … Joint7`, an 8-digit hexadecimal key id \
                     and two decimal counters)",
                    i + 1
                )),
            };
            let words: Vec<&str> = line.split_whitespace().collect();
            if words.is_empty() {
                continue;
            }
            let [name, id, verified, signed] = words[..] else {
                return Err(bad("not four fields"));
            };
            let node = NodeId::JOINTS
                .into_iter()
                .find(|n| n.name() == name)
                .ok_or_else(|| bad("unknown node"))?;
            let record = NodeRecord {
                key_id: u32::from_str_radix(id, 16).map_err(|_| bad("bad key id"))?,
                verified: verified.parse().map_err(|_| bad("bad counter"))?,
                signed: signed.parse().map_err(|_| bad("bad counter"))?,
            };
            if out.records.insert(node, record).is_some() {
                return Err(bad("a node named twice"));
            }
        }
        Ok(out)
    }

    /// Writes them to `dir`'s `node-counters` (atomically, fsynced).
    pub fn save(&self, dir: &Path) -> Result<(), StateError> {
        let text: String = self
            .records
            .iter()
            .map(|(node, r)| {
                format!(
                    "{} {:08x} {} {}\n",
                    node.name(),
                    r.key_id,
                    r.verified,
                    r.signed
                )
            })
            .collect();
        write(dir, NODE_COUNTERS, &text)
    }

    /// What is known of `node` under `key` (nothing if the record was made with another key).
    pub fn record(&self, node: NodeId, key: &Key) -> Option<NodeRecord> {
        self.records
            .get(&node)
            .copied()
            .filter(|r| r.key_id == key.id())
    }

    /// The counters `node` (holding `key`) may have: from the last it proved to the highest
    /// this controller signed. `None` when nothing is known (the first push with this key).
    pub fn window(&self, node: NodeId, key: &Key) -> Option<(u32, u32)> {
        self.record(node, key)
            .map(|r| (r.verified, r.verified.max(r.signed)))
    }

    fn entry(&mut self, node: NodeId, key: &Key, counter: u32) -> &mut NodeRecord {
        let id = key.id();
        let fresh = NodeRecord {
            key_id: id,
            verified: counter,
            signed: counter,
        };
        let r = self.records.entry(node).or_insert(fresh);
        if r.key_id != id {
            *r = fresh;
        }
        r
    }

    /// `node` proved `counter` (an answer whose MAC verified, within its window); returns
    /// whether the record changed.
    pub fn verified(&mut self, node: NodeId, key: &Key, counter: u32) -> bool {
        let before = self.records.get(&node).copied();
        let r = self.entry(node, key, counter);
        r.verified = r.verified.max(counter);
        before != Some(*r)
    }

    /// This controller signs a `CommitAuth` with `counter` for `node`; returns whether the
    /// record changed (it must then be saved before the frame goes out).
    pub fn signed(&mut self, node: NodeId, key: &Key, counter: u32) -> bool {
        let before = self.records.get(&node).copied();
        let r = self.entry(node, key, counter);
        r.signed = r.signed.max(counter);
        before != Some(*r)
    }
}

/// Reads the last accepted trigger counter from `dir` (0 when there is none yet).
pub fn load_trigger_counter(dir: &Path) -> Result<u32, StateError> {
    let Some(text) = read(dir, TRIGGER_COUNTER)? else {
        return Ok(0);
    };
    text.trim().parse().map_err(|_| StateError {
        doing: "reading",
        path: dir.join(TRIGGER_COUNTER),
        source: invalid(
            "not a trigger counter (a decimal number); it guards against replayed triggers: \
             restore it, or delete it only with a new trigger key"
                .into(),
        ),
    })
}

/// Writes the last accepted trigger counter to `dir` (atomically, fsynced).
pub fn save_trigger_counter(dir: &Path, counter: u32) -> Result<(), StateError> {
    write(dir, TRIGGER_COUNTER, &format!("{counter}\n"))
}

/// The next stream nonce, recorded in `dir` before it is sent: one above the last sent (the one
/// `dir` records, and `last`, this run's), raised to the tenths of a second since
/// [`STREAM_NONCE_EPOCH_S`] by `now` when the clock is ahead. The record alone keeps nonces
/// rising on a controller without a real-time clock; the clock keeps them above what the
/// nodes hold when the record is new (another state directory, a replaced controller).
pub fn next_stream_nonce(
    dir: Option<&Path>,
    last: u32,
    now: SystemTime,
) -> Result<u32, StateError> {
    let path = |d: &Path| d.join(STREAM_NONCE);
    let recorded = match dir {
        Some(d) => match read(d, STREAM_NONCE)? {
            None => 0,
            Some(text) => text.trim().parse::<u32>().map_err(|_| StateError {
                doing: "reading",
                path: path(d),
                source: invalid(
                    "not a stream nonce (a decimal number below 2^32); nodes take only a nonce \
                     above the last they took: restore it, or delete it and reboot the nodes"
                        .into(),
                ),
            })?,
        },
        None => 0,
    };
    let tenths = now
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() / 100)
        .saturating_sub(u128::from(STREAM_NONCE_EPOCH_S) * 10);
    let clock = u32::try_from(tenths).unwrap_or(u32::MAX);
    let next = recorded.max(last).checked_add(1).map(|n| n.max(clock));
    let Some(next) = next.filter(|&n| n < u32::MAX) else {
        return Err(StateError {
            doing: "choosing",
            path: dir.map_or_else(|| PathBuf::from(STREAM_NONCE), path),
            source: invalid(
                "no stream nonce left (the last was 2^32 - 2): give the nodes new keys".into(),
            ),
        });
    };
    if let Some(d) = dir {
        write(d, STREAM_NONCE, &format!("{next}\n"))?;
    }
    Ok(next)
}

/// The state directory systemd gives the unit (`$STATE_DIRECTORY`; the first one if it names
/// several), if any.
pub fn from_env() -> Option<PathBuf> {
    let dirs = std::env::var_os("STATE_DIRECTORY")?;
    let first = dirs.to_str()?.split(':').next()?.to_string();
    (!first.is_empty()).then(|| PathBuf::from(first))
}

#[cfg(test)]
mod tests {
    use super::*;
    use exocal_dbc::auth::KeySet;

    fn dir(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("exocald-state-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        d
    }

    #[test]
    fn node_counters_round_trip_and_a_new_key_starts_afresh() {
        let d = dir("nodes");
        let keys = KeySet::derived(1);
        let (j3, j5) = (NodeId::JOINTS[2], NodeId::JOINTS[4]);
        let k3 = keys.node(j3).unwrap();
        let mut c = NodeCounters::load(&d).unwrap();
        assert_eq!(c.window(j3, k3), None);
        assert!(c.verified(j3, k3, 41));
        assert!(c.signed(j3, k3, 42));
        assert!(!c.signed(j3, k3, 42));
        assert!(!c.verified(j3, k3, 40), "never lowered");
        c.verified(j5, keys.node(j5).unwrap(), 7);
        c.save(&d).unwrap();
        let back = NodeCounters::load(&d).unwrap();
        assert_eq!(back, c);
        assert_eq!(back.window(j3, k3), Some((41, 42)));
        assert_eq!(back.window(j5, keys.node(j5).unwrap()), Some((7, 7)));
        let text = std::fs::read_to_string(d.join(NODE_COUNTERS)).unwrap();
        assert!(text.starts_with("Joint3 "), "{text}");
        assert!(!d.join("node-counters.tmp").exists());
        // Another key: nothing known; its first counter replaces the record.
        let other = KeySet::derived(2);
        let k3b = other.node(j3).unwrap();
        assert_eq!(back.window(j3, k3b), None);
        let mut c = back;
        c.verified(j3, k3b, 3);
        assert_eq!(c.window(j3, k3b), Some((3, 3)));
        assert_eq!(c.window(j3, k3), None);
        let _ = std::fs::remove_dir_all(&d);
    }

    #[test]
    fn a_damaged_state_file_is_an_error_naming_it_never_a_reset() {
        let d = dir("bad");
        std::fs::create_dir_all(&d).unwrap();
        for bad in [
            "Joint3 zz 1 2\n",
            "Joint9 00000000 1 2\n",
            "Joint3 00000000 1\n",
            "Joint3 00000000 1 2\nJoint3 00000000 1 2\n",
            "Joint3 00000000 -1 2\n",
        ] {
            std::fs::write(d.join(NODE_COUNTERS), bad).unwrap();
            let e = NodeCounters::load(&d).unwrap_err().to_string();
            assert!(
                e.contains("node-counters") && e.contains("line"),
                "{bad}: {e}"
            );
        }
        std::fs::write(d.join(TRIGGER_COUNTER), "many").unwrap();
        let e = load_trigger_counter(&d).unwrap_err().to_string();
        assert!(e.contains("trigger-counter"), "{e}");
        let _ = std::fs::remove_dir_all(&d);
    }

    /// Stream nonces rise whatever the clock does, and above it when it is
    /// ahead; the record is kept before a nonce goes out.
    #[test]
    fn stream_nonces_rise_over_runs_and_a_clock_without_rtc() {
        let d = dir("stream");
        let epoch = UNIX_EPOCH;
        let a = next_stream_nonce(Some(&d), 0, epoch).unwrap();
        assert_eq!(a, 1, "no record, clock at 1970");
        // Another run (last 0), the clock still at 1970: above the record.
        assert_eq!(next_stream_nonce(Some(&d), 0, epoch).unwrap(), 2);
        assert_eq!(
            std::fs::read_to_string(d.join(STREAM_NONCE)).unwrap(),
            "2\n"
        );
        // A clock that is right lifts it to its tenths of a second.
        let t = UNIX_EPOCH + std::time::Duration::from_secs(STREAM_NONCE_EPOCH_S + 3600);
        assert_eq!(next_stream_nonce(Some(&d), 0, t).unwrap(), 36_000);
        // Then the clock steps back: still above.
        assert_eq!(next_stream_nonce(Some(&d), 0, epoch).unwrap(), 36_001);
        // A new state directory, the clock right: above the nonces sent before.
        let other = dir("stream-other");
        let later = t + std::time::Duration::from_secs(1);
        assert_eq!(next_stream_nonce(Some(&other), 0, later).unwrap(), 36_010);
        // Without a directory, this run's last.
        assert_eq!(next_stream_nonce(None, 36_010, epoch).unwrap(), 36_011);
        std::fs::write(d.join(STREAM_NONCE), "soon").unwrap();
        let e = next_stream_nonce(Some(&d), 0, epoch)
            .unwrap_err()
            .to_string();
        assert!(e.contains("stream-nonce"), "{e}");
        std::fs::write(d.join(STREAM_NONCE), format!("{}", u32::MAX - 1)).unwrap();
        let e = next_stream_nonce(Some(&d), 0, epoch)
            .unwrap_err()
            .to_string();
        assert!(e.contains("new keys"), "{e}");
        let _ = std::fs::remove_dir_all(&d);
        let _ = std::fs::remove_dir_all(&other);
    }

    #[test]
    fn the_trigger_counter_persists() {
        let d = dir("trigger");
        assert_eq!(load_trigger_counter(&d).unwrap(), 0);
        save_trigger_counter(&d, 0x1_0001).unwrap();
        assert_eq!(load_trigger_counter(&d).unwrap(), 0x1_0001);
        assert!(!d.join("trigger-counter.tmp").exists());
        let _ = std::fs::remove_dir_all(&d);
    }
}
