//! Table transfer: the node side ([`NodeTransfer`]) and the controller side ([`Upload`]).
//!
//! # Why our own segmented messages
//! A table is 24 bytes, always six fields. ISO-TP would add flow control and a reassembly buffer
//! and would hide the fields inside an opaque byte stream that DBC tools cannot show; a
//! CANopen-style SDO would need an object dictionary the nodes otherwise have no use for. Our
//! `TableCmd`/`TableReply` frames are stop-and-wait, one field per frame with its own scaled DBC
//! signal, so candump + cantools (or SavvyCAN) show every value in its unit, and the state
//! machines below fit a Cortex-M without allocation.
//!
//! # Protocol (per node, one transfer at a time)
//! `Begin(s)` opens a staging area for session `s` (discarding any older one); `Segment(k, v)`
//! stages field `k` and must come in order (a repeat of an already staged segment with the same
//! value is re-acknowledged, so lost ACKs are harmless); `Commit(s, crc)` installs the staged
//! table if and only if all six fields are staged, `crc` equals their CRC-32, and the storage
//! write succeeds. Every command is answered with an ACK or NACK carrying the CRC of the table
//! the node holds *now* (installed, never staged). `Readback` returns the six held fields then an
//! ACK. `Abort` drops the staging. Staging lives in RAM only: a reboot or
//! [`STAGING_TIMEOUT_US`] of silence drops it and the old table stays.
//!
//! The node never holds a mixed table: the installed table changes only at a successful Commit,
//! and only as a whole (the storage write is the caller's, via [`TableStorage`]).
//!
//! # Authentication (exocal-3)
//! A node installs nothing without a key: a node built without one ([`NodeTransfer::new`]:
//! never provisioned, or its key or counter unreadable at boot) NACKs `Begin`, `CommitAuth` and
//! `Commit` with `NoKey` (it still answers `Readback`, unsigned). A node holding a key
//! ([`NodeTransfer::with_key`]) answers `Begin(nonce)` with its stored freshness counter
//! ([`Reply::Freshness`]) and a MAC over node, session, the controller's nonce, the counter and
//! its held CRC ([`Reply::FreshnessMac`], [`crate::auth::freshness_mac`]) before the ACK; an
//! authenticated [`Upload`] takes the counter only from such an answer, so the counter it signs
//! above is the node's own and nobody without the key can make it sign one far ahead (a
//! `CommitAuth` kept for later would otherwise outlive every genuine push). It installs a table
//! only after a `CommitAuth(counter_lo, mac)` whose MAC ([`crate::auth::commit_mac`]) verifies
//! for the staged table, this session and the full counter the low bits stand for
//! ([`crate::auth::next_counter`]: above the stored one). A plain Commit, a wrong MAC or a stale
//! counter is NACKed (`BadMac`, `StaleCounter`) and the staging dropped. A staging so authorised
//! is dropped by any command on the node's identifier but its Commit (or the same `CommitAuth`
//! again, its ACK lost): another session, a segment, a readback, an abort. At the commit the
//! counter is written first on its own ([`TableStorage::store_counter`], kept apart from the
//! table image so that a lost or corrupt image never takes it back), then with the table
//! ([`TableStorage::store`]): a recorded transfer never installs twice. Its readback carries
//! [`Reply::ReadbackMac`] over the controller's nonce, the held CRC and the table
//! ([`crate::auth::readback_mac`]) before the ACK; an authenticated [`Upload`] reports success
//! only on such an answer, so forged replies can make it fail but never succeed. It judges at
//! most [`MAX_BAD_ANSWERS`] answers whose MAC does not verify per Begin and per readback (each
//! is a guess at a 32-bit MAC), then fails.

use crate::auth::{self, Key};
use crate::message::{CmdCode, Command, NackReason, Reply, TableCmd, TableReply};
use crate::table::{Field, Table};
use crate::NodeId;

/// A staging area untouched for this long is dropped.
pub const STAGING_TIMEOUT_US: u64 = 5_000_000;

/// Answers whose MAC does not verify that an [`Upload`] judges for one Begin or one readback
/// before it gives up ([`UploadError::BadAnswer`]): each is a guess at a 32-bit MAC, and judging
/// them costs a CMAC each.
pub const MAX_BAD_ANSWERS: u32 = 4;

/// Persistent storage of the installed table and of the freshness counter (emulated flash in
/// the hil, real flash on a node).
pub trait TableStorage {
    /// Writes the freshness `counter` durably on its own, apart from the table image (its own
    /// record or sector): a table image lost or corrupt must not take the counter back, or a
    /// recorded transfer would install again. Called at every commit before
    /// [`TableStorage::store`], with the counter the commit consumes; on error nothing is
    /// installed.
    fn store_counter(&mut self, counter: u32) -> Result<(), StorageError>;

    /// Writes `table` and the freshness `counter` durably, in one write; on error the previous
    /// content must still be readable.
    fn store(&mut self, table: &Table, counter: u32) -> Result<(), StorageError>;
}

/// A failed storage write.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct StorageError;

impl core::fmt::Display for StorageError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str("table storage write failed")
    }
}

/// Up to eight replies to one command (an authenticated Readback: six fields, the MAC and an
/// ACK).
pub type Replies = heapless::Vec<TableReply, 8>;

/// What a verified `CommitAuth` authorised: the counter, and the frame's own fields (the same
/// frame again keeps the authorisation).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Authorised {
    counter: u32,
    counter_lo: u16,
    mac: u32,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Staging {
    session: u8,
    staged: [i64; 6],
    next: u8,
    last_us: u64,
    authorised: Option<Authorised>,
}

impl Staging {
    /// Whether this staging is `session`'s (else `BadSession`) with all six segments (else
    /// `Incomplete`): what `CommitAuth` and `Commit` need.
    fn complete_in(&self, session: u8) -> Result<(), NackReason> {
        if self.session != session {
            return Err(NackReason::BadSession);
        }
        if self.next < 6 {
            return Err(NackReason::Incomplete);
        }
        Ok(())
    }
}

/// Node side of the transfer.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct NodeTransfer {
    node: NodeId,
    held: Option<Table>,
    staging: Option<Staging>,
    last_commit: Option<(u8, u32)>,
    counter: u32,
    key: Option<Key>,
}

impl NodeTransfer {
    /// A freshly booted node holding `held` (as read from its storage), without a key: it
    /// installs nothing (NACK `NoKey`) until it is given one ([`NodeTransfer::with_key`]). This
    /// is also what a node must boot as when its key or its counter cannot be read: fail closed.
    pub fn new(node: NodeId, held: Option<Table>) -> Self {
        NodeTransfer {
            node,
            held,
            staging: None,
            last_commit: None,
            counter: 0,
            key: None,
        }
    }

    /// The same node holding `key`, with the freshness `counter` its storage holds (the
    /// highest of its counter record and its table image): it then installs only authenticated
    /// tables and signs its answers (see the module docs).
    pub fn with_key(mut self, key: Key, counter: u32) -> Self {
        self.key = Some(key);
        self.counter = counter;
        self
    }

    /// The installed table.
    pub fn held(&self) -> Option<&Table> {
        self.held.as_ref()
    }

    /// The freshness counter stored with the installed table.
    pub fn counter(&self) -> u32 {
        self.counter
    }

    /// Whether the node holds a key (without one it installs nothing).
    pub fn is_keyed(&self) -> bool {
        self.key.is_some()
    }

    /// CRC-32 of the installed table, 0 when none.
    pub fn held_crc(&self) -> u32 {
        self.held.map_or(0, |t| t.crc())
    }

    /// Whether a transfer is open at `now_us`.
    pub fn is_staging(&self, now_us: u64) -> bool {
        self.staging
            .is_some_and(|s| now_us.saturating_sub(s.last_us) < STAGING_TIMEOUT_US)
    }

