//! The table transfer under an adversarial bus: an authenticated controller [`Upload`] of NEW to
//! a node holding OLD and a key, through a channel whose losses, duplicates, reorderings and
//! delays are fuzzer-chosen, with node reboots (state rebuilt from storage: table and freshness
//! counter), failing storage writes (every write, or the table image only: the counter record
//! written, the image not), injected foreign commands (arbitrary sessions, fields, nonces,
//! CRCs, counters, MACs), complete foreign transfers of arbitrary tables with correct CRCs (with
//! no `CommitAuth` or one with a guessed MAC), replays of any command delivered earlier, and
//! forged replies to the controller (arbitrary, including forged freshness counters and MACs,
//! or answering its last command with NEW's CRC and fields).
//!
//! Invariants checked after every step: the node's held table is OLD or NEW, never anything
//! else (never mixed, never a foreign table); storage and the node agree, counter included;
//! the stored counter never decreases; after a reboot the node holds what storage holds; an
//! upload that reports `Ok(crc)` has crc = CRC(NEW) and the node holds NEW.
#![no_main]

use arbitrary::Arbitrary;
use exocal_dbc::auth::{Key, KeySet};
use exocal_dbc::table::Table;
use exocal_dbc::transfer::{NodeTransfer, RetryPolicy, StorageError, TableStorage, Upload};
use exocal_dbc::{CmdCode, Command, Field, NodeId, Reply, TableCmd, TableReply};
use libfuzzer_sys::fuzz_target;

#[derive(Arbitrary, Debug)]
enum Step {
    /// Advance time by this many ms and let the controller send.
    Tick(u16),
    /// Deliver the oldest queued command / reply.
    DeliverCmd,
    DeliverReply,
    /// Deliver the queued command / reply at this index (reordering).
    DeliverCmdAt(u8),
    DeliverReplyAt(u8),
    /// Drop one queued command / reply.
    DropCmd(u8),
    DropReply(u8),
    /// Duplicate one queued command / reply.
    DupCmd(u8),
    DupReply(u8),
    /// Power-cycle the node.
    Reboot,
    /// Make the next storage writes fail (or not).
    FlashFails(Fault),
    /// A foreign command reaches the node.
    Foreign(Foreign),
    /// A complete foreign transfer with the right CRC reaches the node.
    ForeignTransfer(ForeignTransfer),
    /// A command delivered earlier (any session, any sender) reaches the node again.
    Replay(u16),
    /// A forged reply reaches the controller.
    ForgedReply(ForgedReply),
}

/// Which storage writes fail.
#[derive(Arbitrary, Debug, Clone, Copy, PartialEq, Eq)]
enum Fault {
    None,
    /// Every write: the counter record and the table image.
    All,
    /// The table image only: the counter record is written, the image is not.
    TableOnly,
}

#[derive(Arbitrary, Debug)]
struct ForeignTransfer {
    session: u8,
    nonce: u32,
    table: [i32; 6],
    /// `(counter_lo, mac)` of a `CommitAuth` before the Commit, or none.
    auth: Option<(u16, u32)>,
}

#[derive(Arbitrary, Debug)]
struct ForgedReply {
    session: u8,
    kind: u8,
    field: u8,
    raw: i64,
    value: u32,
}

#[derive(Arbitrary, Debug)]
struct Foreign {
    session: u8,
    kind: u8,
    field: u8,
    raw: i64,
    crc: u32,
    counter_lo: u16,
}

#[derive(Arbitrary, Debug)]
struct Input {
    old: Option<[i32; 6]>,
    new: [i32; 6],
    session: u8,
    counter: u32,
    steps: Vec<Step>,
}

/// The node's storage: the table image and the counter record, apart; `counter` is the
/// highest of the record and the image's (what a node boots with).
struct Flash {
    table: Option<Table>,
    counter: u32,
    fail: Fault,
}

impl TableStorage for Flash {
    fn store_counter(&mut self, counter: u32) -> Result<(), StorageError> {
        if self.fail == Fault::All {
            return Err(StorageError);
        }
        self.counter = self.counter.max(counter);
        Ok(())
    }

    fn store(&mut self, t: &Table, counter: u32) -> Result<(), StorageError> {
        if self.fail != Fault::None {
            return Err(StorageError);
        }
        self.table = Some(*t);
        self.counter = self.counter.max(counter);
        Ok(())
    }
}

/// The node and the controller share this key; the fuzzer never sees it.
fn key() -> Key {
    KeySet::derived(0x00ab_cdef)
        .node(NodeId::JOINTS[2])
        .unwrap()
        .clone()
}

fn boot(node: NodeId, flash: &Flash) -> NodeTransfer {
    NodeTransfer::new(node, flash.table).with_key(key(), flash.counter)
}

/// A valid table near `raw` (values clamped into each field's bounds).
fn table(raw: [i32; 6]) -> Table {
    let mut v = [0i64; 6];
    for f in Field::ALL {
        let (lo, hi) = f.raw_bounds();
        v[f.seq() as usize] = i64::from(raw[f.seq() as usize]).clamp(lo, hi);
    }
    Table::from_raw(v).expect("clamped values are in range")
}

fn pick<T>(q: &mut Vec<T>, i: u8) -> Option<T> {
    if q.is_empty() {
        None
    } else {
        Some(q.remove(usize::from(i) % q.len()))
    }
}

