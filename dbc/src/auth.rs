//! Authentication of table transfers and triggers: AES-128-CMAC truncated to 32 bits, with
//! freshness counters (the AUTOSAR SecOC recipe for classic CAN).
//!
//! Contract:
//! - every MAC is the first four bytes (read big-endian) of AES-128-CMAC ([`cmac`] over [`aes`],
//!   both `no_std`) with the key of the node concerned (the trigger key for [`Trigger`]s), over
//!   a one-byte domain tag followed by fixed-size fields, integers little-endian:
//!
//!   | MAC | tag | fields |
//!   |---|---|---|
//!   | [`freshness_mac`] | `F` | node id, session, the Begin's nonce (u32), counter (u32), held CRC-32 (u32) |
//!   | [`commit_mac`] | `C` | node id, session, counter (u32), the 24 table bytes, CRC-32 (u32) |
//!   | [`readback_mac`] | `R` | node id, nonce (u32), held CRC-32 (u32), the 24 table bytes |
//!   | [`trigger_mac`] | `T` | command, counter (u32) |
//!   | [`nonce`] | `N` | node id, session, time (u64, µs) |
//!   | [`Key::id`] | `I` | (nothing) |
//!
//!   so no MAC of one kind verifies as another;
//! - a frame carries the low 16 bits of a counter; the receiver stored the last counter it
//!   accepted and takes the smallest value above it with those low bits ([`next_counter`]): a
//!   sender may skip at most 65,535 values, a replay or a stale sender never verifies;
//! - the counter a controller signs above comes to it authenticated: a node answers Begin with
//!   its counter and a [`freshness_mac`] over the controller's nonce, so nobody without the key
//!   can make a controller sign for a counter far ahead of the node's (and keep that
//!   `CommitAuth` for a later replay);
//! - [`verify_freshness`], [`verify_commit`], [`verify_readback`] and [`verify_trigger`]
//!   compare in constant time;
//! - a [`Key`] never shows in `Debug` output, has no `Display`, and is zeroised when dropped
//!   ([`zeroize`]); a [`KeySet`] refuses an all-zero key and a key given twice.
//!
//! Time is an argument here as everywhere in this crate: [`nonce`] is a MAC of the time the
//! caller passes, so it is unpredictable without the key and never repeats for one node and
//! session while time moves on.

use aes::Aes128;
use cmac::{Cmac, Mac};
use zeroize::{Zeroize, ZeroizeOnDrop};

use crate::message::{Trigger, TriggerCommand};
use crate::table::Table;
use crate::NodeId;

/// Length of a key, bytes (AES-128).
pub const KEY_LEN: usize = 16;

/// An AES-128 key. `Debug` prints `Key(..)`: a key never reaches a log by accident; its bytes
/// are overwritten with zeros when it is dropped (a core dump or a freed page keeps no copy).
#[derive(Clone, PartialEq, Eq)]
pub struct Key([u8; KEY_LEN]);

/// Fewest distinct byte values a key may have ([`Key::weakness`]).
pub const MIN_DISTINCT_BYTES: usize = 8;
/// Fewest hex digits in which two keys of one key file may differ (random keys differ in about
/// 30 of 32; one a digit or two from another was edited from it).
pub const MIN_DIGITS_APART: u32 = 8;

impl Drop for Key {
    fn drop(&mut self) {
        self.0.zeroize();
    }
}

impl Zeroize for Key {
    fn zeroize(&mut self) {
        self.0.zeroize();
    }
}

impl ZeroizeOnDrop for Key {}

impl core::fmt::Debug for Key {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str("Key(..)")
    }
}

impl Key {
    /// The key with these bytes.
    pub const fn new(bytes: [u8; KEY_LEN]) -> Key {
        Key(bytes)
    }

    /// The key bytes (to store them; never to print them).
    pub fn bytes(&self) -> &[u8; KEY_LEN] {
        &self.0
    }

