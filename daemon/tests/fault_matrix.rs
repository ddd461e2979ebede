//! The fault matrix: one seeded, time-bounded daemon session (`run_session`, the same code as
//! `exocald calibrate`) against the emulated suit on the in-process bus per fault class the hil
//! can inject, checked for:
//! - no panic, and a session that ends (success or a typed refusal/error);
//! - the degraded node reported (clock jumps/reboots in the clock report, a babbling node named
//!   by its repeated frames, malformed/NaN frame counts, a silent node's push entry not `New`);
//! - no table that fails validation pushed: if the verdict refuses, nothing is pushed and every
//!   node's flash still holds its factory table; whatever a node's flash holds is its factory
//!   table or exactly the table pushed to it;
//! - with loss ≤ 10 %, the held-out mean pose error within 2× of the clean run's;
//! - loss bursts, reordering and delay accepted: they cost frames, which alignment bridges
//!   (and the EM's jump test knows the fills), not the calibration.
//!
//! `cargo test -p exocald --test fault_matrix` runs the bounded CI subset. The whole matrix,
//! which rewrites `docs/faults.md`:
//! `EXOCAL_FAULTS_FULL=1 EXOCAL_FAULTS_DOC=docs/faults.md cargo test -p exocald --test fault_matrix -- --nocapture`.

use std::path::{Path, PathBuf};

use exocal_bus::InProcessBus;
use exocal_bus::SimClock;
use exocal_dbc::NodeId;
use exocal_hil::scenario::{
    Babble, ClockJump, NodeClockSpec, Reboot, Scenario, TransferBehaviour, TransferFault,
};
use exocal_hil::Hil;
use exocald::cmd::demo::{session_against_suit, RunningSuit, SuitSession};
use exocald::config::Config;
use exocald::push::Holds;
use exocald::shell::summary::SessionSummary;

const SPEED: f64 = 10.0;
const SESSION_S: f64 = 40.0;

/// What a case expects the daemon to notice.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Expect {
    /// Nothing in particular (clean or loss-like faults).
    Nothing,
    /// The fault costs frames, not the calibration: the session is accepted (a loss burst, a
    /// page held back: alignment bridges the holes, and the EM's jump test knows the fills).
    Accepted,
    /// Clock discontinuities on this node (reboot, jump).
    ClockJump(u8),
    /// Frames refused as malformed or unknown.
    Malformed,
    /// This node named as babbling (repeating its frames), and no other.
    Babbling(u8),
    /// Joint angles flagged invalid.
    Nan,
    /// This node does not hold the new table and the push report says so.
    PushFails(u8),
    /// Clock skew of this node (ppm, node rate) seen by the daemon within 100 ppm.
    Skew(u8, f64),
    /// The verdict refuses the calibration (and so nothing is pushed).
    Refused,
}

struct Case {
    name: &'static str,
    ci: bool,
    /// Loss-like: the held-out accuracy must stay within 2× of the clean run.
    accuracy_bound: bool,
    expect: Expect,
    apply: fn(&mut Scenario),
}

/// The security case: the configured anatomical bounds exclude the true arm (a₃ = 0.401 m,
/// bounds [0.42, 0.485] m), so the calibrated table is out of bounds and must never be pushed.
const OUT_OF_BOUNDS: &str = "table outside the anatomical bounds";

