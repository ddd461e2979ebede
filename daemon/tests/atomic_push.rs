//! Atomic table push under transfer faults: the daemon's [`push_tables`] against the emulated
//! suit (exocal-hil, real node state machine and flash files) on the in-process bus, with
//! seeded loss, duplication, reordering, delay and node reboots during the transfer.
//!
//! For every run and every joint node the flash file after the run must hold exactly the old
//! table or the new one (by CRC): never anything else. The daemon's report must agree with the
//! flash in every run, for every node: `New` ⇒ flash holds the new table, `Old` ⇒ the old one.
//! `Unknown` (the node did not answer, or did not answer the final CRC query after a Commit)
//! claims nothing and is allowed; it is counted and printed with its reason.
//!
//! Simulated time is virtual (a paused runtime), so a run's outcome depends on its seed alone.
//!
//! `cargo test -p exocald --test atomic_push` runs `EXOCAL_PUSH_RUNS` seeded runs (default 40,
//! bounded for CI); the documented figure is `EXOCAL_PUSH_RUNS=1000`.

use std::path::PathBuf;
use std::time::Duration;

use exocal_bus::InProcessBus;
use exocal_bus::SimClock;
use exocal_dbc::auth::KeySet;
use exocal_dbc::table::Table;
use exocal_dbc::NodeId;
use exocal_hil::trial::{new_tables, TransferMix};
use exocal_hil::Hil;
use exocald::cmd::demo::{PushTally, RunningSuit};
use exocald::config::PushPolicy;
use exocald::push::push_tables;

/// Simulated seconds per second of the (paused, virtual) runtime clock.
const SPEED: f64 = 50.0;
/// Simulated time at which the push starts.
const PUSH_AT_S: f64 = 0.5;

/// The faults a trial draws from (the documented figure's bounds).
const MIX: TransferMix = TransferMix {
    losses: &[0.0, 0.01, 0.05, 0.1, 0.2, 0.4],
    burst_start: 0.02,
    max_fraction: 0.2,
    reorder_max_ms: 200.0,
    delay_max_ms: 300.0,
    reboots: 4,
    push_at_s: PUSH_AT_S,
    reboot_window_s: 2.0,
    down_s: (0.01, 1.5),
    refusal: 0.2,
    nack: true,
};

fn temp_dir(seed: u64) -> PathBuf {
    let d = std::env::temp_dir().join(format!("exocal-atomic-push-{}-{seed}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

async fn one_run(seed: u64, tally: &mut PushTally) {
    let dir = temp_dir(seed);
    let scenario = MIX.scenario(seed);
    // Authenticated, as on a suit: every node holds its key, the daemon has them all.
    let keys = KeySet::derived(seed);
    exocal_hil::flash::provision(&dir, &keys).expect("key slots");
    let hil = Hil::new(scenario.clone(), &dir).expect("hil");
    let trial = new_tables(hil.suit(), seed ^ 0xa5a5);
    let tables: Vec<(NodeId, Table)> = trial.iter().map(|(n, _, new)| (*n, *new)).collect();
    let clock = SimClock::new(SPEED).expect("speed");
    let bus = InProcessBus::with_clock(InProcessBus::DEFAULT_CAPACITY, clock.bus_clock());
    let suit = RunningSuit::start(hil, bus.attach(), clock);
    let mut daemon_end = bus.attach();
    tokio::time::sleep(Duration::from_secs_f64(PUSH_AT_S / SPEED)).await;
    let policy = PushPolicy {
        retries: 3,
        backoff_initial_ms: 100,
        backoff_max_ms: 800,
        timeout_ms: (SPEED * 20.0) as u64,
        authenticate: true,
        keys,
        state_dir: None,
    };
    let mut ignore = |_: bool, _: &exocal_bus::Frame, _: Duration| {};
    let report = push_tables(
        &mut daemon_end,
        &clock.bus_clock(),
        &tables,
        &policy,
        (seed % 256) as u8,
        &mut ignore,
    )
    .await
    .expect("bus");
    // Let delayed and duplicated frames drain (max hold-back 300 ms simulated), then stop.
    tokio::time::sleep(Duration::from_secs_f64(0.5 / SPEED)).await;
    let flash = suit.stop().await;
    tally.add(
        &format!("seed {seed}"),
        &scenario.faults,
        &trial,
        &flash,
        &report,
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// On a paused runtime: simulated time is virtual, so the trials (timeouts, hold-backs, reboots,
/// all in simulated time) come out the same on an idle or a busy machine.
#[tokio::test(start_paused = true)]
async fn no_node_ever_holds_a_mixed_table_and_the_report_matches_flash() {
    let runs: u64 = std::env::var("EXOCAL_PUSH_RUNS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(40);
    let mut tally = PushTally::default();
    for seed in 0..runs {
        one_run(1000 + seed, &mut tally).await;
    }
    println!(
        "atomic push: {} runs, {} node transfers: report New {}, Old {}, Unknown {}; mixed tables {}; problems {}",
        tally.runs,
        tally.nodes,
        tally.new,
        tally.old,
        tally.unknown,
        tally.mixed,
        tally.problems.len(),
    );
    for u in &tally.unknown_why {
        println!("Unknown: {u}");
    }
    assert_eq!(
        tally.mixed, 0,
        "a node holds a table that is neither old nor new"
    );
    assert!(
        tally.problems.is_empty(),
        "the push report disagrees with flash ({} of {} node transfers):\n{}",
        tally.problems.len(),
        tally.nodes,
        tally.problems.join("\n")
    );
    // The faults are survivable: most transfers must succeed.
    assert!(tally.new * 10 >= tally.nodes * 7, "{tally:?}");
}