    /// Handles one command addressed to this node (others are ignored: empty reply).
    pub fn handle<S: TableStorage>(
        &mut self,
        cmd: &TableCmd,
        now_us: u64,
        storage: &mut S,
    ) -> Replies {
        let mut out = Replies::new();
        if cmd.node != self.node {
            return out;
        }
        if !self.is_staging(now_us) {
            self.staging = None;
        }
        self.keep_authorised_only_for_its_commit(cmd);
        let session = cmd.session;
        let code = cmd.cmd.code();
        let reply = match cmd.cmd {
            Command::Begin { nonce } => match &self.key {
                None => Err(NackReason::NoKey),
                Some(key) => {
                    self.staging = Some(Staging {
                        session,
                        staged: [0; 6],
                        next: 0,
                        last_us: now_us,
                        authorised: None,
                    });
                    let counter = self.counter;
                    let mac = auth::freshness_mac(
                        key,
                        self.node,
                        session,
                        nonce,
                        counter,
                        self.held_crc(),
                    );
                    let _ = out.push(self.reply(session, Reply::Freshness { counter }));
                    let _ = out.push(self.reply(session, Reply::FreshnessMac { mac }));
                    Ok(())
                }
            },
            Command::Segment(field, raw) => self.segment(session, field, raw, now_us),
            Command::CommitAuth { counter_lo, mac } => {
                self.commit_auth(session, counter_lo, mac, now_us)
            }
            Command::Commit { crc } => self.commit(session, crc, storage),
            Command::Readback { nonce } => match self.held {
                Some(table) => {
                    for f in Field::ALL {
                        let _ = out.push(self.reply(session, Reply::Readback(f, table.raw(f))));
                    }
                    if let Some(key) = &self.key {
                        let mac = auth::readback_mac(
                            key,
                            self.node,
                            nonce,
                            table.crc(),
                            &table.to_bytes(),
                        );
                        let _ = out.push(self.reply(session, Reply::ReadbackMac { mac }));
                    }
                    Ok(())
                }
                None => Err(NackReason::NoTable),
            },
            Command::Abort => {
                if self.staging.is_some_and(|s| s.session == session) {
                    self.staging = None;
                }
                Ok(())
            }
        };
        let held_crc = self.held_crc();
        let reply = match reply {
            Ok(()) => Reply::Ack {
                cmd: code,
                held_crc,
            },
            Err(reason) => Reply::Nack {
                cmd: code,
                held_crc,
                reason,
            },
        };
        let _ = out.push(self.reply(session, reply));
        out
    }

    /// An authorised staging lives only until its Commit: any other command on this node's
    /// identifier (another session, a segment, a readback, an abort, a Begin) drops it, so a
    /// `CommitAuth` whose Commit did not follow cannot be completed later. The same
    /// `CommitAuth` again (its ACK was lost) keeps it.
    fn keep_authorised_only_for_its_commit(&mut self, cmd: &TableCmd) {
        let Some(st) = self.staging else {
            return;
        };
        let Some(a) = st.authorised else {
            return;
        };
        let continues = cmd.session == st.session
            && match cmd.cmd {
                Command::Commit { .. } => true,
                Command::CommitAuth { counter_lo, mac } => {
                    (counter_lo, mac) == (a.counter_lo, a.mac)
                }
                _ => false,
            };
        if !continues {
            self.staging = None;
        }
    }

    fn reply(&self, session: u8, reply: Reply) -> TableReply {
        TableReply {
            node: self.node,
            session,
            reply,
        }
    }

    fn segment(
        &mut self,
        session: u8,
        field: Field,
        raw: i64,
        now_us: u64,
    ) -> Result<(), NackReason> {
        let st = self.staging.as_mut().ok_or(NackReason::NotStaging)?;
        if st.session != session {
            return Err(NackReason::BadSession);
        }
        let (lo, hi) = field.raw_bounds();
        if raw < lo || raw > hi {
            return Err(NackReason::OutOfRange);
        }
        let k = field.seq();
        if k > st.next || (k < st.next && st.staged[k as usize] != raw) {
            return Err(NackReason::OutOfOrder);
        }
        st.staged[k as usize] = raw;
        if k == st.next {
            st.next += 1;
        }
        st.last_us = now_us;
        Ok(())
    }

    /// Verifies a `CommitAuth` against the complete staging; a failure drops the staging (a
    /// guess at the MAC costs a whole transfer).
    fn commit_auth(
        &mut self,
        session: u8,
        counter_lo: u16,
        mac: u32,
        now_us: u64,
    ) -> Result<(), NackReason> {
        let Some(key) = &self.key else {
            return Err(NackReason::NoKey);
        };
        let st = self.staging.as_mut().ok_or(NackReason::NotStaging)?;
        st.complete_in(session)?;
        st.last_us = now_us;
        let table = Table::from_raw(st.staged).map_err(|_| NackReason::OutOfRange)?;
        let verifies = |counter: Option<u32>| {
            counter.is_some_and(|c| auth::verify_commit(key, self.node, session, c, &table, mac))
        };
        let next = auth::next_counter(self.counter, counter_lo);
        if let (true, Some(counter)) = (verifies(next), next) {
            st.authorised = Some(Authorised {
                counter,
                counter_lo,
                mac,
            });
            return Ok(());
        }
        let stale = verifies(auth::previous_counter(self.counter, counter_lo));
        self.staging = None;
        Err(if stale {
            NackReason::StaleCounter
        } else {
            NackReason::BadMac
        })
    }

    fn commit<S: TableStorage>(
        &mut self,
        session: u8,
        crc: u32,
        storage: &mut S,
    ) -> Result<(), NackReason> {
        if self.key.is_none() {
            return Err(NackReason::NoKey);
        }
        let Some(st) = self.staging else {
            // A repeated Commit whose ACK was lost: idempotent.
            if self.last_commit == Some((session, crc)) && self.held_crc() == crc {
                return Ok(());
            }
            return Err(NackReason::NotStaging);
        };
        st.complete_in(session)?;
        self.staging = None;
        let table = Table::from_raw(st.staged).map_err(|_| NackReason::OutOfRange)?;
        if table.crc() != crc {
            return Err(NackReason::CrcMismatch);
        }
        let counter = st.authorised.ok_or(NackReason::BadMac)?.counter;
        // The counter first, on its own: whatever happens to the table image after this, the
        // authorisation is spent.
        storage
            .store_counter(counter)
            .map_err(|_| NackReason::FlashError)?;
        self.counter = counter;
        storage
            .store(&table, counter)
            .map_err(|_| NackReason::FlashError)?;
        self.held = Some(table);
        self.last_commit = Some((session, crc));
        Ok(())
    }
}

/// Retry policy of the controller side.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RetryPolicy {
    /// Time to wait for a reply before resending, µs.
    pub timeout_us: u64,
    /// Sends of one command before giving up.
    pub max_attempts: u32,
    /// Restarts from Begin after a NACK before giving up.
    pub max_restarts: u32,
}

impl Default for RetryPolicy {
    fn default() -> Self {
        RetryPolicy {
            timeout_us: 50_000,
            max_attempts: 5,
            max_restarts: 3,
        }
    }
}

/// Why an upload failed. The node then holds its old table (or, after a lost final ACK
/// sequence, possibly the new one: [`Upload::held_crc`] says which, when known).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum UploadError {
    /// No reply to this command after all attempts.
    Timeout(CmdCode),
    /// Refused too many times; the last refusal.
    Nacked(CmdCode, NackReason),
    /// Commit was acknowledged with a CRC other than the table's.
    CommitCrc(u32),
    /// The table read back differs from the one sent (authenticated: the node holds another
    /// table).
    ReadbackMismatch,
    /// Answers to this command came, but none carried a MAC that verifies (forged or garbled),
    /// or [`MAX_BAD_ANSWERS`] did not.
    BadAnswer(CmdCode),
    /// The node's authenticated counter is outside the window the controller allowed
    /// ([`Upload::with_counter_window`]): it went back (its storage lost it), or it is ahead of
    /// every counter this controller signed (another key holder committed to it). Nothing was
    /// signed.
    Counter {
        /// The node's counter (from an answer whose MAC verified).
        counter: u32,
        /// The lowest counter allowed.
        low: u32,
        /// The highest counter allowed.
        high: u32,
    },
}