fn cases() -> Vec<Case> {
    vec![
        Case {
            name: "clean",
            ci: true,
            accuracy_bound: true,
            expect: Expect::Nothing,
            apply: |_| {},
        },
        Case {
            name: "loss 0.1%",
            ci: false,
            accuracy_bound: true,
            expect: Expect::Nothing,
            apply: |s| s.faults.loss = 0.001,
        },
        Case {
            name: "loss 1%",
            ci: false,
            accuracy_bound: true,
            expect: Expect::Nothing,
            apply: |s| s.faults.loss = 0.01,
        },
        Case {
            name: "loss 10%",
            ci: true,
            accuracy_bound: true,
            expect: Expect::Nothing,
            apply: |s| s.faults.loss = 0.10,
        },
        Case {
            name: "loss bursts (0.5% start, 20 frames)",
            ci: true,
            accuracy_bound: true,
            expect: Expect::Accepted,
            apply: |s| {
                s.faults.burst_start = 0.005;
                s.faults.burst_len = 20;
            },
        },
        Case {
            name: "duplication 5%",
            ci: false,
            accuracy_bound: true,
            expect: Expect::Nothing,
            apply: |s| s.faults.duplicate = 0.05,
        },
        Case {
            name: "reordering 5% ≤ 20 ms",
            ci: false,
            accuracy_bound: true,
            expect: Expect::Accepted,
            apply: |s| {
                s.faults.reorder = 0.05;
                s.faults.reorder_max_ms = 20.0;
            },
        },
        Case {
            name: "delay 5% × 50 ms",
            ci: false,
            accuracy_bound: true,
            expect: Expect::Accepted,
            apply: |s| {
                s.faults.delay = 0.05;
                s.faults.delay_ms = 50.0;
            },
        },
        Case {
            name: "clock skew +200 ppm (node 3)",
            ci: false,
            accuracy_bound: true,
            expect: Expect::Skew(3, 200.0),
            apply: |s| {
                s.clocks.node.push(NodeClockSpec {
                    node: 3,
                    offset_us: None,
                    skew_ppm: Some(200.0),
                    jitter_us: None,
                });
            },
        },
        Case {
            name: "clock skew −200 ppm (node 5)",
            ci: false,
            accuracy_bound: true,
            expect: Expect::Skew(5, -200.0),
            apply: |s| {
                s.clocks.node.push(NodeClockSpec {
                    node: 5,
                    offset_us: None,
                    skew_ppm: Some(-200.0),
                    jitter_us: None,
                });
            },
        },
        Case {
            name: "clock jump +0.5 s (node 2)",
            ci: false,
            accuracy_bound: false,
            expect: Expect::ClockJump(2),
            apply: |s| {
                s.faults.clock_jumps.push(ClockJump {
                    node: 2,
                    at_s: 15.0,
                    jump_us: 500_000.0,
                });
            },
        },
        Case {
            name: "node reboot mid-session (node 4)",
            ci: true,
            accuracy_bound: false,
            expect: Expect::ClockJump(4),
            apply: |s| {
                s.faults.reboots.push(Reboot {
                    node: 4,
                    at_s: 20.0,
                    down_s: 0.5,
                });
            },
        },
        Case {
            name: "babbling node (node 6, 2 kHz, 5 s)",
            ci: false,
            accuracy_bound: false,
            expect: Expect::Babbling(6),
            apply: |s| {
                s.faults.babble.push(Babble {
                    node: 6,
                    from_s: 10.0,
                    to_s: 15.0,
                    rate_hz: 2000.0,
                });
            },
        },
        Case {
            name: "malformed frames 50/s",
            ci: true,
            accuracy_bound: true,
            expect: Expect::Malformed,
            apply: |s| s.faults.malformed_hz = 50.0,
        },
        Case {
            name: "NaN values 1%",
            ci: false,
            accuracy_bound: true,
            expect: Expect::Nan,
            apply: |s| s.faults.nan = 0.01,
        },
        Case {
            name: "node never answers transfers (node 7)",
            ci: true,
            accuracy_bound: true,
            expect: Expect::PushFails(7),
            apply: |s| {
                s.faults.transfer.push(TransferFault {
                    node: 7,
                    behaviour: TransferBehaviour::Silent,
                });
            },
        },
        Case {
            name: "node refuses transfers (node 1, NACK)",
            ci: false,
            accuracy_bound: true,
            expect: Expect::PushFails(1),
            apply: |s| {
                s.faults.transfer.push(TransferFault {
                    node: 1,
                    behaviour: TransferBehaviour::Nack,
                });
            },
        },
        Case {
            name: OUT_OF_BOUNDS,
            ci: true,
            accuracy_bound: false,
            expect: Expect::Refused,
            apply: |_| {},
        },
    ]
}

