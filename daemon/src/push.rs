//! Pushing the validated tables to the joint nodes.
//!
//! Contract:
//! - every node gets its own [`exocal_dbc::transfer::Upload`] (Begin, six segments, Commit with
//!   the CRC, then a Readback compared field by field), all nodes in parallel on the bus;
//! - with `push.authenticate` (the default) each upload is authenticated with the node's key
//!   ([`exocal_dbc::transfer::Upload::authenticated`]): a `CommitAuth` (freshness counter above
//!   the node's, AES-128-CMAC) before the Commit, and a Readback with a fresh nonce whose answer
//!   must carry the node's MAC. **`New` is reported only on such an answer**, so forged ACK or
//!   readback frames can make a push fail but never report `New`; a node without a key in
//!   `push.keys` is not pushed to (`Unknown`, "no key");
//! - the node's counter reaches the push only in an answer to Begin whose MAC verifies over the
//!   upload's nonce (protocol `exocal-3`), so nobody without the key can make it sign a
//!   `CommitAuth` for a counter far ahead of the node's. With a state directory
//!   (`push.state_dir`, [`crate::state`]) the push also accepts a node's counter only between
//!   the last one it proved and the highest one signed for it ([`NodeCounters::window`]): a
//!   counter that went back or jumped is refused before anything is signed (the node's report
//!   says which, and it is not retried); a counter is recorded (fsynced) before the
//!   `CommitAuth` that signs it goes out, and is not sent if it cannot be; a state file that does
//!   not read pushes nothing;
//! - the report carries, per node, the CRC the node proved holding in an answer whose MAC
//!   verified once no Commit of the push could still land (`verified_crc`: the signed readback,
//!   the fence's, or the Begin of a job that never sent a Commit) and its proved counter: what
//!   the log records and `exocald nodes` compares with;
//! - a failed upload is retried up to `push.retries` times, each in a fresh transfer session,
//!   after an exponential backoff ([`crate::config::PushPolicy::backoff_ms`]);
//! - the node-side state machine installs a table only whole, at a Commit whose CRC matches, so
//!   a node is never left with a partial table; the [`NodeReport`] says which table each node
//!   holds afterwards, by CRC: the new one (verified by readback), the old one, or unknown —
//!   never a wrong `New`, and without an attacker on the bus never a wrong `Old` (`Old` rests on
//!   the CRC in a node's ACK or NACK, which carry no MAC: a forger can turn `New` into `Old` or
//!   `Unknown`, as anyone who can jam the bus can, but nothing into `New`);
//! - a Commit sent by a failed attempt may still be processed after that attempt gave up (a
//!   lagging node, a delayed frame), so a CRC the node reported earlier is not final. When a job
//!   fails after sending any Commit, the push waits one `timeout_ms`, then *fences* the node:
//!   a `Begin` in a fresh session, resent every `timeout_ms` up to `(1 + retries)` ×
//!   `RetryPolicy::max_attempts` times (as many as one command over all attempts). It discards
//!   every older staging, so no stale Commit can install anything afterwards, and its ACK or
//!   NACK carries the CRC the node holds from then on; an `Abort` of that session follows. The
//!   report takes the node's answer to the fence (authenticated: it then reads the table back
//!   with a nonce, [`exocal_dbc::transfer::Upload::verify`], and says `New` only if the signed
//!   answer is the new table); with no answer it says `Unknown`;
//! - a bus that fails mid-way (a send or receive error: ENOBUFS that does not clear, bus-off,
//!   the interface gone) ends the push with [`PushFailed`]: the error and the report as far as
//!   it went, per node — `Old` where no Commit went out and the node's answer says so,
//!   `Unknown` where a Commit went out and nothing was heard since — which the session logs
//!   before it fails;
//! - a calibration is pushed with [`push_calibration`]: its tables ([`node_tables`]) to every
//!   node, the report per node, and how the push ended ([`PushError`]: nodes that do not hold
//!   their new table, or a bus that failed mid-way);
//! - time comes from the bus clock (simulated in the demo), never from the system directly;
//!   timeouts and backoffs run on its monotonic reading ([`Clock::monotonic`]), so a step of
//!   the wall clock cannot stall or hurry a push.

use std::time::Duration;

use exocal_bus::{Clock, Frame, Received, Transport};
use exocal_dbc::auth::{self, Key};
use exocal_dbc::message::{CmdCode, Command, Reply, TableCmd};
use exocal_dbc::table::Table;
use exocal_dbc::transfer::{RetryPolicy, Upload, UploadError};
use exocal_dbc::{Message, NodeId};
use exocal_session::pipeline::Outcome;
use serde::Serialize;

use crate::config::{Config, PushPolicy};
use crate::state::NodeCounters;

/// Which table a node holds after the push.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub enum Holds {
    /// The new table, committed and read back identical (authenticated: in an answer carrying
    /// the node's MAC over our nonce).
    New,
    /// Its previous table (the CRC it reported last, after which no Commit of this push can
    /// land, is not the new one).
    Old,
    /// Nothing is known: the node never answered, or did not answer the final CRC query
    /// after a Commit was sent, or (authenticated) never in an answer whose MAC verifies.
    Unknown,
}

/// The push outcome of one node.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct NodeReport {
    /// The node's name (`Joint1` … `Joint7`).
    pub node: String,
    /// CRC-32 of the table sent.
    pub new_crc: u32,
    /// CRC the node last reported holding.
    pub held_crc: Option<u32>,
    /// Which table it holds after the push.
    pub holds: Holds,
    /// Uploads started (1 + retries used).
    pub attempts: u32,
    /// Whether the transfer was authenticated (CommitAuth, signed readback).
    pub authenticated: bool,
    /// The CRC of the table the node proved holding at the end, in an answer whose MAC
    /// verified over our nonce (`None`: nothing proved, or unauthenticated).
    pub verified_crc: Option<u32>,
    /// The node's freshness counter from its last answer whose MAC verified.
    pub counter: Option<u32>,
    /// The last failure, if the node does not hold the new table.
    pub error: Option<String>,
}