    /// From 32 hexadecimal digits (either case); `None` for anything else.
    pub fn from_hex(text: &str) -> Option<Key> {
        let text = text.as_bytes();
        if text.len() != 2 * KEY_LEN {
            return None;
        }
        // Built in place: a key half parsed is zeroised when dropped, like a whole one.
        let mut key = Key([0u8; KEY_LEN]);
        for (byte, pair) in key.0.iter_mut().zip(text.chunks_exact(2)) {
            *byte = (hex_digit(pair[0])? << 4) | hex_digit(pair[1])?;
        }
        Some(key)
    }

    /// Whether every byte is zero (a placeholder, never a key).
    pub fn is_zero(&self) -> bool {
        self.0.iter().all(|&b| b == 0)
    }

    /// Why this key cannot be a random one (all zero, few distinct bytes, or counting up or
    /// down byte by byte), if it cannot: a random key has fewer than [`MIN_DISTINCT_BYTES`]
    /// distinct bytes with a probability of about 2·10⁻⁹.
    pub fn weakness(&self) -> Option<&'static str> {
        if self.is_zero() {
            return Some("an all-zero key is a placeholder, not a key");
        }
        let mut seen = [false; 256];
        for &b in &self.0 {
            seen[usize::from(b)] = true;
        }
        if seen.iter().filter(|&&s| s).count() < MIN_DISTINCT_BYTES {
            return Some(
                "a key of a few repeated bytes is not random: generate one (e.g. `openssl rand -hex 16`)",
            );
        }
        let step = self.0[1].wrapping_sub(self.0[0]);
        if self.0.windows(2).all(|w| w[1].wrapping_sub(w[0]) == step) {
            return Some(
                "a key counting byte by byte (00 01 02 …) is not random: generate one (e.g. `openssl rand -hex 16`)",
            );
        }
        None
    }

    /// In how many of its 32 hex digits this key differs from `other`.
    pub fn digits_apart(&self, other: &Key) -> u32 {
        self.0
            .iter()
            .zip(&other.0)
            .map(|(a, b)| {
                let x = a ^ b;
                u32::from(x & 0x0f != 0) + u32::from(x & 0xf0 != 0)
            })
            .sum()
    }

    /// A 32-bit identifier of this key (a MAC of `I`): to tell, in stored state, which key a
    /// record was made with, without storing the key.
    pub fn id(&self) -> u32 {
        truncated(cmac(self, &[b"I"]))
    }

    /// A key derived from this one for `label` (the full 16-byte CMAC of `K`, `label`): to make
    /// per-node keys from one master key (the demo's, from its seed).
    pub fn derive(&self, label: &[u8]) -> Key {
        let mut mac = self.mac();
        mac.update(b"K");
        mac.update(label);
        Key(mac.finalize().into_bytes().into())
    }

    fn mac(&self) -> Cmac<Aes128> {
        <Cmac<Aes128> as Mac>::new_from_slice(&self.0).expect("a 16-byte key fits AES-128")
    }
}

fn hex_digit(c: u8) -> Option<u8> {
    match c {
        b'0'..=b'9' => Some(c - b'0'),
        b'a'..=b'f' => Some(c - b'a' + 10),
        b'A'..=b'F' => Some(c - b'A' + 10),
        _ => None,
    }
}

/// The CMAC of `parts` under `key`, not yet finalised.
pub(crate) fn cmac(key: &Key, parts: &[&[u8]]) -> Cmac<Aes128> {
    let mut mac = key.mac();
    for p in parts {
        mac.update(p);
    }
    mac
}

pub(crate) fn truncated(mac: Cmac<Aes128>) -> u32 {
    let tag = mac.finalize().into_bytes();
    u32::from_be_bytes([tag[0], tag[1], tag[2], tag[3]])
}

pub(crate) fn verify(mac: Cmac<Aes128>, got: u32) -> bool {
    mac.verify_truncated_left(&got.to_be_bytes()).is_ok()
}

