//! Authenticated sensor streams: each node signs the data frames it streams with a digest frame
//! every [`DIGEST_PERIOD_US`], and the controller takes a node's frames only once the digest
//! that covers them verifies.
//!
//! Contract:
//! - the stream key is [`stream_key`]: the node's table key derived with the label `stream`
//!   ([`Key::derive`]), so a stream MAC never verifies as a transfer MAC and the reverse;
//! - the controller gives each node the collection's nonce in a `StreamNonce_<node>` frame signed
//!   for it ([`sign_nonce`]: the first 32 bits of AES-128-CMAC under the node's stream key over
//!   `N`, the node id and the nonce, u32 LE). A node takes a nonce only if that MAC verifies and
//!   the nonce is above the last it took since boot ([`Signer::set_nonce`], [`NonceReject`]): a
//!   forged nonce, one for another node, or a replayed one changes nothing. The controller
//!   makes every nonce above all it sent before (a counter it persists), so its own next nonce
//!   always wins over a replay, also after a node reboots;
//! - a digest's MAC is the first 40 bits (big-endian) of AES-128-CMAC under the stream key over
//!   `S`, the node id, the collection's nonce (u64 LE), then for each covered
//!   frame its identifier (u16 LE), its length and its data zero-padded to 8 bytes, then the
//!   digest's full sequence number (u32 LE) and the number of frames covered (u8);
//! - the data frames are those of [`covered`] families (JointState, EePose, the IMU families)
//!   whose identifier carries the node's id; heartbeats and transfer replies are not covered;
//! - a node's sequence restarts at 0 under each new nonce; the [`Verifier`] accepts only
//!   sequence numbers above the last one that verified (a replayed or old digest is
//!   [`Reject::Stale`]); a gap (lost digests) is allowed, but the span it closes then fails on
//!   its count; only a verified digest moves the sequence on, so a forged one cannot lock a
//!   node out;
//! - a digest covers at most [`MAX_COVERED`] frames: the [`Signer`] closes a span early
//!   when it is full;
//! - no clock is read: time is an argument; no allocation (the frames a verifier checks are
//!   passed in by the caller, who holds them).

use aes::Aes128;
use cmac::{Cmac, Mac};

use crate::auth::{self, Key};
use crate::message::{StreamDigest, StreamNonce};
use crate::spec::Kind;
use crate::NodeId;

/// Period of a node's digests, µs (10 Hz).
pub const DIGEST_PERIOD_US: u64 = 100_000;
/// Most frames one digest covers (its `Count` is 8 bits).
pub const MAX_COVERED: u8 = u8::MAX;
/// Width of the truncated MAC, bits.
pub const MAC_BITS: u32 = 40;

/// The stream key of a node whose table key is `table_key` (separate key usage).
pub fn stream_key(table_key: &Key) -> Key {
    table_key.derive(b"stream")
}

/// The `StreamNonce_<node>` frame giving `node`, whose stream key is `key` ([`stream_key`]), the
/// collection's `nonce` (the controller side).
pub fn sign_nonce(key: &Key, node: NodeId, nonce: u32) -> StreamNonce {
    StreamNonce {
        node,
        nonce,
        mac: auth::truncated(nonce_mac(key, node, nonce)),
    }
}

fn nonce_mac(key: &Key, node: NodeId, nonce: u32) -> Cmac<Aes128> {
    auth::cmac(key, &[b"N", &[node.raw()], &nonce.to_le_bytes()])
}

/// Why a node did not take a `StreamNonce` (it keeps the nonce it has).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum NonceReject {
    /// Addressed to another node.
    OtherNode,
    /// The MAC does not verify: forged, or made with another key.
    BadMac,
    /// Signed, but not above the nonce the node took last: a replay.
    Stale {
        /// The node's nonce.
        held: u32,
    },
}

impl core::fmt::Display for NonceReject {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match *self {
            NonceReject::OtherNode => f.write_str("a nonce for another node"),
            NonceReject::BadMac => f.write_str("the nonce's MAC does not verify"),
            NonceReject::Stale { held } => {
                write!(f, "a replayed nonce (not above the node's {held})")
            }
        }
    }
}

