//! The rogue sender: four attacks on a suit whose nodes hold keys, on any transport
//! (the in-process bus in `rogue.rs`, vcan0 in `reliability_vcan.rs`: the same code).
//!
//! Beside exocal-hil (keyed nodes, flash files) and the daemon's `push_tables` (the node keys),
//! a third endpoint, the rogue, which knows everything on the bus but no key:
//!
//! - (a) a well-formed transfer with a correct CRC and no `CommitAuth`, then one with a
//!   `CommitAuth` whose MAC is wrong;
//! - (b) a replay, frame by frame, of an earlier genuine push's `/can/tx` (the frames the daemon
//!   sent, as the session's MCAP log records them) after a later genuine push;
//! - (c) a transfer with a valid MAC (a stolen key) for a counter the node already used;
//! - (d) the daemon pushes to a node that stays silent (transfer fault `Silent`) while the rogue
//!   answers for it: Freshness, ACKs with the right CRCs, the readback fields, a guessed MAC.
//!
//! - the rollback by an inflated freshness ([`rollback`]): an inflated, unauthenticated
//!   `Freshness` answer and a forged NACK, the 8 frames kept and replayed with a Commit after
//!   later pushes.
//!
//! Each attack must leave the attacked node's flash CRC unchanged, and the node's refusal
//! (NACK `BadMac` / `StaleCounter`) must be seen, so the attack is known to have reached it;
//! the daemon must never report `New` for (d).

use std::path::{Path, PathBuf};
use std::time::Duration;

use exocal_bus::{Clock, Frame, SimClock, Transport};
use exocal_dbc::auth::{commit_mac, KeySet};
use exocal_dbc::table::{Field, Table};
use exocal_dbc::{CmdCode, Command, Message, NackReason, NodeId, Reply, TableCmd};
use exocal_hil::flash::FlashImage;
use exocal_hil::scenario::{TransferBehaviour, TransferFault};
use exocal_hil::{Hil, Scenario};
use exocald::config::PushPolicy;
use exocald::push::{push_tables, Holds, PushObserver};

/// The node attacked by (a)–(c).
pub const TARGET: NodeId = NodeId::JOINTS[2];
/// The node that stays silent in (d) (give the scenario a `Silent` transfer fault for it).
pub const SILENT: NodeId = NodeId::JOINTS[6];

/// What the attacks did.
#[derive(Debug, Default)]
pub struct Findings {
    /// One line per attack: what was sent, the node's answer, the flash after.
    pub lines: Vec<String>,
    /// Violations (empty when every attack failed as it must).
    pub problems: Vec<String>,
}

impl Findings {
    /// Prints every attack's line.
    pub fn print(&self) {
        for line in &self.lines {
            println!("{line}");
        }
    }

    /// Asserts that no attack got through and that `lines` attacks ran (`why` says which).
    #[track_caller]
    pub fn assert_clean(&self, lines: usize, why: &str) {
        assert!(self.problems.is_empty(), "{}", self.problems.join("\n"));
        assert_eq!(self.lines.len(), lines, "{why}");
    }
}

/// How long things take on a transport.
pub struct Timing {
    /// From starting exocal-hil to the first push (the nodes boot and stream).
    pub settle: Duration,
    /// The daemon's push: the first backoff, up to the timeout (one retry).
    pub backoff_initial_ms: u64,
    /// The daemon's push: each exchange's timeout and the longest backoff.
    pub timeout_ms: u64,
    /// How long the rogue listens for an answer to each frame it sends.
    pub wait: Duration,
}

impl Timing {
    /// The daemon's authenticated push with `keys` (and its state in `state_dir`).
    fn policy(&self, keys: KeySet, state_dir: Option<PathBuf>) -> PushPolicy {
        PushPolicy {
            retries: 1,
            backoff_initial_ms: self.backoff_initial_ms,
            backoff_max_ms: self.timeout_ms,
            timeout_ms: self.timeout_ms,
            authenticate: true,
            keys,
            state_dir,
        }
    }
}