fuzz_target!(|input: Input| {
    let node = NodeId::JOINTS[2];
    let old = input.old.map(table);
    let new = table(input.new);
    let policy = RetryPolicy {
        timeout_us: 20_000,
        max_attempts: 4,
        max_restarts: 3,
    };
    let mut flash = Flash {
        table: old,
        counter: input.counter,
        fail: Fault::None,
    };
    let mut nt = boot(node, &flash);
    let mut up = Upload::authenticated(node, input.session, new, policy, key());
    let mut history: Vec<TableCmd> = Vec::new();
    let mut last_counter = flash.counter;
    let mut now = 0u64;
    let mut cmds: Vec<TableCmd> = Vec::new();
    let mut replies: Vec<TableReply> = Vec::new();
    let deliver = |nt: &mut NodeTransfer,
                   flash: &mut Flash,
                   cmd: TableCmd,
                   now: u64,
                   replies: &mut Vec<TableReply>,
                   history: &mut Vec<TableCmd>| {
        if history.len() < 1024 {
            history.push(cmd);
        }
        for r in nt.handle(&cmd, now, flash) {
            replies.push(r);
        }
    };
    for step in input.steps.into_iter().take(4096) {
        match step {
            Step::Tick(ms) => {
                now += u64::from(ms) * 1000;
                if let Some(c) = up.poll(now) {
                    cmds.push(c);
                }
            }
            Step::DeliverCmd => {
                if let Some(c) = pick(&mut cmds, 0) {
                    deliver(&mut nt, &mut flash, c, now, &mut replies, &mut history);
                }
            }
            Step::DeliverCmdAt(i) => {
                if let Some(c) = pick(&mut cmds, i) {
                    deliver(&mut nt, &mut flash, c, now, &mut replies, &mut history);
                }
            }
            Step::DeliverReply => {
                if let Some(r) = pick(&mut replies, 0) {
                    up.on_reply(&r);
                }
            }
            Step::DeliverReplyAt(i) => {
                if let Some(r) = pick(&mut replies, i) {
                    up.on_reply(&r);
                }
            }
            Step::DropCmd(i) => {
                let _ = pick(&mut cmds, i);
            }
            Step::DropReply(i) => {
                let _ = pick(&mut replies, i);
            }
            Step::DupCmd(i) => {
                if !cmds.is_empty() && cmds.len() < 64 {
                    let c = cmds[usize::from(i) % cmds.len()];
                    cmds.push(c);
                }
            }
            Step::DupReply(i) => {
                if !replies.is_empty() && replies.len() < 64 {
                    let r = replies[usize::from(i) % replies.len()];
                    replies.push(r);
                }
            }
            Step::Reboot => {
                nt = boot(node, &flash);
                assert_eq!(nt.held(), flash.table.as_ref(), "boot reads storage");
            }
            Step::FlashFails(f) => flash.fail = f,
            Step::Foreign(f) => {
                let field = Field::ALL[usize::from(f.field) % 6];
                let cmd = match f.kind % 6 {
                    0 => Command::Begin { nonce: f.crc },
                    1 => Command::Segment(field, f.raw),
                    2 => Command::Commit { crc: f.crc },
                    3 => Command::Readback { nonce: f.crc },
                    4 => Command::CommitAuth {
                        counter_lo: f.counter_lo,
                        mac: f.crc,
                    },
                    _ => Command::Abort,
                };
                let c = TableCmd {
                    node,
                    session: f.session,
                    cmd,
                };
                deliver(&mut nt, &mut flash, c, now, &mut replies, &mut history);
            }
            Step::ForeignTransfer(f) => {
                let t = table(f.table);
                let mut cmds = vec![Command::Begin { nonce: f.nonce }];
                cmds.extend(Field::ALL.map(|k| Command::Segment(k, t.raw(k))));
                if let Some((counter_lo, mac)) = f.auth {
                    cmds.push(Command::CommitAuth { counter_lo, mac });
                }
                cmds.push(Command::Commit { crc: t.crc() });
                for cmd in cmds {
                    let c = TableCmd {
                        node,
                        session: f.session,
                        cmd,
                    };
                    deliver(&mut nt, &mut flash, c, now, &mut replies, &mut history);
                }
            }
            Step::Replay(i) => {
                if !history.is_empty() {
                    let c = history[usize::from(i) % history.len()];
                    deliver(&mut nt, &mut flash, c, now, &mut replies, &mut history);
                }
            }
            Step::ForgedReply(f) => {
                let field = Field::ALL[usize::from(f.field) % 6];
                let reply = match f.kind % 7 {
                    0 => Reply::Ack {
                        cmd: CmdCode::Readback,
                        held_crc: new.crc(),
                    },
                    1 => Reply::Readback(field, new.raw(field)),
                    2 => Reply::ReadbackMac { mac: f.value },
                    3 => Reply::Freshness { counter: f.value },
                    6 => Reply::FreshnessMac { mac: f.value },
                    4 => Reply::Ack {
                        cmd: CmdCode::Commit,
                        held_crc: f.value,
                    },
                    _ => Reply::Readback(
                        field,
                        f.raw.clamp(field.raw_bounds().0, field.raw_bounds().1),
                    ),
                };
                up.on_reply(&TableReply {
                    node,
                    session: f.session,
                    reply,
                });
            }
        }
        let held = nt.held().copied();
        assert!(
            held == old || held == Some(new),
            "node holds a table that is neither the old nor the new one: {held:?}"
        );
        assert_eq!(held, flash.table, "node and storage disagree");
        assert_eq!(
            nt.counter(),
            flash.counter,
            "counter in RAM and storage disagree"
        );
        assert!(
            flash.counter >= last_counter,
            "the stored counter went back"
        );
        last_counter = flash.counter;
        if let Some(Ok(crc)) = up.outcome() {
            assert_eq!(crc, new.crc());
            assert_eq!(
                held,
                Some(new),
                "upload reported success but the node holds another table"
            );
        }
    }
});