fn freshness_input(
    key: &Key,
    node: NodeId,
    session: u8,
    nonce: u32,
    counter: u32,
    held_crc: u32,
) -> Cmac<Aes128> {
    cmac(
        key,
        &[
            b"F",
            &[node.raw(), session],
            &nonce.to_le_bytes(),
            &counter.to_le_bytes(),
            &held_crc.to_le_bytes(),
        ],
    )
}

/// The MAC of a keyed node's answer to `Begin(nonce)` in `session`: it stores freshness
/// `counter` and holds the table whose CRC is `held_crc`.
pub fn freshness_mac(
    key: &Key,
    node: NodeId,
    session: u8,
    nonce: u32,
    counter: u32,
    held_crc: u32,
) -> u32 {
    truncated(freshness_input(
        key, node, session, nonce, counter, held_crc,
    ))
}

/// Whether `mac` is [`freshness_mac`] of these values (constant time).
pub fn verify_freshness(
    key: &Key,
    node: NodeId,
    session: u8,
    nonce: u32,
    counter: u32,
    held_crc: u32,
    mac: u32,
) -> bool {
    verify(
        freshness_input(key, node, session, nonce, counter, held_crc),
        mac,
    )
}

fn commit_input(key: &Key, node: NodeId, session: u8, counter: u32, table: &Table) -> Cmac<Aes128> {
    cmac(
        key,
        &[
            b"C",
            &[node.raw(), session],
            &counter.to_le_bytes(),
            &table.to_bytes(),
            &table.crc().to_le_bytes(),
        ],
    )
}

/// The MAC of a `CommitAuth`: `table` (and its CRC) committed to `node` in `session` with
/// freshness `counter`.
pub fn commit_mac(key: &Key, node: NodeId, session: u8, counter: u32, table: &Table) -> u32 {
    truncated(commit_input(key, node, session, counter, table))
}

/// Whether `mac` is [`commit_mac`] of these values (constant time).
pub fn verify_commit(
    key: &Key,
    node: NodeId,
    session: u8,
    counter: u32,
    table: &Table,
    mac: u32,
) -> bool {
    verify(commit_input(key, node, session, counter, table), mac)
}

fn readback_input(
    key: &Key,
    node: NodeId,
    nonce: u32,
    held_crc: u32,
    table: &[u8; 24],
) -> Cmac<Aes128> {
    cmac(
        key,
        &[
            b"R",
            &[node.raw()],
            &nonce.to_le_bytes(),
            &held_crc.to_le_bytes(),
            table,
        ],
    )
}

/// The MAC of a node's readback answer: it holds `table` (24 bytes, [`Table::to_bytes`]) whose
/// CRC it reports as `held_crc`, asked with `nonce`.
pub fn readback_mac(key: &Key, node: NodeId, nonce: u32, held_crc: u32, table: &[u8; 24]) -> u32 {
    truncated(readback_input(key, node, nonce, held_crc, table))
}

/// Whether `mac` is [`readback_mac`] of these values (constant time).
pub fn verify_readback(
    key: &Key,
    node: NodeId,
    nonce: u32,
    held_crc: u32,
    table: &[u8; 24],
    mac: u32,
) -> bool {
    verify(readback_input(key, node, nonce, held_crc, table), mac)
}

fn trigger_input(key: &Key, command: TriggerCommand, counter: u32) -> Cmac<Aes128> {
    cmac(key, &[b"T", &[command as u8], &counter.to_le_bytes()])
}

/// The MAC of a [`Trigger`] with `command` and freshness `counter`.
pub fn trigger_mac(key: &Key, command: TriggerCommand, counter: u32) -> u32 {
    truncated(trigger_input(key, command, counter))
}

/// Whether `mac` is [`trigger_mac`] of these values (constant time).
pub fn verify_trigger(key: &Key, command: TriggerCommand, counter: u32, mac: u32) -> bool {
    verify(trigger_input(key, command, counter), mac)
}

