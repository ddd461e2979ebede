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
//! # Authentication (a node holding a key, [`NodeTransfer::with_key`])
//! Such a node answers `Begin` with its stored freshness counter ([`Reply::Freshness`]) before
//! the ACK, and installs a table only after a `CommitAuth(counter_lo, mac)` whose MAC
//! ([`crate::auth::commit_mac`]) verifies for the staged table, this session and the full
//! counter the low bits stand for ([`crate::auth::next_counter`]: above the stored one). A plain
//! Commit, a wrong MAC or a stale counter is NACKed (`BadMac`, `StaleCounter`) and the staging
//! dropped; the counter is stored with the table in one storage write
//! ([`TableStorage::store`]), so a recorded transfer never installs twice. Its readback carries
//! [`Reply::ReadbackMac`] over the controller's nonce, the held CRC and the table
//! ([`crate::auth::readback_mac`]) before the ACK; an authenticated [`Upload`] reports success
//! only on such an answer, so forged replies can make it fail but never succeed. A node without
//! a key behaves as protocol version 1 (benches without keys).

use crate::auth::{self, Key};
use crate::message::{CmdCode, Command, NackReason, Reply, TableCmd, TableReply};
use crate::table::{Field, Table};
use crate::NodeId;

/// A staging area untouched for this long is dropped.
pub const STAGING_TIMEOUT_US: u64 = 5_000_000;