/// A suit under attack: exocal-hil playing on the bus, the daemon's and the rogue's endpoints.
struct Bed<T> {
    daemon: T,
    rogue: T,
    hil: tokio::task::AbortHandle,
}

/// Provisions `keys` into the flash files in `flash`, starts exocal-hil playing `scenario` on
/// them at real time, and returns after `settle`. `attach` opens one endpoint on the bus for
/// `"hil"`, `"daemon"` and `"rogue"`, in that order.
async fn start<T: Transport + Send + 'static>(
    scenario: Scenario,
    flash: &Path,
    keys: &KeySet,
    mut attach: impl FnMut(&str) -> T,
    settle: Duration,
) -> Bed<T> {
    exocal_hil::flash::provision(flash, keys).expect("key slots");
    let mut hil = Hil::new(scenario, flash).expect("hil");
    let clock = SimClock::new(1.0).expect("speed");
    let mut hil_end = attach("hil");
    let (daemon, rogue) = (attach("daemon"), attach("rogue"));
    let hil = tokio::spawn(async move { hil.run(&mut hil_end, &clock).await }).abort_handle();
    tokio::time::sleep(settle).await;
    Bed { daemon, rogue, hil }
}

/// [`attacks`] on a suit playing `scenario` (with [`SILENT`] made silent to transfers, the
/// nodes keyed with `KeySet::derived(20)`), its flash files in `flash`, on the bus `attach`
/// opens endpoints on (see [`start`]).
pub async fn run_attacks<T: Transport + Send + 'static>(
    mut scenario: Scenario,
    flash: &Path,
    attach: impl FnMut(&str) -> T,
    timing: &Timing,
) -> Findings {
    scenario.faults.transfer.push(TransferFault {
        node: SILENT.raw(),
        behaviour: TransferBehaviour::Silent,
    });
    let keys = KeySet::derived(20);
    let mut bed = start(scenario, flash, &keys, attach, timing.settle).await;
    let policy = timing.policy(keys.clone(), None);
    let found = attacks(
        &mut bed.daemon,
        &mut bed.rogue,
        flash,
        &keys,
        &policy,
        timing.wait,
    )
    .await;
    bed.hil.abort();
    found
}

/// [`rollback`] on a suit playing `scenario` (the nodes keyed with `KeySet::derived(34)`), its
/// flash files in `flash`, the daemon's state in `state`, on the bus `attach` opens endpoints
/// on (see [`start`]).
pub async fn run_rollback<T: Transport + Send + 'static>(
    scenario: Scenario,
    flash: &Path,
    state: &Path,
    attach: impl FnMut(&str) -> T,
    timing: &Timing,
) -> Findings {
    let keys = KeySet::derived(34);
    let mut bed = start(scenario, flash, &keys, attach, timing.settle).await;
    let policy = timing.policy(keys, Some(state.to_path_buf()));
    let found = rollback(&mut bed.daemon, &mut bed.rogue, flash, &policy, timing.wait).await;
    bed.hil.abort();
    found
}

/// Pushes `t` to [`TARGET`] from the daemon (sessions from `session`): a problem unless the
/// report says `New` and the node's flash (in `flash`) holds `t`.
async fn genuine_push<T: Transport>(
    daemon: &mut T,
    flash: &Path,
    policy: &PushPolicy,
    t: Table,
    session: u8,
    observer: &mut dyn PushObserver,
) -> Result<(), String> {
    let report = push_tables(
        daemon,
        &Clock::Wall,
        &[(TARGET, t)],
        policy,
        session,
        observer,
    )
    .await
    .expect("bus");
    let r = &report.nodes[0];
    if r.holds != Holds::New || flash_crc(flash, TARGET).0 != Some(t.crc()) {
        return Err(format!("genuine push of {:#010x} failed: {r:?}", t.crc()));
    }
    Ok(())
}