/// What the push did, per node.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PushReport {
    /// One report per joint node.
    pub nodes: Vec<NodeReport>,
}

impl PushReport {
    /// Whether every node holds its new table.
    pub fn complete(&self) -> bool {
        self.nodes.iter().all(|n| n.holds == Holds::New)
    }

    /// The lines of the nodes that do not hold their new table, joined by "; ".
    pub fn failures(&self) -> String {
        let lines = self.lines().into_iter().zip(&self.nodes);
        let failed: Vec<String> = (lines.filter(|(_, n)| n.holds != Holds::New))
            .map(|(l, _)| l)
            .collect();
        failed.join("; ")
    }

    /// One line per node.
    pub fn lines(&self) -> Vec<String> {
        self.nodes
            .iter()
            .map(|n| {
                let held = n
                    .held_crc
                    .map_or_else(|| "none".to_string(), |c| format!("{c:#010x}"));
                let mut s = format!(
                    "{}: {:?} table (sent {:#010x}, holds {held}, {} attempt(s))",
                    n.node, n.holds, n.new_crc, n.attempts
                );
                if let Some(e) = &n.error {
                    s.push_str(&format!(": {e}"));
                }
                s
            })
            .collect()
    }
}

/// Node tables to push, from the calibrated rows.
pub fn node_tables(outcome: &Outcome, config: &Config) -> Result<Vec<(NodeId, Table)>, String> {
    outcome
        .node_rows
        .iter()
        .enumerate()
        .map(|(i, r)| {
            let node = NodeId::new(config.calibration.joint_nodes[i])
                .ok_or_else(|| format!("joint {}: no node id", i + 1))?;
            let table = Table::from_si(r.a, r.alpha, r.d, r.theta_offset, r.tau, r.sigma)
                .map_err(|e| format!("{node}: the table does not fit the DBC: {e}"))?;
            Ok((node, table))
        })
        .collect()
}

/// Watches the push: every frame sent or received (for the log) and every loop turn (to feed
/// the watchdog and flush the log while waiting on slow nodes).
pub trait PushObserver {
    /// A frame sent (`sent`) or received, at bus time `t`.
    fn frame(&mut self, sent: bool, frame: &Frame, t: Duration);
    /// One turn of the push loop (at least every few milliseconds).
    fn tick(&mut self) {}
}

impl<F: FnMut(bool, &Frame, Duration)> PushObserver for F {
    fn frame(&mut self, sent: bool, frame: &Frame, t: Duration) {
        self(sent, frame, t)
    }
}

struct Job {
    node: NodeId,
    table: Table,
    /// The node's key, when the push is authenticated.
    key: Option<Key>,
    upload: Option<Upload>,
    attempts: u32,
    /// Start of the next attempt (µs on the bus clock), after a backoff.
    next_start_us: u64,
    last_error: Option<String>,
    held_crc: Option<u32>,
    /// Whether any attempt sent a Commit (the node may then hold the new table even if the
    /// job failed).
    commit_sent: bool,
    /// The final CRC query of a failed job that sent a Commit (see the module doc).
    fence: Option<Fence>,
    /// What an authenticated readback after the fence proved: `Some(true)` the node holds the
    /// new table, `Some(false)` another one.
    verified: Option<bool>,
    /// The CRC the node proved holding (an answer whose MAC verified) once no Commit of this
    /// push could still land.
    verified_crc: Option<u32>,
    /// The node's counter from its last answer to Begin whose MAC verified (within its window).
    counter: Option<u32>,
    done: bool,
    ok: bool,
}

/// The fence of a failed job: `Begin` in its own session until answered, then `Abort` (and,
/// authenticated, a signed readback).
struct Fence {
    session: u8,
    /// When the next `Begin` is due (µs on the bus clock).
    next_send_us: u64,
    sends: u32,
    /// The CRC from the node's answer, once answered.
    answer: Option<u32>,
    /// The authenticated readback after the answer.
    verify: Option<Upload>,
}

fn micros(d: Duration) -> u64 {
    d.as_micros().min(u128::from(u64::MAX)) as u64
}

/// A push the bus stopped mid-way (ENOBUFS for long, bus-off, the interface gone): the error,
/// and per node what was sent and what is known it holds ([`NodeReport`]; a node whose Commit
/// went out and that was not heard from since is `Unknown`), for the log and `exocald nodes`.
#[derive(Debug)]
pub struct PushFailed {
    /// What the bus did.
    pub error: exocal_bus::BusError,
    /// What the push knows of every node at that point.
    pub report: PushReport,
}

impl std::fmt::Display for PushFailed {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "the bus failed mid-way through the push: {}", self.error)
    }
}

impl std::error::Error for PushFailed {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        Some(&self.error)
    }
}

/// Why a push did not leave every node holding its new table ([`push_calibration`]).
#[derive(Debug)]
pub enum PushError {
    /// The nodes that do not hold their new table, a line each, joined by "; ".
    Incomplete(String),
    /// The bus failed mid-way ([`PushFailed`]).
    Bus(exocal_bus::BusError),
}

impl std::fmt::Display for PushError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            PushError::Incomplete(failed) => write!(f, "not every node holds its table: {failed}"),
            PushError::Bus(e) => write!(f, "the bus failed mid-way through the push: {e}"),
        }
    }
}

impl std::error::Error for PushError {}

/// Pushes a calibration's `tables` ([`node_tables`]) with [`push_tables`]. Returns the report
/// (as far as the push went, when the bus failed mid-way) and how the push ended.
pub async fn push_calibration<T: Transport>(
    bus: &mut T,
    clock: &Clock,
    tables: &[(NodeId, Table)],
    policy: &PushPolicy,
    first_session: u8,
    observer: &mut dyn PushObserver,
) -> (PushReport, Result<(), PushError>) {
    match push_tables(bus, clock, tables, policy, first_session, observer).await {
        Ok(report) if report.complete() => (report, Ok(())),
        Ok(report) => {
            let failed = report.failures();
            (report, Err(PushError::Incomplete(failed)))
        }
        Err(failed) => (failed.report, Err(PushError::Bus(failed.error))),
    }
}

