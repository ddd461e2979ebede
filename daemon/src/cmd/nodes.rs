//! `exocald nodes`: what each joint node holds, asked over the bus, against the last push.
//!
//! Contract:
//! - every joint node is sent a table `Readback` (the read of the table transfer protocol,
//!   `exocal_dbc::transfer`), all nodes at once, each resent after `push.timeout_ms` up to
//!   [`RetryPolicy::max_attempts`] times; the answer — six fields, then an ACK carrying the CRC
//!   of the table held, or a NACK `NoTable` — is folded by [`TableRead::on_reply`], the one
//!   place that judges a node's answer; an answer whose fields do not give the CRC it states is
//!   not an answer. With keys (`push.authenticate`), each Readback carries a fresh nonce and an
//!   answer counts only with a `ReadbackMac` that verifies over it (a forged answer is no
//!   answer, as in the push); each node's line says whether its answer was signed;
//! - "the last push" of a node is the push outcome the newest session log (by modification
//!   time) of the output directory records for it in its `/calibration` record
//!   ([`exocal_log::proto::NodePush`]): the CRC the node proved holding at the end of the push,
//!   in an answer whose MAC verified (`verified_crc`). Never a readback found in `/can/rx`: any
//!   sender on the bus can put one there after the verified one. A node the push
//!   proved nothing of is shown with its outcome and compared with nothing. A log cut short is
//!   read through [`exocal_log::recover`]. `--log FILE` names the log instead;
//! - a node that does not answer is named; [`read_tables`] never fails for a silent node, only
//!   for the bus ([`exocal_bus::BusError`]).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Duration;

use exocal_bus::{Clock, Frame, Transport};
use exocal_dbc::auth::{self, Key, KeySet};
use exocal_dbc::message::{CmdCode, Command, NackReason, Reply, TableCmd, TableReply};
use exocal_dbc::table::{Field, Table};
use exocal_dbc::transfer::RetryPolicy;
use exocal_dbc::{Message, NodeId};
use serde::Serialize;

use crate::exit::DaemonError;

/// What a node answered to a table read.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Answer {
    /// It holds `table` (whose CRC it stated).
    Holds(Table),
    /// It holds no table (NACK `NoTable`, CRC 0).
    NoTable,
}

/// One node's table read, in one transfer session: the command to send and the replies folded
/// into an [`Answer`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TableRead {
    node: NodeId,
    session: u8,
    fields: [Option<i64>; 6],
    /// The node's key and this read's nonce: the answer must carry a MAC over them.
    auth: Option<(Key, u32)>,
    mac: Option<u32>,
    answer: Option<Answer>,
}

impl TableRead {
    /// A read of `node`'s table in transfer session `session`.
    pub fn new(node: NodeId, session: u8) -> Self {
        TableRead {
            node,
            session,
            fields: [None; 6],
            auth: None,
            mac: None,
            answer: None,
        }
    }

    /// A read whose answer counts only with a `ReadbackMac` by `key` over `nonce`.
    pub fn authenticated(node: NodeId, session: u8, key: Key, nonce: u32) -> Self {
        TableRead {
            auth: Some((key, nonce)),
            ..TableRead::new(node, session)
        }
    }

    /// The command that asks for the table.
    pub fn command(&self) -> TableCmd {
        TableCmd {
            node: self.node,
            session: self.session,
            cmd: Command::Readback {
                nonce: self.auth.as_ref().map_or(0, |(_, nonce)| *nonce),
            },
        }
    }

    /// The answer, once complete.
    pub fn answer(&self) -> Option<Answer> {
        self.answer
    }

