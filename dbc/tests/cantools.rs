//! Cross-checks with python `cantools`, a DBC parser independent of the `can-dbc` crate that
//! `build.rs` generates the tables with: the generated tables hold what cantools reads from
//! `exocal.dbc`, every message and signal of it; and frames encoded by Rust decode in cantools
//! to the values the Rust messages hold, signal by signal.
//!
//! Needs python3 (and PyPI on first run, to create the venv `tools/pyenv.sh` makes). Without
//! them the tests fail; they never skip.

use exocal_dbc::pose::Pose;
use exocal_dbc::spec::{lookup, MuxRole, ALL};
use exocal_dbc::{
    CmdCode, Command, Field, Heartbeat, ImuVector, JointState, Message, NackReason, NodeId,
    NodeState, PosePage, Reply, TableCmd, TableReply, Trigger, TriggerCommand,
};
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::PathBuf;
use std::process::Command as Proc;

fn crate_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// The python with cantools (created on first use), or a panic saying why not.
pub fn cantools_python() -> PathBuf {
    let out = Proc::new("sh")
        .arg(crate_dir().join("tools/pyenv.sh"))
        .output()
        .expect("sh runs tools/pyenv.sh");
    assert!(
        out.status.success(),
        "tools/pyenv.sh failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    PathBuf::from(String::from_utf8(out.stdout).unwrap().trim())
}

fn cmd_name(c: CmdCode) -> f64 {
    f64::from(c.code())
}

/// What the Rust message says each signal holds: `(name, value)`, NaN for the invalid marker.
fn signals(m: &Message) -> Vec<(&'static str, f64)> {
    match *m {
        Message::JointState(j) => vec![
            ("Timestamp", f64::from(j.timestamp_us)),
            ("Angle", j.angle),
            ("Rate", j.rate),
        ],
        Message::EePose(p) => {
            let mut v = vec![
                ("Page", f64::from(p.page.number())),
                ("Seq", f64::from(p.seq)),
            ];
            match p.page {
                PosePage::TimePosX { timestamp_us, x } => {
                    v.extend([("Timestamp", f64::from(timestamp_us)), ("PosX", x)])
                }
                PosePage::PosYZ { y, z } => v.extend([("PosY", y), ("PosZ", z)]),
                PosePage::QuatWX { w, x } => v.extend([("QuatW", w), ("QuatX", x)]),
                PosePage::QuatYZ { y, z } => v.extend([("QuatY", y), ("QuatZ", z)]),
            }
            v
        }
        Message::ImuGyro(i) | Message::ImuAccel(i) | Message::ImuMag(i) => {
            vec![
                ("X", i.xyz[0]),
                ("Y", i.xyz[1]),
                ("Z", i.xyz[2]),
                ("TimestampLo", f64::from(i.timestamp_lo)),
            ]
        }
        Message::Heartbeat(h) => vec![
            ("State", h.state as u8 as f64),
            ("BootCount", f64::from(h.boot_count)),
            ("TxErrors", f64::from(h.tx_errors)),
            ("RxErrors", f64::from(h.rx_errors)),
            ("TableCrc", f64::from(h.table_crc)),
            ("FwMajor", f64::from(h.fw_major)),
            ("FwMinor", f64::from(h.fw_minor)),
        ],
        Message::TableCmd(c) => {
            let mut v = vec![
                ("Cmd", cmd_name(c.cmd.code())),
                ("Session", f64::from(c.session)),
            ];
            match c.cmd {
                Command::Begin { nonce } => {
                    v.extend([("SegmentCount", 6.0), ("BeginNonce", f64::from(nonce))])
                }
                Command::Segment(f, raw) => v.push((SEG[f as usize], raw as f64 * 1e-6)),
                Command::Commit { crc } => v.push(("TableCrc", f64::from(crc))),
                Command::CommitAuth { counter_lo, mac } => v.extend([
                    ("CounterLo", f64::from(counter_lo)),
                    ("CommitMac", f64::from(mac)),
                ]),
                Command::Readback { nonce } => v.push(("Nonce", f64::from(nonce))),
                Command::Abort => {}
            }
            v
        }
        Message::TableReply(r) => {
            let mut v = vec![("Session", f64::from(r.session))];
            match r.reply {
                Reply::Ack { cmd, held_crc } => v.extend([
                    ("Reply", 0.0),
                    ("AckedCmd", cmd_name(cmd)),
                    ("HeldCrc", f64::from(held_crc)),
                ]),
                Reply::Nack {
                    cmd,
                    held_crc,
                    reason,
                } => v.extend([
                    ("Reply", 1.0),
                    ("NackedCmd", cmd_name(cmd)),
                    ("NackHeldCrc", f64::from(held_crc)),
                    ("NackReason", reason as u8 as f64),
                ]),
                Reply::Readback(f, raw) => v.extend([
                    ("Reply", 16.0 + f64::from(f.seq())),
                    (RB[f as usize], raw as f64 * 1e-6),
                ]),
                Reply::Freshness { counter } => {
                    v.extend([("Reply", 2.0), ("NodeCounter", f64::from(counter))])
                }
                Reply::ReadbackMac { mac } => v.extend([("Reply", 3.0), ("RbMac", f64::from(mac))]),
                Reply::FreshnessMac { mac } => {
                    v.extend([("Reply", 4.0), ("FreshMac", f64::from(mac))])
                }
            }
            v
        }
        Message::Trigger(t) => vec![
            ("Command", t.command as u8 as f64),
            ("CounterLo", f64::from(t.counter_lo)),
            ("Mac", f64::from(t.mac)),
        ],
        Message::StreamDigest(d) => vec![
            ("Seq", f64::from(d.seq_lo)),
            ("Count", f64::from(d.count)),
            ("Mac", d.mac as f64),
        ],
        Message::StreamNonce(n) => vec![("Nonce", f64::from(n.nonce)), ("Mac", f64::from(n.mac))],
    }
}

const SEG: [&str; 6] = [
    "SegA",
    "SegAlpha",
    "SegD",
    "SegThetaOffset",
    "SegTau",
    "SegSigma",
];
const RB: [&str; 6] = ["RbA", "RbAlpha", "RbD", "RbThetaOffset", "RbTau", "RbSigma"];

/// A deterministic spread of messages: every family, every node, edge and middle values.
fn corpus() -> Vec<Message> {
    let mut out = Vec::new();
    let mut lcg = 0x2545_F491_4F6C_DD1Du64;
    let mut unit = move || {
        lcg = lcg
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (lcg >> 11) as f64 / (1u64 << 53) as f64
    };
    for node in NodeId::ALL {
        for k in 0..6 {
            let u = unit();
            let ts = (u * u32::MAX as f64) as u32;
            let edge = |lo: f64, hi: f64, u: f64| match k {
                0 => lo,
                1 => hi,
                2 => f64::NAN,
                _ => lo + (hi - lo) * u,
            };
            if node != NodeId::END_EFFECTOR {
                out.push(Message::JointState(JointState {
                    node,
                    timestamp_us: ts,
                    angle: edge(-5.24287, 5.24287, unit()),
                    rate: edge(-20.47, 20.47, unit()),
                }));
            }
            let imu = |r: f64, a: f64, b: f64, c: f64| ImuVector {
                node,
                xyz: [
                    edge(-r, r, a),
                    edge(-r, r, b),
                    if k == 2 { 0.0 } else { edge(-r, r, c) },
                ],
                timestamp_lo: ts as u16,
            };
            out.push(Message::ImuGyro(imu(32.767, unit(), unit(), unit())));
            out.push(Message::ImuAccel(imu(65.534, unit(), unit(), unit())));
            out.push(Message::ImuMag(imu(327.67, unit(), unit(), unit())));
            out.push(Message::Heartbeat(Heartbeat {
                node,
                state: [
                    NodeState::Boot,
                    NodeState::Operational,
                    NodeState::Staging,
                    NodeState::Fault,
                ][k % 4],
                boot_count: (ts % 16) as u8,
                tx_errors: (ts >> 8) as u8,
                rx_errors: (ts >> 16) as u8,
                table_crc: ts,
                fw_major: (k % 16) as u8,
                fw_minor: 15 - k as u8,
            }));
            if node != NodeId::END_EFFECTOR {
                let session = (ts >> 24) as u8;
                let f = Field::ALL[k];
                let (lo, hi) = f.raw_bounds();
                let raw = [
                    lo,
                    hi,
                    0,
                    lo + ((hi - lo) as f64 * unit()) as i64,
                    hi / 3,
                    lo + 1,
                ][k];
                let cmds = [
                    Command::Begin {
                        nonce: ts.rotate_left(7),
                    },
                    Command::Segment(f, raw),
                    Command::Commit { crc: ts },
                    Command::CommitAuth {
                        counter_lo: ts as u16,
                        mac: !ts,
                    },
                    Command::Readback { nonce: ts ^ 0x5555 },
                    Command::Abort,
                ];
                for cmd in cmds {
                    out.push(Message::TableCmd(TableCmd { node, session, cmd }));
                }
                let reasons = [
                    NackReason::BadSession,
                    NackReason::CrcMismatch,
                    NackReason::NoTable,
                    NackReason::BadMac,
                    NackReason::StaleCounter,
                    NackReason::NoKey,
                ];
                for reply in [
                    Reply::Ack {
                        cmd: CmdCode::Segment(f),
                        held_crc: ts,
                    },
                    Reply::Nack {
                        cmd: CmdCode::Commit,
                        held_crc: !ts,
                        reason: reasons[k % reasons.len()],
                    },
                    Reply::Readback(f, raw),
                    Reply::Freshness { counter: ts },
                    Reply::ReadbackMac { mac: !ts },
                    Reply::FreshnessMac { mac: ts ^ 0xa5a5 },
                ] {
                    out.push(Message::TableReply(TableReply {
                        node,
                        session,
                        reply,
                    }));
                }
            }
        }
    }
    for seq in [0u8, 1, 62, 63] {
        let (s, c) = (0.3f64.sin(), 0.3f64.cos());
        let pose = Pose {
            seq,
            timestamp_us: u32::MAX - u32::from(seq),
            position: [-2.0, 0.123456, 2.0],
            quat: [c, 0.0, s, 0.0],
        };
        out.extend(pose.pages().map(Message::EePose));
    }
    for (command, counter_lo, mac) in [
        (TriggerCommand::StartCalibration, 0, 0),
        (TriggerCommand::Abort, u16::MAX, u32::MAX),
        (TriggerCommand::StartCalibration, 0x1234, 0xdead_beef),
    ] {
        out.push(Message::Trigger(Trigger {
            command,
            counter_lo,
            mac,
        }));
    }
    out
}

#[test]
fn rust_encoded_frames_decode_identically_in_cantools() {
    let mut lines = String::new();
    let corpus = corpus();
    for m in &corpus {
        let (id, data, _) = m.encode().unwrap_or_else(|e| panic!("{m:?}: {e}"));
        let values: Vec<String> = signals(m)
            .into_iter()
            .map(|(n, v)| {
                if v.is_nan() {
                    format!("{n}=Invalid")
                } else {
                    format!("{n}={v:?}")
                }
            })
            .collect();
        let hex: String = data.iter().map(|b| format!("{b:02x}")).collect();
        writeln!(lines, "{id:03x} {hex} {}", values.join(",")).unwrap();
    }
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR"));
    let input = dir.join("cantools_frames.txt");
    std::fs::write(&input, lines).unwrap();
    let stdout = run_python(
        "cantools_check.py",
        &[&crate_dir().join("exocal.dbc"), &input],
    );
    assert!(
        stdout.contains(&format!("checked {} frames, 0 mismatches", corpus.len())),
        "{stdout}"
    );
}

/// Runs one of the python scripts in `tests/` with the given arguments; its stdout.
fn run_python(script: &str, args: &[&std::path::Path]) -> String {
    let out = Proc::new(cantools_python())
        .arg(crate_dir().join("tests").join(script))
        .args(args)
        .output()
        .expect("python runs");
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        out.status.success(),
        "{script} failed:\n{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    stdout
}

#[test]
fn generated_tables_hold_what_cantools_reads_from_the_dbc() {
    let dump = run_python("cantools_layout.py", &[&crate_dir().join("exocal.dbc")]);
    // Signals seen per message name.
    let mut seen: BTreeMap<String, usize> = BTreeMap::new();
    for line in dump.lines() {
        let fields: [&str; 16] = line
            .split('\t')
            .collect::<Vec<_>>()
            .try_into()
            .unwrap_or_else(|_| panic!("unexpected line {line:?}"));
        let [id, extended, message, dlc, name, start, len, order, signed, scale, offset, min, max, unit, mux, choices] =
            fields;
        let what = format!("{message}.{name}");
        assert_eq!(
            (extended, dlc, order),
            ("False", "8", "little_endian"),
            "{what}"
        );
        let id = u16::from_str_radix(id, 16).unwrap();
        let (spec, node) =
            lookup(id).unwrap_or_else(|| panic!("{message} ({id:#x}) not generated"));
        let full = match node {
            Some(node) => format!("{}_{}", spec.name, node.name()),
            None => spec.name.to_string(),
        };
        assert_eq!(full, message, "name of {id:#x}");
        let s = spec
            .signal(name)
            .unwrap_or_else(|| panic!("{what} not generated"));
        let float = |v: &str| v.parse::<f64>().unwrap();
        assert_eq!(s.start.to_string(), start, "{what} start");
        assert_eq!(s.len.to_string(), len, "{what} length");
        assert_eq!(
            s.signed.to_string(),
            signed.to_lowercase(),
            "{what} signedness"
        );
        // repr() and Rust's parser both round exactly: the doubles must be equal, not close.
        assert_eq!(s.factor, float(scale), "{what} factor");
        assert_eq!(s.offset, float(offset), "{what} offset");
        assert_eq!(s.min, float(min), "{what} min");
        assert_eq!(s.max, float(max), "{what} max");
        assert_eq!(s.unit, unit, "{what} unit");
        let role = match mux {
            "M" => MuxRole::Switch,
            "-" => MuxRole::Plain,
            case => MuxRole::Case(case.strip_prefix('m').unwrap().parse().unwrap()),
        };
        assert_eq!(s.mux, role, "{what} multiplexing");
        let mut invalid = None;
        let mut values = Vec::new();
        for choice in choices.split(';').filter(|c| !c.is_empty()) {
            let (raw, label) = choice.split_once('=').unwrap();
            let raw: i64 = raw.parse().unwrap();
            if label == "Invalid" {
                invalid = Some(raw);
            } else {
                values.push((raw, label));
            }
        }
        assert_eq!(s.invalid_raw, invalid, "{what} invalid marker");
        assert_eq!(s.values, values, "{what} VAL_ table");
        *seen.entry(full).or_default() += 1;
    }
    // Nothing generated that the DBC lacks: every family, every node, every signal.
    let mut generated = BTreeMap::new();
    for spec in ALL {
        let names: Vec<String> = if spec.nodes.is_empty() {
            vec![spec.name.to_string()]
        } else {
            spec.nodes
                .iter()
                .map(|&n| format!("{}_{}", spec.name, NodeId::new(n).unwrap().name()))
                .collect()
        };
        for name in names {
            generated.insert(name, spec.signals.len());
        }
    }
    assert_eq!(seen, generated);
}