/// The `Trigger` frame content for `command` with freshness `counter`, signed with `key`.
pub fn trigger(key: &Key, command: TriggerCommand, counter: u32) -> Trigger {
    Trigger {
        command,
        counter_lo: counter as u16,
        mac: trigger_mac(key, command, counter),
    }
}

/// A nonce for `node`'s Begin or readback in `session` at time `now_us`, from the caller's
/// `seed` (drawn from the OS random source: the clock alone repeats across boots of a controller
/// without a real-time clock): a MAC, so nobody without the key can predict it and ask the node
/// for the answer beforehand.
pub fn nonce(key: &Key, node: NodeId, session: u8, seed: u64, now_us: u64) -> u32 {
    truncated(cmac(
        key,
        &[
            b"N",
            &[node.raw(), session],
            &seed.to_le_bytes(),
            &now_us.to_le_bytes(),
        ],
    ))
}

/// The full counter meant by low bits `lo`, given the receiver's `stored` one: the smallest
/// value above `stored` whose low 16 bits are `lo`; `None` past `u32::MAX`.
pub fn next_counter(stored: u32, lo: u16) -> Option<u32> {
    let candidate = (stored & !0xFFFF) | u32::from(lo);
    if candidate > stored {
        Some(candidate)
    } else {
        candidate.checked_add(0x1_0000)
    }
}

/// The latest counter at or below `stored` with low bits `lo`: what a replayed or stale frame
/// was made for (to tell a stale counter from a forged MAC).
pub fn previous_counter(stored: u32, lo: u16) -> Option<u32> {
    let candidate = (stored & !0xFFFF) | u32::from(lo);
    if candidate <= stored {
        Some(candidate)
    } else {
        candidate.checked_sub(0x1_0000)
    }
}

/// Why a key file could not be read.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct KeyFileError {
    /// 1-based line.
    pub line: usize,
    /// What is wrong with it (never its text: it may hold a key).
    pub what: &'static str,
}

impl core::fmt::Display for KeyFileError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        write!(f, "line {}: {}", self.line, self.what)
    }
}

#[cfg(feature = "std")]
impl std::error::Error for KeyFileError {}

/// The keys of a suit: one per joint node, and the trigger key.
///
/// Key file (the `exocal-keys` credential): one `NAME HEX` pair per line, NAME a DBC node name
/// (`Joint1` … `Joint7`) or `Trigger`, HEX 32 hexadecimal digits; blank lines and lines
/// starting with `#` are ignored. Every key must be its own: an all-zero key and a key given
/// for two names are refused (one stolen node would give away the other; zeros are a
/// placeholder left in a template). Errors name the line, never its content.
#[derive(Clone, Default, PartialEq, Eq)]
pub struct KeySet {
    nodes: [Option<Key>; 8],
    trigger: Option<Key>,
}

impl core::fmt::Debug for KeySet {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        let mut list = f.debug_list();
        for node in NodeId::ALL {
            if self.node(node).is_some() {
                list.entry(&node.name());
            }
        }
        if self.trigger.is_some() {
            list.entry(&"Trigger");
        }
        list.finish()
    }
}