/// Whether frames of this family are covered by the sending node's digests.
pub fn covered(kind: Kind) -> bool {
    matches!(
        kind,
        Kind::JointState | Kind::EePose | Kind::ImuGyro | Kind::ImuAccel | Kind::ImuMag
    )
}

/// The running CMAC of one span: opened with the node and nonce, fed frame by frame, closed
/// with the sequence number and count.
#[derive(Clone)]
struct Span {
    mac: Cmac<Aes128>,
    count: u32,
}

impl Span {
    fn open(key: &Key, node: NodeId, nonce: u64) -> Span {
        let mut mac =
            <Cmac<Aes128> as Mac>::new_from_slice(key.bytes()).expect("a 16-byte key fits AES-128");
        mac.update(b"S");
        mac.update(&[node.raw()]);
        mac.update(&nonce.to_le_bytes());
        Span { mac, count: 0 }
    }

    fn add(&mut self, id: u16, data: &[u8]) {
        let mut padded = [0u8; 8];
        let len = data.len().min(8);
        padded[..len].copy_from_slice(&data[..len]);
        self.mac.update(&id.to_le_bytes());
        self.mac.update(&[len as u8]);
        self.mac.update(&padded);
        self.count += 1;
    }

    fn close(mut self, seq: u32, count: u8) -> Cmac<Aes128> {
        self.mac.update(&seq.to_le_bytes());
        self.mac.update(&[count]);
        self.mac
    }
}

fn tag40(mac: Cmac<Aes128>) -> u64 {
    let t = mac.finalize().into_bytes();
    u64::from_be_bytes([0, 0, 0, t[0], t[1], t[2], t[3], t[4]])
}

fn verify40(mac: Cmac<Aes128>, got: u64) -> bool {
    got < 1 << MAC_BITS && mac.verify_truncated_left(&got.to_be_bytes()[3..]).is_ok()
}

/// The node side: signs what the node streams.
#[derive(Clone)]
pub struct Signer {
    key: Key,
    node: NodeId,
    nonce: u32,
    seq: u32,
    span: Span,
    opened_us: u64,
}

impl Signer {
    /// A node's signer with its stream key ([`stream_key`]), before any nonce (nonce 0: its
    /// digests verify nowhere until the controller's `StreamNonce` arrives).
    pub fn new(node: NodeId, key: Key, now_us: u64) -> Signer {
        Signer {
            span: Span::open(&key, node, 0),
            key,
            node,
            nonce: 0,
            seq: 0,
            opened_us: now_us,
        }
    }

    /// The controller's `StreamNonce` for this node: taken only if its MAC verifies and it is
    /// above the nonce held (then the stream restarts: sequence 0, the open span dropped);
    /// otherwise nothing changes.
    pub fn set_nonce(&mut self, nonce: StreamNonce, now_us: u64) -> Result<(), NonceReject> {
        if nonce.node != self.node {
            return Err(NonceReject::OtherNode);
        }
        if !auth::verify(nonce_mac(&self.key, self.node, nonce.nonce), nonce.mac) {
            return Err(NonceReject::BadMac);
        }
        if nonce.nonce <= self.nonce {
            return Err(NonceReject::Stale { held: self.nonce });
        }
        self.nonce = nonce.nonce;
        self.seq = 0;
        self.span = Span::open(&self.key, self.node, u64::from(self.nonce));
        self.opened_us = now_us;
        Ok(())
    }

    /// The nonce the node holds (0 until it took one).
    pub fn nonce(&self) -> u32 {
        self.nonce
    }

    /// Adds a data frame the node sends (call it for [`covered`] frames only). Returns the
    /// digest to send right after it when the span is full.
    pub fn add(&mut self, id: u16, data: &[u8], now_us: u64) -> Option<StreamDigest> {
        self.span.add(id, data);
        (self.span.count >= u32::from(MAX_COVERED)).then(|| self.digest(now_us))
    }

    /// Whether a digest is due at `now_us` (a period since the span opened, and frames in it).
    pub fn due(&self, now_us: u64) -> bool {
        self.span.count > 0 && now_us.saturating_sub(self.opened_us) >= DIGEST_PERIOD_US
    }