/// Pushes `tables` to their nodes; `first_session` numbers the transfer sessions (incremented
/// per upload, mod 256). Every frame sent or received goes to `observer`. A bus error ends the
/// push with what is known per node ([`PushFailed`]).
pub async fn push_tables<T: Transport>(
    bus: &mut T,
    clock: &Clock,
    tables: &[(NodeId, Table)],
    policy: &PushPolicy,
    first_session: u8,
    observer: &mut dyn PushObserver,
) -> Result<PushReport, Box<PushFailed>> {
    let retry = RetryPolicy {
        timeout_us: policy.timeout_ms * 1000,
        ..RetryPolicy::default()
    };
    let mut session = first_session;
    let fence_sends = retry
        .max_attempts
        .saturating_mul(policy.retries.saturating_add(1));
    // The nodes' counters, when the push keeps them (authenticated, with a state directory).
    let mut state: Option<(&std::path::Path, NodeCounters)> = None;
    let mut state_error = None;
    if let (true, Some(dir)) = (policy.authenticate, policy.state_dir.as_deref()) {
        match NodeCounters::load(dir) {
            Ok(c) => state = Some((dir, c)),
            Err(e) => {
                state_error = Some(format!(
                    "the state directory does not read ({e}): not pushed"
                ))
            }
        }
    }
    let mut jobs: Vec<Job> = tables
        .iter()
        .map(|&(node, table)| {
            let key = policy
                .keys
                .node(node)
                .filter(|_| policy.authenticate)
                .cloned();
            // Authenticated without a key, or without readable counters: nothing is sent.
            let refused = match (&key, &state_error) {
                (_, Some(e)) => Some(e.clone()),
                (None, None) if policy.authenticate => {
                    Some(format!("no key for {node}: not pushed"))
                }
                _ => None,
            };
            Job {
                node,
                table,
                key,
                upload: None,
                attempts: 0,
                next_start_us: 0,
                done: refused.is_some(),
                last_error: refused,
                held_crc: None,
                commit_sent: false,
                fence: None,
                verified: None,
                verified_crc: None,
                counter: None,
                ok: false,
            }
        })
        .collect();
    // Counters proved but not yet saved (those signed are saved before their CommitAuth).
    let mut unsaved = false;
    let mut failed = None;
    'push: while jobs.iter().any(|j| !j.done) {
        // Frames are stamped with the bus clock; deadlines run on its monotonic reading, so a
        // step of the host's wall clock neither stalls nor hurries a push.
        let now = clock.now();
        let now_us = micros(clock.monotonic());
        for job in jobs.iter_mut().filter(|j| !j.done) {
            if job.fence.is_some() {
                if let Err(e) =
                    fence_step(bus, job, retry, fence_sends, now, now_us, observer).await
                {
                    failed = Some(e);
                    break 'push;
                }
                continue;
            }
            if job.upload.is_none() && now_us >= job.next_start_us {
                job.attempts += 1;
                job.upload = Some(match &job.key {
                    Some(key) => {
                        let up =
                            Upload::authenticated(job.node, session, job.table, retry, key.clone())
                                .seeded(crate::keys::nonce_seed());
                        match state.as_ref().and_then(|(_, c)| c.window(job.node, key)) {
                            Some((low, high)) => up.with_counter_window(low, high),
                            None => up,
                        }
                    }
                    None => Upload::new(job.node, session, job.table, retry),
                });
                session = session.wrapping_add(1);
            }
            let Some(up) = job.upload.as_mut() else {
                continue;
            };
            let mut refused = None;
            if let Some(cmd) = up.poll(now_us) {
                if let (Command::CommitAuth { .. }, Some((dir, counters)), Some(key)) =
                    (cmd.cmd, state.as_mut(), &job.key)
                {
                    // Recorded before it goes out: after a power loss from here on, the node's
                    // counter may be this one, and must not look like a jump.
                    let proved = up
                        .verified_counter()
                        .is_some_and(|v| counters.verified(job.node, key, v));
                    let signed = up
                        .signed_counter()
                        .is_some_and(|c| counters.signed(job.node, key, c));
                    if proved || signed || unsaved {
                        match counters.save(dir) {
                            Ok(()) => unsaved = false,
                            Err(e) => {
                                refused = Some(format!(
                                    "not signed: the counter could not be recorded ({e})"
                                ))
                            }
                        }
                    }
                }
                if refused.is_none() {
                    job.commit_sent |= matches!(cmd.cmd, Command::Commit { .. });
                    if let Err(e) = send(bus, &cmd, now, observer).await {
                        failed = Some(e);
                        break 'push;
                    }
                }
            }
            let result = match refused {
                Some(e) => Some(Err((e, true))),
                None => up.outcome().map(|r| {
                    r.map_err(|e| (e.to_string(), matches!(e, UploadError::Counter { .. })))
                }),
            };
            let Some(result) = result else {
                continue;
            };
            job.held_crc = up.held_crc().or(job.held_crc);
            let counter_refused = matches!(result, Err((_, true)));
            if let (Some(v), false) = (up.verified_counter(), counter_refused) {
                job.counter = Some(v);
                if let (Some((_, counters)), Some(key)) = (state.as_mut(), &job.key) {
                    unsaved |= counters.verified(job.node, key, v);
                }
            }
            if !job.commit_sent || result.is_ok() {
                // No Commit of this push can land after this answer.
                job.verified_crc = up.verified_crc().or(job.verified_crc);
            }
            job.upload = None;
            match result {
                Ok(_) => {
                    job.done = true;
                    job.ok = true;
                    job.last_error = None;
                }
                Err((e, last)) => {
                    job.last_error = Some(e);
                    if job.attempts > policy.retries || last {
                        if job.commit_sent {
                            job.fence = Some(Fence {
                                session,
                                next_send_us: now_us + retry.timeout_us,
                                sends: 0,
                                answer: None,
                                verify: None,
                            });
                            session = session.wrapping_add(1);
                        } else {
                            job.done = true;
                        }
                    } else {
                        job.next_start_us = now_us + policy.backoff_ms(job.attempts) * 1000;
                    }
                }
            }
        }
        observer.tick();
        if jobs.iter().all(|j| j.done) {
            break;
        }
        // Wait a little for replies (a tokio timer: real time, or simulated on the demo's paused
        // runtime; the logic runs on the bus clock).
        match tokio::time::timeout(Duration::from_millis(1), bus.recv()).await {
            Ok(Ok(rx)) => on_received(&rx, &mut jobs, observer),
            Ok(Err(e)) => {
                failed = Some(e);
                break 'push;
            }
            Err(_) => {}
        }
    }
    if let Some(e) = &failed {
        for job in jobs.iter_mut().filter(|j| !j.done) {
            // Sent before the bus failed: a Commit may have landed, or may still.
            let note = if job.commit_sent {
                job.held_crc = None;
                job.verified = None;
                job.verified_crc = None;
                format!("the bus failed after its Commit was sent ({e}): either table")
            } else {
                // No Commit can land: what the node answered so far holds.
                if let Some(up) = &job.upload {
                    job.held_crc = up.held_crc().or(job.held_crc);
                    job.verified_crc = up.verified_crc().or(job.verified_crc);
                }
                format!("the bus failed before its Commit was sent ({e})")
            };
            job.last_error = Some(match job.last_error.take() {
                Some(prev) => format!("{prev}; {note}"),
                None => note,
            });
        }
    }
    if let (Some((dir, counters)), true) = (&state, unsaved) {
        if let Err(e) = counters.save(dir) {
            for j in jobs.iter_mut().filter(|j| j.key.is_some()) {
                let note = format!("the state directory was not updated ({e})");
                j.last_error = Some(match j.last_error.take() {
                    Some(prev) => format!("{prev}; {note}"),
                    None => note,
                });
            }
        }
    }
    let report = PushReport {
        nodes: jobs
            .iter()
            .map(|j| report(j, policy.authenticate))
            .collect(),
    };
    match failed {
        None => Ok(report),
        Some(error) => Err(Box::new(PushFailed { error, report })),
    }
}