impl core::fmt::Display for UploadError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            UploadError::Timeout(c) => write!(f, "no reply to {c:?}"),
            UploadError::Nacked(c, r) => write!(f, "{c:?} refused: {r:?}"),
            UploadError::CommitCrc(crc) => write!(
                f,
                "commit acknowledged with CRC {crc:#010x}, not the table's"
            ),
            UploadError::ReadbackMismatch => {
                f.write_str("table read back differs from the table sent")
            }
            UploadError::BadAnswer(c) => write!(
                f,
                "no answer to {c:?} with a valid MAC (forged or garbled replies)"
            ),
            UploadError::Counter { counter, low, high } if counter < low => write!(
                f,
                "the node's authenticated freshness counter {counter} is below {low}, the last \
                 this controller verified: its storage lost the counter (re-provision the node \
                 with a new key); nothing was signed"
            ),
            UploadError::Counter { counter, high, .. } => write!(
                f,
                "the node's authenticated freshness counter {counter} is above {high}, the \
                 highest this controller signed: another holder of its key committed to it, or \
                 the state directory is not this suit's; nothing was signed"
            ),
        }
    }
}

/// What a readback has gathered so far.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
struct Answer {
    fields: [Option<i64>; 6],
    mac: Option<u32>,
    ack_crc: Option<u32>,
}

/// What a keyed node's answer to Begin has brought so far (from any resend: one nonce for all).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
struct Fresh {
    counter: Option<u32>,
    mac: Option<u32>,
    ack_crc: Option<u32>,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Step {
    Send(Command),
    Readback(Answer),
    Done(Result<u32, UploadError>),
}

/// The controller's side of authentication: the node's key and what it has learnt.
#[derive(Clone, Debug, PartialEq, Eq)]
struct UploadAuth {
    key: Key,
    /// The nonce of the current Begin or readback (kept over its resends, so that the pieces
    /// of the answer may come from different resends: they all answer the same nonce).
    nonce: Option<u32>,
    /// The current Begin's answer, while incomplete.
    fresh: Fresh,
    /// Answers to the current command whose MAC did not verify.
    bad_answers: u32,
    /// The counters the node may have (inclusive), if the caller knows.
    window: Option<(u32, u32)>,
    /// The node's counter, from its last answer to Begin whose MAC verified.
    verified: Option<u32>,
    /// The counter of the `CommitAuth` signed.
    signed: Option<u32>,
    /// The CRC the node held in its last answer whose MAC verified (Begin or readback).
    verified_crc: Option<u32>,
    /// The caller's random seed for the nonces ([`Upload::seeded`]).
    seed: u64,
}

/// Controller side: pushes one table to one node, then verifies it by readback.
///
/// Drive it with [`Upload::poll`] (what to send now, if anything) and [`Upload::on_reply`];
/// [`Upload::outcome`] is `Some` once finished: `Ok(crc)` means the node acknowledged the
/// commit with the table's CRC and read it back identically (for an
/// [`Upload::authenticated`] one: in an answer whose MAC verifies).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Upload {
    node: NodeId,
    session: u8,
    table: Table,
    policy: RetryPolicy,
    step: Step,
    attempts: u32,
    restarts: u32,
    deadline_us: Option<u64>,
    held_crc: Option<u32>,
    auth: Option<UploadAuth>,
    /// Only the readback ([`Upload::verify`]): a NACK ends it instead of restarting a transfer.
    verify_only: bool,
}

/// `Begin` as stored in a step; its nonce is filled in when sent ([`Upload::current`]).
const BEGIN: Command = Command::Begin { nonce: 0 };

impl Upload {
    /// A new upload of `table` to `node` in `session` (choose a fresh session per upload),
    /// unauthenticated (protocol `exocal-1`: nodes of `exocal-3` refuse its Commit).
    pub fn new(node: NodeId, session: u8, table: Table, policy: RetryPolicy) -> Self {
        Upload {
            node,
            session,
            table,
            policy,
            step: Step::Send(BEGIN),
            attempts: 0,
            restarts: 0,
            deadline_us: None,
            held_crc: None,
            auth: None,
            verify_only: false,
        }
    }

    /// An authenticated upload to a node holding `key`: the node's counter only from an answer
    /// to Begin whose MAC verifies over our nonce, `CommitAuth` above it before `Commit`, and
    /// success only on a readback answer whose MAC verifies.
    pub fn authenticated(
        node: NodeId,
        session: u8,
        table: Table,
        policy: RetryPolicy,
        key: Key,
    ) -> Self {
        let mut up = Upload::new(node, session, table, policy);
        up.auth = Some(UploadAuth {
            key,
            nonce: None,
            fresh: Fresh::default(),
            bad_answers: 0,
            window: None,
            verified: None,
            signed: None,
            verified_crc: None,
            seed: 0,
        });
        up
    }

    /// Seeds the nonces of an authenticated upload with `seed`, which the caller draws from the
    /// OS random source ([`auth::nonce`]): without it a nonce is a MAC of the node, session and
    /// clock alone, which repeat across boots of a controller without a real-time clock.
    pub fn seeded(mut self, seed: u64) -> Self {
        if let Some(a) = self.auth.as_mut() {
            a.seed = seed;
        }
        self
    }

    /// Refuses (before signing anything, [`UploadError::Counter`]) a node whose authenticated
    /// counter is not within `low..=high`: the last counter the caller verified for it, and the
    /// highest it signed. No effect on an unauthenticated upload.
    pub fn with_counter_window(mut self, low: u32, high: u32) -> Self {
        if let Some(a) = self.auth.as_mut() {
            a.window = Some((low, high.max(low)));
        }
        self
    }

    /// Only the readback of an upload (authenticated when `key` is given): `Ok(crc)` if the
    /// node holds `table`, [`UploadError::ReadbackMismatch`] if it holds another one, a NACK
    /// (`NoTable`) ends it.
    pub fn verify(
        node: NodeId,
        session: u8,
        table: Table,
        policy: RetryPolicy,
        key: Option<Key>,
    ) -> Self {
        let mut up = match key {
            Some(key) => Upload::authenticated(node, session, table, policy, key),
            None => Upload::new(node, session, table, policy),
        };
        up.step = Step::Readback(Answer::default());
        up.verify_only = true;
        up
    }

    /// The node addressed.
    pub fn node(&self) -> NodeId {
        self.node
    }

    /// The result, once finished.
    pub fn outcome(&self) -> Option<Result<u32, UploadError>> {
        match self.step {
            Step::Done(r) => Some(r),
            _ => None,
        }
    }

    /// The CRC of the table the node last said it holds (unauthenticated: a forger can make it
    /// say anything; see [`Upload::verified_crc`]).
    pub fn held_crc(&self) -> Option<u32> {
        self.held_crc
    }

    /// The CRC of the table the node held in its last answer whose MAC verified (to Begin or to
    /// the readback); `None` unauthenticated or before one.
    pub fn verified_crc(&self) -> Option<u32> {
        self.auth.as_ref().and_then(|a| a.verified_crc)
    }

    /// The node's freshness counter from its last answer to Begin whose MAC verified.
    pub fn verified_counter(&self) -> Option<u32> {
        self.auth.as_ref().and_then(|a| a.verified)
    }

    /// The counter of the `CommitAuth` this upload signed, once it did (a caller keeping the
    /// highest signed counter records it before the `CommitAuth` goes out: [`Upload::poll`]
    /// returns that frame with it set).
    pub fn signed_counter(&self) -> Option<u32> {
        self.auth.as_ref().and_then(|a| a.signed)
    }

    fn current(&self) -> Option<Command> {
        let nonce = self.auth.as_ref().and_then(|a| a.nonce).unwrap_or(0);
        match self.step {
            Step::Send(Command::Begin { .. }) => Some(Command::Begin { nonce }),
            Step::Send(c) => Some(c),
            Step::Readback(_) => Some(Command::Readback { nonce }),
            Step::Done(_) => None,
        }
    }

