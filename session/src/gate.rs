//! The stream gate: a node's data frames reach ingest only once the digest that covers them
//! verifies ([`exocal_dbc::stream_auth`]).
//!
//! Contract:
//! - [`StreamGate::on_frame`] takes every received frame in arrival order and hands on, in
//!   order, the frames ingest may take now: frames the digests do not cover (heartbeats,
//!   transfer replies, digests, unknown identifiers) at once; a node's data frames when its
//!   digest covering them verifies, all of them together;
//! - a span that does not verify — bad MAC, a count mismatch, a node without a key, more
//!   frames held than one digest covers ([`MAX_COVERED`]: no digest came) — is dropped and
//!   counted in [`GateStats`] (spans, frames, seconds of the node's stream); a surplus of frames
//!   over a digest's count is counted as a second sender on that node's identifiers, unless the
//!   digest's sequence number shows digests lost before it (then the surplus is their frames:
//!   counted as frames without a digest). Nothing is timed on the receive clock: frames arrive
//!   in the order they were sent, so a receiver that stalls delays a span and its digest alike;
//! - the start: until a node's first span verifies, and for at most [`START_GRACE`] after the
//!   gate's first frame, what the gate drops of it is counted apart
//!   ([`GateStats::start_frames`]), neither loss nor a second sender: frames the node sent
//!   before the collection's nonce reached it (signed under its previous nonce, or in flight
//!   when the nonce went out) are not attacks. They are dropped all the same;
//! - a node whose heartbeat shows a new boot count lost the nonce with its RAM (and restarts
//!   its sequence): the gate drops every node's held frames, [`StreamGate::nonce_wanted`] says
//!   so once, and the caller sends every node a new nonce and gives it to
//!   [`StreamGate::renonce`] (a new nonce, so that the spans of this collection cannot be
//!   replayed into its second part). Those drops count as loss, not start frames: a heartbeat
//!   is not authenticated, and a spoofed one must not hide which spans an injection spoiled
//!   (a real reboot costs a second or two of stream, within [`MAX_DROPPED_FRACTION`]);
//! - a `StreamNonce` frame on the bus is never this controller's (a socket does not receive
//!   its own frames): forged, or a replay of one of ours. A node takes only a nonce signed for
//!   it and above the one it holds ([`exocal_dbc::stream_auth::Signer::set_nonce`]), which
//!   neither is, so the stream goes on; the gate counts it ([`GateStats::foreign_nonces`]) for
//!   the caller to name. Should a node take one all the same (its key known to the sender),
//!   its spans stop verifying: loss. At most [`MAX_RENONCES`] new nonces per collection
//!   ([`GateStats::renonces_capped`] past them): a flood of spoofed reboots then shows as loss;
//! - memory is bounded: at most [`MAX_COVERED`] frames held per node, at most
//!   [`MAX_REJECT_RUNS`] recorded verdicts;
//! - the gate is deterministic given the frames and each digest's verdict: it records the
//!   digests that did not verify ([`StreamGate::rejects`], runs per node, which the log keeps),
//!   and [`StreamGate::replaying`] re-applies them to the logged frames without keys, so an
//!   offline replay takes exactly the frames the live session took;
//! - time is the frames' receive time; no clock is read.

use std::collections::VecDeque;

use embedded_can::Frame as _;
use std::time::Duration;

use exocal_dbc::auth::KeySet;
use exocal_dbc::spec;
use exocal_dbc::stream_auth::{covered, stream_key, Reject, Verifier};
use exocal_dbc::{Message, NodeId, Received};
use serde::Serialize;

pub use exocal_dbc::stream_auth::MAX_COVERED;
/// How long after the gate's first frame a node's drops before its first verified span are
/// start drops ([`GateStats::start_frames`]): the nonce's way to the nodes and one digest
/// period, with room for a loaded controller.
pub const START_GRACE: Duration = Duration::from_secs(1);
/// Most dropped spans, as a fraction of all spans, a collection may have and still calibrate
/// ([`crate::Session::on_tick`], [`crate::Session::at_end`]). On a CAN bus frames are not lost
/// on the wire; a node's reboot costs its stream for a second or two (a few % of a 15-s
/// session); beyond this the receiver or the bus is failing, or someone is on it.
pub const MAX_DROPPED_FRACTION: f64 = 0.05;

/// Most new nonces a collection sends after its first ([`StreamGate::nonce_wanted`]): nodes
/// that reboot (or spoofed heartbeats saying so) beyond that are loss.
pub const MAX_RENONCES: u64 = 8;

/// Most runs of rejected digests recorded (a run: consecutive digests of one node).
pub const MAX_REJECT_RUNS: usize = 4096;

/// Consecutive digests of one node that did not verify: the `first`..`first + count` digests
/// (0-based, in arrival order) it sent in the collection.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct RejectRun {
    /// The node id.
    pub node: u8,
    /// Ordinal of the first digest.
    pub first: u64,
    /// Digests in the run.
    pub count: u64,
    /// Replayed (stale) digests, which leave the held frames held; else the frames were
    /// dropped.
    pub stale: bool,
}

