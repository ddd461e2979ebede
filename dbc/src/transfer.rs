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

use crate::message::{CmdCode, Command, NackReason, Reply, TableCmd, TableReply};
use crate::table::{Field, Table};
use crate::NodeId;

/// A staging area untouched for this long is dropped.
pub const STAGING_TIMEOUT_US: u64 = 5_000_000;

/// Persistent storage of the installed table (emulated flash in the hil, real flash on a node).
pub trait TableStorage {
    /// Writes `table` durably; on error the previous content must still be readable.
    fn store(&mut self, table: &Table) -> Result<(), StorageError>;
}

/// A failed storage write.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct StorageError;

impl core::fmt::Display for StorageError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str("table storage write failed")
    }
}

/// Up to seven replies to one command (Readback: six fields and an ACK).
pub type Replies = heapless::Vec<TableReply, 7>;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Staging {
    session: u8,
    staged: [i64; 6],
    next: u8,
    last_us: u64,
}

/// Node side of the transfer.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct NodeTransfer {
    node: NodeId,
    held: Option<Table>,
    staging: Option<Staging>,
    last_commit: Option<(u8, u32)>,
}

impl NodeTransfer {
    /// A freshly booted node holding `held` (as read from its storage).
    pub fn new(node: NodeId, held: Option<Table>) -> Self {
        NodeTransfer {
            node,
            held,
            staging: None,
            last_commit: None,
        }
    }

    /// The installed table.
    pub fn held(&self) -> Option<&Table> {
        self.held.as_ref()
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
                });
                Ok(())
            }
            Command::Segment(field, raw) => self.segment(session, field, raw, now_us),
            Command::Commit { crc } => self.commit(session, crc, storage),
            Command::Readback => match self.held {
                Some(table) => {
                    for f in Field::ALL {
                        let _ = out.push(self.reply(session, Reply::Readback(f, table.raw(f))));
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
        storage.store(&table).map_err(|_| NackReason::FlashError)?;
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
    /// The table read back differs from the one sent.
    ReadbackMismatch,
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
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Step {
    Send(Command),
    Readback([Option<i64>; 6]),
    Done(Result<u32, UploadError>),
}

/// Controller side: pushes one table to one node, then verifies it by readback.
///
/// Drive it with [`Upload::poll`] (what to send now, if anything) and [`Upload::on_reply`];
/// [`Upload::outcome`] is `Some` once finished: `Ok(crc)` means the node acknowledged the
/// commit with the table's CRC and read it back identically.
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
        }
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

    /// The CRC of the table the node last said it holds.
    pub fn held_crc(&self) -> Option<u32> {
        self.held_crc
    }

    fn current(&self) -> Option<Command> {
        match self.step {
            Step::Send(c) => Some(c),
            Step::Readback(_) => Some(Command::Readback),
            Step::Done(_) => None,
        }
    }

    /// The command to send at `now_us`, if one is due (first send or a resend after timeout).
    pub fn poll(&mut self, now_us: u64) -> Option<TableCmd> {
        let cmd = self.current()?;
        if self.deadline_us.is_some_and(|d| now_us < d) {
            return None;
        }
        if self.attempts >= self.policy.max_attempts {
            self.step = Step::Done(Err(UploadError::Timeout(cmd.code())));
            return None;
        }
        self.attempts += 1;
        self.deadline_us = Some(now_us.saturating_add(self.policy.timeout_us));
        if let Step::Readback(got) = &mut self.step {
            *got = [None; 6];
        }
        Some(TableCmd {
            node: self.node,
            session: self.session,
            cmd,
        })
    }

    fn advance(&mut self, step: Step) {
        self.step = step;
        self.attempts = 0;
        self.deadline_us = None;
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
                if let Step::Readback(got) = &mut self.step {
                    got[field as usize] = Some(raw);
                }
            }
            Reply::Ack { cmd, held_crc } if cmd == current.code() => {
                self.held_crc = Some(held_crc);
                let next = match current {
                    Command::Begin => {
                        Step::Send(Command::Segment(Field::A, self.table.raw(Field::A)))
                    }
                    Command::Segment(f, _) => match Field::from_seq(f.seq() + 1) {
                        Some(n) => Step::Send(Command::Segment(n, self.table.raw(n))),
                        None => Step::Send(Command::Commit {
                            crc: self.table.crc(),
                        }),
                    },
                    Command::Commit { crc } if held_crc != crc => {
                        Step::Done(Err(UploadError::CommitCrc(held_crc)))
                    }
                    Command::Commit { .. } => Step::Readback([None; 6]),
                    Command::Readback => {
                        let Step::Readback(got) = self.step else {
                            return;
                        };
                        let matches = Field::ALL
                            .iter()
                            .all(|f| got[*f as usize] == Some(self.table.raw(*f)));
                        if !matches || held_crc != self.table.crc() {
                            Step::Done(Err(UploadError::ReadbackMismatch))
                        } else {
                            Step::Done(Ok(held_crc))
                        }
                    }
                    Command::Abort => Step::Done(Err(UploadError::Nacked(
                        CmdCode::Abort,
                        NackReason::NotStaging,
                    ))),
                };
                self.advance(next);
            }
            Reply::Nack {
                cmd,
                held_crc,
                reason,
            } if cmd == current.code() => {
                self.held_crc = Some(held_crc);
                if self.restarts >= self.policy.max_restarts {
                    self.advance(Step::Done(Err(UploadError::Nacked(cmd, reason))));
                } else {
                    self.restarts += 1;
                    self.advance(Step::Send(Command::Begin));
                }
            }
            _ => {}
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[derive(Default)]
    struct Flash {
        table: Option<Table>,
        fail: bool,
    }
    impl TableStorage for Flash {
        fn store(&mut self, table: &Table) -> Result<(), StorageError> {
            if self.fail {
                return Err(StorageError);
            }
            self.table = Some(*table);
            Ok(())
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
                    fail: false,
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
                fail: false,
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
            fail: false,
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
            fail: false,
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
            cmd: Command::Readback,
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
    ) -> (Option<Result<u32, UploadError>>, Option<Table>) {
        let mut flash = Flash {
            table: Some(old()),
            fail: false,
        };
        let mut node = NodeTransfer::new(NODE, flash.table);
        let mut up = Upload::new(
            NODE,
            3,
            new(),
            RetryPolicy {
                timeout_us: 10_000,
                max_attempts: 8,
                max_restarts: 4,
            },
        );
        let mut to_node: Vec<TableCmd> = Vec::new();
        let mut to_ctrl: Vec<TableReply> = Vec::new();
        let mut now = 0u64;
        for (i, &(op, r)) in ops.iter().enumerate() {
            now += 1_000 * u64::from(op % 7);
            if let Some(c) = up.poll(now) {
                to_node.push(c);
            }
            match op % 5 {
                0 if r % 40 == 0 => node = NodeTransfer::new(NODE, flash.table), // reboot
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
}