    /// The command to send at `now_us`, if one is due (first send or a resend after timeout).
    pub fn poll(&mut self, now_us: u64) -> Option<TableCmd> {
        let code = self.current()?.code();
        if self.deadline_us.is_some_and(|d| now_us < d) {
            return None;
        }
        if self.attempts >= self.policy.max_attempts {
            let bad = self.auth.as_ref().is_some_and(|a| a.bad_answers > 0);
            let error = if bad && matches!(code, CmdCode::Readback | CmdCode::Begin) {
                UploadError::BadAnswer(code)
            } else {
                UploadError::Timeout(code)
            };
            self.step = Step::Done(Err(error));
            return None;
        }
        self.attempts += 1;
        self.deadline_us = Some(now_us.saturating_add(self.policy.timeout_us));
        let (node, session) = (self.node, self.session);
        match (&mut self.step, self.auth.as_mut()) {
            (Step::Readback(answer), None) => *answer = Answer::default(),
            (Step::Readback(_) | Step::Send(Command::Begin { .. }), Some(a)) => {
                a.nonce
                    .get_or_insert_with(|| auth::nonce(&a.key, node, session, a.seed, now_us));
            }
            _ => {}
        }
        Some(TableCmd {
            node,
            session,
            cmd: self.current()?,
        })
    }

    fn advance(&mut self, step: Step) {
        self.step = step;
        self.attempts = 0;
        self.deadline_us = None;
        if let Some(a) = self.auth.as_mut() {
            a.nonce = None;
            a.fresh = Fresh::default();
            a.bad_answers = 0;
        }
    }

    /// The step after the last segment: `CommitAuth` (with the counter above the node's) when
    /// authenticated, else `Commit`.
    fn after_segments(&mut self) -> Step {
        let (node, session, table) = (self.node, self.session, self.table);
        let Some(a) = self.auth.as_mut() else {
            return Step::Send(Command::Commit { crc: table.crc() });
        };
        match a.verified.and_then(|c| c.checked_add(1)) {
            Some(counter) => {
                a.signed = Some(counter);
                Step::Send(Command::CommitAuth {
                    counter_lo: counter as u16,
                    mac: auth::commit_mac(&a.key, node, session, counter, &table),
                })
            }
            None => Step::Done(Err(UploadError::Nacked(
                CmdCode::CommitAuth,
                NackReason::StaleCounter,
            ))),
        }
    }

    /// Feeds a reply from the bus; replies of other nodes, other sessions or other commands
    /// are ignored.
    pub fn on_reply(&mut self, reply: &TableReply) {
        if reply.node != self.node || reply.session != self.session {
            return;
        }
        let Some(current) = self.current() else {
            return;
        };
        match reply.reply {
            Reply::Readback(field, raw) => {
                if let Step::Readback(answer) = &mut self.step {
                    answer.fields[field as usize] = Some(raw);
                    self.judge_answer();
                }
            }
            Reply::ReadbackMac { mac } => {
                if let Step::Readback(answer) = &mut self.step {
                    answer.mac = Some(mac);
                    self.judge_answer();
                }
            }
            Reply::Freshness { counter } => {
                if let (Command::Begin { .. }, Some(a)) = (current, self.auth.as_mut()) {
                    a.fresh.counter = Some(counter);
                    self.judge_freshness();
                }
            }
            Reply::FreshnessMac { mac } => {
                if let (Command::Begin { .. }, Some(a)) = (current, self.auth.as_mut()) {
                    a.fresh.mac = Some(mac);
                    self.judge_freshness();
                }
            }
            Reply::Ack { cmd, held_crc } if cmd == current.code() => match current {
                Command::Begin { .. } => {
                    self.held_crc = Some(held_crc);
                    match self.auth.as_mut() {
                        Some(a) => {
                            a.fresh.ack_crc = Some(held_crc);
                            self.judge_freshness();
                        }
                        None => self.advance(Self::first_segment(&self.table)),
                    }
                }
                Command::Readback { .. } => {
                    self.held_crc = Some(held_crc);
                    if let Step::Readback(answer) = &mut self.step {
                        answer.ack_crc = Some(held_crc);
                        self.judge_answer();
                    }
                }
                _ => {
                    self.held_crc = Some(held_crc);
                    let next = match current {
                        Command::Segment(f, _) => match Field::from_seq(f.seq() + 1) {
                            Some(n) => Step::Send(Command::Segment(n, self.table.raw(n))),
                            None => self.after_segments(),
                        },
                        Command::CommitAuth { .. } => Step::Send(Command::Commit {
                            crc: self.table.crc(),
                        }),
                        Command::Commit { crc } if held_crc != crc => {
                            Step::Done(Err(UploadError::CommitCrc(held_crc)))
                        }
                        Command::Commit { .. } => Step::Readback(Answer::default()),
                        _ => Step::Done(Err(UploadError::Nacked(
                            CmdCode::Abort,
                            NackReason::NotStaging,
                        ))),
                    };
                    self.advance(next);
                }
            },
            Reply::Nack {
                cmd,
                held_crc,
                reason,
            } if cmd == current.code() => {
                self.held_crc = Some(held_crc);
                let hopeless = matches!(reason, NackReason::NoKey);
                if self.restarts >= self.policy.max_restarts || self.verify_only || hopeless {
                    self.advance(Step::Done(Err(UploadError::Nacked(cmd, reason))));
                } else {
                    self.restarts += 1;
                    self.advance(Step::Send(BEGIN));
                }
            }
            _ => {}
        }
    }

    fn first_segment(table: &Table) -> Step {
        Step::Send(Command::Segment(Field::A, table.raw(Field::A)))
    }

    /// One more answer whose MAC did not verify: judged, and the upload gives up after
    /// [`MAX_BAD_ANSWERS`] of them for one command.
    fn bad_answer(&mut self, code: CmdCode) {
        let Some(a) = self.auth.as_mut() else {
            return;
        };
        a.bad_answers += 1;
        if a.bad_answers >= MAX_BAD_ANSWERS {
            self.advance(Step::Done(Err(UploadError::BadAnswer(code))));
        }
    }

    /// Decides an authenticated Begin once its answer is complete (counter, MAC and ACK, from
    /// any of its resends): a MAC that does not verify drops the answer (the upload waits for
    /// a resend's); a verified counter outside the window ends the upload before anything is
    /// signed; else on to the first segment.
    fn judge_freshness(&mut self) {
        let (node, session) = (self.node, self.session);
        let Some(a) = self.auth.as_mut() else {
            return;
        };
        let (Some(counter), Some(mac), Some(crc), Some(nonce)) =
            (a.fresh.counter, a.fresh.mac, a.fresh.ack_crc, a.nonce)
        else {
            return;
        };
        a.fresh = Fresh::default();
        if !auth::verify_freshness(&a.key, node, session, nonce, counter, crc, mac) {
            self.bad_answer(CmdCode::Begin);
            return;
        }
        a.verified = Some(counter);
        a.verified_crc = Some(crc);
        if let Some((low, high)) = a.window {
            if counter < low || counter > high {
                let error = UploadError::Counter { counter, low, high };
                self.advance(Step::Done(Err(error)));
                return;
            }
        }
        self.advance(Self::first_segment(&self.table));
    }