impl RejectRun {
    /// Whether digest `ordinal` is in the run (`first + count` may pass `u64::MAX` in a
    /// damaged log: no overflow).
    pub fn covers(&self, ordinal: u64) -> bool {
        ordinal
            .checked_sub(self.first)
            .is_some_and(|k| k < self.count)
    }
}

/// What the gate passed and dropped.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct GateStats {
    /// Spans whose digest verified.
    pub verified_spans: u64,
    /// Frames those spans held.
    pub verified_frames: u64,
    /// Spans dropped (any reason).
    pub dropped_spans: u64,
    /// Frames those spans held.
    pub dropped_frames: u64,
    /// Seconds of stream those spans held (receive time, first to last frame, summed).
    pub dropped_s: f64,
    /// Dropped for a MAC that does not verify.
    pub bad_mac: u64,
    /// Dropped for fewer frames than the digest covers.
    pub deficit: u64,
    /// Dropped for no digest in time, a full buffer, or a node without a key.
    pub no_digest: u64,
    /// Digests ignored as replays (old sequence numbers).
    pub stale: u64,
    /// Frames dropped at the start (see the module docs): sent before the nonce reached the
    /// node. Not in `dropped_spans` or `dropped_frames`.
    pub start_frames: u64,
    /// Per node (index = node id), spans with more frames than the digest covers: a second
    /// sender on that node's identifiers.
    pub second_sender: [u64; 9],
    /// More rejected digests than [`MAX_REJECT_RUNS`] runs: the record is incomplete (an
    /// offline replay then differs, and `exocald offline` refuses the log).
    pub rejects_truncated: bool,
    /// Digests over no held frames that did not verify (forged, or a node without a key):
    /// they drop nothing, so they are counted, not recorded (live only; a replay skips them).
    pub empty_rejects: u64,
    /// `StreamNonce` frames received: sent by another sender on the bus (forged, or a second
    /// controller), never by this one.
    pub foreign_nonces: u64,
    /// Heartbeats that showed a node's new boot count (a reboot, or a spoofed heartbeat).
    pub reboots: u64,
    /// New nonces wanted after the first (at most [`MAX_RENONCES`]).
    pub renonces: u64,
    /// More were wanted than [`MAX_RENONCES`]: the rest were not sent.
    pub renonces_capped: bool,
}

impl GateStats {
    /// Whether the dropped spans exceed [`MAX_DROPPED_FRACTION`] of all spans.
    pub fn heavy_loss(&self) -> bool {
        let all = self.verified_spans + self.dropped_spans;
        self.dropped_spans as f64 > MAX_DROPPED_FRACTION * all as f64
    }

    /// The nodes on whose identifiers a second sender was seen, with the count of spans.
    pub fn second_senders(&self) -> impl Iterator<Item = (NodeId, u64)> + '_ {
        NodeId::ALL
            .into_iter()
            .map(|n| (n, self.second_sender[usize::from(n.raw())]))
            .filter(|&(_, c)| c > 0)
    }
}

/// Why a span was dropped (what [`StreamGate::on_frame`] reports per dropped span).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Dropped {
    /// The node whose identifiers the frames came on.
    pub node: NodeId,
    /// Frames dropped.
    pub frames: usize,
    /// The digest's verdict; `None` for no digest in time (or no key, or a full buffer).
    pub reject: Option<Reject>,
}

impl std::fmt::Display for Dropped {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{}: {} frames dropped unverified: ",
            self.node, self.frames
        )?;
        match self.reject {
            Some(Reject::Surplus { received, covered }) => write!(
                f,
                "a second sender on {}'s identifiers ({received} frames for a digest covering {covered})",
                self.node
            ),
            Some(r) => write!(f, "{r}"),
            None => f.write_str("no digest covered them"),
        }
    }
}

#[derive(Debug, Clone)]
struct NodeGate {
    verifier: Option<Verifier>,
    held: VecDeque<Received>,
    /// A digest of this node verified.
    verified: bool,
    /// The boot count of its last heartbeat.
    boot: Option<u8>,
    /// The sequence number (low 16 bits) of its last digest.
    last_seq: Option<u16>,
}

/// The gate of one collection (see the module docs).
#[derive(Debug, Clone)]
pub struct StreamGate {
    nodes: Vec<NodeGate>,
    stats: GateStats,
    /// Digests seen per node (index = node id − 1).
    ordinals: [u64; 8],
    /// The verdicts recorded so far (live), or to re-apply (replay).
    rejects: Vec<RejectRun>,
    replaying: bool,
    /// Receive time of the first frame.
    opened: Option<Duration>,
    /// A node rebooted since the nonce went out.
    nonce_wanted: bool,
    /// Receive time of the last frame.
    last: Option<Duration>,
}