    /// Folds one reply in; replies of other nodes, sessions or commands are ignored. A resent
    /// `Readback` is answered again from the first field, so a field seen twice is the later.
    pub fn on_reply(&mut self, reply: &TableReply) {
        if reply.node != self.node || reply.session != self.session || self.answer.is_some() {
            return;
        }
        match reply.reply {
            Reply::Readback(field, raw) => self.fields[field as usize] = Some(raw),
            Reply::ReadbackMac { mac } => self.mac = Some(mac),
            Reply::Ack {
                cmd: CmdCode::Readback,
                held_crc,
            } => {
                let raw = self.fields.map(|f| f.unwrap_or(i64::MIN));
                let signed = |t: &Table| match &self.auth {
                    None => true,
                    Some((key, nonce)) => {
                        self.mac
                            == Some(auth::readback_mac(
                                key,
                                self.node,
                                *nonce,
                                held_crc,
                                &t.to_bytes(),
                            ))
                    }
                };
                self.answer = Table::from_raw(raw)
                    .ok()
                    .filter(|t| t.crc() == held_crc && signed(t))
                    .map(Answer::Holds);
                self.fields = [None; 6];
                self.mac = None;
            }
            Reply::Nack {
                cmd: CmdCode::Readback,
                reason: NackReason::NoTable,
                ..
            } => self.answer = Some(Answer::NoTable),
            _ => {}
        }
    }
}

fn micros(d: Duration) -> u64 {
    d.as_micros().min(u128::from(u64::MAX)) as u64
}

/// Reads the table of every node in `nodes` (see the module docs): its answer, or `None` for a
/// node that did not answer after `attempts` sends `timeout` apart. `first_session` numbers the
/// transfer sessions (one per node, mod 256). With `keys`, a node's answer counts only if it
/// is signed by its key ([`TableRead::authenticated`]); a node without a key in `keys` is read
/// unauthenticated.
pub async fn read_tables<T: Transport>(
    bus: &mut T,
    clock: &Clock,
    nodes: &[NodeId],
    timeout: Duration,
    attempts: u32,
    first_session: u8,
    keys: Option<&KeySet>,
) -> Result<Vec<(NodeId, Option<Answer>)>, exocal_bus::BusError> {
    struct Pending {
        read: TableRead,
        sends: u32,
        deadline_us: u64,
    }
    let mut pending: Vec<Pending> = nodes
        .iter()
        .enumerate()
        .map(|(i, &node)| Pending {
            read: {
                let session = first_session.wrapping_add(i as u8);
                match keys.and_then(|k| k.node(node)) {
                    Some(key) => {
                        let seed = crate::keys::nonce_seed();
                        let nonce = auth::nonce(key, node, session, seed, micros(clock.now()));
                        TableRead::authenticated(node, session, key.clone(), nonce)
                    }
                    None => TableRead::new(node, session),
                }
            },
            sends: 0,
            deadline_us: 0,
        })
        .collect();
    let timeout_us = micros(timeout).max(1);
    loop {
        let now_us = micros(clock.monotonic());
        for p in pending.iter_mut().filter(|p| p.read.answer().is_none()) {
            if now_us >= p.deadline_us && p.sends < attempts {
                p.sends += 1;
                p.deadline_us = now_us + timeout_us;
                if let Ok(frame) = Message::TableCmd(p.read.command()).to_frame::<Frame>() {
                    bus.send(&frame).await?;
                }
            }
        }
        let waiting = pending.iter().filter(|p| {
            p.read.answer().is_none() && !(p.sends >= attempts && now_us >= p.deadline_us)
        });
        let Some(next_us) = waiting.map(|p| p.deadline_us).min() else {
            break;
        };
        let wait = Duration::from_micros(next_us.saturating_sub(now_us).max(1_000));
        match tokio::time::timeout(wait, bus.recv()).await {
            Ok(Ok(rx)) => {
                if let Ok(Message::TableReply(reply)) = exocal_dbc::decode_frame(&rx.frame) {
                    for p in pending.iter_mut() {
                        p.read.on_reply(&reply);
                    }
                }
            }
            Ok(Err(e)) => return Err(e),
            Err(_) => {}
        }
    }
    Ok(pending
        .into_iter()
        .map(|p| (p.read.node, p.read.answer()))
        .collect())
}

/// What a session log says the last push left on a node.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LastPush {
    /// The CRC the node proved holding at the end of the push (an answer whose MAC verified);
    /// `None` when the push proved nothing of it.
    pub verified_crc: Option<u32>,
    /// The CRC of the table the push sent it.
    pub sent_crc: u32,
    /// The push's outcome for it (`new`, `old`, `unknown`).
    pub holds: String,
}