fn temp_dir(name: &str) -> PathBuf {
    let slug: String = name
        .chars()
        .map(|c| if c.is_ascii_alphanumeric() { c } else { '-' })
        .collect();
    let d = std::env::temp_dir().join(format!("exocal-faults-{}-{slug}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

async fn run_case(case: &Case) -> SuitSession {
    let dir = temp_dir(case.name);
    let flash_dir = dir.join("flash");
    std::fs::create_dir_all(&flash_dir).unwrap();
    let mut scenario = Scenario::paper();
    scenario.seed = 7;
    (case.apply)(&mut scenario);
    scenario.validate().expect("case scenario is valid");
    let mut config = exocald::cmd::demo::demo_config(Config::default_config(), &dir, SPEED);
    config.calibration.window.min_duration_s = SESSION_S;
    config.calibration.window.max_duration_s = SESSION_S + 20.0;
    if case.name == OUT_OF_BOUNDS {
        config.calibration.bounds.a[2] = (0.42, 0.485);
    }
    scenario.duration_s = config.calibration.window.max_duration_s + 120.0;
    // Authenticated, as on a suit (the demo's derived keys).
    config.push.keys = exocal_dbc::auth::KeySet::derived(7);
    // The wire's faults are this matrix's subject: the stream gate would drop every span a
    // lost, duplicated or corrupted frame touches (10 % loss leaves no verified data;
    // docs/reliability.md section 7). Stream authentication has its own tests.
    config.verify_streams = false;
    exocal_hil::flash::provision(&flash_dir, &config.push.keys).expect("key slots");
    let hil = Hil::new(scenario, &flash_dir).expect("hil");
    let clock = SimClock::new(SPEED).unwrap();
    let bus = InProcessBus::with_clock(InProcessBus::DEFAULT_CAPACITY, clock.bus_clock());
    let suit = RunningSuit::start(hil, bus.attach(), clock);
    let (_stop, shutdown) = exocald::shell::shutdown::Shutdown::manual();
    let o = session_against_suit(
        suit,
        &mut bus.attach(),
        &clock.bus_clock(),
        &config,
        shutdown.wait(),
    )
    .await;
    let _ = std::fs::remove_dir_all(&dir);
    o
}

fn summary(o: &SuitSession) -> Option<&SessionSummary> {
    o.summary()
}

fn heldout_error(o: &SuitSession) -> Option<f64> {
    summary(o)?
        .outcome
        .as_ref()
        .map(|c| c.verdict.candidate.mean_error)
}

/// Checks one outcome; returns the problems found (empty = pass) and the "noticed" text.
fn check(case: &Case, o: &SuitSession, clean_err: Option<f64>) -> (Vec<String>, String) {
    let mut bad = o.problems();
    let s = summary(o);
    let noticed = match (case.expect, s) {
        (_, None) => "no summary".to_string(),
        (Expect::Nothing, _) => "-".to_string(),
        (Expect::Accepted, Some(s)) => match s.outcome.as_ref() {
            Some(c) if c.verdict.accepted() => "-".to_string(),
            Some(c) => {
                let why = lines(&c.verdict.reasons);
                bad.push(format!("refused for frames the fault cost: {why}"));
                format!("refused: {why}")
            }
            None => {
                bad.push("not calibrated".into());
                "not calibrated".into()
            }
        },
        (Expect::ClockJump(n), Some(s)) => {
            let name = NodeId::ALL[usize::from(n) - 1].name();
            let j = s
                .clocks
                .iter()
                .find(|c| c.node == name)
                .map_or(0, |c| c.jumps);
            if j == 0 {
                bad.push(format!("{name}: no clock discontinuity reported"));
            }
            format!("{name}: {j} clock discontinuit(ies)")
        }
        (Expect::Skew(n, ppm), Some(s)) => {
            let name = NodeId::ALL[usize::from(n) - 1].name();
            let est = s
                .clocks
                .iter()
                .find(|c| c.node == name)
                .and_then(|c| c.skew_ppm);
            // The daemon reports the host clock's rate against the node's (a node running
            // +200 ppm fast reads ≈ −200 ppm). Receive stamps carry the emulator's ~1 ms real
            // (10 ms simulated) delivery jitter, so allow 100 ppm; the others are within ±50.
            if est.is_none_or(|e| (e + ppm).abs() > 100.0) {
                bad.push(format!(
                    "{name}: skew estimate {est:?} ppm, expected ≈{}",
                    -ppm
                ));
            }
            format!("{name}: skew {:.0} ppm", est.unwrap_or(f64::NAN))
        }
        (Expect::Refused, Some(s)) => match s.outcome.as_ref() {
            Some(c) if !c.verdict.accepted() => {
                format!("refused: {}", lines(&c.verdict.reasons))
            }
            _ => {
                bad.push("an out-of-bounds calibration was not refused".into());
                "accepted".into()
            }
        },
        (Expect::Babbling(n), Some(s)) => {
            let named = s.frames.babbling();
            let names: Vec<String> = named
                .iter()
                .map(|(node, r)| format!("{node}: babbling ({r} repeated frames)"))
                .collect();
            if named.iter().map(|(node, _)| node.raw()).ne([n]) {
                bad.push(format!("babbling node {n} not named alone: {names:?}"));
            }
            if names.is_empty() {
                "none named".into()
            } else {
                names.join(", ")
            }
        }
        (Expect::Malformed, Some(s)) => {
            let m = s.frames.malformed + s.frames.unknown;
            if m == 0 {
                bad.push("no malformed/unknown frames counted".into());
            }
            format!("{m} malformed/unknown frames")
        }
        (Expect::Nan, Some(s)) => {
            if s.frames.invalid_angles == 0 {
                bad.push("no invalid angles counted".into());
            }
            format!("{} invalid angles", s.frames.invalid_angles)
        }
        (Expect::PushFails(n), Some(s)) => {
            let name = NodeId::ALL[usize::from(n) - 1].name();
            match s
                .push
                .as_ref()
                .and_then(|p| p.nodes.iter().find(|r| r.node == name))
            {
                Some(r) if r.holds != Holds::New => format!(
                    "{name}: push {:?} ({})",
                    r.holds,
                    r.error.as_deref().unwrap_or("")
                ),
                Some(r) => {
                    bad.push(format!("{name} reported {:?}", r.holds));
                    format!("{name}: {:?}", r.holds)
                }
                None => "nothing pushed".into(),
            }
        }
    };
    if case.accuracy_bound {
        match (heldout_error(o), clean_err) {
            (Some(e), Some(c)) if e > 2.0 * c => {
                bad.push(format!("held-out error {e:.3e} > 2× clean {c:.3e}"))
            }
            (None, Some(_)) => bad.push("no calibration".into()),
            _ => {}
        }
    }
    (bad, noticed)
}

fn row(
    case: &Case,
    o: &SuitSession,
    clean_err: Option<f64>,
    bad: &[String],
    noticed: &str,
) -> String {
    let s = summary(o);
    let result = match &o.result {
        Ok(_) => "ok".to_string(),
        Err(e) => format!("{}", e.error).replace('|', "/"),
    };
    let verdict = s
        .and_then(|s| s.outcome.as_ref())
        .map_or("-".to_string(), |c| {
            if c.verdict.accepted() {
                "accepted".into()
            } else {
                format!("refused ({})", lines(&c.verdict.reasons))
            }
        });
    let err = heldout_error(o).map_or("-".into(), |e| {
        format!("{e:.3e} ({:.2}×)", clean_err.map_or(f64::NAN, |c| e / c))
    });
    let pushed = s
        .and_then(|s| s.push.as_ref())
        .map_or("none".to_string(), |p| {
            let new = p.nodes.iter().filter(|n| n.holds == Holds::New).count();
            format!("{new}/{} New", p.nodes.len())
        });
    let status = if bad.is_empty() {
        "pass".to_string()
    } else {
        format!("FAIL: {}", bad.join("; "))
    };
    format!(
        "| {} | {result} | {verdict} | {err} | {pushed} | {noticed} | {:.0} s | {status} |",
        case.name,
        o.wall.as_secs_f64()
    )
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_fault_class_is_survived_reported_and_never_pushes_a_bad_table() {
    let full = std::env::var_os("EXOCAL_FAULTS_FULL").is_some();
    let cases: Vec<Case> = cases().into_iter().filter(|c| full || c.ci).collect();
    let mut rows = Vec::new();
    let mut failures = Vec::new();
    let mut clean_err = None;
    for case in &cases {
        let o = run_case(case).await;
        if case.name == "clean" {
            clean_err = heldout_error(&o);
        }
        let (bad, noticed) = check(case, &o, clean_err);
        let r = row(case, &o, clean_err, &bad, &noticed);
        println!("{r}");
        rows.push(r);
        if !bad.is_empty() {
            failures.push(format!("{}: {}", case.name, bad.join("; ")));
        }
    }
    if let Some(path) = std::env::var_os("EXOCAL_FAULTS_DOC") {
        write_doc(Path::new(&path), &rows).expect("write the fault doc");
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

/// The closing paragraph of `docs/faults.md`: where the vcan subset is.
const VCAN_NOTE: &str =
    "\nOn real vcan: `tests/tests/reliability_vcan.rs` (run through `cargo xtask vcan` or \
     `cargo xtask test`) plays seven rows as 6-s real-time sessions on vcan0 with the daemon and \
     the emulated suit on separate SocketCAN sockets — 1% loss with node 7 silent to transfers, \
     a babbling node, 10% loss, a node reboot, a node clock jump, a bus stall then a node \
     reboot, malformed frames with 1% NaN values — with the same checks except the accuracy bound; figures in \
     `docs/reliability.md`.\n";

fn write_doc(path: &Path, rows: &[String]) -> std::io::Result<()> {
    let mut text = String::from(
        "# Fault matrix\n\n\
         Generated by `EXOCAL_FAULTS_FULL=1 EXOCAL_FAULTS_DOC=$PWD/docs/faults.md cargo test -p exocald \
         --test fault_matrix -- --nocapture` (daemon `run_session` against exocal-hil on the \
         in-process bus, paper scenario seed 7, sessions of 40 to 60 s (at least 40 s, then the \
         default stop-when-good-enough rule) at 10× real time; CI runs the rows marked `ci` in `daemon/tests/fault_matrix.rs`).\n\n\
         Checks per row: no panic; the degraded node noticed (column *noticed*); no table \
         failing validation pushed; every node's flash holds its factory table or exactly the \
         table pushed to it, and agrees with the push report; for loss-like faults the held-out \
         mean pose error (candidate table) within 2× of the clean run; loss bursts, reordering and \
         delay accepted (the frames they cost are bridged, not a reason to refuse).\n\n\
         | fault | session | verdict | held-out error (vs clean) | push | noticed | wall | check |\n\
         |---|---|---|---|---|---|---|---|\n",
    );
    for r in rows {
        text.push_str(r);
        text.push('\n');
    }
    text.push_str(VCAN_NOTE);
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir)?;
    }
    std::fs::write(path, text)
}

/// Every refusal's line, `; `-separated.
fn lines(reasons: &[exocal_session::validate::Refusal]) -> String {
    let all: Vec<String> = reasons.iter().map(ToString::to_string).collect();
    all.join("; ")
}