/// One turn of a job's fence (see the module doc).
async fn fence_step<T: Transport>(
    bus: &mut T,
    job: &mut Job,
    retry: RetryPolicy,
    fence_sends: u32,
    now: Duration,
    now_us: u64,
    observer: &mut dyn PushObserver,
) -> Result<(), exocal_bus::BusError> {
    let Some(fence) = job.fence.as_mut() else {
        return Ok(());
    };
    if let Some(verify) = fence.verify.as_mut() {
        if let Some(cmd) = verify.poll(now_us) {
            send(bus, &cmd, now, observer).await?;
        }
        if let Some(result) = verify.outcome() {
            job.verified = match result {
                Ok(_) => Some(true),
                Err(UploadError::ReadbackMismatch) => Some(false),
                Err(_) => None,
            };
            job.held_crc = match result {
                Ok(crc) => Some(crc),
                _ => verify.held_crc().or(fence.answer),
            };
            // The fence discarded every staging first: nothing can land after this answer.
            job.verified_crc = verify.verified_crc().or(job.verified_crc);
            job.done = true;
        }
    } else if let Some(answer) = fence.answer {
        // Best effort: an unanswered Abort only leaves an empty staging, which the node drops
        // on its own timeout.
        let abort = fence_cmd(job.node, fence.session, Command::Abort);
        send(bus, &abort, now, observer).await?;
        job.held_crc = Some(answer);
        match &job.key {
            Some(key) => {
                // Resent as often as the fence's Begin: a signed answer is eight frames, all
                // of which must arrive (from any of the resends).
                let policy = RetryPolicy {
                    max_attempts: fence_sends,
                    ..retry
                };
                let key = Some(key.clone());
                fence.verify = Some(Upload::verify(
                    job.node,
                    fence.session,
                    job.table,
                    policy,
                    key,
                ));
            }
            None => job.done = true,
        }
    } else if now_us >= fence.next_send_us {
        if fence.sends >= fence_sends {
            job.held_crc = None;
            job.done = true;
        } else {
            fence.sends += 1;
            fence.next_send_us = now_us + retry.timeout_us;
            // A keyed node signs its answer over the nonce; the fence takes only the CRC (its
            // signed readback follows).
            let nonce = job.key.as_ref().map_or(0, |k| {
                auth::nonce(
                    k,
                    job.node,
                    fence.session,
                    crate::keys::nonce_seed(),
                    now_us,
                )
            });
            let begin = fence_cmd(job.node, fence.session, Command::Begin { nonce });
            send(bus, &begin, now, observer).await?;
        }
    }
    Ok(())
}

/// What a finished job reports.
fn report(j: &Job, authenticated: bool) -> NodeReport {
    let new_crc = j.table.crc();
    // After a fence, `held_crc` is the fence's answer (or None); without one, no Commit was
    // ever sent, so the node's last reported CRC cannot change. Authenticated, only a signed
    // answer says `New`; an unsigned CRC can still say the node holds another table.
    let holds = match (j.ok, j.verified, j.held_crc) {
        (true, _, _) | (false, Some(true), _) => Holds::New,
        (false, Some(false), _) => Holds::Old,
        (false, None, Some(c)) if c != new_crc => Holds::Old,
        (false, None, Some(_)) if !authenticated => Holds::New,
        _ => Holds::Unknown,
    };
    let error = if j.ok {
        None
    } else if j.fence.is_some() && j.held_crc.is_none() {
        Some(format!(
            "{}; no answer to the final CRC query",
            j.last_error.as_deref().unwrap_or("failed")
        ))
    } else if authenticated && j.held_crc == Some(new_crc) {
        Some(format!(
            "{}; the node's CRC is the new table's, but no answer with a valid MAC proved it",
            j.last_error.as_deref().unwrap_or("failed")
        ))
    } else {
        j.last_error.clone()
    };
    NodeReport {
        node: j.node.name().to_string(),
        new_crc,
        held_crc: j.held_crc,
        holds,
        attempts: j.attempts,
        authenticated,
        verified_crc: j.verified_crc,
        counter: j.counter,
        error,
    }
}

