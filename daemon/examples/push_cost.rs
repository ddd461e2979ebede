//! What an authenticated push costs: `cargo run --release -p exocald --example push_cost [RUNS]`.
//!
//! Pushes a table to all seven joint nodes of exocal-hil on the in-process bus (the suit at 1×
//! real time, nodes answering after 0.3 ms like the emulated firmware), RUNS times (default 20),
//! keyed nodes and `push.authenticate`; prints per push the wall time and the frames on the bus
//! per node, and the host's cost of one AES-128-CMAC of each kind. (There is no unauthenticated
//! push to compare with: a node without a key fails closed and installs nothing.)
//! BENCHMARKS.md records the figures; docs/reliability.md quotes them.

use std::time::{Duration, Instant};

use exocal_bus::{Clock, Frame, InProcessBus, SimClock};
use exocal_dbc::auth::{self, KeySet};
use exocal_dbc::table::{Field, Table};
use exocal_dbc::{NodeId, TriggerCommand};
use exocal_hil::{Hil, Scenario};
use exocald::config::PushPolicy;
use exocald::push::{push_tables, Holds};

fn moved(t: &Table, k: i64) -> Table {
    let mut raw = t.raw_values();
    for f in Field::ALL {
        let (lo, hi) = f.raw_bounds();
        raw[f as usize] = (raw[f as usize] + k).clamp(lo, hi);
    }
    Table::from_raw(raw).expect("in range")
}

/// (median ms per push, sent frames per node, received table replies per node).
async fn measure(runs: u32) -> (f64, f64, f64) {
    let dir = std::env::temp_dir().join(format!("exocal-push-cost-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let keys = KeySet::derived(1);
    exocal_hil::flash::provision(&dir, &keys).expect("key slots");
    let mut scenario = Scenario::paper();
    scenario.duration_s = 3600.0;
    scenario.rates.joint_state_hz = 1.0;
    scenario.rates.imu_hz = 1.0;
    scenario.rates.pose_hz = 1.0;
    let mut hil = Hil::new(scenario, &dir).expect("hil");
    let factory: Vec<(NodeId, Table)> = NodeId::JOINTS
        .iter()
        .map(|&n| (n, hil.suit().held_table(n).expect("factory table")))
        .collect();
    let clock = SimClock::new(1.0).expect("speed");
    let bus = InProcessBus::new();
    let mut hil_end = bus.attach();
    let mut daemon = bus.attach();
    let hil_task = tokio::spawn(async move { hil.run(&mut hil_end, &clock).await });
    tokio::time::sleep(Duration::from_millis(200)).await;
    let policy = PushPolicy {
        retries: 3,
        backoff_initial_ms: 10,
        backoff_max_ms: 100,
        timeout_ms: 50,
        authenticate: true,
        keys,
        state_dir: None,
    };
    let (mut times, mut sent, mut replies) = (Vec::new(), 0u64, 0u64);
    for run in 0..runs {
        let tables: Vec<(NodeId, Table)> = factory
            .iter()
            .map(|(n, t)| (*n, moved(t, 1 + i64::from(run))))
            .collect();
        let mut count = |tx: bool, f: &Frame, _: Duration| {
            let id = f.raw_id();
            if tx {
                sent += 1;
            } else if id & !0xF == 0x580 {
                replies += 1;
            }
        };
        let started = Instant::now();
        let report = push_tables(
            &mut daemon,
            &Clock::Wall,
            &tables,
            &policy,
            run as u8,
            &mut count,
        )
        .await
        .expect("bus");
        times.push(started.elapsed().as_secs_f64() * 1e3);
        assert!(
            report.nodes.iter().all(|r| r.holds == Holds::New),
            "{:?}",
            report.lines()
        );
    }
    hil_task.abort();
    let _ = std::fs::remove_dir_all(&dir);
    times.sort_by(f64::total_cmp);
    let per_node = f64::from(runs) * 7.0;
    (
        times[times.len() / 2],
        sent as f64 / per_node,
        replies as f64 / per_node,
    )
}

fn cmac_us(f: impl Fn() -> u32) -> f64 {
    let n = 20_000;
    let started = Instant::now();
    let mut acc = 0u32;
    for _ in 0..n {
        acc ^= std::hint::black_box(f());
    }
    std::hint::black_box(acc);
    started.elapsed().as_secs_f64() * 1e6 / f64::from(n)
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() {
    let runs: u32 = std::env::args()
        .nth(1)
        .map_or(20, |a| a.parse().expect("RUNS: a number"));
    println!("| push of 7 tables, in-process bus, hil at 1x | median wall per push | commands per node | replies per node |");
    println!("|---|---|---|---|");
    let (ms, sent, replies) = measure(runs).await;
    println!("| authenticated (keyed nodes) | {ms:.1} ms | {sent:.1} | {replies:.1} |");
    let keys = KeySet::derived(2);
    let (node, key) = (NodeId::JOINTS[0], keys.node(NodeId::JOINTS[0]).unwrap());
    let t = Table::from_si(0.431, 1.2, 0.0, 0.01, 1.0, 1.0).unwrap();
    let bytes = t.to_bytes();
    println!(
        "\nhost (this build): commit MAC {:.2} µs, readback MAC {:.2} µs, trigger MAC {:.2} µs",
        cmac_us(|| auth::commit_mac(key, node, 1, 2, &t)),
        cmac_us(|| auth::readback_mac(key, node, 1, 2, &bytes)),
        cmac_us(|| auth::trigger_mac(key, TriggerCommand::StartCalibration, 3)),
    );
}