impl KeySet {
    /// Parses a key file (see the type's docs).
    pub fn parse(text: &str) -> Result<KeySet, KeyFileError> {
        let mut keys = KeySet::default();
        for (i, line) in text.lines().enumerate() {
            let err = |what| KeyFileError { line: i + 1, what };
            let line = line.trim();
            if line.is_empty() || line.starts_with('#') {
                continue;
            }
            let mut words = line.split_whitespace();
            let (Some(name), Some(hex), None) = (words.next(), words.next(), words.next()) else {
                return Err(err("expected `NAME HEX` (e.g. `Joint1` and 32 hex digits)"));
            };
            let key = Key::from_hex(hex).ok_or(err("the key is not 32 hexadecimal digits"))?;
            let slot = if name == "Trigger" {
                None
            } else {
                let node = NodeId::ALL
                    .into_iter()
                    .find(|n| n.name() == name)
                    .ok_or(err(
                        "unknown name: expected Joint1 … Joint7, EndEffector or Trigger",
                    ))?;
                Some(usize::from(node.raw() - 1))
            };
            let held = match slot {
                None => &keys.trigger,
                Some(i) => &keys.nodes[i],
            };
            if held.is_some() {
                return Err(err("this name has a key on an earlier line"));
            }
            if let Some(why) = key.weakness() {
                return Err(err(why));
            }
            let nearest = keys
                .nodes
                .iter()
                .chain([&keys.trigger])
                .flatten()
                .map(|k| k.digits_apart(&key))
                .min();
            match nearest {
                Some(0) => return Err(err(
                    "the same key as an earlier line: every node and the trigger need their own",
                )),
                Some(d) if d < MIN_DIGITS_APART => {
                    return Err(err(
                        "nearly the same key as an earlier line (a few hex digits apart): every \
                         node and the trigger need their own random key",
                    ))
                }
                _ => {}
            }
            match slot {
                None => keys.trigger = Some(key),
                Some(i) => keys.nodes[i] = Some(key),
            }
        }
        Ok(keys)
    }

    /// Keys derived from `seed` (per node and for the trigger, [`Key::derive`]): for the demo
    /// and tests only; anyone who knows the seed knows them.
    pub fn derived(seed: u64) -> KeySet {
        let mut master = [0u8; KEY_LEN];
        master[..8].copy_from_slice(&seed.to_le_bytes());
        master[8..].copy_from_slice(b"exocal-d");
        let master = Key(master);
        let mut keys = KeySet::default();
        for node in NodeId::ALL {
            keys.nodes[usize::from(node.raw() - 1)] = Some(master.derive(&[node.raw()]));
        }
        keys.trigger = Some(master.derive(b"Trigger"));
        keys
    }

    /// The key of `node`, if the set has one.
    pub fn node(&self, node: NodeId) -> Option<&Key> {
        self.nodes[usize::from(node.raw() - 1)].as_ref()
    }

    /// Sets (or removes) the key of `node`.
    pub fn set_node(&mut self, node: NodeId, key: Option<Key>) {
        self.nodes[usize::from(node.raw() - 1)] = key;
    }

    /// The trigger key, if the set has one.
    pub fn trigger(&self) -> Option<&Key> {
        self.trigger.as_ref()
    }

    /// Sets (or removes) the trigger key.
    pub fn set_trigger(&mut self, key: Option<Key>) {
        self.trigger = key;
    }