impl StreamGate {
    /// The gate for the collection with `nonce`, verifying each node with its key in `keys`
    /// (a node without one has its data frames dropped).
    pub fn new(keys: &KeySet, nonce: u32) -> StreamGate {
        StreamGate {
            nodes: NodeId::ALL
                .into_iter()
                .map(|n| NodeGate {
                    verifier: keys.node(n).map(|k| Verifier::new(n, stream_key(k), nonce)),
                    held: VecDeque::new(),
                    verified: false,
                    boot: None,
                    last_seq: None,
                })
                .collect(),
            stats: GateStats::default(),
            ordinals: [0; 8],
            rejects: Vec::new(),
            replaying: false,
            opened: None,
            nonce_wanted: false,
            last: None,
        }
    }

    /// Whether a node rebooted (its heartbeat's boot count changed) since the last call: the
    /// caller sends every node a new nonce (at most [`MAX_RENONCES`] times per collection).
    pub fn nonce_wanted(&mut self) -> bool {
        std::mem::take(&mut self.nonce_wanted)
    }

    /// Wants a new nonce sent, within [`MAX_RENONCES`].
    fn want_nonce(&mut self) {
        if self.nonce_wanted {
            return;
        }
        if self.stats.renonces < MAX_RENONCES {
            self.stats.renonces += 1;
            self.nonce_wanted = true;
        } else {
            self.stats.renonces_capped = true;
        }
    }

    /// The caller sent every node the new `nonce` (see [`StreamGate::nonce_wanted`]): the
    /// verifiers restart under it, and the frames held until then, which no digest under it
    /// covers, are dropped (loss, once past the start).
    pub fn renonce(&mut self, nonce: u32) {
        let now = self.last.unwrap_or_default();
        for i in 0..self.nodes.len() {
            if let Some(v) = self.nodes[i].verifier.as_mut() {
                v.restart(nonce);
            }
            self.drop_held(i, None, now);
        }
    }

    /// The gate of an offline replay: the digests in `rejects` did not verify live, every
    /// other did (see the module docs).
    pub fn replaying(rejects: &[RejectRun]) -> StreamGate {
        let mut g = StreamGate::new(&KeySet::default(), 0);
        g.rejects = rejects.iter().take(MAX_REJECT_RUNS).copied().collect();
        g.replaying = true;
        g
    }

    /// The digests that did not verify, as runs per node.
    pub fn rejects(&self) -> &[RejectRun] {
        &self.rejects
    }

    /// The verdict on `node`'s digest `d` over its held frames: checked with its key live,
    /// looked up when replaying.
    fn verdict(&mut self, i: usize, d: &exocal_dbc::StreamDigest) -> Result<(), Reject> {
        let ordinal = self.ordinals[i];
        self.ordinals[i] += 1;
        let gate = &mut self.nodes[i];
        if self.replaying {
            let node = (i + 1) as u8;
            let run = self
                .rejects
                .iter()
                .find(|r| r.node == node && r.covers(ordinal));
            let held = gate.held.len() as u32;
            return match run {
                None => Ok(()),
                Some(r) if r.stale => Err(Reject::Stale),
                Some(_) if held > u32::from(d.count) => Err(Reject::Surplus {
                    received: held,
                    covered: d.count,
                }),
                Some(_) if held < u32::from(d.count) => Err(Reject::Deficit {
                    received: held,
                    covered: d.count,
                }),
                Some(_) => Err(Reject::BadMac),
            };
        }
        let verdict = match gate.verifier.as_mut() {
            Some(v) => v.check(
                d,
                gate.held
                    .iter()
                    .map(|r| (r.frame.raw_id() as u16, r.frame.data())),
            ),
            None => Err(Reject::BadMac),
        };
        if verdict.is_err() {
            self.record(i, ordinal, verdict == Err(Reject::Stale));
        }
        verdict
    }

    /// A digest over no held frames passes and drops nothing whatever its verdict, so the
    /// verdict is counted ([`GateStats::empty_rejects`]), never recorded (one forged digest
    /// after each genuine span would otherwise fill the record in half a second). Live it
    /// is checked (a genuine one moves the verifier's sequence on); replaying, it is skipped.
    /// Either way it takes its ordinal and its sequence number, so replay and live stay in
    /// step, and it verifies no span (`verified`, `verified_spans` are of spans with frames).
    fn empty_digest(&mut self, i: usize, d: &exocal_dbc::StreamDigest) {
        self.ordinals[i] += 1;
        let gate = &mut self.nodes[i];
        if !self.replaying {
            let verdict = gate.verifier.as_mut().map(|v| {
                let none: [(u16, &[u8]); 0] = [];
                v.check(d, none)
            });
            if !matches!(verdict, Some(Ok(()))) {
                self.stats.empty_rejects += 1;
            }
        }
        gate.last_seq = Some(d.seq_lo);
    }

    fn record(&mut self, i: usize, ordinal: u64, stale: bool) {
        let node = (i + 1) as u8;
        let full = self.rejects.len() >= MAX_REJECT_RUNS;
        let last = self.rejects.iter_mut().rev().find(|r| r.node == node);
        match last {
            Some(r) if r.stale == stale && r.first.checked_add(r.count) == Some(ordinal) => {
                r.count += 1
            }
            _ if full => self.stats.rejects_truncated = true,
            _ => self.rejects.push(RejectRun {
                node,
                first: ordinal,
                count: 1,
                stale,
            }),
        }
    }