/// The push outcome per node recorded in a session log ([`exocal_log::read::McapSession::push`]).
pub fn pushed(records: &[exocal_log::proto::NodePush]) -> BTreeMap<NodeId, LastPush> {
    records
        .iter()
        .filter_map(|r| {
            let node = NodeId::JOINTS.into_iter().find(|n| n.name() == r.node)?;
            let last = LastPush {
                verified_crc: r.verified_crc,
                sent_crc: r.new_crc,
                holds: r.holds.clone(),
            };
            Some((node, last))
        })
        .collect()
}

/// A session log's push outcome per node ([`pushed`]), read as a stream without its frames (the
/// memory of one chunk, whatever the log's size); a log cut short is read up to where it stops.
pub fn log_push(path: &Path) -> Result<BTreeMap<NodeId, LastPush>, DaemonError> {
    let file = std::fs::File::open(path).map_err(|source| DaemonError::Io {
        what: format!("reading {}", path.display()),
        source,
    })?;
    let session = exocal_log::read::read_mcap_record(std::io::BufReader::new(file))
        .map_err(|e| DaemonError::Input(format!("{}: {e}", path.display())))?;
    Ok(pushed(&session.push))
}

/// A session log, and what its push left on each node ([`pushed`]).
pub type Pushed = (PathBuf, BTreeMap<NodeId, LastPush>);

/// The newest session log in `dir` (by modification time) that records a push, with its
/// outcome per node; `None` if no log has one. Unreadable logs are skipped, each named on
/// stderr.
pub fn last_push(dir: &Path) -> Result<Option<Pushed>, DaemonError> {
    let entries = match std::fs::read_dir(dir) {
        Ok(e) => e,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(source) => {
            return Err(DaemonError::Io {
                what: format!("listing {}", dir.display()),
                source,
            })
        }
    };
    let mut logs: Vec<(std::time::SystemTime, PathBuf)> = entries
        .filter_map(Result::ok)
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|x| x == "mcap"))
        .filter_map(|p| Some((std::fs::metadata(&p).ok()?.modified().ok()?, p)))
        .collect();
    logs.sort();
    for (_, path) in logs.into_iter().rev() {
        match log_push(&path) {
            Ok(t) if !t.is_empty() => return Ok(Some((path, t))),
            Ok(_) => {}
            Err(e) => eprintln!("exocald: skipping {}: {e}", path.display()),
        }
    }
    Ok(None)
}

/// `exocald nodes` on `bus`: reads every joint node of `config` (push timeout, as many sends as
/// an upload makes of one command), then compares with the tables of `log`, or of the last push
/// in `output.directory` ([`last_push`]).
pub async fn list<T: Transport>(
    bus: &mut T,
    clock: &Clock,
    config: &crate::config::Config,
    log: Option<&Path>,
) -> Result<Listing, DaemonError> {
    let nodes = config.joint_node_ids();
    let session = (micros(clock.now()) / 1000 % 251) as u8;
    let answers = read_tables(
        bus,
        clock,
        &nodes,
        Duration::from_millis(config.push.timeout_ms),
        RetryPolicy::default().max_attempts,
        session,
        config.push.authenticate.then_some(&config.push.keys),
    )
    .await
    .map_err(|source| DaemonError::Bus {
        what: "reading the nodes' tables".into(),
        source,
    })?;
    let last = match log {
        Some(p) => Some((p.to_path_buf(), log_push(p)?)),
        None => last_push(&config.output.directory)?,
    };
    let signed: Vec<bool> = nodes
        .iter()
        .map(|&n| config.push.authenticate && config.push.keys.node(n).is_some())
        .collect();
    Ok(Listing::new(&config.interface, &answers, &signed, last))
}

/// A table in SI units, for people and scripts.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct TableSi {
    /// D-H link length a (m).
    pub a_m: f64,
    /// D-H link twist α (rad).
    pub alpha_rad: f64,
    /// D-H link offset d (m).
    pub d_m: f64,
    /// D-H joint-angle offset (rad).
    pub theta_offset_rad: f64,
    /// Drift correlation time τ (s).
    pub tau_s: f64,
    /// Drift σ as the paper defines it (eq. 8, rad/s, on the session's grid Δt); the
    /// stationary deviation of the angle error is σ·Δt/√(1+e^(−Δt/τ)).
    pub sigma_rad_s: f64,
}