    /// Whether the set holds no key at all.
    pub fn is_empty(&self) -> bool {
        self.trigger.is_none() && self.nodes.iter().all(Option::is_none)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// RFC 4493, section 4: AES-128 key 2b7e1516…, the CMAC of the empty message and of 16
    /// bytes: the crates compute AES-CMAC, truncated as we say.
    #[test]
    fn cmac_matches_rfc_4493() {
        let key = Key::from_hex("2b7e151628aed2a6abf7158809cf4f3c").unwrap();
        assert_eq!(truncated(cmac(&key, &[])), 0xbb1d_6929);
        let m = [
            0x6b, 0xc1, 0xbe, 0xe2, 0x2e, 0x40, 0x9f, 0x96, 0xe9, 0x3d, 0x7e, 0x11, 0x73, 0x93,
            0x17, 0x2a,
        ];
        assert_eq!(truncated(cmac(&key, &[&m])), 0x070a_16b4);
        assert!(verify(cmac(&key, &[&m]), 0x070a_16b4));
        assert!(!verify(cmac(&key, &[&m]), 0x070a_16b5));
    }

    fn table() -> Table {
        Table::from_si(0.431, 1.2345678, 0.0, 0.01, 1.0, 1.0).unwrap()
    }

    #[test]
    fn every_field_is_covered_and_kinds_do_not_mix() {
        let k = KeySet::derived(1);
        let key = k.node(NodeId::JOINTS[0]).unwrap();
        let other = k.node(NodeId::JOINTS[1]).unwrap();
        let (n, t) = (NodeId::JOINTS[0], table());
        let mac = commit_mac(key, n, 5, 100, &t);
        assert!(verify_commit(key, n, 5, 100, &t, mac));
        let moved = Table::from_raw({
            let mut r = t.raw_values();
            r[3] += 1;
            r
        })
        .unwrap();
        for bad in [
            verify_commit(other, n, 5, 100, &t, mac),
            verify_commit(key, NodeId::JOINTS[1], 5, 100, &t, mac),
            verify_commit(key, n, 6, 100, &t, mac),
            verify_commit(key, n, 5, 101, &t, mac),
            verify_commit(key, n, 5, 100, &moved, mac),
            verify_commit(key, n, 5, 100, &t, mac ^ 1),
        ] {
            assert!(!bad);
        }
        let fm = freshness_mac(key, n, 5, 0xabcd, 100, t.crc());
        assert!(verify_freshness(key, n, 5, 0xabcd, 100, t.crc(), fm));
        for bad in [
            verify_freshness(other, n, 5, 0xabcd, 100, t.crc(), fm),
            verify_freshness(key, NodeId::JOINTS[1], 5, 0xabcd, 100, t.crc(), fm),
            verify_freshness(key, n, 6, 0xabcd, 100, t.crc(), fm),
            verify_freshness(key, n, 5, 0xabce, 100, t.crc(), fm),
            verify_freshness(key, n, 5, 0xabcd, 60_100, t.crc(), fm),
            verify_freshness(key, n, 5, 0xabcd, 100, t.crc() ^ 1, fm),
        ] {
            assert!(!bad);
        }
        assert_ne!(key.id(), other.id());
        let rb = readback_mac(key, n, 77, t.crc(), &t.to_bytes());
        assert!(verify_readback(key, n, 77, t.crc(), &t.to_bytes(), rb));
        assert!(!verify_readback(key, n, 78, t.crc(), &t.to_bytes(), rb));
        assert!(!verify_readback(key, n, 77, t.crc() ^ 1, &t.to_bytes(), rb));
        assert_ne!(rb, mac);
        let tr = trigger(key, TriggerCommand::StartCalibration, 0x1_0203);
        assert_eq!(tr.counter_lo, 0x0203);
        assert!(verify_trigger(
            key,
            TriggerCommand::StartCalibration,
            0x1_0203,
            tr.mac
        ));
        assert!(!verify_trigger(
            key,
            TriggerCommand::Abort,
            0x1_0203,
            tr.mac
        ));
        assert_ne!(nonce(key, n, 1, 0, 10), nonce(key, n, 1, 0, 11));
        assert_ne!(
            nonce(key, n, 1, 5, 10),
            nonce(key, n, 1, 6, 10),
            "the seed counts"
        );
    }

    #[test]
    fn counters_come_back_from_their_low_bits() {
        assert_eq!(next_counter(0, 1), Some(1));
        assert_eq!(next_counter(0, 0), Some(0x1_0000));
        assert_eq!(next_counter(0x1_fffe, 0xffff), Some(0x1_ffff));
        assert_eq!(next_counter(0x1_ffff, 0), Some(0x2_0000));
        assert_eq!(next_counter(0x1_0005, 3), Some(0x2_0003));
        assert_eq!(next_counter(u32::MAX - 1, 0xffff), Some(u32::MAX));
        assert_eq!(next_counter(u32::MAX, 0xffff), None);
        assert_eq!(previous_counter(0x1_0005, 3), Some(0x1_0003));
        assert_eq!(previous_counter(0x1_0005, 5), Some(0x1_0005));
        assert_eq!(previous_counter(0x1_0005, 6), Some(0x6));
        assert_eq!(previous_counter(5, 6), None);
        for stored in [0u32, 1, 0xffff, 0x1_0000, 0x2_3456] {
            for step in [1u32, 2, 0x7fff, 0xffff] {
                let next = stored + step;
                assert_eq!(next_counter(stored, next as u16), Some(next));
                assert_eq!(previous_counter(next, stored as u16), Some(stored));
            }
        }
    }

    #[test]
    fn key_files_parse_and_errors_name_the_line_not_the_key() {
        let text = "# suit 42\n\nJoint1 3babf2654c93cdfe26a520652b3b5198\n  Trigger 1D3CD88FF38903ABB8F0CA36D13DBFB1  \n";
        let k = KeySet::parse(text).unwrap();
        assert_eq!(k.node(NodeId::JOINTS[0]).unwrap().bytes()[15], 0x98);
        assert_eq!(k.trigger().unwrap().bytes()[0], 0x1d);
        assert!(k.node(NodeId::JOINTS[1]).is_none());
        assert_eq!(format!("{k:?}"), r#"["Joint1", "Trigger"]"#);
        assert_eq!(format!("{:?}", k.trigger().unwrap()), "Key(..)");
        for (bad, line) in [
            ("Joint1 0001", 1),
            ("\nJoint9 3babf2654c93cdfe26a520652b3b5198", 2),
            ("Joint1 3babf2654c93cdfe26a520652b3b519g", 1),
            ("Joint1", 1),
            ("Joint1 00 11", 1),
            (
                "Joint1 3babf2654c93cdfe26a520652b3b5198\nJoint1 3babf2654c93cdfe26a520652b3b5198",
                2,
            ),
            // An all-zero key, and one key for two names (a node and the trigger).
            ("Joint2 00000000000000000000000000000000", 1),
            // Keys that are not random, and one edited from another.
            ("Joint2 abababababababab0101010101010101", 1),
            ("Joint2 000102030405060708090a0b0c0d0e0f", 1),
            ("Joint2 f0e0d0c0b0a090807060504030201000", 1),
            (
                "Joint1 3babf2654c93cdfe26a520652b3b5198\nJoint2 3babf2654c93cdfe26a520652b3b5199",
                2,
            ),
            (
                "Joint1 3babf2654c93cdfe26a520652b3b5198\nTrigger 3babf2654c93cdfe26a5206aab3b5198",
                2,
            ),
            (
                "Joint1 3babf2654c93cdfe26a520652b3b5198\n# x\nJoint2 3BABF2654C93CDFE26A520652B3B5198",
                3,
            ),
            (
                "Trigger 3babf2654c93cdfe26a520652b3b5198\nJoint7 3babf2654c93cdfe26a520652b3b5198",
                2,
            ),
        ] {
            let e = KeySet::parse(bad).unwrap_err();
            assert_eq!(e.line, line, "{bad}: {e}");
            assert!(!e.to_string().to_lowercase().contains("3babf2"), "{e}");
        }
        let d = KeySet::derived(2024);
        assert_eq!(d, KeySet::derived(2024));
        assert_ne!(d, KeySet::derived(2025));
        assert_ne!(d.node(NodeId::JOINTS[0]), d.node(NodeId::JOINTS[1]));
        assert!(!d.is_empty() && KeySet::default().is_empty());
    }

    /// A key is zeroised when dropped (and on demand): the type says so, and zeroising works.
    #[test]
    fn keys_are_zeroised() {
        fn zeroised_on_drop<T: ZeroizeOnDrop>() {}
        zeroised_on_drop::<Key>();
        let mut k = Key::from_hex("ffeeddccbbaa99887766554433221100").unwrap();
        assert!(!k.is_zero());
        k.zeroize();
        assert!(k.is_zero());
        assert_eq!(k.bytes(), &[0u8; KEY_LEN]);
    }
}