    /// Decides the readback once its answer is complete: for an unauthenticated upload at the
    /// ACK; for an authenticated one when the six fields, the MAC and the ACK are in, from any
    /// of the readback's resends (one nonce for all). An answer whose MAC does not verify is
    /// dropped (the upload waits for a resend's answer, at most [`MAX_BAD_ANSWERS`] times).
    fn judge_answer(&mut self) {
        let Step::Readback(answer) = self.step else {
            return;
        };
        let Some(ack_crc) = answer.ack_crc else {
            return;
        };
        let fields: Option<[i64; 6]> = answer
            .fields
            .iter()
            .copied()
            .collect::<Option<heapless::Vec<i64, 6>>>()
            .and_then(|v| v.into_array().ok());
        let held = fields.and_then(|raw| Table::from_raw(raw).ok());
        let (node, table) = (self.node, self.table);
        if let Some(a) = self.auth.as_mut() {
            let (Some(held), Some(mac), Some(nonce)) = (held, answer.mac, a.nonce) else {
                return;
            };
            if !auth::verify_readback(&a.key, node, nonce, ack_crc, &held.to_bytes(), mac) {
                self.step = Step::Readback(Answer::default());
                self.bad_answer(CmdCode::Readback);
                return;
            }
            a.verified_crc = Some(ack_crc);
        }
        let result = if held == Some(table) && ack_crc == table.crc() {
            Ok(ack_crc)
        } else {
            Err(UploadError::ReadbackMismatch)
        };
        self.advance(Step::Done(result));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// A node's storage: the table image (table and the counter written with it) and the
    /// counter record kept apart from it.
    #[derive(Default)]
    struct Flash {
        table: Option<Table>,
        counter: u32,
        record: u32,
        fail: bool,
    }
    impl TableStorage for Flash {
        fn store_counter(&mut self, counter: u32) -> Result<(), StorageError> {
            if self.fail {
                return Err(StorageError);
            }
            self.record = counter;
            Ok(())
        }
        fn store(&mut self, table: &Table, counter: u32) -> Result<(), StorageError> {
            if self.fail {
                return Err(StorageError);
            }
            self.table = Some(*table);
            self.counter = counter;
            Ok(())
        }
    }

    fn key() -> Key {
        crate::auth::KeySet::derived(3).node(NODE).unwrap().clone()
    }

    /// Flash holding `t`, its image's counter at `counter` and its counter record at `record`.
    fn holding(t: Table, counter: u32, record: u32) -> Flash {
        Flash {
            table: Some(t),
            counter,
            record,
            fail: false,
        }
    }

    /// A node booted from `flash`, holding [`key`], its counter the higher of the record and
    /// the image's.
    fn boot(flash: &Flash) -> NodeTransfer {
        NodeTransfer::new(NODE, flash.table).with_key(key(), flash.counter.max(flash.record))
    }

    const NODE: NodeId = NodeId::JOINTS[2];

    fn old() -> Table {
        Table::from_si(0.431, 1.2345678, 0.0, 0.0, 1.0, 1.0).unwrap()
    }
    fn new() -> Table {
        Table::from_si(0.401, 1.2345678, 0.001, 0.01, 1.0, 1.0).unwrap()
    }

    fn cmd(session: u8, cmd: Command) -> TableCmd {
        TableCmd {
            node: NODE,
            session,
            cmd,
        }
    }

    /// Begin, the six segments and Commit of `t` in `session`, without a `CommitAuth`.
    fn plain(t: &Table, session: u8) -> Vec<TableCmd> {
        let mut cmds = vec![Command::Begin { nonce: 0x0b }];
        cmds.extend(Field::ALL.map(|f| Command::Segment(f, t.raw(f))));
        cmds.push(Command::Commit { crc: t.crc() });
        cmds.into_iter().map(|c| cmd(session, c)).collect()
    }

    /// The commands of one authenticated transfer of `t` in `session` with `counter`, signed
    /// with `key`: Begin, six segments, CommitAuth, Commit.
    fn signed(t: &Table, session: u8, counter: u32, key: &Key) -> Vec<TableCmd> {
        let mut cmds = plain(t, session);
        let mac = crate::auth::commit_mac(key, NODE, session, counter, t);
        let auth = Command::CommitAuth {
            counter_lo: counter as u16,
            mac,
        };
        cmds.insert(7, cmd(session, auth));
        cmds
    }

    /// [`signed`] with [`key`].
    fn transfer(t: &Table, session: u8, counter: u32) -> Vec<TableCmd> {
        signed(t, session, counter, &key())
    }

    /// Delivers `cmds` to a node booted from `flash`, rebooting (rebuilding from flash) just
    /// before command index `reboot_at`; returns the table installed at the end.
    fn run(cmds: &[TableCmd], reboot_at: Option<usize>, flash: &mut Flash) -> Option<Table> {
        let mut node = boot(flash);
        for (i, c) in cmds.iter().enumerate() {
            if reboot_at == Some(i) {
                node = boot(flash);
            }
            node.handle(c, i as u64 * 1000, flash);
        }
        assert_eq!(node.held().copied(), flash.table, "RAM and flash agree");
        node.held().copied()
    }

    #[test]
    fn exhaustive_over_delivered_subsets_and_reboots() {
        let full = transfer(&new(), 7, 1);
        // Every subset of the 9 frames (in order), with no reboot or a reboot before any of them
        // (or at the end): the new table is installed iff all nine frames arrived within one
        // boot of the node.
        for mask in 0u32..512 {
            let delivered: Vec<(usize, TableCmd)> = full
                .iter()
                .copied()
                .enumerate()
                .filter(|(i, _)| mask >> i & 1 == 1)
                .collect();
            for reboot in std::iter::once(None).chain((0..=delivered.len()).map(Some)) {
                let mut flash = holding(old(), 0, 0);
                let cmds: Vec<TableCmd> = delivered.iter().map(|(_, c)| *c).collect();
                let got = run(&cmds, reboot, &mut flash);
                let split = reboot.unwrap_or(0);
                let complete = split == 9 || delivered.len() - split == 9;
                let want = if complete { new() } else { old() };
                assert_eq!(got, Some(want), "mask {mask:09b} reboot {reboot:?}");
            }
        }
    }

    #[test]
    fn every_prefix_leaves_the_old_table_and_the_node_can_continue_after() {
        let full = transfer(&new(), 1, 1);
        for p in 0..9 {
            let mut flash = holding(old(), 0, 0);
            assert_eq!(run(&full[..p], None, &mut flash), Some(old()), "prefix {p}");
            // Then a complete second transfer still works.
            let mut node = boot(&flash);
            for c in full[..p].iter().chain(transfer(&new(), 2, 1).iter()) {
                node.handle(c, 0, &mut flash);
            }
            assert_eq!(node.held(), Some(&new()));
        }
    }

    #[test]
    fn commit_with_wrong_crc_or_failing_flash_keeps_the_old_table() {
        let mut wrong_crc = transfer(&new(), 1, 1);
        wrong_crc[8].cmd = Command::Commit {
            crc: new().crc() ^ 1,
        };
        for (cmds, fail, reason) in [
            (wrong_crc, false, NackReason::CrcMismatch),
            (transfer(&new(), 1, 1), true, NackReason::FlashError),
        ] {
            let mut flash = Flash {
                fail,
                ..holding(old(), 0, 0)
            };
            let mut node = boot(&flash);
            assert_eq!(deliver(&mut node, &cmds, &mut flash), refused(reason));
            assert_eq!(node.held(), Some(&old()));
        }
    }

    #[test]
    fn foreign_session_segments_and_stale_staging_are_refused() {
        let mut flash = holding(old(), 0, 0);
        let mut node = boot(&flash);
        let a = transfer(&new(), 1, 1);
        let b = transfer(&new(), 2, 1);
        node.handle(&a[0], 0, &mut flash);
        let r = node.handle(&b[1], 0, &mut flash);
        assert!(matches!(
            r.last().unwrap().reply,
            Reply::Nack {
                reason: NackReason::BadSession,
                ..
            }
        ));
        node.handle(&a[1], 0, &mut flash);
        let r = node.handle(&a[2], STAGING_TIMEOUT_US + 1, &mut flash);
        assert!(matches!(
            r[0].reply,
            Reply::Nack {
                reason: NackReason::NotStaging,
                ..
            }
        ));
        assert!(!node.is_staging(STAGING_TIMEOUT_US + 1));
    }

    #[test]
    fn readback_returns_the_held_table_then_an_ack() {
        let mut flash = Flash::default();
        let rb = cmd(9, Command::Readback { nonce: 1 });
        // A node without a key still tells what it holds, unsigned.
        let mut node = NodeTransfer::new(NODE, None);
        let r = node.handle(&rb, 0, &mut flash);
        assert!(matches!(
            r[..],
            [TableReply {
                reply: Reply::Nack {
                    reason: NackReason::NoTable,
                    held_crc: 0,
                    ..
                },
                ..
            }]
        ));
        let mut node = NodeTransfer::new(NODE, Some(new()));
        let r = node.handle(&rb, 0, &mut flash);
        assert_eq!(r.len(), 7);
        for f in Field::ALL {
            assert_eq!(r[f as usize].reply, Reply::Readback(f, new().raw(f)));
        }
        assert_eq!(
            r[6].reply,
            Reply::Ack {
                cmd: CmdCode::Readback,
                held_crc: new().crc()
            }
        );
    }

    /// A lossy, duplicating, reordering channel between an [`Upload`] and a node that may reboot.
    fn simulate(
        ops: &[(u8, u8)],
        loss_pct: u8,
    ) -> (Option<Result<u32, UploadError>>, Option<Table>) {
        let mut flash = holding(old(), 41, 0);
        let mut node = boot(&flash);
        let policy = RetryPolicy {
            timeout_us: 10_000,
            max_attempts: 8,
            max_restarts: 4,
        };
        let mut up = Upload::authenticated(NODE, 3, new(), policy, key());
        let mut to_node: Vec<TableCmd> = Vec::new();
        let mut to_ctrl: Vec<TableReply> = Vec::new();
        let mut now = 0u64;
        for (i, &(op, r)) in ops.iter().enumerate() {
            now += 1_000 * u64::from(op % 7);
            if let Some(c) = up.poll(now) {
                to_node.push(c);
            }
            match op % 5 {
                0 if r % 40 == 0 => node = boot(&flash), // reboot
                1 if !to_node.is_empty() => {
                    let k = usize::from(r) % to_node.len();
                    to_node.swap(0, k) // reorder
                }
                2 if !to_node.is_empty() => to_node.push(to_node[0]), // duplicate
                _ => {}
            }
            if !to_node.is_empty() {
                let c = to_node.remove(0);
                if r % 100 >= loss_pct {
                    to_ctrl.extend(node.handle(&c, now, &mut flash));
                }
            }
            while !to_ctrl.is_empty() {
                let rep = to_ctrl.remove(0);
                if (r.wrapping_add(i as u8)) % 100 >= loss_pct {
                    up.on_reply(&rep);
                }
            }
            if up.outcome().is_some() {
                break;
            }
        }
        (up.outcome(), node.held().copied())
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(2000))]
        #[test]
        fn lossy_channel_never_leaves_a_mixed_table(ops in prop::collection::vec((any::<u8>(), any::<u8>()), 0..400), loss in 0u8..40) {
            let (outcome, held) = simulate(&ops, loss);
            prop_assert!(held == Some(old()) || held == Some(new()), "held {:?}", held);
            if let Some(Ok(crc)) = outcome {
                prop_assert_eq!(crc, new().crc());
                prop_assert_eq!(held, Some(new()));
            }
        }
    }

    #[test]
    fn clean_channel_upload_succeeds_and_verifies() {
        let ops: Vec<(u8, u8)> = (0..200).map(|_| (3, 50)).collect();
        let (outcome, held) = simulate(&ops, 0);
        assert_eq!(outcome, Some(Ok(new().crc())));
        assert_eq!(held, Some(new()));
    }

    #[test]
    fn silent_node_times_out_naming_the_command() {
        let mut up = Upload::new(
            NODE,
            1,
            new(),
            RetryPolicy {
                timeout_us: 10,
                max_attempts: 3,
                max_restarts: 0,
            },
        );
        let mut sent = 0;
        for t in 0..100 {
            sent += usize::from(up.poll(t).is_some());
        }
        assert_eq!(sent, 3);
        assert_eq!(
            up.outcome(),
            Some(Err(UploadError::Timeout(CmdCode::Begin)))
        );
    }

    /// Delivers `cmds` to `node`; returns the last reply.
    fn deliver(node: &mut NodeTransfer, cmds: &[TableCmd], flash: &mut Flash) -> Reply {
        let mut last = None;
        for c in cmds {
            last = node.handle(c, 0, flash).last().map(|r| r.reply);
        }
        last.expect("a reply")
    }

    fn refused(reason: NackReason) -> Reply {
        Reply::Nack {
            cmd: CmdCode::Commit,
            held_crc: old().crc(),
            reason,
        }
    }

    #[test]
    fn a_keyed_node_installs_only_authenticated_fresh_tables() {
        let mut flash = holding(old(), 0x1_fff0, 0);
        let mut node = boot(&flash);
        // (a) a well-formed transfer with the right CRC and no CommitAuth.
        let plain = plain(&new(), 1);
        assert_eq!(
            deliver(&mut node, &plain, &mut flash),
            refused(NackReason::BadMac)
        );
        // (a) the same with a CommitAuth whose MAC is wrong (another key, or one bit off).
        let other = crate::auth::KeySet::derived(4).node(NODE).unwrap().clone();
        let forged = signed(&new(), 2, 0x1_fff1, &other);
        let r = node.handle(&forged[0], 0, &mut flash);
        assert_eq!(r[0].reply, Reply::Freshness { counter: 0x1_fff0 });
        for c in &forged[1..7] {
            node.handle(c, 0, &mut flash);
        }
        let r = node.handle(&forged[7], 0, &mut flash);
        assert_eq!(
            r[0].reply,
            Reply::Nack {
                cmd: CmdCode::CommitAuth,
                held_crc: old().crc(),
                reason: NackReason::BadMac
            }
        );
        // The failed CommitAuth dropped the staging: the Commit finds none.
        assert_eq!(
            node.handle(&forged[8], 0, &mut flash)[0].reply,
            refused(NackReason::NotStaging)
        );
        let mut flipped = signed(&new(), 3, 0x1_fff1, &key());
        if let Command::CommitAuth { mac, .. } = &mut flipped[7].cmd {
            *mac ^= 1 << 17;
        }
        deliver(&mut node, &flipped, &mut flash);
        // (c) a valid MAC for a counter at or below the stored one.
        for stale in [0x1_fff0, 0x1_ffef, 0x1] {
            let r = deliver(&mut node, &signed(&new(), 4, stale, &key()), &mut flash);
            assert!(
                matches!(
                    r,
                    Reply::Nack {
                        reason: NackReason::NotStaging | NackReason::StaleCounter,
                        ..
                    }
                ),
                "{stale:#x}: {r:?}"
            );
        }
        let mut node2 = boot(&flash);
        let stale = signed(&new(), 4, 0x1_fff0, &key());
        for c in &stale[..7] {
            node2.handle(c, 0, &mut flash);
        }
        assert_eq!(
            node2.handle(&stale[7], 0, &mut flash)[0].reply,
            Reply::Nack {
                cmd: CmdCode::CommitAuth,
                held_crc: old().crc(),
                reason: NackReason::StaleCounter
            }
        );
        assert_eq!((flash.table, flash.counter), (Some(old()), 0x1_fff0));
        assert_eq!(node.held(), Some(&old()));
        // The genuine transfer, counter across a 16-bit wrap, installs and stores the counter
        // in the same write.
        let genuine = signed(&new(), 5, 0x2_0003, &key());
        assert_eq!(
            deliver(&mut node, &genuine, &mut flash),
            Reply::Ack {
                cmd: CmdCode::Commit,
                held_crc: new().crc()
            }
        );
        assert_eq!((flash.table, flash.counter), (Some(new()), 0x2_0003));
        // (b) its replay, and the replay of an older genuine transfer, change nothing.
        let mut node = boot(&flash);
        let older = signed(&old(), 6, 0x2_0001, &key());
        for replay in [&genuine, &older] {
            deliver(&mut node, replay, &mut flash);
            assert_eq!((flash.table, flash.counter), (Some(new()), 0x2_0003));
        }
        // A repeated Commit (its ACK lost) is still acknowledged, and installs nothing.
        assert_eq!(
            node.handle(&genuine[8], 0, &mut flash)[0].reply,
            Reply::Nack {
                cmd: CmdCode::Commit,
                held_crc: new().crc(),
                reason: NackReason::NotStaging
            }
        );
    }

    #[test]
    fn a_keyed_readback_is_signed_over_the_nonce() {
        let mut flash = holding(new(), 9, 0);
        let mut node = boot(&flash);
        let rb = |nonce| TableCmd {
            node: NODE,
            session: 2,
            cmd: Command::Readback { nonce },
        };
        let r = node.handle(&rb(0xfeed), 0, &mut flash);
        assert_eq!(r.len(), 8);
        let Reply::ReadbackMac { mac } = r[6].reply else {
            panic!("{:?}", r[6]);
        };
        let t = new();
        assert!(crate::auth::verify_readback(
            &key(),
            NODE,
            0xfeed,
            t.crc(),
            &t.to_bytes(),
            mac
        ));
        let Reply::ReadbackMac { mac: other } = node.handle(&rb(0xfeee), 0, &mut flash)[6].reply
        else {
            panic!()
        };
        assert_ne!(mac, other);
    }

    /// (d) The node stays silent; a forger answers every command as the node would (it sees
    /// the table on the bus, so its CRCs and fields are right), with guessed MACs. The upload
    /// never reports success; an unauthenticated one would.
    #[test]
    fn forged_answers_never_make_an_authenticated_upload_succeed() {
        let policy = RetryPolicy {
            timeout_us: 1_000,
            max_attempts: 3,
            max_restarts: 2,
        };
        for keyed in [true, false] {
            let mut up = if keyed {
                Upload::authenticated(NODE, 7, new(), policy, key())
            } else {
                Upload::new(NODE, 7, new(), policy)
            };
            let mut guess = 0x1234_5678u32;
            for t in 0..10_000u64 {
                let Some(cmd) = up.poll(t * 100) else {
                    if up.outcome().is_some() {
                        break;
                    }
                    continue;
                };
                let forge = |reply| TableReply {
                    node: NODE,
                    session: 7,
                    reply,
                };
                let ack = Reply::Ack {
                    cmd: cmd.cmd.code(),
                    held_crc: new().crc(),
                };
                let mut replies = Vec::new();
                match cmd.cmd {
                    Command::Begin { .. } => {
                        guess = guess.wrapping_mul(0x9e37_79b9).wrapping_add(1);
                        replies.push(Reply::Freshness { counter: 5 });
                        replies.push(Reply::FreshnessMac { mac: guess });
                    }
                    Command::Readback { .. } => {
                        for f in Field::ALL {
                            replies.push(Reply::Readback(f, new().raw(f)));
                        }
                        guess = guess.wrapping_mul(0x9e37_79b9).wrapping_add(1);
                        replies.push(Reply::ReadbackMac { mac: guess });
                    }
                    _ => {}
                }
                replies.push(ack);
                for r in replies {
                    up.on_reply(&forge(r));
                }
            }
            let outcome = up.outcome();
            if keyed {
                // Its forged counter never verifies: nothing is signed, nothing succeeds.
                assert_eq!(outcome, Some(Err(UploadError::BadAnswer(CmdCode::Begin))));
                assert_eq!(up.signed_counter(), None);
            } else {
                assert_eq!(
                    outcome,
                    Some(Ok(new().crc())),
                    "the forgery works without keys"
                );
            }
        }
    }

    #[test]
    fn verify_alone_tells_new_from_old_by_an_authenticated_answer() {
        let policy = RetryPolicy::default();
        for (held, want) in [
            (new(), Ok(new().crc())),
            (old(), Err(UploadError::ReadbackMismatch)),
        ] {
            let mut flash = holding(held, 0, 0);
            let mut node = boot(&flash);
            let mut up = Upload::verify(NODE, 8, new(), policy, Some(key()));
            let cmd = up.poll(0).unwrap();
            assert!(matches!(cmd.cmd, Command::Readback { .. }));
            for r in node.handle(&cmd, 0, &mut flash) {
                up.on_reply(&r);
            }
            assert_eq!(up.outcome(), Some(want));
        }
    }
    /// No key, no commit: a node booted without one (never provisioned, or its key or counter
    /// unreadable) refuses Begin, `CommitAuth` and `Commit`, whatever they carry, and an
    /// upload to it ends at once, naming why.
    #[test]
    fn a_node_without_a_key_installs_nothing() {
        let mut flash = holding(old(), 0, 0);
        let mut node = NodeTransfer::new(NODE, flash.table);
        assert!(!node.is_keyed());
        let no_key = |cmd| Reply::Nack {
            cmd,
            held_crc: old().crc(),
            reason: NackReason::NoKey,
        };
        for cmds in [plain(&new(), 1), transfer(&new(), 2, 1)] {
            for c in &cmds {
                let r = node.handle(c, 0, &mut flash);
                match c.cmd {
                    Command::Begin { .. } | Command::CommitAuth { .. } | Command::Commit { .. } => {
                        assert_eq!(r[..].last().unwrap().reply, no_key(c.cmd.code()), "{c:?}")
                    }
                    _ => assert!(matches!(
                        r[0].reply,
                        Reply::Nack {
                            reason: NackReason::NotStaging,
                            ..
                        }
                    )),
                }
                assert_eq!(r.len(), 1, "no Freshness from a node without a key");
            }
        }
        assert_eq!(
            (flash.table, flash.counter, flash.record),
            (Some(old()), 0, 0)
        );
        for mut up in [
            Upload::new(NODE, 4, new(), RetryPolicy::default()),
            Upload::authenticated(NODE, 5, new(), RetryPolicy::default(), key()),
        ] {
            let c = up.poll(0).unwrap();
            for r in node.handle(&c, 0, &mut flash) {
                up.on_reply(&r);
            }
            assert_eq!(
                up.outcome(),
                Some(Err(UploadError::Nacked(CmdCode::Begin, NackReason::NoKey)))
            );
        }
    }

    /// The counter is written on its own before the table image, so losing the image (a
    /// corrupt sector reads as no table, counter 0) does not take it back: the genuine transfer
    /// that installed the lost table, replayed, is still stale. A counter write that fails
    /// installs nothing.
    #[test]
    fn the_counter_survives_a_lost_table_image() {
        let mut flash = holding(old(), 7, 7);
        let genuine = transfer(&new(), 1, 8);
        assert_eq!(run(&genuine, None, &mut flash), Some(new()));
        assert_eq!((flash.counter, flash.record), (8, 8));
        // The table image is lost.
        flash.table = None;
        flash.counter = 0;
        let mut node = boot(&flash);
        assert_eq!(
            node.counter(),
            8,
            "the counter comes back from its own record"
        );
        let r = deliver(&mut node, &genuine, &mut flash);
        assert!(
            matches!(
                r,
                Reply::Nack {
                    reason: NackReason::NotStaging,
                    ..
                }
            ),
            "{r:?}"
        );
        let mut node = boot(&flash);
        for c in &genuine[..7] {
            node.handle(c, 0, &mut flash);
        }
        assert_eq!(
            node.handle(&genuine[7], 0, &mut flash)[0].reply,
            Reply::Nack {
                cmd: CmdCode::CommitAuth,
                held_crc: 0,
                reason: NackReason::StaleCounter
            }
        );
        assert_eq!((flash.table, flash.record), (None, 8));
        // A counter record that cannot be written: nothing installed.
        flash.fail = true;
        let mut node = boot(&flash);
        let r = deliver(&mut node, &transfer(&old(), 2, 9), &mut flash);
        assert_eq!(
            r,
            Reply::Nack {
                cmd: CmdCode::Commit,
                held_crc: 0,
                reason: NackReason::FlashError
            }
        );
        assert_eq!((flash.table, node.held()), (None, None));
    }

    /// Once a `CommitAuth` verified, the staging waits for its Commit only: any other command
    /// on the node's identifier drops it (a Begin, a command of another session, a segment
    /// resent, a readback, an abort, another `CommitAuth`), so the authorisation cannot be
    /// completed later by whoever kept the Commit. The same `CommitAuth` again keeps it.
    #[test]
    fn an_authorised_staging_is_dropped_by_any_other_command_or_session() {
        let cmds = transfer(&new(), 1, 1);
        let mut other_auth = cmds[7];
        if let Command::CommitAuth { mac, .. } = &mut other_auth.cmd {
            *mac ^= 1;
        }
        let interlopers = [
            cmd(2, Command::Begin { nonce: 3 }),
            cmd(2, Command::Segment(Field::A, new().raw(Field::A))),
            cmd(2, Command::Abort),
            cmd(1, Command::Segment(Field::Sigma, new().raw(Field::Sigma))),
            cmd(1, Command::Readback { nonce: 4 }),
            cmd(1, Command::Abort),
            other_auth,
        ];
        for interloper in interlopers {
            let mut flash = holding(old(), 0, 0);
            let mut node = boot(&flash);
            let r = deliver(&mut node, &cmds[..8], &mut flash);
            assert_eq!(
                r,
                Reply::Ack {
                    cmd: CmdCode::CommitAuth,
                    held_crc: old().crc()
                }
            );
            node.handle(&interloper, 0, &mut flash);
            let r = node.handle(&cmds[8], 0, &mut flash);
            assert!(
                matches!(r[0].reply, Reply::Nack { .. }),
                "{interloper:?}: {r:?}"
            );
            assert_eq!(flash.table, Some(old()), "{interloper:?}");
        }
        let mut flash = holding(old(), 0, 0);
        let mut node = boot(&flash);
        deliver(&mut node, &cmds[..8], &mut flash);
        let again = deliver(&mut node, &cmds[7..], &mut flash);
        assert_eq!(
            again,
            Reply::Ack {
                cmd: CmdCode::Commit,
                held_crc: new().crc()
            }
        );
    }

    /// The rollback by an inflated freshness, with the real state machines: a sender without
    /// the key answers Begin first with `Freshness = counter + 60,000`, NACKs the `CommitAuth`
    /// and keeps the 8 frames the controller sent; two genuine pushes follow; then it replays
    /// the 8 frames and a Commit. Were the controller to sign for the forged counter, the
    /// replay would put the older table back. The forged answer does not verify (it is
    /// counted, not believed), the controller signs only the node's own counter + 1, and the
    /// replay is refused as stale: the node keeps the newest table.
    #[test]
    fn rollback_by_an_inflated_freshness_never_lands() {
        const C: u32 = 100;
        let t = |k: i64| {
            let mut raw = old().raw_values();
            raw[0] += k;
            Table::from_raw(raw).unwrap()
        };
        let (t1, t2, t3) = (t(1), t(2), t(3));
        let mut flash = holding(old(), C, C);
        let mut node = boot(&flash);
        let policy = RetryPolicy::default();
        // Push 1, the rogue on the bus: its answers reach the controller first.
        let mut up = Upload::authenticated(NODE, 1, t1, policy, key());
        let (mut kept, mut nacked, mut signed_lo) = (Vec::new(), false, Vec::new());
        let mut now = 0;
        while up.outcome().is_none() {
            now += 1_000;
            let Some(c) = up.poll(now) else { continue };
            let mut forged = Vec::new();
            match c.cmd {
                Command::Begin { .. } if !nacked => {
                    kept = vec![c];
                    forged.push(Reply::Freshness {
                        counter: C + 60_000,
                    });
                    forged.push(Reply::FreshnessMac { mac: 0xdead_beef });
                    forged.push(Reply::Ack {
                        cmd: CmdCode::Begin,
                        held_crc: old().crc(),
                    });
                }
                Command::Segment(..) if !nacked => kept.push(c),
                Command::CommitAuth { counter_lo, .. } => {
                    signed_lo.push(counter_lo);
                    if !nacked {
                        kept.push(c);
                        nacked = true;
                        forged.push(Reply::Nack {
                            cmd: CmdCode::CommitAuth,
                            held_crc: old().crc(),
                            reason: NackReason::BadSession,
                        });
                    }
                }
                _ => {}
            }
            for reply in forged {
                up.on_reply(&TableReply {
                    node: NODE,
                    session: c.session,
                    reply,
                });
            }
            for r in node.handle(&c, now, &mut flash) {
                up.on_reply(&r);
            }
        }
        assert_eq!(up.outcome(), Some(Ok(t1.crc())), "push 1 still lands");
        assert_eq!(
            kept.len(),
            8,
            "the rogue kept Begin, six segments, CommitAuth"
        );
        assert!(nacked);
        assert!(
            signed_lo.iter().all(|&lo| lo == (C + 1) as u16),
            "the controller signed only the node's counter + 1: {signed_lo:?}"
        );
        assert_eq!(up.verified_counter(), Some(C));
        // Two genuine pushes.
        for (session, table) in [(2, t2), (3, t3)] {
            let mut up = Upload::authenticated(NODE, session, table, policy, key());
            let mut now = 0;
            while up.outcome().is_none() {
                now += 1_000;
                if let Some(c) = up.poll(now) {
                    for r in node.handle(&c, now, &mut flash) {
                        up.on_reply(&r);
                    }
                }
            }
            assert_eq!(up.outcome(), Some(Ok(table.crc())));
        }
        assert_eq!((flash.table, flash.record), (Some(t3), C + 3));
        // The replay, on a live node and on one just rebooted.
        for mut target in [node.clone(), boot(&flash)] {
            let mut replies = Vec::new();
            for c in kept
                .iter()
                .chain([&cmd(1, Command::Commit { crc: t1.crc() })])
            {
                replies.extend(target.handle(c, 0, &mut flash).into_iter().map(|r| r.reply));
            }
            assert!(
                replies.contains(&Reply::Nack {
                    cmd: CmdCode::CommitAuth,
                    held_crc: t3.crc(),
                    reason: NackReason::StaleCounter
                }),
                "{replies:?}"
            );
            assert_eq!(target.held(), Some(&t3));
        }
        assert_eq!((flash.table, flash.record), (Some(t3), C + 3));
    }

    /// A window from the caller's records: a node whose authenticated counter is below the
    /// last verified one or above the highest signed is refused before anything is signed.
    #[test]
    fn a_counter_outside_the_window_is_refused_before_signing() {
        for (low, high, want) in [
            (10, 11, Ok(new().crc())),
            (
                11,
                12,
                Err(UploadError::Counter {
                    counter: 10,
                    low: 11,
                    high: 12,
                }),
            ),
            (
                5,
                9,
                Err(UploadError::Counter {
                    counter: 10,
                    low: 5,
                    high: 9,
                }),
            ),
        ] {
            let mut flash = holding(old(), 10, 10);
            let mut node = boot(&flash);
            let mut up = Upload::authenticated(NODE, 1, new(), RetryPolicy::default(), key())
                .with_counter_window(low, high);
            let mut now = 0;
            let mut auths = 0;
            while up.outcome().is_none() {
                now += 1_000;
                if let Some(c) = up.poll(now) {
                    auths += usize::from(c.cmd.code() == CmdCode::CommitAuth);
                    for r in node.handle(&c, now, &mut flash) {
                        up.on_reply(&r);
                    }
                }
            }
            assert_eq!(up.outcome(), Some(want), "{low}..={high}");
            assert_eq!(up.verified_counter(), Some(10));
            assert_eq!(auths, usize::from(want.is_ok()));
            assert_eq!(up.signed_counter(), want.ok().map(|_| 11));
        }
    }

    /// Each answer whose MAC does not verify is a guess at it: an upload judges at most
    /// [`MAX_BAD_ANSWERS`] per Begin and per readback, then fails, however many arrive.
    #[test]
    fn bad_answers_are_judged_at_most_max_bad_answers_times() {
        let forged_begin = |mac| {
            [
                Reply::Freshness { counter: 3 },
                Reply::FreshnessMac { mac },
                Reply::Ack {
                    cmd: CmdCode::Begin,
                    held_crc: 1,
                },
            ]
        };
        let mut up = Upload::authenticated(NODE, 1, new(), RetryPolicy::default(), key());
        up.poll(0).unwrap();
        for guess in 0..1_000u32 {
            for reply in forged_begin(guess) {
                up.on_reply(&TableReply {
                    node: NODE,
                    session: 1,
                    reply,
                });
            }
            let done = up.outcome().is_some();
            assert_eq!(
                done,
                guess + 1 >= MAX_BAD_ANSWERS,
                "after {} guesses",
                guess + 1
            );
            if done {
                break;
            }
        }
        assert_eq!(
            up.outcome(),
            Some(Err(UploadError::BadAnswer(CmdCode::Begin)))
        );

        let mut up = Upload::verify(NODE, 2, new(), RetryPolicy::default(), Some(key()));
        up.poll(0).unwrap();
        let mut judged = 0;
        for guess in 0..1_000u32 {
            if up.outcome().is_some() {
                break;
            }
            judged += 1;
            let replies = Field::ALL
                .map(|f| Reply::Readback(f, new().raw(f)))
                .into_iter()
                .chain([
                    Reply::ReadbackMac { mac: guess },
                    Reply::Ack {
                        cmd: CmdCode::Readback,
                        held_crc: new().crc(),
                    },
                ]);
            for reply in replies {
                up.on_reply(&TableReply {
                    node: NODE,
                    session: 2,
                    reply,
                });
            }
        }
        assert_eq!(judged, MAX_BAD_ANSWERS);
        assert_eq!(
            up.outcome(),
            Some(Err(UploadError::BadAnswer(CmdCode::Readback)))
        );
    }
}