    /// Closes the open span: its digest, and a new span opens.
    pub fn digest(&mut self, now_us: u64) -> StreamDigest {
        let count = self.span.count.min(u32::from(MAX_COVERED)) as u8;
        let span = core::mem::replace(
            &mut self.span,
            Span::open(&self.key, self.node, u64::from(self.nonce)),
        );
        let mac = tag40(span.close(self.seq, count));
        let d = StreamDigest {
            node: self.node,
            seq_lo: self.seq as u16,
            count,
            mac,
        };
        self.seq = self.seq.wrapping_add(1);
        self.opened_us = now_us;
        d
    }
}

/// Why a span did not verify.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Reject {
    /// More frames arrived on the node's identifiers than its digest covers: a second sender
    /// (or duplicates on the wire).
    Surplus {
        /// Frames received.
        received: u32,
        /// Frames the digest covers.
        covered: u8,
    },
    /// Fewer frames arrived than the digest covers (lost frames or digests).
    Deficit {
        /// Frames received.
        received: u32,
        /// Frames the digest covers.
        covered: u8,
    },
    /// The count matches, the MAC does not (a forged or altered frame, or another nonce).
    BadMac,
    /// The digest's sequence number is not above the last one seen (a replayed digest); the
    /// held frames stay held.
    Stale,
}

impl core::fmt::Display for Reject {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match *self {
            Reject::Surplus { received, covered } => write!(
                f,
                "{received} frames for a digest covering {covered}: a second sender"
            ),
            Reject::Deficit { received, covered } => {
                write!(
                    f,
                    "{received} frames for a digest covering {covered}: frames lost"
                )
            }
            Reject::BadMac => f.write_str("the digest's MAC does not verify"),
            Reject::Stale => f.write_str("a replayed or old digest sequence number"),
        }
    }
}

/// The controller side for one node: checks a digest against the frames held since the last.
#[derive(Clone, Debug)]
pub struct Verifier {
    key: Key,
    node: NodeId,
    nonce: u32,
    /// The lowest sequence number still acceptable.
    next_seq: u32,
}

impl Verifier {
    /// The verifier of `node`'s stream under `key` ([`stream_key`]) for the collection with
    /// `nonce`.
    pub fn new(node: NodeId, key: Key, nonce: u32) -> Verifier {
        Verifier {
            key,
            node,
            nonce,
            next_seq: 0,
        }
    }

    /// The node this verifier checks.
    pub fn node(&self) -> NodeId {
        self.node
    }

    /// The controller sent the collection a new nonce (a node rebooted and lost the old one):
    /// every node restarts its sequence under it, and so does the verifier. Spans signed under
    /// the old nonce no longer verify.
    pub fn restart(&mut self, nonce: u32) {
        self.nonce = nonce;
        self.next_seq = 0;
    }