impl From<&Table> for TableSi {
    fn from(t: &Table) -> Self {
        TableSi {
            a_m: t.si(Field::A),
            alpha_rad: t.si(Field::Alpha),
            d_m: t.si(Field::D),
            theta_offset_rad: t.si(Field::ThetaOffset),
            tau_s: t.si(Field::Tau),
            sigma_rad_s: t.si(Field::Sigma),
        }
    }
}

/// One node in the listing.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct NodeStatus {
    /// The node's name (`Joint1` … `Joint7`).
    pub node: String,
    /// Its CAN node id.
    pub id: u8,
    /// Whether it answered the table query.
    pub answered: bool,
    /// CRC-32 of the table held (0: none), when it answered.
    pub crc: Option<u32>,
    /// The table held, when it answered and holds one.
    pub table: Option<TableSi>,
    /// Whether its answer was signed (a `ReadbackMac` over our nonce that verified).
    pub signed: bool,
    /// CRC of the table the last push left on it, as the node proved it then (the log's push
    /// record, `verified_crc`); `None` when the log proved nothing of this node.
    pub last_pushed_crc: Option<u32>,
    /// The last push's outcome for it (`new`, `old`, `unknown`), when the log has one.
    pub last_push: Option<String>,
    /// Whether it holds that table (`None`: no answer, or nothing proved to compare with).
    pub matches_last_push: Option<bool>,
}

/// The whole listing (what `--json` prints).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Listing {
    /// The CAN interface the nodes were read on.
    pub interface: String,
    /// The session log compared with, if any.
    pub compared_with: Option<PathBuf>,
    /// One entry per node queried.
    pub nodes: Vec<NodeStatus>,
    /// The nodes that did not answer.
    pub missing: Vec<String>,
}

impl Listing {
    /// The listing of `answers` (each `signed` or not), compared with what `last` (a log and
    /// its push outcome) proved.
    pub fn new(
        interface: &str,
        answers: &[(NodeId, Option<Answer>)],
        signed: &[bool],
        last: Option<Pushed>,
    ) -> Listing {
        let (compared_with, pushed) = match last {
            Some((p, t)) => (Some(p), t),
            None => (None, BTreeMap::new()),
        };
        let nodes: Vec<NodeStatus> = answers
            .iter()
            .enumerate()
            .map(|(i, (node, answer))| {
                let held = match answer {
                    Some(Answer::Holds(t)) => Some(*t),
                    _ => None,
                };
                let crc = answer.map(|_| held.map_or(0, |t| t.crc()));
                let last = pushed.get(node);
                let proved = last.and_then(|l| l.verified_crc);
                NodeStatus {
                    node: node.name().to_string(),
                    id: node.raw(),
                    answered: answer.is_some(),
                    crc,
                    table: held.as_ref().map(TableSi::from),
                    signed: answer.is_some() && signed.get(i).copied().unwrap_or(false),
                    last_pushed_crc: proved,
                    last_push: last.map(|l| l.holds.clone()),
                    matches_last_push: match (crc, proved) {
                        (Some(c), Some(p)) => Some(c == p),
                        _ => None,
                    },
                }
            })
            .collect();
        let missing = nodes
            .iter()
            .filter(|n| !n.answered)
            .map(|n| n.node.clone())
            .collect();
        Listing {
            interface: interface.to_string(),
            compared_with,
            nodes,
            missing,
        }
    }