    /// What was passed and dropped so far.
    pub fn stats(&self) -> &GateStats {
        &self.stats
    }

    /// Takes one received frame; appends to `pass` the frames ingest takes now, and returns
    /// the spans dropped on the way (see the module docs).
    pub fn on_frame(&mut self, rx: &Received, pass: &mut Vec<Received>) -> Vec<Dropped> {
        let mut dropped = Vec::new();
        let now = rx.timestamp;
        self.opened.get_or_insert(now);
        self.last = Some(now);
        let id = rx.frame.raw_id();
        let family = u16::try_from(id)
            .ok()
            .filter(|_| !rx.frame.is_extended())
            .and_then(spec::lookup);
        match family {
            Some((f, Some(node))) if covered(f.kind) => {
                let i = usize::from(node.raw() - 1);
                // More than one digest covers: its digest was lost, or the node sends none.
                if self.nodes[i].held.len() >= usize::from(MAX_COVERED) {
                    dropped.push(self.drop_held(i, None, now));
                }
                self.nodes[i].held.push_back(*rx);
            }
            Some((f, Some(node))) if f.kind == spec::Kind::StreamDigest => {
                let digest = match exocal_dbc::decode_frame(&rx.frame) {
                    Ok(Message::StreamDigest(d)) => Some(d),
                    _ => None,
                };
                let i = usize::from(node.raw() - 1);
                if let Some(d) = digest.filter(|_| self.nodes[i].held.is_empty()) {
                    self.empty_digest(i, &d);
                } else if let Some(d) = digest {
                    let verdict = self.verdict(i, &d);
                    let gate = &mut self.nodes[i];
                    // Digests lost before this one: a surplus is their frames, not a sender's.
                    let lost_before = gate.last_seq.is_some_and(|s| d.seq_lo != s.wrapping_add(1));
                    if verdict != Err(Reject::Stale) {
                        gate.last_seq = Some(d.seq_lo);
                    }
                    let verdict = match verdict {
                        Err(Reject::Surplus { .. }) if lost_before => Err(Reject::Deficit {
                            received: gate.held.len() as u32,
                            covered: d.count,
                        }),
                        v => v,
                    };
                    match verdict {
                        Ok(()) => {
                            gate.verified = true;
                            self.stats.verified_spans += 1;
                            self.stats.verified_frames += gate.held.len() as u64;
                            pass.extend(gate.held.drain(..));
                        }
                        Err(Reject::Stale) => self.stats.stale += 1,
                        Err(_) if gate.verifier.is_none() && !self.replaying => {
                            dropped.push(self.drop_held(i, None, now));
                        }
                        Err(r) => dropped.push(self.drop_held(i, Some(r), now)),
                    }
                }
                pass.push(*rx);
            }
            Some((f, Some(node))) if f.kind == spec::Kind::Heartbeat => {
                if let Ok(Message::Heartbeat(h)) = exocal_dbc::decode_frame(&rx.frame) {
                    let boot = &mut self.nodes[usize::from(node.raw() - 1)].boot;
                    let rebooted = boot.is_some_and(|b| b != h.boot_count);
                    *boot = Some(h.boot_count);
                    if rebooted {
                        // A new nonce goes to every node: the held spans will not verify
                        // under it. Their drops are loss (the heartbeat may be spoofed).
                        self.stats.reboots += 1;
                        self.want_nonce();
                        for i in 0..self.nodes.len() {
                            dropped.push(self.drop_held(i, None, now));
                        }
                    }
                }
                pass.push(*rx);
            }
            Some((f, Some(_))) if f.kind == spec::Kind::StreamNonce => {
                // Not ours (see the module docs), and no node takes it.
                self.stats.foreign_nonces += 1;
                pass.push(*rx);
            }
            _ => pass.push(*rx),
        }
        dropped.retain(|d| d.frames > 0);
        dropped
    }

