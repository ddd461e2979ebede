//! The rogue sender (issue 20) on the in-process bus: exocal-hil with keyed nodes, the daemon's
//! push with the keys, and a third endpoint that knows everything on the bus but no key. The
//! attacks and what they must not achieve are in `common/rogue.rs`; `reliability_vcan.rs` runs
//! the same code on vcan0.

use std::time::Duration;

use exocal_bus::{InProcessBus, SimClock};
use exocal_dbc::auth::KeySet;
use exocal_hil::scenario::{Scenario, TransferBehaviour, TransferFault};
use exocal_hil::Hil;
use exocald::config::PushPolicy;

#[path = "common/rogue.rs"]
mod rogue;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_rogue_sender_changes_no_table_and_never_makes_the_daemon_report_new() {
    let dir = std::env::temp_dir().join(format!("exocal-rogue-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let keys = KeySet::derived(20);
    exocal_hil::flash::provision(&dir, &keys).expect("key slots");
    let mut scenario = Scenario::paper();
    scenario.duration_s = 600.0;
    scenario.rates.joint_state_hz = 1.0;
    scenario.rates.imu_hz = 1.0;
    scenario.rates.pose_hz = 1.0;
    scenario.faults.transfer.push(TransferFault {
        node: rogue::SILENT.raw(),
        behaviour: TransferBehaviour::Silent,
    });
    let mut hil = Hil::new(scenario, &dir).expect("hil");
    let clock = SimClock::new(1.0).expect("speed");
    let bus = InProcessBus::new();
    let mut hil_end = bus.attach();
    let mut daemon = bus.attach();
    let mut rogue_end = bus.attach();
    let hil_task = tokio::spawn(async move { hil.run(&mut hil_end, &clock).await });
    tokio::time::sleep(Duration::from_millis(200)).await;
    let policy = PushPolicy {
        retries: 1,
        backoff_initial_ms: 10,
        backoff_max_ms: 50,
        timeout_ms: 50,
        authenticate: true,
        keys: keys.clone(),
        state_dir: None,
    };
    let found = rogue::attacks(
        &mut daemon,
        &mut rogue_end,
        &dir,
        &keys,
        &policy,
        Duration::from_millis(100),
    )
    .await;
    hil_task.abort();
    let _ = std::fs::remove_dir_all(&dir);
    for line in &found.lines {
        println!("{line}");
    }
    assert!(found.problems.is_empty(), "{}", found.problems.join("\n"));
    assert_eq!(found.lines.len(), 6, "every attack ran");
}

/// Issue 34, item 1: the rollback the review reproduced (an inflated, unsigned `Freshness`, a
/// forged NACK, the kept `CommitAuth` replayed with a Commit after two later genuine pushes)
/// on the in-process bus, against exocal-hil's keyed nodes and the daemon's push with its
/// state directory: the older table never lands (`common/rogue.rs`, [`rogue::rollback`]).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rollback_by_an_inflated_freshness_never_lands_in_process() {
    let dir = std::env::temp_dir().join(format!("exocal-rollback-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let state = dir.join("state");
    std::fs::create_dir_all(&state).unwrap();
    let keys = KeySet::derived(34);
    exocal_hil::flash::provision(&dir, &keys).expect("key slots");
    let mut scenario = Scenario::paper();
    scenario.duration_s = 600.0;
    scenario.rates.joint_state_hz = 1.0;
    scenario.rates.imu_hz = 1.0;
    scenario.rates.pose_hz = 1.0;
    let mut hil = Hil::new(scenario, &dir).expect("hil");
    let clock = SimClock::new(1.0).expect("speed");
    let bus = InProcessBus::new();
    let mut hil_end = bus.attach();
    let mut daemon = bus.attach();
    let mut rogue_end = bus.attach();
    let hil_task = tokio::spawn(async move { hil.run(&mut hil_end, &clock).await });
    tokio::time::sleep(Duration::from_millis(200)).await;
    let policy = PushPolicy {
        retries: 1,
        backoff_initial_ms: 10,
        backoff_max_ms: 50,
        timeout_ms: 50,
        authenticate: true,
        keys,
        state_dir: Some(state.clone()),
    };
    let found = rogue::rollback(
        &mut daemon,
        &mut rogue_end,
        &dir,
        &policy,
        Duration::from_millis(100),
    )
    .await;
    hil_task.abort();
    let counters = std::fs::read_to_string(state.join("node-counters")).unwrap_or_default();
    let _ = std::fs::remove_dir_all(&dir);
    for line in &found.lines {
        println!("{line}");
    }
    println!("state directory's node-counters: {counters:?}");
    assert!(found.problems.is_empty(), "{}", found.problems.join("\n"));
    assert_eq!(found.lines.len(), 2, "the attack ran to its replay");
    assert!(counters.contains("Joint3"), "{counters:?}");
}