/// [`TARGET`]'s image in the flash files in `dir` (it holds one from the factory).
fn target_image(dir: &Path) -> FlashImage {
    exocal_hil::flash::read(dir, TARGET)
        .expect("flash readable")
        .expect("a factory table")
}

/// A table near `t`, every field moved by `k` raw units (kept in range).
pub fn moved(t: &Table, k: i64) -> Table {
    let mut raw = t.raw_values();
    for f in Field::ALL {
        let (lo, hi) = f.raw_bounds();
        raw[f as usize] = (raw[f as usize] + k).clamp(lo, hi);
    }
    Table::from_raw(raw).expect("in range")
}

fn frame(cmd: TableCmd) -> Frame {
    Message::TableCmd(cmd).to_frame().expect("encodable")
}

/// Sends `frames` from the rogue, one at a time, each followed by up to `wait` for the
/// node's answer (its ACK or NACK, in the frame's session); returns every reply seen.
async fn send_and_listen<T: Transport>(
    rogue: &mut T,
    frames: &[Frame],
    node: NodeId,
    wait: Duration,
) -> Vec<Reply> {
    // Whatever queued up while the rogue was not listening is not an answer to it.
    while let Ok(Ok(_)) = tokio::time::timeout(Duration::from_millis(1), rogue.recv()).await {}
    let mut seen = Vec::new();
    for f in frames {
        let Ok(Message::TableCmd(cmd)) = exocal_dbc::decode_frame(f) else {
            continue;
        };
        rogue.send(f).await.expect("rogue sends");
        let deadline = tokio::time::Instant::now() + wait;
        while let Ok(Ok(rx)) = tokio::time::timeout_at(deadline, rogue.recv()).await {
            if let Ok(Message::TableReply(r)) = exocal_dbc::decode_frame(&rx.frame) {
                if r.node == node && r.session == cmd.session {
                    let last = matches!(r.reply, Reply::Ack { .. } | Reply::Nack { .. });
                    seen.push(r.reply);
                    if last {
                        break;
                    }
                }
            }
        }
    }
    seen
}

/// The frames of a transfer of `t` to `node` in `session`, with `auth` = (counter, MAC) as a
/// `CommitAuth` before the Commit, or none.
fn transfer(node: NodeId, session: u8, t: &Table, auth: Option<(u32, u32)>) -> Vec<Frame> {
    let mut cmds = vec![Command::Begin { nonce: 0x5eed }];
    cmds.extend(Field::ALL.map(|f| Command::Segment(f, t.raw(f))));
    if let Some((counter, mac)) = auth {
        cmds.push(Command::CommitAuth {
            counter_lo: counter as u16,
            mac,
        });
    }
    cmds.push(Command::Commit { crc: t.crc() });
    cmds.into_iter()
        .map(|cmd| frame(TableCmd { node, session, cmd }))
        .collect()
}

fn flash_crc(dir: &Path, node: NodeId) -> (Option<u32>, u32) {
    let image = exocal_hil::flash::read(dir, node).expect("flash readable");
    (image.map(|i| i.table.crc()), image.map_or(0, |i| i.counter))
}

fn refused(replies: &[Reply], reason: NackReason) -> bool {
    replies
        .iter()
        .any(|r| matches!(r, Reply::Nack { reason: got, .. } if *got == reason))
}