fn fence_cmd(node: NodeId, session: u8, cmd: Command) -> TableCmd {
    TableCmd { node, session, cmd }
}

async fn send<T: Transport>(
    bus: &mut T,
    cmd: &TableCmd,
    now: Duration,
    observer: &mut dyn PushObserver,
) -> Result<(), exocal_bus::BusError> {
    // Encoding a TableCmd built from a valid Table cannot fail; if it ever did, the command
    // counts as lost (the upload times out and is reported), never panics.
    if let Ok(frame) = Message::TableCmd(*cmd).to_frame::<Frame>() {
        bus.send(&frame).await?;
        observer.frame(true, &frame, now);
    }
    Ok(())
}

fn on_received(rx: &Received, jobs: &mut [Job], observer: &mut dyn PushObserver) {
    observer.frame(false, &rx.frame, rx.timestamp);
    if let Ok(Message::TableReply(reply)) = exocal_dbc::decode_frame(&rx.frame) {
        for job in jobs.iter_mut().filter(|j| j.node == reply.node) {
            if let Some(up) = job.upload.as_mut() {
                up.on_reply(&reply);
            }
            if let Some(fence) = job.fence.as_mut() {
                if let Some(verify) = fence.verify.as_mut() {
                    verify.on_reply(&reply);
                } else if reply.session == fence.session {
                    if let Reply::Ack {
                        cmd: CmdCode::Begin,
                        held_crc,
                    }
                    | Reply::Nack {
                        cmd: CmdCode::Begin,
                        held_crc,
                        ..
                    } = reply.reply
                    {
                        fence.answer.get_or_insert(held_crc);
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::Config;
    use exocal_bus::{Endpoint, InProcessBus};
    use exocal_dbc::auth::KeySet;
    use exocal_dbc::transfer::{NodeTransfer, StorageError, TableStorage};
    use std::sync::{Arc, Mutex};

    /// A node's storage: its table, and its counter (kept apart).
    #[derive(Default, Clone)]
    struct Flash(Arc<Mutex<Option<Table>>>, Arc<Mutex<u32>>);
    impl Flash {
        /// Storage holding `t`, its counter 0.
        fn holding(t: Table) -> Self {
            let f = Flash::default();
            *f.0.lock().unwrap() = Some(t);
            f
        }
    }
    impl TableStorage for Flash {
        fn store_counter(&mut self, counter: u32) -> Result<(), StorageError> {
            *self.1.lock().unwrap() = counter;
            Ok(())
        }
        fn store(&mut self, t: &Table, _counter: u32) -> Result<(), StorageError> {
            *self.0.lock().unwrap() = Some(*t);
            Ok(())
        }
    }

    fn keys() -> KeySet {
        KeySet::derived(9)
    }

    /// A node booted holding what `flash` holds, its counter and its key from [`keys`].
    fn keyed(node: NodeId, flash: &Flash) -> NodeTransfer {
        let held = *flash.0.lock().unwrap();
        let counter = *flash.1.lock().unwrap();
        NodeTransfer::new(node, held).with_key(keys().node(node).unwrap().clone(), counter)
    }

    fn table(k: f64) -> Table {
        Table::from_si(0.04 + k * 1e-3, 1.5, 0.001, 0.01 * k, 1.0, 1.0).unwrap()
    }

    /// Emulated nodes answering on a new bus, and the daemon's endpoint on it; replies are
    /// dropped when `lose(n)` says so for the n-th reply, and `silent` nodes never answer.
    fn spawn_nodes(
        flashes: Vec<(NodeId, Flash)>,
        lose: impl Fn(u64) -> bool + Send + 'static,
        silent: Vec<NodeId>,
    ) -> (tokio::task::JoinHandle<()>, Endpoint) {
        let bus = InProcessBus::new();
        let mut ep = bus.attach();
        let nodes = tokio::spawn(async move {
            let mut nodes: Vec<(NodeTransfer, Flash)> = flashes
                .into_iter()
                .map(|(n, f)| (keyed(n, &f), f))
                .collect();
            let mut n = 0u64;
            while let Ok(rx) = ep.recv().await {
                let Ok(Message::TableCmd(cmd)) = exocal_dbc::decode_frame(&rx.frame) else {
                    continue;
                };
                if silent.contains(&cmd.node) {
                    continue;
                }
                let now_us = micros(rx.timestamp);
                for (node, flash) in nodes.iter_mut() {
                    for reply in node.handle(&cmd, now_us, flash) {
                        n += 1;
                        if lose(n) {
                            continue;
                        }
                        let f: Frame = Message::TableReply(reply).to_frame().unwrap();
                        ep.send_now(&f);
                    }
                }
            }
        });
        (nodes, bus.attach())
    }

    /// `push_tables` on the wall clock, sessions from `first_session`; the bus does not fail.
    async fn push(
        ep: &mut impl Transport,
        tables: &[(NodeId, Table)],
        policy: &PushPolicy,
        first_session: u8,
        observer: &mut dyn PushObserver,
    ) -> PushReport {
        let clock = Clock::Wall;
        push_tables(ep, &clock, tables, policy, first_session, observer)
            .await
            .unwrap()
    }

    type Setup = (Vec<(NodeId, Flash)>, Vec<(NodeId, Table)>);

    fn setup(old: bool) -> Setup {
        let flashes: Vec<(NodeId, Flash)> = NodeId::JOINTS
            .iter()
            .map(|&n| {
                let f = if old {
                    Flash::holding(table(0.0))
                } else {
                    Flash::default()
                };
                (n, f)
            })
            .collect();
        let tables = NodeId::JOINTS
            .iter()
            .enumerate()
            .map(|(i, &n)| (n, table(i as f64 + 1.0)))
            .collect();
        (flashes, tables)
    }

    fn policy() -> PushPolicy {
        PushPolicy {
            retries: 3,
            backoff_initial_ms: 5,
            backoff_max_ms: 20,
            timeout_ms: 20,
            authenticate: true,
            keys: keys(),
            state_dir: None,
        }
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn every_node_gets_its_table_by_crc() {
        let (flashes, tables) = setup(true);
        let (nodes, mut ep) = spawn_nodes(flashes.clone(), |_| false, vec![]);
        let mut sent = 0;
        let mut sink = |tx: bool, _: &Frame, _: Duration| sent += usize::from(tx);
        let report = push(&mut ep, &tables, &policy(), 1, &mut sink).await;
        assert!(report.complete(), "{:#?}", report.lines());
        for ((_, flash), (_, t)) in flashes.iter().zip(&tables) {
            assert_eq!(flash.0.lock().unwrap().unwrap().crc(), t.crc());
        }
        // Begin, 6 segments, CommitAuth, Commit, Readback per node.
        assert_eq!(sent, 7 * 10);
        nodes.abort();
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn lost_replies_are_retried_and_a_silent_node_is_reported() {
        let (flashes, tables) = setup(true);
        // Lose every 5th reply; node 4 never answers.
        let silent = NodeId::JOINTS[3];
        let (nodes, mut ep) = spawn_nodes(flashes.clone(), |n| n % 5 == 0, vec![silent]);
        let mut sink = |_: bool, _: &Frame, _: Duration| {};
        let report = push(&mut ep, &tables, &policy(), 200, &mut sink).await;
        assert!(!report.complete());
        for (r, ((node, flash), (_, t))) in report.nodes.iter().zip(flashes.iter().zip(&tables)) {
            let held = flash.0.lock().unwrap().unwrap();
            if *node == silent {
                assert_eq!(r.holds, Holds::Unknown, "{r:?}");
                assert_eq!(r.attempts, 4);
                assert!(r.error.as_deref().unwrap().contains("no reply"), "{r:?}");
                assert_eq!(held, table(0.0), "the silent node keeps its old table");
            } else {
                assert_eq!(r.holds, Holds::New, "{r:?}");
                assert_eq!(held.crc(), t.crc());
            }
        }
        let lines = report.lines();
        assert!(lines[3].starts_with("Joint4: Unknown table"), "{lines:?}");
        nodes.abort();
    }

    /// One emulated node that lags at its first Commit: it installs the table only after
    /// `lag` more commands have queued up behind it, and every reply to the Commit and to the
    /// queued commands is lost (a node too slow to answer in time). Commands after that are
    /// handled normally.
    fn spawn_lagging_node(
        bus: &InProcessBus,
        node: NodeId,
        flash: Flash,
        lag: usize,
    ) -> tokio::task::JoinHandle<()> {
        let mut ep = bus.attach();
        tokio::spawn(async move {
            let mut flash = flash;
            let mut nt = keyed(node, &flash);
            let mut queued: Option<Vec<(TableCmd, u64)>> = None;
            let mut lagged = false;
            while let Ok(rx) = ep.recv().await {
                let Ok(Message::TableCmd(cmd)) = exocal_dbc::decode_frame(&rx.frame) else {
                    continue;
                };
                let now_us = micros(rx.timestamp);
                if let Some(q) = queued.as_mut() {
                    q.push((cmd, now_us));
                    if q.len() > lag {
                        for (c, t) in queued.take().unwrap() {
                            let _ = nt.handle(&c, t, &mut flash);
                        }
                    }
                    continue;
                }
                if !lagged && matches!(cmd.cmd, Command::Commit { .. }) {
                    lagged = true;
                    queued = Some(vec![(cmd, now_us)]);
                    continue;
                }
                for reply in nt.handle(&cmd, now_us, &mut flash) {
                    let f: Frame = Message::TableReply(reply).to_frame().unwrap();
                    ep.send_now(&f);
                }
            }
        })
    }

    /// A Commit of an earlier attempt that the node processes after the last attempt gave up
    /// installs the new table, so the report must not say `Old` (a rare race: 11–18 of 7,000
    /// transfers in the atomic-push campaign). The node here holds back its first Commit
    /// until every command of all later attempts has arrived, then installs the new table
    /// silently; the report must say `New` (learnt from the final CRC query), matching flash.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_late_commit_after_the_last_attempt_is_not_reported_old() {
        let bus = InProcessBus::new();
        let node = NodeId::JOINTS[2];
        let flash = Flash::holding(table(0.0));
        let policy = policy();
        let sends = RetryPolicy::default().max_attempts as usize;
        // The Commit's own resends, then every Begin of the later attempts (each unanswered).
        let lag = (sends - 1) + policy.retries as usize * sends;
        assert!(
            policy.authenticate,
            "the fence's answer is then proved by a signed readback"
        );
        let emulated = spawn_lagging_node(&bus, node, flash.clone(), lag);
        let mut ep = bus.attach();
        let new = table(3.0);
        let mut sink = |_: bool, _: &Frame, _: Duration| {};
        let report = push(&mut ep, &[(node, new)], &policy, 7, &mut sink).await;
        emulated.abort();
        let held = flash.0.lock().unwrap().unwrap();
        assert_eq!(held, new, "the late Commit installed the new table");
        let r = &report.nodes[0];
        assert_eq!(r.attempts, policy.retries + 1, "{r:?}");
        assert!(r.error.is_some(), "every attempt failed: {r:?}");
        assert_eq!(r.holds, Holds::New, "{r:?}");
        assert_eq!(r.held_crc, Some(new.crc()), "{r:?}");
    }

    /// A failed job that sent a Commit and then gets no answer to the final CRC query is
    /// reported `Unknown`, not `Old` from the CRC the node sent before the Commit.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn an_unanswered_final_crc_query_is_reported_unknown() {
        let bus = InProcessBus::new();
        let node = NodeId::JOINTS[0];
        let flash = Flash::holding(table(0.0));
        // The node never gets past its first Commit.
        let emulated = spawn_lagging_node(&bus, node, flash.clone(), usize::MAX);
        let mut ep = bus.attach();
        let mut sink = |_: bool, _: &Frame, _: Duration| {};
        let report = push(&mut ep, &[(node, table(2.0))], &policy(), 9, &mut sink).await;
        emulated.abort();
        let r = &report.nodes[0];
        assert_eq!(r.holds, Holds::Unknown, "{r:?}");
        assert_eq!(r.held_crc, None, "{r:?}");
        assert!(
            r.error.as_deref().unwrap().contains("final CRC query"),
            "{r:?}"
        );
    }

    /// The node stays silent; a forger on the bus answers every command as the node would
    /// (right session, right CRCs and fields, a Freshness, a guessed MAC). Authenticated, the
    /// report never says `New`; without authentication the same forgery is believed.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn forged_replies_never_report_new() {
        for authenticate in [true, false] {
            let bus = InProcessBus::new();
            let node = NodeId::JOINTS[5];
            let mut forger = bus.attach();
            let forging = tokio::spawn(async move {
                let mut guess = 1u32;
                while let Ok(rx) = forger.recv().await {
                    let Ok(Message::TableCmd(cmd)) = exocal_dbc::decode_frame(&rx.frame) else {
                        continue;
                    };
                    let mut replies = Vec::new();
                    let held_crc = table(4.0).crc();
                    match cmd.cmd {
                        Command::Begin { .. } => {
                            guess = guess.wrapping_mul(0x9e37_79b9).wrapping_add(7);
                            replies.push(Reply::Freshness { counter: 3 });
                            replies.push(Reply::FreshnessMac { mac: guess });
                        }
                        Command::Readback { .. } => {
                            for f in exocal_dbc::Field::ALL {
                                replies.push(Reply::Readback(f, table(4.0).raw(f)));
                            }
                            guess = guess.wrapping_mul(0x9e37_79b9).wrapping_add(7);
                            replies.push(Reply::ReadbackMac { mac: guess });
                        }
                        _ => {}
                    }
                    replies.push(Reply::Ack {
                        cmd: cmd.cmd.code(),
                        held_crc,
                    });
                    for reply in replies {
                        let m = Message::TableReply(exocal_dbc::TableReply {
                            node: cmd.node,
                            session: cmd.session,
                            reply,
                        });
                        forger.send_now(&m.to_frame().unwrap());
                    }
                }
            });
            let mut ep = bus.attach();
            let policy = PushPolicy {
                authenticate,
                ..policy()
            };
            let mut sink = |_: bool, _: &Frame, _: Duration| {};
            let report = push(&mut ep, &[(node, table(4.0))], &policy, 3, &mut sink).await;
            forging.abort();
            let r = &report.nodes[0];
            if authenticate {
                assert_ne!(r.holds, Holds::New, "{r:?}");
                assert!(r.error.as_deref().unwrap().contains("MAC"), "{r:?}");
            } else {
                assert_eq!(r.holds, Holds::New, "the forgery works without keys: {r:?}");
            }
        }
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_node_without_a_key_is_not_pushed_to() {
        let (flashes, tables) = setup(true);
        let (nodes, mut ep) = spawn_nodes(flashes.clone(), |_| false, vec![]);
        let mut policy = policy();
        policy.keys.set_node(NodeId::JOINTS[1], None);
        let mut sent = 0;
        let mut sink = |tx: bool, _: &Frame, _: Duration| sent += usize::from(tx);
        let report = push(&mut ep, &tables, &policy, 1, &mut sink).await;
        nodes.abort();
        let r = &report.nodes[1];
        assert_eq!((r.holds, r.attempts), (Holds::Unknown, 0), "{r:?}");
        assert!(r.error.as_deref().unwrap().contains("no key"), "{r:?}");
        assert_eq!(*flashes[1].1 .0.lock().unwrap(), Some(table(0.0)));
        assert_eq!(sent, 6 * 10);
    }

    /// A push the bus stops mid-way (ENOBUFS from then on, from the fault injector) returns
    /// what it knows of every node, not only the bus error, so the log has a per-node record
    /// and `exocald nodes` does not compare with an older log: `Old` only where no Commit went
    /// out (and the node does hold its old table), `Unknown` with "after its Commit was sent"
    /// where one did (or where the node had not answered yet); never a wrong `New` or `Old`.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_push_the_bus_stops_mid_way_reports_every_node() {
        let (mut before, mut after) = (0, 0);
        for fail_after in [3, 20, 45, 62, 67] {
            let (flashes, tables) = setup(true);
            let (nodes, ep) = spawn_nodes(flashes.clone(), |_| false, vec![]);
            let wire = exocal_bus::FaultConfig {
                fail_sends_after: Some(fail_after),
                ..Default::default()
            };
            let mut bus = exocal_bus::FaultInjector::new(ep, wire, 1);
            let mut sink = |_: bool, _: &Frame, _: Duration| {};
            let failed = push_tables(&mut bus, &Clock::Wall, &tables, &policy(), 9, &mut sink)
                .await
                .expect_err("the bus fails");
            nodes.abort();
            assert!(failed.to_string().contains("mid-way"), "{failed}");
            assert_eq!(failed.report.nodes.len(), 7);
            for (r, ((_, flash), (_, t))) in
                failed.report.nodes.iter().zip(flashes.iter().zip(&tables))
            {
                let held = flash.0.lock().unwrap().unwrap();
                let error = r.error.as_deref().unwrap_or_default();
                match r.holds {
                    Holds::New => assert_eq!(held.crc(), t.crc(), "{r:?}"),
                    Holds::Old => {
                        assert_eq!(held, table(0.0), "{r:?}");
                        assert!(error.contains("before its Commit"), "{r:?}");
                        before += 1;
                    }
                    // Not answered yet: nothing known but that no Commit went out.
                    Holds::Unknown if error.contains("before its Commit") => {
                        assert_eq!(held, table(0.0), "{r:?}");
                    }
                    Holds::Unknown => {
                        assert!(error.contains("after its Commit was sent"), "{r:?}");
                        assert_eq!(r.verified_crc, None, "{r:?}");
                        after += 1;
                    }
                }
            }
        }
        assert!(
            before > 0 && after > 0,
            "{before} before, {after} after a Commit"
        );
    }

    #[test]
    fn the_config_policy_is_usable() {
        let p = Config::default_config().push;
        assert!(p.timeout_ms > 0 && p.retries > 0);
        assert!(
            p.authenticate && p.keys.is_empty(),
            "keys never come from the file"
        );
    }

    fn state_dir(name: &str) -> std::path::PathBuf {
        let d = std::env::temp_dir().join(format!("exocald-push-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        d
    }

    /// With a state directory, a node whose authenticated counter went back
    /// below the last one proved, or jumped above the highest one signed, is refused before
    /// anything is signed (no `CommitAuth` on the bus, not retried, the table stays); within
    /// its window the push goes on and records what the node proved and what was signed.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_counter_that_went_back_or_jumped_is_refused_before_signing() {
        let node = NodeId::JOINTS[1];
        let key = keys().node(node).unwrap().clone();
        for (record, want) in [
            ((10, 11), Err("is above 11")),
            ((60, 60), Err("is below 60")),
            ((49, 50), Ok(())),
        ] {
            let dir = state_dir(&format!("window-{}", record.0));
            let mut counters = NodeCounters::default();
            counters.verified(node, &key, record.0);
            counters.signed(node, &key, record.1);
            counters.save(&dir).unwrap();
            let flash = Flash::holding(table(0.0));
            *flash.1.lock().unwrap() = 50;
            let (nodes, mut ep) = spawn_nodes(vec![(node, flash.clone())], |_| false, vec![]);
            let policy = PushPolicy {
                state_dir: Some(dir.clone()),
                ..policy()
            };
            let mut auths = 0;
            let mut sink = |tx: bool, f: &Frame, _: Duration| {
                if let (true, Ok(Message::TableCmd(c))) = (tx, exocal_dbc::decode_frame(f)) {
                    auths += usize::from(c.cmd.code() == CmdCode::CommitAuth);
                }
            };
            let report = push(&mut ep, &[(node, table(5.0))], &policy, 1, &mut sink).await;
            nodes.abort();
            let r = &report.nodes[0];
            let after = NodeCounters::load(&dir)
                .unwrap()
                .record(node, &key)
                .unwrap();
            match want {
                Err(said) => {
                    assert_eq!((r.holds, r.attempts, auths), (Holds::Old, 1, 0), "{r:?}");
                    assert!(r.error.as_deref().unwrap().contains(said), "{r:?}");
                    assert_eq!(*flash.0.lock().unwrap(), Some(table(0.0)));
                    assert_eq!(r.verified_crc, Some(table(0.0).crc()), "{r:?}");
                    assert_eq!((after.verified, after.signed), record, "nothing recorded");
                }
                Ok(()) => {
                    assert_eq!(r.holds, Holds::New, "{r:?}");
                    assert_eq!(
                        (r.verified_crc, r.counter),
                        (Some(table(5.0).crc()), Some(50))
                    );
                    assert_eq!((after.verified, after.signed), (50, 51));
                    assert_eq!(*flash.1.lock().unwrap(), 51);
                }
            }
            let _ = std::fs::remove_dir_all(&dir);
        }
    }

    /// The counter a `CommitAuth` signs is in the state file before the frame is on the bus;
    /// a state file that does not read pushes nothing.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn the_signed_counter_is_recorded_before_its_commit_auth_goes_out() {
        let node = NodeId::JOINTS[4];
        let key = keys().node(node).unwrap().clone();
        let dir = state_dir("before");
        let flash = Flash::default();
        *flash.1.lock().unwrap() = 7;
        let (nodes, mut ep) = spawn_nodes(vec![(node, flash.clone())], |_| false, vec![]);
        let policy = PushPolicy {
            state_dir: Some(dir.clone()),
            ..policy()
        };
        let mut on_the_bus = Vec::new();
        let mut sink = |tx: bool, f: &Frame, _: Duration| {
            if let (true, Ok(Message::TableCmd(c))) = (tx, exocal_dbc::decode_frame(f)) {
                if c.cmd.code() == CmdCode::CommitAuth {
                    on_the_bus.push(NodeCounters::load(&dir).unwrap().record(node, &key));
                }
            }
        };
        let report = push(&mut ep, &[(node, table(2.0))], &policy, 1, &mut sink).await;
        assert_eq!(report.nodes[0].holds, Holds::New);
        assert!(!on_the_bus.is_empty());
        for r in on_the_bus {
            let r = r.expect("recorded");
            assert_eq!((r.verified, r.signed), (7, 8));
        }
        // A damaged state file: nothing is sent at all.
        std::fs::write(dir.join(crate::state::NODE_COUNTERS), "Joint5 what\n").unwrap();
        let mut sent = 0;
        let mut sink = |tx: bool, _: &Frame, _: Duration| sent += usize::from(tx);
        let report = push(&mut ep, &[(node, table(3.0))], &policy, 9, &mut sink).await;
        nodes.abort();
        let r = &report.nodes[0];
        assert_eq!((r.holds, r.attempts, sent), (Holds::Unknown, 0, 0), "{r:?}");
        assert!(
            r.error.as_deref().unwrap().contains("node-counters"),
            "{r:?}"
        );
        let _ = std::fs::remove_dir_all(&dir);
    }
}