    /// Drops node `i`'s held frames at receive time `now` for `reject` (`None`: no digest).
    fn drop_held(&mut self, i: usize, reject: Option<Reject>, now: Duration) -> Dropped {
        let start = !self.nodes[i].verified
            && self
                .opened
                .is_some_and(|t0| now.saturating_sub(t0) <= START_GRACE);
        let held = &mut self.nodes[i].held;
        let node = NodeId::ALL[i];
        let mut frames = held.len();
        if start {
            self.stats.start_frames += frames as u64;
            frames = 0;
        } else if frames > 0 {
            let s = &mut self.stats;
            s.dropped_spans += 1;
            s.dropped_frames += frames as u64;
            let (first, last) = (held[0].timestamp, held[frames - 1].timestamp);
            s.dropped_s += last.saturating_sub(first).as_secs_f64();
            match reject {
                Some(Reject::Surplus { .. }) => s.second_sender[usize::from(node.raw())] += 1,
                Some(Reject::Deficit { .. }) => s.deficit += 1,
                Some(Reject::BadMac) => s.bad_mac += 1,
                Some(Reject::Stale) | None => s.no_digest += 1,
            }
        }
        held.clear();
        Dropped {
            node,
            frames,
            reject,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use exocal_dbc::stream_auth::Signer;
    use exocal_dbc::{Frame, JointState};

    const NONCE: u32 = 77;

    fn joint(angle: f64, t_ms: u64) -> Received {
        let frame: Frame = Message::JointState(JointState {
            node: NodeId::JOINTS[2],
            timestamp_us: t_ms as u32 * 1000,
            angle,
            rate: 0.0,
        })
        .to_frame()
        .unwrap();
        Received {
            frame,
            timestamp: Duration::from_millis(t_ms),
        }
    }

    fn setup() -> (StreamGate, Signer) {
        let keys = KeySet::derived(3);
        let node = NodeId::JOINTS[2];
        let mut s = Signer::new(node, stream_key(keys.node(node).unwrap()), 0);
        s.set_nonce(signed(NONCE), 0).unwrap();
        (StreamGate::new(&keys, NONCE), s)
    }

    /// The controller's `StreamNonce` for Joint3 (under `KeySet::derived(3)`).
    fn signed(nonce: u32) -> exocal_dbc::StreamNonce {
        let node = NodeId::JOINTS[2];
        let key = stream_key(KeySet::derived(3).node(node).unwrap());
        exocal_dbc::stream_auth::sign_nonce(&key, node, nonce)
    }

    fn digest(s: &mut Signer, t_ms: u64) -> Received {
        Received {
            frame: Message::StreamDigest(s.digest(0)).to_frame().unwrap(),
            timestamp: Duration::from_millis(t_ms),
        }
    }

    /// Sends ten genuine frames (signed) plus `rogue` (unsigned) frames, then the digest.
    fn span(
        g: &mut StreamGate,
        s: &mut Signer,
        t0: u64,
        rogue: usize,
    ) -> (Vec<Received>, Vec<Dropped>) {
        let mut pass = Vec::new();
        let mut dropped = Vec::new();
        for k in 0..10 {
            let rx = joint(0.1 * k as f64, t0 + k);
            s.add(rx.frame.raw_id() as u16, rx.frame.data(), 0);
            dropped.extend(g.on_frame(&rx, &mut pass));
            assert!(pass.is_empty(), "held until the digest");
            if k < rogue as u64 {
                dropped.extend(g.on_frame(&joint(1.0, t0 + k), &mut pass));
            }
        }
        dropped.extend(g.on_frame(&digest(s, t0 + 10), &mut pass));
        (pass, dropped)
    }

    #[test]
    fn verified_spans_pass_in_order_and_a_rogue_sender_is_dropped_and_named() {
        let (mut g, mut s) = setup();
        let (pass, dropped) = span(&mut g, &mut s, 0, 0);
        assert!(dropped.is_empty());
        assert_eq!(pass.len(), 11); // ten frames and the digest
        assert!(pass.windows(2).all(|w| w[0].timestamp <= w[1].timestamp));
        let (pass, dropped) = span(&mut g, &mut s, 100, 2);
        assert_eq!(pass.len(), 1, "only the digest");
        assert_eq!(dropped.len(), 1);
        assert!(dropped[0].to_string().contains("a second sender on Joint3"));
        let st = g.stats();
        assert_eq!((st.verified_spans, st.verified_frames), (1, 10));
        assert_eq!((st.dropped_spans, st.dropped_frames), (1, 12));
        assert_eq!(
            st.second_senders().collect::<Vec<_>>(),
            [(NodeId::JOINTS[2], 1)]
        );
        // The stream resumes.
        let (pass, _) = span(&mut g, &mut s, 200, 0);
        assert_eq!(pass.len(), 11);
    }

    /// A Joint3 heartbeat with `boot_count` at `t_ms`.
    fn heartbeat(boot_count: u8, t_ms: u64) -> Received {
        use exocal_dbc::{Heartbeat, NodeState};
        let frame: Frame = Message::Heartbeat(Heartbeat {
            node: NodeId::JOINTS[2],
            state: NodeState::Operational,
            boot_count,
            tx_errors: 0,
            rx_errors: 0,
            table_crc: 0,
            fw_major: 1,
            fw_minor: 0,
        })
        .to_frame()
        .unwrap();
        Received {
            frame,
            timestamp: Duration::from_millis(t_ms),
        }
    }

    /// Opens `g` with a heartbeat at time 0: spans from [`START_GRACE`] on are past the start.
    fn opened(g: &mut StreamGate) {
        let mut pass = Vec::new();
        g.on_frame(&heartbeat(0, 0), &mut pass);
        assert_eq!(pass.len(), 1, "heartbeats pass at once");
    }

    const PAST_START: u64 = START_GRACE.as_millis() as u64 + 100;

    #[test]
    fn frames_sent_before_the_nonce_are_start_drops_not_a_second_sender() {
        let (mut g, mut s) = setup();
        let mut pass = Vec::new();
        // Frames in flight when the nonce went out (signed under the previous nonce): the
        // node's first digest covers only what it sent after.
        for k in 0..5 {
            g.on_frame(&joint(0.5, k), &mut pass);
        }
        let (pass, dropped) = span(&mut g, &mut s, 10, 0);
        assert_eq!(pass.len(), 1, "only the digest");
        assert!(dropped.is_empty(), "{dropped:?}");
        let st = g.stats();
        assert_eq!(st.start_frames, 15);
        assert_eq!((st.dropped_spans, st.second_senders().count()), (0, 0));
        // The next span verifies; after it, a surplus is a second sender even at the start.
        let (pass, _) = span(&mut g, &mut s, 110, 0);
        assert_eq!(pass.len(), 11);
        let (pass, dropped) = span(&mut g, &mut s, 210, 1);
        assert_eq!((pass.len(), dropped.len()), (1, 1));
        assert_eq!(g.stats().second_senders().count(), 1);
    }

    #[test]
    fn past_the_start_a_node_that_never_verified_is_dropped_and_counted() {
        let (mut g, mut s) = setup();
        opened(&mut g);
        let (_, dropped) = span(&mut g, &mut s, PAST_START, 2);
        assert_eq!(dropped.len(), 1);
        assert_eq!(g.stats().second_senders().count(), 1);
        assert_eq!(g.stats().start_frames, 0);
    }

    #[test]
    fn a_lost_digest_is_loss_not_a_second_sender() {
        let (mut g, mut s) = setup();
        opened(&mut g);
        span(&mut g, &mut s, PAST_START, 0);
        // The next span's digest never arrives: its frames are held into the following span.
        let mut pass = Vec::new();
        for k in 0..10 {
            let rx = joint(0.1 * k as f64, PAST_START + 100 + k);
            s.add(rx.frame.raw_id() as u16, rx.frame.data(), 0);
            g.on_frame(&rx, &mut pass);
        }
        let _lost = s.digest(0);
        let (pass, dropped) = span(&mut g, &mut s, PAST_START + 200, 0);
        assert_eq!((pass.len(), dropped.len()), (1, 1));
        let st = g.stats();
        assert_eq!((st.second_senders().count(), st.deficit), (0, 1), "{st:?}");
        let (pass, _) = span(&mut g, &mut s, PAST_START + 300, 0);
        assert_eq!(pass.len(), 11, "the stream resumes");
    }

    #[test]
    fn a_stalled_receiver_delays_spans_and_digests_alike_and_drops_nothing() {
        let (mut g, mut s) = setup();
        opened(&mut g);
        let mut pass = Vec::new();
        // Half a span, then the receiver reads nothing for 2 s, then the rest and the digest.
        for k in 0..10 {
            let t = PAST_START + k + if k < 5 { 0 } else { 2000 };
            let rx = joint(0.1 * k as f64, t);
            s.add(rx.frame.raw_id() as u16, rx.frame.data(), 0);
            assert!(g.on_frame(&rx, &mut pass).is_empty());
        }
        g.on_frame(&digest(&mut s, PAST_START + 2010), &mut pass);
        assert_eq!(pass.len(), 11);
        assert_eq!(g.stats().dropped_spans, 0);
    }

    #[test]
    fn after_a_reboot_the_stream_verifies_again_under_a_new_nonce() {
        let (mut g, mut s) = setup();
        opened(&mut g);
        g.on_frame(&heartbeat(1, PAST_START), &mut Vec::new());
        span(&mut g, &mut s, PAST_START, 0);
        // Joint3 reboots: its signer starts over without a nonce, and says so in its heartbeat.
        let keys = KeySet::derived(3);
        let node = NodeId::JOINTS[2];
        let mut s = Signer::new(node, stream_key(keys.node(node).unwrap()), 0);
        let (pass, _) = span(&mut g, &mut s, PAST_START + 100, 0);
        assert_eq!(pass.len(), 1, "signed under no nonce: dropped");
        g.on_frame(&heartbeat(2, PAST_START + 200), &mut Vec::new());
        assert!(g.nonce_wanted());
        g.renonce(78);
        s.set_nonce(signed(78), 0).unwrap();
        let (pass, dropped) = span(&mut g, &mut s, PAST_START + 300, 0);
        assert_eq!(pass.len(), 11, "{dropped:?}");
        // A span recorded under the first nonce does not verify under the new one.
        let (_, mut old) = setup();
        let (pass, _) = span(&mut g, &mut old, PAST_START + 400, 0);
        assert_eq!(pass.len(), 1);
    }

    /// A keyless sender injects into 3 spans in 10 and spoofs two heartbeats (a new boot
    /// count, then the old one) before each of their digests. The held frames, rogue ones
    /// included, count as loss, not as start frames (which would hide the injection: 0 spans
    /// dropped, no second sender, no heavy loss): the 3 spans show, and heavy loss refuses the
    /// session; the new nonces the spoofs ask for stop at [`MAX_RENONCES`].
    #[test]
    fn spoofed_heartbeats_do_not_hide_an_injection() {
        let (mut g, mut s) = setup();
        opened(&mut g);
        let mut pass = Vec::new();
        for k in 0..10u64 {
            let t0 = PAST_START + 100 * k;
            let attacked = k % 3 == 1;
            for i in 0..10 {
                let rx = joint(0.1 * i as f64, t0 + i);
                s.add(rx.frame.raw_id() as u16, rx.frame.data(), 0);
                g.on_frame(&rx, &mut pass);
                if attacked && i < 2 {
                    g.on_frame(&joint(1.0, t0 + i), &mut pass);
                }
            }
            if attacked {
                g.on_frame(&heartbeat(1, t0 + 10), &mut pass);
                g.on_frame(&heartbeat(0, t0 + 10), &mut pass);
                if g.nonce_wanted() {
                    // The controller sends a new nonce; the node takes it.
                    let fresh = 1000 + k as u32;
                    g.renonce(fresh);
                    s.set_nonce(signed(fresh), 0).unwrap();
                }
            }
            g.on_frame(&digest(&mut s, t0 + 10), &mut pass);
        }
        let st = g.stats();
        assert_eq!(st.start_frames, 0, "{st:?}");
        assert_eq!((st.reboots, st.renonces), (6, 3), "{st:?}");
        assert_eq!(st.dropped_spans, 3, "{st:?}");
        assert!(st.heavy_loss(), "{st:?}");
        // A flood of spoofed heartbeats: the new nonces stop at the limit.
        for k in 0..40u64 {
            g.on_frame(
                &heartbeat((k % 2) as u8 + 1, PAST_START + 2000 + k),
                &mut pass,
            );
            g.nonce_wanted();
        }
        assert_eq!(g.stats().renonces, MAX_RENONCES);
        assert!(g.stats().renonces_capped);
    }

    /// One unsigned `StreamNonce` frame, and a replay of a genuine one from before. A node
    /// that obeyed any `StreamNonce` would verify none of the 40 later spans, and the session
    /// would end as failed authentication, the frame never named. The node takes neither, the
    /// stream goes on verifying with no span lost and no new nonce, and the gate counts both
    /// for the daemon to name.
    #[test]
    fn a_spoofed_nonce_or_a_replayed_one_changes_nothing() {
        let (mut g, mut s) = setup();
        opened(&mut g);
        let (pass, _) = span(&mut g, &mut s, PAST_START, 0);
        assert_eq!(pass.len(), 11);
        let forged = exocal_dbc::StreamNonce {
            node: NodeId::JOINTS[2],
            nonce: 666,
            mac: 0,
        };
        // A genuine nonce of an earlier collection (below the one the node holds).
        let replayed = signed(NONCE - 1);
        for (k, n) in [forged, replayed].into_iter().enumerate() {
            let mut pass = Vec::new();
            g.on_frame(
                &Received {
                    frame: Message::StreamNonce(n).to_frame().unwrap(),
                    timestamp: Duration::from_millis(PAST_START + 50 + k as u64),
                },
                &mut pass,
            );
            assert_eq!(pass.len(), 1, "passed on, for ingest to name");
            // The node, as exocal-hil's and real firmware does, offers it to its signer.
            assert!(s.set_nonce(n, 0).is_err());
        }
        let (pass, _) = span(&mut g, &mut s, PAST_START + 100, 0);
        assert_eq!(pass.len(), 11, "the stream goes on verifying");
        assert!(!g.nonce_wanted());
        let st = g.stats();
        assert_eq!(
            (st.foreign_nonces, st.renonces, st.dropped_spans),
            (2, 0, 0),
            "{st:?}"
        );
    }

    #[test]
    fn a_new_boot_count_wants_the_nonce_again_once() {
        let (mut g, _) = setup();
        let mut pass = Vec::new();
        g.on_frame(&heartbeat(3, 0), &mut pass);
        g.on_frame(&heartbeat(3, 1000), &mut pass);
        assert!(!g.nonce_wanted());
        g.on_frame(&heartbeat(4, 2000), &mut pass);
        assert!(g.nonce_wanted());
        assert!(!g.nonce_wanted(), "said once");
    }

    #[test]
    fn more_than_the_tolerated_fraction_of_dropped_spans_is_heavy_loss() {
        let mut st = GateStats {
            verified_spans: 95,
            dropped_spans: 5,
            ..GateStats::default()
        };
        assert!(!st.heavy_loss());
        st.dropped_spans = 6;
        assert!(st.heavy_loss());
    }

    #[test]
    fn frames_without_a_digest_are_dropped_beyond_one_digests_worth_and_memory_is_bounded() {
        let (mut g, _) = setup();
        opened(&mut g);
        let mut pass = Vec::new();
        let mut dropped = 0;
        for t in PAST_START..PAST_START + 2000 {
            dropped += g
                .on_frame(&joint(0.0, t), &mut pass)
                .iter()
                .map(|d| d.frames)
                .sum::<usize>();
            assert!(g.nodes[2].held.len() <= usize::from(MAX_COVERED));
        }
        assert!(pass.is_empty());
        assert!(dropped >= 2000 - usize::from(MAX_COVERED), "{dropped}");
        assert!(g.stats().no_digest > 0);
    }

    #[test]
    fn a_replay_with_the_recorded_verdicts_passes_exactly_what_the_live_gate_passed() {
        let (mut g, mut s) = setup();
        let mut input = Vec::new();
        let mut live = Vec::new();
        for (k, rogue) in [0, 3, 0, 1, 1, 0].into_iter().enumerate() {
            let t0 = 100 * k as u64;
            for i in 0..10 {
                let rx = joint(0.1 * i as f64, t0 + i);
                s.add(rx.frame.raw_id() as u16, rx.frame.data(), 0);
                input.push(rx);
                if i < rogue {
                    input.push(joint(1.0, t0 + i));
                }
            }
            input.push(digest(&mut s, t0 + 10));
        }
        for rx in &input {
            g.on_frame(rx, &mut live);
        }
        assert_eq!(g.stats().dropped_spans, 3);
        let runs = g.rejects().to_vec();
        assert_eq!(runs.len(), 2, "{runs:?}"); // span 1, spans 3-4
        let mut r = StreamGate::replaying(&runs);
        let mut replayed = Vec::new();
        for rx in &input {
            r.on_frame(rx, &mut replayed);
        }
        assert_eq!(replayed, live);
        assert_eq!(r.stats().dropped_frames, g.stats().dropped_frames);
    }

    /// A forged digest after each genuine span, over no frames, drops nothing; recorded as a
    /// run of its own, 4,097 of them (half a second of bus) would fill the record, leave later
    /// rejects unrecorded, and let an offline replay pass the injected frames live dropped.
    /// They are counted instead, the record keeps the one span that was attacked, and the
    /// replay passes exactly what live passed.
    #[test]
    fn a_full_reject_record_cannot_be_filled_by_digests_over_no_frames() {
        let (mut g, mut s) = setup();
        let node = NodeId::JOINTS[2];
        let forged = |k: u64, t_ms: u64| Received {
            frame: Message::StreamDigest(exocal_dbc::StreamDigest {
                node,
                seq_lo: 0xBEEF,
                count: (k % 3) as u8,
                mac: k,
            })
            .to_frame()
            .unwrap(),
            timestamp: Duration::from_millis(t_ms),
        };
        let spans = MAX_REJECT_RUNS as u64 + 10;
        let (mut input, mut injected) = (Vec::new(), Vec::new());
        for k in 0..spans {
            let t0 = 10 * k;
            for i in 0..2 {
                let rx = joint(0.1 * i as f64, t0 + i);
                s.add(rx.frame.raw_id() as u16, rx.frame.data(), 0);
                input.push(rx);
                if k == spans - 5 {
                    injected.push(joint(1.0, t0 + i));
                    input.push(joint(1.0, t0 + i));
                }
            }
            input.push(digest(&mut s, t0 + 5));
            input.push(forged(k, t0 + 6));
        }
        let mut live = Vec::new();
        for rx in &input {
            g.on_frame(rx, &mut live);
        }
        let st = g.stats();
        assert_eq!(st.empty_rejects, spans, "{st:?}");
        assert!(!st.rejects_truncated);
        assert_eq!(g.rejects().len(), 1, "only the attacked span");
        assert_eq!((st.dropped_spans, st.dropped_frames), (1, 4));
        assert!(!live
            .iter()
            .any(|rx| rx.frame.data()[..] == joint(1.0, 0).frame.data()[..]));
        let mut r = StreamGate::replaying(g.rejects());
        let mut replayed = Vec::new();
        for rx in &input {
            r.on_frame(rx, &mut replayed);
        }
        assert_eq!(replayed, live);
        assert_eq!(r.stats().dropped_frames, st.dropped_frames);
        assert_eq!(r.stats().verified_spans, st.verified_spans);
    }

    /// A log is hostile: recorded runs at the end of the ordinals' range (`first + count` past
    /// `u64::MAX`) are read without overflow (found reading the code beside the fuzz run).
    #[test]
    fn a_replay_of_runs_at_the_end_of_the_range_does_not_overflow() {
        let (mut g, mut s) = setup();
        let mut input = Vec::new();
        for i in 0..10 {
            let rx = joint(0.1 * i as f64, i);
            s.add(rx.frame.raw_id() as u16, rx.frame.data(), 0);
            input.push(rx);
        }
        input.push(digest(&mut s, 10));
        let mut live = Vec::new();
        for rx in &input {
            g.on_frame(rx, &mut live);
        }
        assert!(g.rejects().is_empty());
        // Joint 3's digest (the gate numbers nodes from 1, joint 1 first).
        let runs = [RejectRun {
            node: 3,
            first: u64::MAX - 1,
            count: u64::MAX,
            stale: false,
        }];
        let mut r = StreamGate::replaying(&runs);
        let mut replayed = Vec::new();
        for rx in &input {
            r.on_frame(rx, &mut replayed);
        }
        assert_eq!(replayed, live, "ordinal 0 is not in the run");
    }

    #[test]
    fn a_node_without_a_key_is_never_passed() {
        let mut keys = KeySet::derived(3);
        keys.set_node(NodeId::JOINTS[2], None);
        let mut g = StreamGate::new(&keys, NONCE);
        opened(&mut g);
        let (_, mut s) = setup();
        let (pass, dropped) = span(&mut g, &mut s, PAST_START, 0);
        assert_eq!(pass.len(), 1);
        assert_eq!(dropped[0].frames, 10);
    }
}