/// Runs the four attacks. `daemon` and `rogue` are two endpoints on the bus the hil (flash in
/// `flash`, nodes keyed with `keys`, [`SILENT`] silent to transfers) plays on; `policy` is the
/// daemon's push policy (its keys); `wait` bounds each exchange of the rogue.
pub async fn attacks<T: Transport>(
    daemon: &mut T,
    rogue: &mut T,
    flash: &Path,
    keys: &KeySet,
    policy: &PushPolicy,
    wait: Duration,
) -> Findings {
    let mut out = Findings::default();
    let clock = Clock::Wall;
    let factory = target_image(flash).table;
    // Two genuine pushes; the first one's /can/tx is recorded for (b).
    let (t1, t2) = (moved(&factory, 101), moved(&factory, 202));
    let mut tx1 = Vec::new();
    let mut record = |sent: bool, f: &Frame, _: Duration| {
        if sent {
            tx1.push(*f)
        }
    };
    for (t, session, observer) in [
        (t1, 10u8, &mut record as &mut dyn PushObserver),
        (t2, 20, &mut |_: bool, _: &Frame, _: Duration| {}),
    ] {
        if let Err(problem) = genuine_push(daemon, flash, policy, t, session, observer).await {
            out.problems.push(problem);
            return out;
        }
    }
    let (held, counter) = flash_crc(flash, TARGET);
    out.lines.push(format!(
        "genuine pushes: {TARGET} holds {:#010x}, counter {counter}; {} frames recorded from the first",
        held.unwrap_or(0),
        tx1.len()
    ));
    let check = |what: &str, replies: &[Reply], want: NackReason, out: &mut Findings| {
        let now = flash_crc(flash, TARGET);
        let line = format!(
            "{what}: {TARGET} refused it with {:?}; flash {:#010x} counter {}",
            replies.iter().find(|r| matches!(r, Reply::Nack { .. })),
            now.0.unwrap_or(0),
            now.1
        );
        if now != (held, counter) {
            out.problems.push(format!("{line}: the flash changed"));
        }
        if !refused(replies, want) {
            out.problems.push(format!("{line}: no {want:?} seen"));
        }
        out.lines.push(line);
    };

    // (a) correct CRC, no MAC; then a wrong MAC.
    let t3 = moved(&factory, 303);
    let replies = send_and_listen(rogue, &transfer(TARGET, 30, &t3, None), TARGET, wait).await;
    check("(a) no CommitAuth", &replies, NackReason::BadMac, &mut out);
    let guess = Some((counter + 1, 0x5eed_f00d));
    let replies = send_and_listen(rogue, &transfer(TARGET, 31, &t3, guess), TARGET, wait).await;
    check("(a) wrong MAC", &replies, NackReason::BadMac, &mut out);

    // (b) the first genuine push again, frame for frame.
    let commits: Vec<Frame> = tx1
        .iter()
        .copied()
        .filter(|f| {
            matches!(
                exocal_dbc::decode_frame(f),
                Ok(Message::TableCmd(c)) if c.cmd.code() != CmdCode::Readback
            )
        })
        .collect();
    let replies = send_and_listen(rogue, &commits, TARGET, wait).await;
    check(
        "(b) replay of push 1",
        &replies,
        NackReason::StaleCounter,
        &mut out,
    );

    // (c) a valid MAC (the key is known) for the counter the node already used.
    let key = keys.node(TARGET).expect("target key");
    let stale = Some((counter, commit_mac(key, TARGET, 40, counter, &t3)));
    let replies = send_and_listen(rogue, &transfer(TARGET, 40, &t3, stale), TARGET, wait).await;
    check(
        "(c) stale counter",
        &replies,
        NackReason::StaleCounter,
        &mut out,
    );

    // (d) the rogue answers for the silent node while the daemon pushes to it.
    let silent_before = flash_crc(flash, SILENT);
    let t4 = moved(
        &exocal_hil::flash::read(flash, SILENT)
            .unwrap()
            .unwrap()
            .table,
        404,
    );
    let mut ignore = |_: bool, _: &Frame, _: Duration| {};
    let tables = [(SILENT, t4)];
    let push = push_tables(daemon, &clock, &tables, policy, 50, &mut ignore);
    tokio::pin!(push);
    let (mut forged, mut guess) = (0u64, 0x0bad_cafe_u32);
    let report = loop {
        let got = tokio::select! {
            r = &mut push => break r,
            rx = rogue.recv() => rx,
        };
        if let Ok(rx) = got {
            forged += forge(rogue, &rx.frame, SILENT, &t4, &mut guess).await;
        }
    };
    let r = &report.expect("bus").nodes[0];
    let line = format!(
        "(d) forged answers for the silent {SILENT}: {forged} forged frames; report {:?} ({}); flash unchanged: {}",
        r.holds,
        r.error.as_deref().unwrap_or(""),
        flash_crc(flash, SILENT) == silent_before
    );
    if r.holds == Holds::New || forged == 0 || flash_crc(flash, SILENT) != silent_before {
        out.problems.push(line.clone());
    }
    out.lines.push(line);
    out
}