    /// The table for people: one line per node, then what it was compared with and a count.
    pub fn lines(&self) -> Vec<String> {
        let mut out = vec![format!(
            "{:<7} {:>2} {:<10} {:>9} {:>9} {:>9} {:>10} {:>7} {:>11}  {}",
            "node",
            "id",
            "CRC",
            "a (mm)",
            "α (°)",
            "d (mm)",
            "θ off (°)",
            "τ (s)",
            "σ (rad/s)",
            "last push"
        )];
        for n in &self.nodes {
            let mut vs = match (n.matches_last_push, n.last_pushed_crc, &n.last_push) {
                (Some(true), _, _) => "holds it".to_string(),
                (Some(false), Some(c), _) => format!("differs (pushed {c:#010x})"),
                (None, Some(c), _) if !n.answered => format!("(pushed {c:#010x})"),
                (_, None, Some(h)) => format!("not proved by the push ({h})"),
                _ => "-".to_string(),
            };
            if n.answered && !n.signed {
                vs.push_str(" [unsigned answer]");
            }
            let line = match (&n.table, n.answered) {
                (Some(t), _) => format!(
                    "{:<7} {:>2} {:<10} {:>9.3} {:>9.4} {:>9.3} {:>10.4} {:>7.3} {:>11.4}  {vs}",
                    n.node,
                    n.id,
                    format!("{:#010x}", n.crc.unwrap_or(0)),
                    t.a_m * 1e3,
                    t.alpha_rad.to_degrees(),
                    t.d_m * 1e3,
                    t.theta_offset_rad.to_degrees(),
                    t.tau_s,
                    t.sigma_rad_s
                ),
                (None, true) => format!(
                    "{:<7} {:>2} {:<10} holds no table  {vs}",
                    n.node, n.id, "0x00000000"
                ),
                (None, false) => format!("{:<7} {:>2} no answer  {vs}", n.node, n.id),
            };
            out.push(line);
        }
        out.push(match &self.compared_with {
            Some(p) => format!(
                "last push: the tables the nodes proved holding (signed answers) in {}",
                p.display()
            ),
            None => "last push: no session log with a push in the output directory".into(),
        });
        let answered = self.nodes.iter().filter(|n| n.answered).count();
        let matching = self
            .nodes
            .iter()
            .filter(|n| n.matches_last_push == Some(true))
            .count();
        let mut summary = format!("{answered} of {} nodes answered", self.nodes.len());
        if self.compared_with.is_some() {
            summary.push_str(&format!(", {matching} hold the table last pushed"));
        }
        if !self.missing.is_empty() {
            summary.push_str(&format!("; no answer from {}", self.missing.join(", ")));
        }
        out.push(summary);
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The listing compares with what the push proved (`verified_crc`), not
    /// with what it sent or claimed. A node whose push proved nothing (all its answers forged
    /// or lost) is "not proved", even when it holds the sent table; a push that proved the old
    /// table makes a node holding the sent one "differs".
    #[test]
    fn the_listing_compares_with_the_verified_crc_of_the_push_record() {
        let sent = Table::from_si(0.03, -1.5, 0.03, 0.01, 1.2, 0.9).unwrap();
        let old = Table::from_si(0.031, -1.5, 0.03, 0.01, 1.2, 0.9).unwrap();
        let record =
            |node: NodeId, holds: &str, verified: Option<u32>| exocal_log::proto::NodePush {
                node: node.name().to_string(),
                new_crc: sent.crc(),
                holds: holds.to_string(),
                verified_crc: verified,
                ..Default::default()
            };
        let [j1, j2, j3] = [NodeId::JOINTS[0], NodeId::JOINTS[1], NodeId::JOINTS[2]];
        let records = [
            record(j1, "new", Some(sent.crc())),
            record(j2, "unknown", None),
            record(j3, "old", Some(old.crc())),
        ];
        let last = Some((PathBuf::from("s.mcap"), pushed(&records)));
        let answers = [
            (j1, Some(Answer::Holds(sent))),
            (j2, Some(Answer::Holds(sent))),
            (j3, Some(Answer::Holds(sent))),
        ];
        let listing = Listing::new("vcan0", &answers, &[true; 3], last);
        let got: Vec<_> = listing
            .nodes
            .iter()
            .map(|n| (n.last_pushed_crc, n.matches_last_push))
            .collect();
        assert_eq!(
            got,
            [
                (Some(sent.crc()), Some(true)),
                (None, None),
                (Some(old.crc()), Some(false)),
            ]
        );
        let text = listing.lines().join("\n");
        assert!(text.contains("not proved by the push (unknown)"), "{text}");
        assert!(
            text.contains(&format!("differs (pushed {:#010x})", old.crc())),
            "{text}"
        );
    }
}