    /// Checks `digest` against the frames (identifier, data) held since the previous digest,
    /// in their order of arrival. `Ok` when they are exactly what the node signed; on any
    /// `Err` but [`Reject::Stale`] the caller drops the held frames (and on `Stale` keeps
    /// them for the genuine digest).
    pub fn check<'a>(
        &mut self,
        digest: &StreamDigest,
        frames: impl IntoIterator<Item = (u16, &'a [u8])>,
    ) -> Result<(), Reject> {
        let seq = (self.next_seq & !0xFFFF) | u32::from(digest.seq_lo);
        let seq = if seq >= self.next_seq {
            seq
        } else {
            seq.checked_add(0x1_0000).ok_or(Reject::Stale)?
        };
        // A sequence number far ahead is a digest from before a restart or a replay of one.
        if seq - self.next_seq > 0x8000 {
            return Err(Reject::Stale);
        }
        let mut span = Span::open(&self.key, self.node, u64::from(self.nonce));
        for (id, data) in frames {
            span.add(id, data);
        }
        let received = span.count;
        let mac = span.close(seq, digest.count);
        // Only a verified digest moves the sequence on: a forged one cannot lock the node out.
        match received.cmp(&u32::from(digest.count)) {
            core::cmp::Ordering::Greater => Err(Reject::Surplus {
                received,
                covered: digest.count,
            }),
            core::cmp::Ordering::Less => Err(Reject::Deficit {
                received,
                covered: digest.count,
            }),
            core::cmp::Ordering::Equal if !verify40(mac, digest.mac) => Err(Reject::BadMac),
            core::cmp::Ordering::Equal => {
                self.next_seq = seq.wrapping_add(1);
                Ok(())
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const NODE: NodeId = NodeId::END_EFFECTOR;

    fn key() -> Key {
        stream_key(&Key::new([7; 16]))
    }

    fn frames(n: u8, salt: u8) -> std::vec::Vec<(u16, [u8; 8])> {
        (0..n)
            .map(|i| (0x148, [i, salt, 1, 2, 3, 4, 5, 6]))
            .collect()
    }

    /// Signs `frames` as one span under `nonce`; returns the digest.
    fn sign(s: &mut Signer, frames: &[(u16, [u8; 8])]) -> StreamDigest {
        for (id, d) in frames {
            assert!(s.add(*id, d, 0).is_none());
        }
        s.digest(0)
    }

    fn refs(f: &[(u16, [u8; 8])]) -> impl Iterator<Item = (u16, &[u8])> {
        f.iter().map(|(id, d)| (*id, &d[..]))
    }

    fn pair(nonce: u32) -> (Signer, Verifier) {
        let mut s = Signer::new(NODE, key(), 0);
        s.set_nonce(sign_nonce(&key(), NODE, nonce), 0).unwrap();
        (s, Verifier::new(NODE, key(), nonce))
    }

    #[test]
    fn good_spans_verify_in_sequence() {
        let (mut s, mut v) = pair(42);
        for k in 0..5 {
            let f = frames(40, k);
            let d = sign(&mut s, &f);
            assert_eq!(d.seq_lo, u16::from(k));
            assert_eq!(d.count, 40);
            assert!(d.mac < 1 << MAC_BITS);
            assert_eq!(v.check(&d, refs(&f)), Ok(()));
        }
    }

    #[test]
    fn a_forged_frame_fails_the_mac() {
        let (mut s, mut v) = pair(42);
        let mut f = frames(10, 0);
        let d = sign(&mut s, &f);
        f[3].1[2] ^= 0x10; // a biased value in place of the node's
        assert_eq!(v.check(&d, refs(&f)), Err(Reject::BadMac));
    }

    #[test]
    fn an_injected_extra_frame_is_a_surplus() {
        let (mut s, mut v) = pair(42);
        let mut f = frames(10, 0);
        let d = sign(&mut s, &f);
        f.insert(4, (0x148, [9; 8]));
        assert_eq!(
            v.check(&d, refs(&f)),
            Err(Reject::Surplus {
                received: 11,
                covered: 10
            })
        );
        // The stream goes on: the next genuine span verifies.
        let f = frames(10, 1);
        let d = sign(&mut s, &f);
        assert_eq!(v.check(&d, refs(&f)), Ok(()));
    }

    #[test]
    fn a_dropped_frame_is_a_deficit() {
        let (mut s, mut v) = pair(42);
        let mut f = frames(10, 0);
        let d = sign(&mut s, &f);
        f.remove(0);
        assert_eq!(
            v.check(&d, refs(&f)),
            Err(Reject::Deficit {
                received: 9,
                covered: 10
            })
        );
    }

    #[test]
    fn a_span_recorded_under_another_nonce_does_not_verify() {
        let (mut s, _) = pair(1);
        let f = frames(10, 0);
        let d = sign(&mut s, &f);
        let (_, mut other) = pair(2);
        assert_eq!(other.check(&d, refs(&f)), Err(Reject::BadMac));
    }

    #[test]
    fn a_replayed_old_sequence_is_stale_and_leaves_the_stream_intact() {
        let (mut s, mut v) = pair(42);
        let old = frames(10, 0);
        let old_digest = sign(&mut s, &old);
        assert_eq!(v.check(&old_digest, refs(&old)), Ok(()));
        assert_eq!(v.check(&old_digest, refs(&old)), Err(Reject::Stale));
        let f = frames(10, 1);
        let d = sign(&mut s, &f);
        assert_eq!(v.check(&d, refs(&f)), Ok(()));
    }

    #[test]
    fn a_forged_digest_does_not_lock_the_node_out() {
        let (mut s, mut v) = pair(42);
        let f = frames(10, 0);
        let forged = StreamDigest {
            node: NODE,
            seq_lo: 0x7000,
            count: 10,
            mac: 0x12_3456_789A,
        };
        assert_eq!(v.check(&forged, refs(&f)), Err(Reject::BadMac));
        let d = sign(&mut s, &f);
        assert_eq!(v.check(&d, refs(&f)), Ok(()));
    }

    #[test]
    fn a_lost_digest_fails_the_span_it_merges_into_then_the_stream_resumes() {
        let (mut s, mut v) = pair(42);
        let a = frames(10, 0);
        let _lost = sign(&mut s, &a);
        let b = frames(10, 1);
        let d = sign(&mut s, &b);
        let held: std::vec::Vec<_> = a.iter().chain(&b).copied().collect();
        assert_eq!(
            v.check(&d, refs(&held)),
            Err(Reject::Surplus {
                received: 20,
                covered: 10
            })
        );
        let c = frames(10, 2);
        let d = sign(&mut s, &c);
        assert_eq!(v.check(&d, refs(&c)), Ok(()));
    }

    #[test]
    fn the_signer_closes_a_full_span_and_is_due_each_period() {
        let mut s = Signer::new(NODE, key(), 0);
        assert!(!s.due(DIGEST_PERIOD_US)); // nothing to cover
        for i in 0..u32::from(MAX_COVERED) - 1 {
            assert!(s.add(0x148, &[0; 8], u64::from(i)).is_none());
        }
        assert!(!s.due(DIGEST_PERIOD_US - 1));
        assert!(s.due(DIGEST_PERIOD_US));
        let d = s.add(0x148, &[0; 8], 10).expect("full");
        assert_eq!(d.count, MAX_COVERED);
        assert!(!s.due(10 + DIGEST_PERIOD_US));
    }

    #[test]
    fn stream_keys_differ_from_table_keys() {
        let table = Key::new([7; 16]);
        assert_ne!(stream_key(&table), table);
    }

    /// A node takes only a signed nonce, for itself, above the one it holds.
    #[test]
    fn a_node_ignores_a_spoofed_nonce_and_a_replayed_one() {
        let (mut s, mut v) = pair(42);
        let before = sign(&mut s, &frames(3, 0));
        assert_eq!(v.check(&before, refs(&frames(3, 0))), Ok(()));
        let forged = StreamNonce {
            node: NODE,
            nonce: 666,
            mac: 0xDEAD_BEEF,
        };
        assert_eq!(s.set_nonce(forged, 0), Err(NonceReject::BadMac));
        let other_key = sign_nonce(&stream_key(&Key::new([8; 16])), NODE, 666);
        assert_eq!(s.set_nonce(other_key, 0), Err(NonceReject::BadMac));
        let for_another = sign_nonce(&key(), NodeId::JOINTS[0], 666);
        assert_eq!(s.set_nonce(for_another, 0), Err(NonceReject::OtherNode));
        let retargeted = StreamNonce {
            node: NODE,
            ..for_another
        };
        assert_eq!(s.set_nonce(retargeted, 0), Err(NonceReject::BadMac));
        for old in [41, 42] {
            assert_eq!(
                s.set_nonce(sign_nonce(&key(), NODE, old), 0),
                Err(NonceReject::Stale { held: 42 })
            );
        }
        // None of them moved the stream: its next span verifies under 42.
        assert_eq!(s.nonce(), 42);
        let f = frames(3, 1);
        let d = sign(&mut s, &f);
        assert_eq!(d.seq_lo, 1);
        assert_eq!(v.check(&d, refs(&f)), Ok(()));
        // The controller's next nonce is taken.
        assert_eq!(s.set_nonce(sign_nonce(&key(), NODE, 43), 0), Ok(()));
        assert_eq!(sign(&mut s, &f).seq_lo, 0);
    }

    #[test]
    fn only_data_families_are_covered() {
        assert!(covered(Kind::JointState) && covered(Kind::EePose) && covered(Kind::ImuMag));
        assert!(!covered(Kind::Heartbeat) && !covered(Kind::TableReply));
        assert!(!covered(Kind::StreamDigest) && !covered(Kind::Trigger));
    }
}