/// If `frame` is a command to `node`, answers it as the node would (right CRCs and fields,
/// no key: a guessed MAC); returns how many frames it forged.
async fn forge<T: Transport>(
    rogue: &mut T,
    frame: &Frame,
    node: NodeId,
    table: &Table,
    guess: &mut u32,
) -> u64 {
    let Ok(Message::TableCmd(cmd)) = exocal_dbc::decode_frame(frame) else {
        return 0;
    };
    if cmd.node != node {
        return 0;
    }
    let mut replies = Vec::new();
    match cmd.cmd {
        Command::Begin { .. } => {
            *guess = guess.rotate_left(5) ^ 0x9e37_79b9;
            replies.push(Reply::Freshness { counter: 7 });
            replies.push(Reply::FreshnessMac { mac: *guess });
        }
        Command::Readback { .. } => {
            replies.extend(Field::ALL.map(|f| Reply::Readback(f, table.raw(f))));
            *guess = guess.rotate_left(5) ^ 0x9e37_79b9;
            replies.push(Reply::ReadbackMac { mac: *guess });
        }
        _ => {}
    }
    replies.push(Reply::Ack {
        cmd: cmd.cmd.code(),
        held_crc: table.crc(),
    });
    for reply in &replies {
        let m = Message::TableReply(exocal_dbc::TableReply {
            node,
            session: cmd.session,
            reply: *reply,
        });
        rogue
            .send(&m.to_frame().expect("encodable"))
            .await
            .expect("rogue sends");
    }
    replies.len() as u64
}