/// Persistent storage of the installed table (emulated flash in the hil, real flash on a node).
pub trait TableStorage {
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

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Staging {
    session: u8,
    staged: [i64; 6],
    next: u8,
    last_us: u64,
    /// The counter a verified `CommitAuth` authorised this staging for.
    authorised: Option<u32>,
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
    /// A freshly booted node holding `held` (as read from its storage), without a key.
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

    /// The same node holding `key`, with the freshness `counter` its storage holds: it then
    /// installs only authenticated tables and signs its readbacks (see the module docs).
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
        let session = cmd.session;
        let code = cmd.cmd.code();
        let reply = match cmd.cmd {
            Command::Begin => {
                self.staging = Some(Staging {
                    session,
                    staged: [0; 6],
                    next: 0,
                    last_us: now_us,
                    authorised: None,
                });
                if self.key.is_some() {
                    let counter = self.counter;
                    let _ = out.push(self.reply(session, Reply::Freshness { counter }));
                }
                Ok(())
            }
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
        let st = self.staging.as_mut().ok_or(NackReason::NotStaging)?;
        if st.session != session {
            return Err(NackReason::BadSession);
        }
        if st.next < 6 {
            return Err(NackReason::Incomplete);
        }
        st.last_us = now_us;
        let Some(key) = &self.key else {
            // Without a key there is nothing to check: protocol version 1.
            return Ok(());
        };
        let table = Table::from_raw(st.staged).map_err(|_| NackReason::OutOfRange)?;
        let verifies = |counter: Option<u32>| {
            counter.is_some_and(|c| auth::verify_commit(key, self.node, session, c, &table, mac))
        };
        let next = auth::next_counter(self.counter, counter_lo);
        if verifies(next) {
            st.authorised = next;
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
        let Some(st) = self.staging else {
            // A repeated Commit whose ACK was lost: idempotent.
            if self.last_commit == Some((session, crc)) && self.held_crc() == crc {
                return Ok(());
            }
            return Err(NackReason::NotStaging);
        };
        if st.session != session {
            return Err(NackReason::BadSession);
        }
        if st.next < 6 {
            return Err(NackReason::Incomplete);
        }
        self.staging = None;
        let table = Table::from_raw(st.staged).map_err(|_| NackReason::OutOfRange)?;
        if table.crc() != crc {
            return Err(NackReason::CrcMismatch);
        }
        let counter = match (&self.key, st.authorised) {
            (None, _) => self.counter,
            (Some(_), Some(counter)) => counter,
            (Some(_), None) => return Err(NackReason::BadMac),
        };
        storage
            .store(&table, counter)
            .map_err(|_| NackReason::FlashError)?;
        self.held = Some(table);
        self.counter = counter;
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
    /// Readback answers came, but none carried a MAC that verifies (forged or garbled).
    BadAnswer,
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
            UploadError::BadAnswer => {
                f.write_str("no readback answer with a valid MAC (forged or garbled replies)")
            }
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
    /// The node's counter, from its answer to the current Begin.
    counter: Option<u32>,
    /// The CRC of the current Begin's ACK, while the counter is still missing.
    begin_ack: Option<u32>,
    /// The nonce of the current readback (kept over its resends, so that the pieces of the
    /// answer may come from different resends: they all answer the same nonce).
    nonce: Option<u32>,
    /// Answers whose MAC did not verify.
    bad_answers: u32,
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

impl Upload {
    /// A new upload of `table` to `node` in `session` (choose a fresh session per upload).
    pub fn new(node: NodeId, session: u8, table: Table, policy: RetryPolicy) -> Self {
        Upload {
            node,
            session,
            table,
            policy,
            step: Step::Send(Command::Begin),
            attempts: 0,
            restarts: 0,
            deadline_us: None,
            held_crc: None,
            auth: None,
            verify_only: false,
        }
    }

    /// An authenticated upload to a node holding `key`: `CommitAuth` before `Commit`, and
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
            counter: None,
            begin_ack: None,
            nonce: None,
            bad_answers: 0,
        });
        up
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
    /// say anything; only [`Upload::outcome`] is authenticated).
    pub fn held_crc(&self) -> Option<u32> {
        self.held_crc
    }

    fn current(&self) -> Option<Command> {
        match self.step {
            Step::Send(c) => Some(c),
            Step::Readback(_) => Some(Command::Readback {
                nonce: self.auth.as_ref().and_then(|a| a.nonce).unwrap_or(0),
            }),
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
            let error = if bad && code == CmdCode::Readback {
                UploadError::BadAnswer
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
            (Step::Readback(_), Some(a)) => {
                a.nonce
                    .get_or_insert_with(|| auth::nonce(&a.key, node, session, now_us));
            }
            (Step::Send(Command::Begin), Some(a)) => {
                a.counter = None;
                a.begin_ack = None;
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
        }
    }

    /// The step after the last segment: `CommitAuth` (with the counter above the node's) when
    /// authenticated, else `Commit`.
    fn after_segments(&self) -> Step {
        let Some(a) = &self.auth else {
            return Step::Send(Command::Commit {
                crc: self.table.crc(),
            });
        };
        match a.counter.and_then(|c| c.checked_add(1)) {
            Some(counter) => Step::Send(Command::CommitAuth {
                counter_lo: counter as u16,
                mac: auth::commit_mac(&a.key, self.node, self.session, counter, &self.table),
            }),
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
                if let (Command::Begin, Some(a)) = (current, self.auth.as_mut()) {
                    a.counter = Some(counter);
                    if let Some(crc) = a.begin_ack {
                        self.begin_acked(crc);
                    }
                }
            }
            Reply::Ack { cmd, held_crc } if cmd == current.code() => match current {
                Command::Begin => self.begin_acked(held_crc),
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
                if self.restarts >= self.policy.max_restarts || self.verify_only {
                    self.advance(Step::Done(Err(UploadError::Nacked(cmd, reason))));
                } else {
                    self.restarts += 1;
                    self.advance(Step::Send(Command::Begin));
                }
            }
            _ => {}
        }
    }

    /// Begin was acknowledged: on to the first segment, once an authenticated upload also
    /// knows the node's counter (its Freshness may come after the ACK).
    fn begin_acked(&mut self, held_crc: u32) {
        self.held_crc = Some(held_crc);
        if let Some(a) = self.auth.as_mut() {
            if a.counter.is_none() {
                a.begin_ack = Some(held_crc);
                return;
            }
        }
        let first = Field::A;
        self.advance(Step::Send(Command::Segment(first, self.table.raw(first))));
    }

    /// Decides the readback once its answer is complete: for an unauthenticated upload at the
    /// ACK; for an authenticated one when the six fields, the MAC and the ACK are in, from any
    /// of the readback's resends (one nonce for all). An answer whose MAC does not verify is
    /// dropped (the upload waits for a resend's answer).
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
                a.bad_answers += 1;
                self.step = Step::Readback(Answer::default());
                return;
            }
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

    #[derive(Default)]
    struct Flash {
        table: Option<Table>,
        counter: u32,
        fail: bool,
    }
    impl TableStorage for Flash {
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

    /// A node booted from `flash`, holding [`key`] when `keyed`.
    fn boot(flash: &Flash, keyed: bool) -> NodeTransfer {
        let node = NodeTransfer::new(NODE, flash.table);
        if keyed {
            node.with_key(key(), flash.counter)
        } else {
            node
        }
    }

    const NODE: NodeId = NodeId::JOINTS[2];

    fn old() -> Table {
        Table::from_si(0.431, 1.2345678, 0.0, 0.0, 1.0, 1.0).unwrap()
    }
    fn new() -> Table {
        Table::from_si(0.401, 1.2345678, 0.001, 0.01, 1.0, 1.0).unwrap()
    }
    fn transfer(t: &Table, session: u8) -> [TableCmd; 8] {
        let mut cmds = [Command::Begin; 8];
        for f in Field::ALL {
            cmds[1 + f as usize] = Command::Segment(f, t.raw(f));
        }
        cmds[7] = Command::Commit { crc: t.crc() };
        cmds.map(|cmd| TableCmd {
            node: NODE,
            session,
            cmd,
        })
    }

    /// Delivers `cmds` to a node booted from `flash`, rebooting (rebuilding from flash) just
    /// before command index `reboot_at`; returns the table installed at the end.
    fn run(cmds: &[TableCmd], reboot_at: Option<usize>, flash: &mut Flash) -> Option<Table> {
        let mut node = NodeTransfer::new(NODE, flash.table);
        for (i, c) in cmds.iter().enumerate() {
            if reboot_at == Some(i) {
                node = NodeTransfer::new(NODE, flash.table);
            }
            node.handle(c, i as u64 * 1000, flash);
        }
        assert_eq!(node.held().copied(), flash.table, "RAM and flash agree");
        node.held().copied()
    }

    #[test]
    fn exhaustive_over_delivered_subsets_and_reboots() {
        let full = transfer(&new(), 7);
        // Every subset of the 8 frames (in order), with no reboot or a reboot before any of them
        // (or at the end): the new table is installed iff all eight frames arrived within one
        // boot of the node.
        for mask in 0u32..256 {
            let delivered: Vec<(usize, TableCmd)> = full
                .iter()
                .copied()
                .enumerate()
                .filter(|(i, _)| mask >> i & 1 == 1)
                .collect();
            for reboot in std::iter::once(None).chain((0..=delivered.len()).map(Some)) {
                let mut flash = Flash {
                    table: Some(old()),
                    ..Flash::default()
                };
                let cmds: Vec<TableCmd> = delivered.iter().map(|(_, c)| *c).collect();
                let got = run(&cmds, reboot, &mut flash);
                let split = reboot.unwrap_or(0);
                let complete = split == 8 || delivered.len() - split == 8;
                let want = if complete { new() } else { old() };
                assert_eq!(got, Some(want), "mask {mask:08b} reboot {reboot:?}");
            }
        }
    }

    #[test]
    fn every_prefix_leaves_the_old_table_and_the_node_can_continue_after() {
        let full = transfer(&new(), 1);
        for p in 0..8 {
            let mut flash = Flash {
                table: Some(old()),
                ..Flash::default()
            };
            assert_eq!(run(&full[..p], None, &mut flash), Some(old()), "prefix {p}");
            // Then a complete second transfer still works.
            let mut node = NodeTransfer::new(NODE, flash.table);
            for c in full[..p].iter().chain(transfer(&new(), 2).iter()) {
                node.handle(c, 0, &mut flash);
            }
            assert_eq!(node.held(), Some(&new()));
        }
    }

    #[test]
    fn commit_with_wrong_crc_or_failing_flash_keeps_the_old_table() {
        let mut cmds = transfer(&new(), 1);
        cmds[7].cmd = Command::Commit {
            crc: new().crc() ^ 1,
        };
        let mut flash = Flash {
            table: Some(old()),
            ..Flash::default()
        };
        let mut node = NodeTransfer::new(NODE, flash.table);
        let mut last = Replies::new();
        for c in &cmds {
            last = node.handle(c, 0, &mut flash);
        }
        assert_eq!(
            last[0].reply,
            Reply::Nack {
                cmd: CmdCode::Commit,
                held_crc: old().crc(),
                reason: NackReason::CrcMismatch
            }
        );
        assert_eq!(node.held(), Some(&old()));

        let mut flash = Flash {
            table: Some(old()),
            fail: true,
            ..Flash::default()
        };
        let mut node = NodeTransfer::new(NODE, flash.table);
        for c in &transfer(&new(), 1) {
            last = node.handle(c, 0, &mut flash);
        }
        assert_eq!(
            last[0].reply,
            Reply::Nack {
                cmd: CmdCode::Commit,
                held_crc: old().crc(),
                reason: NackReason::FlashError
            }
        );
        assert_eq!(node.held(), Some(&old()));
    }

    #[test]
    fn foreign_session_segments_and_stale_staging_are_refused() {
        let mut flash = Flash {
            table: Some(old()),
            ..Flash::default()
        };
        let mut node = NodeTransfer::new(NODE, flash.table);
        let a = transfer(&new(), 1);
        let b = transfer(&new(), 2);
        node.handle(&a[0], 0, &mut flash);
        let r = node.handle(&b[1], 0, &mut flash);
        assert!(matches!(
            r[0].reply,
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
        let mut node = NodeTransfer::new(NODE, None);
        let rb = TableCmd {
            node: NODE,
            session: 9,
            cmd: Command::Readback { nonce: 1 },
        };
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
        for c in &transfer(&new(), 1) {
            node.handle(c, 0, &mut flash);
        }
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
        keyed: bool,
    ) -> (Option<Result<u32, UploadError>>, Option<Table>) {
        let mut flash = Flash {
            table: Some(old()),
            counter: 41,
            ..Flash::default()
        };
        let mut node = boot(&flash, keyed);
        let policy = RetryPolicy {
            timeout_us: 10_000,
            max_attempts: 8,
            max_restarts: 4,
        };
        let mut up = if keyed {
            Upload::authenticated(NODE, 3, new(), policy, key())
        } else {
            Upload::new(NODE, 3, new(), policy)
        };
        let mut to_node: Vec<TableCmd> = Vec::new();
        let mut to_ctrl: Vec<TableReply> = Vec::new();
        let mut now = 0u64;
        for (i, &(op, r)) in ops.iter().enumerate() {
            now += 1_000 * u64::from(op % 7);
            if let Some(c) = up.poll(now) {
                to_node.push(c);
            }
            match op % 5 {
                0 if r % 40 == 0 => node = boot(&flash, keyed), // reboot
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
        fn lossy_channel_never_leaves_a_mixed_table(ops in prop::collection::vec((any::<u8>(), any::<u8>()), 0..400), loss in 0u8..40, keyed in any::<bool>()) {
            let (outcome, held) = simulate(&ops, loss, keyed);
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
        for keyed in [false, true] {
            let (outcome, held) = simulate(&ops, 0, keyed);
            assert_eq!(outcome, Some(Ok(new().crc())), "keyed {keyed}");
            assert_eq!(held, Some(new()));
        }
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

    /// The commands of one authenticated transfer of `t` in `session` with `counter`, signed
    /// with `key`.
    fn signed(t: &Table, session: u8, counter: u32, key: &Key) -> Vec<TableCmd> {
        let mut cmds = transfer(t, session).to_vec();
        let mac = crate::auth::commit_mac(key, NODE, session, counter, t);
        cmds.insert(
            7,
            TableCmd {
                node: NODE,
                session,
                cmd: Command::CommitAuth {
                    counter_lo: counter as u16,
                    mac,
                },
            },
        );
        cmds
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
        let mut flash = Flash {
            table: Some(old()),
            counter: 0x1_fff0,
            ..Flash::default()
        };
        let mut node = boot(&flash, true);
        // (a) a well-formed transfer with the right CRC and no CommitAuth.
        let plain = transfer(&new(), 1);
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
        let mut node2 = boot(&flash, true);
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
        let mut node = boot(&flash, true);
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
        let mut flash = Flash {
            table: Some(new()),
            counter: 9,
            ..Flash::default()
        };
        let mut node = boot(&flash, true);
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
                    Command::Begin => replies.push(Reply::Freshness { counter: 5 }),
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
                assert_eq!(outcome, Some(Err(UploadError::BadAnswer)));
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
            let mut flash = Flash {
                table: Some(held),
                ..Flash::default()
            };
            let mut node = boot(&flash, true);
            let mut up = Upload::verify(NODE, 8, new(), policy, Some(key()));
            let cmd = up.poll(0).unwrap();
            assert!(matches!(cmd.cmd, Command::Readback { .. }));
            for r in node.handle(&cmd, 0, &mut flash) {
                up.on_reply(&r);
            }
            assert_eq!(up.outcome(), Some(want));
        }
    }
}
