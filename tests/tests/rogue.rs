//! The rogue sender on the in-process bus: exocal-hil with keyed nodes, the daemon's
//! push with the keys, and a third endpoint that knows everything on the bus but no key. The
//! attacks and what they must not achieve are in `common/rogue.rs`; `reliability_vcan.rs` runs
//! the same code on vcan0.

use std::path::PathBuf;
use std::time::Duration;

use exocal_bus::InProcessBus;
use exocal_hil::scenario::Scenario;

#[path = "common/rogue.rs"]
mod rogue;

/// In process: the nodes boot within 200 ms, answers take well under 50 ms.
const TIMING: rogue::Timing = rogue::Timing {
    settle: Duration::from_millis(200),
    backoff_initial_ms: 10,
    timeout_ms: 50,
    wait: Duration::from_millis(100),
};

/// A fresh flash directory for the test `name`.
fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("exocal-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    dir
}

/// The paper's suit, its streams slowed to 1 Hz.
fn quiet_scenario() -> Scenario {
    let mut scenario = Scenario::paper();
    scenario.duration_s = 600.0;
    scenario.rates.joint_state_hz = 1.0;
    scenario.rates.imu_hz = 1.0;
    scenario.rates.pose_hz = 1.0;
    scenario
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_rogue_sender_changes_no_table_and_never_makes_the_daemon_report_new() {
    let dir = scratch("rogue");
    let bus = InProcessBus::new();
    let found = rogue::run_attacks(quiet_scenario(), &dir, |_| bus.attach(), &TIMING).await;
    let _ = std::fs::remove_dir_all(&dir);
    found.print();
    found.assert_clean(6, "every attack ran");
}

/// The rollback by an inflated freshness (an inflated, unsigned `Freshness`, a
/// forged NACK, the kept `CommitAuth` replayed with a Commit after two later genuine pushes)
/// on the in-process bus, against exocal-hil's keyed nodes and the daemon's push with its
/// state directory: the older table never lands (`common/rogue.rs`, [`rogue::rollback`]).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rollback_by_an_inflated_freshness_never_lands_in_process() {
    let dir = scratch("rollback");
    let state = dir.join("state");
    std::fs::create_dir_all(&state).unwrap();
    let bus = InProcessBus::new();
    let found =
        rogue::run_rollback(quiet_scenario(), &dir, &state, |_| bus.attach(), &TIMING).await;
    let counters = std::fs::read_to_string(state.join("node-counters")).unwrap_or_default();
    let _ = std::fs::remove_dir_all(&dir);
    found.print();
    println!("state directory's node-counters: {counters:?}");
    found.assert_clean(2, "the attack ran to its replay");
    assert!(counters.contains("Joint3"), "{counters:?}");
}