/// The rollback by an inflated freshness, on any transport. During a genuine push of `t1` to
/// [`TARGET`] the rogue answers the daemon's Begin first, with the node's counter + 60,000, a
/// guessed `FreshnessMac` and an ACK; it keeps Begin, the six
/// segments and the `CommitAuth` the daemon signs, and NACKs that `CommitAuth` in the node's
/// name. Two later genuine pushes (`t2`, `t3`) follow. Then the rogue sends the 8 kept frames
/// and a Commit of `t1`'s CRC, on the live node.
///
/// Must hold: the daemon signs only the node's own counter + 1 (never the forged one); push 1
/// still ends with the node holding `t1`; the replay is refused (`StaleCounter`) and the node
/// keeps `t3`, the newest verified table, with the counter it had.
pub async fn rollback<T: Transport>(
    daemon: &mut T,
    rogue: &mut T,
    flash: &Path,
    policy: &PushPolicy,
    wait: Duration,
) -> Findings {
    let mut out = Findings::default();
    let clock = Clock::Wall;
    let image = target_image(flash);
    let record = exocal_hil::flash::read_counter(flash, TARGET).expect("counter record readable");
    // The node boots with the higher of its counter record and its table image's.
    let (factory, c0) = (image.table, image.counter.max(record.unwrap_or(0)));
    let (t1, t2, t3) = (
        moved(&factory, 111),
        moved(&factory, 222),
        moved(&factory, 333),
    );
    // Push 1, with the rogue answering first.
    let session = 60u8;
    let mut ignore = |_: bool, _: &Frame, _: Duration| {};
    let tables = [(TARGET, t1)];
    let (mut kept, mut nacked, mut signed_lo) = (Vec::<Frame>::new(), false, Vec::new());
    let report = {
        let push = push_tables(daemon, &clock, &tables, policy, session, &mut ignore);
        tokio::pin!(push);
        loop {
            let got = tokio::select! {
                r = &mut push => break r,
                rx = rogue.recv() => rx,
            };
            let Ok(rx) = got else { continue };
            let Ok(Message::TableCmd(cmd)) = exocal_dbc::decode_frame(&rx.frame) else {
                continue;
            };
            if cmd.node != TARGET {
                continue;
            }
            let mut forged = Vec::new();
            match cmd.cmd {
                Command::Begin { .. } if !nacked => {
                    kept = vec![rx.frame];
                    forged.push(Reply::Freshness {
                        counter: c0 + 60_000,
                    });
                    forged.push(Reply::FreshnessMac { mac: 0xdead_beef });
                    forged.push(Reply::Ack {
                        cmd: CmdCode::Begin,
                        held_crc: factory.crc(),
                    });
                }
                Command::Segment(..) if !nacked => kept.push(rx.frame),
                Command::CommitAuth { counter_lo, .. } => {
                    signed_lo.push(counter_lo);
                    if !nacked {
                        kept.push(rx.frame);
                        nacked = true;
                        forged.push(Reply::Nack {
                            cmd: CmdCode::CommitAuth,
                            held_crc: factory.crc(),
                            reason: NackReason::BadSession,
                        });
                    }
                }
                _ => {}
            }
            for reply in forged {
                let m = Message::TableReply(exocal_dbc::TableReply {
                    node: TARGET,
                    session: cmd.session,
                    reply,
                });
                rogue
                    .send(&m.to_frame().expect("encodable"))
                    .await
                    .expect("rogue sends");
            }
        }
    };
    let r1 = &report.expect("bus").nodes[0];
    let after1 = flash_crc(flash, TARGET);
    let line = format!(
        "rollback, push 1 with the rogue answering first: report {:?}, {} frames kept, \
         CommitAuth signed for counter_lo {signed_lo:?} (node counter {c0}), flash {:#010x}",
        r1.holds,
        kept.len(),
        after1.0.unwrap_or(0)
    );
    if kept.len() != 8 || !nacked {
        out.problems
            .push(format!("{line}: the attack did not run as the review's"));
    }
    if signed_lo.iter().any(|&lo| lo != (c0 + 1) as u16) {
        out.problems.push(format!(
            "{line}: a counter other than the node's + 1 was signed"
        ));
    }
    if r1.holds == Holds::New && after1.0 != Some(t1.crc()) {
        out.problems.push(format!(
            "{line}: reported New but the node does not hold it"
        ));
    }
    out.lines.push(line);
    // Two later genuine pushes.
    for (t, session) in [(t2, 61u8), (t3, 62)] {
        if let Err(problem) = genuine_push(daemon, flash, policy, t, session, &mut ignore).await {
            out.problems.push(problem);
            return out;
        }
    }
    let before = flash_crc(flash, TARGET);
    // The replay: the 8 kept frames and a Commit of t1.
    let mut replay = kept.clone();
    replay.push(frame(TableCmd {
        node: TARGET,
        session,
        cmd: Command::Commit { crc: t1.crc() },
    }));
    let replies = send_and_listen(rogue, &replay, TARGET, wait).await;
    let now = flash_crc(flash, TARGET);
    let line = format!(
        "rollback, replay of the kept frames after two genuine pushes: {TARGET} answered {:?}; \
         flash {:#010x} counter {} (t3 {:#010x}, t1 {:#010x})",
        replies
            .iter()
            .filter(|r| matches!(r, Reply::Nack { .. }))
            .collect::<Vec<_>>(),
        now.0.unwrap_or(0),
        now.1,
        t3.crc(),
        t1.crc()
    );
    if now != before || now.0 != Some(t3.crc()) {
        out.problems.push(format!(
            "{line}: the older table landed or the flash changed"
        ));
    }
    if !refused(&replies, NackReason::StaleCounter) {
        out.problems.push(format!("{line}: no StaleCounter seen"));
    }
    out.lines.push(line);
    out
}
