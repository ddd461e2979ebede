//! `exocald demo`: the emulated suit (exocal-hil, the paper's Section 4 scenario) and the daemon
//! in one process on the in-process bus — no CAN, no root.
//!
//! Contract: the whole run is on simulated time. [`run`] makes its own single-threaded tokio
//! runtime with a paused clock, so the hil's clock, the bus timestamps and every timer of the
//! session (housekeeping tick, push timeouts) are virtual: time stands still while any task can
//! run or the calibration is busy, and jumps to the next timer otherwise. The same seed and
//! configuration therefore give the same frames, the same aligned samples, the same pushed
//! tables and the same log messages, on any machine and at any `speed`; `speed` only holds the
//! run to at most that many simulated seconds per real second, so a person can watch it.
//! The hil plays the scenario, the daemon runs one ordinary session
//! ([`crate::runner::run_session`]) on the other end of the bus, and when it is done the hil is
//! stopped and each joint node's flash file is read back: the demo succeeds only if every node
//! persisted exactly the table the daemon pushed (same CRC). SIGTERM or SIGINT interrupts the
//! session as in `calibrate`: the log is finished before the process exits.
//!
//! Keys: with `push.authenticate` (the default) the demo needs no setup: it derives one AES-128
//! key per node from the seed, in-process ([`exocal_dbc::auth::KeySet::derived`]), writes them
//! to the emulated nodes' key slots and gives them to the daemon, so the push is the
//! authenticated one a suit gets. Anyone who knows the seed knows these keys: they are for the
//! emulated suit only (a suit's keys come from the `exocal-keys` credential).

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use exocal_bus::{InProcessBus, SimClock};
use exocal_dbc::NodeId;
use exocal_hil::{Hil, Scenario};

use crate::config::Config;
use crate::exit::DaemonError;
use crate::report::{Notifier, Reporter};
use crate::runner::{run_session, SessionError, SessionSummary};

/// Options of a demo run.
#[derive(Debug, Clone)]
pub struct DemoOptions {
    pub seed: u64,
    /// At most this many simulated seconds per real second (pacing only: the results do not
    /// depend on it).
    pub speed: f64,
    /// Session logs go to `output/`, the emulated nodes' flash to `output/flash/`.
    pub output: PathBuf,
}

/// The demo's result: the session, and per joint node the CRC of its flash after the run.
#[derive(Debug)]
pub struct DemoResult {
    pub summary: SessionSummary,
    pub flash_crc: Vec<(NodeId, Option<u32>)>,
}

/// The configuration for a session against the hil on the in-process bus: the built-in
/// defaults (or `base`), logging to `output`. Push timeouts are in simulated time; a hil whose
/// clock runs `speed` times faster than its runtime's answers within about `speed` ms of it
/// (timers have ~1 ms resolution), so they are scaled up with the speed. The demo's hil runs at
/// speed 1 on virtual time.
pub fn demo_config(base: Config, output: &Path, speed: f64) -> Config {
    let mut c = base;
    c.interface = "in-process".into();
    c.output.directory = output.to_path_buf();
    c.push.timeout_ms = c.push.timeout_ms.max((speed * 20.0).ceil() as u64);
    c
}

/// Runs the demo on its own paused runtime (see the module docs); call it outside any runtime.
pub fn run(config: &Config, opts: &DemoOptions) -> Result<DemoResult, Box<SessionError>> {
    if !(opts.speed.is_finite() && opts.speed > 0.0) {
        return Err(DaemonError::Usage(format!(
            "speed {} (must be finite and positive)",
            opts.speed
        ))
        .into());
    }
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .start_paused(true)
        .build()
        .map_err(|source| DaemonError::Io {
            what: "starting the async runtime".into(),
            source,
        })?;
    runtime.block_on(session(config, opts)).map_err(Box::new)
}

/// Simulated time between two looks at the pace.
const PACE_STEP: Duration = Duration::from_millis(10);

/// Holds simulated time to at most `speed` × real time since the start: every [`PACE_STEP`] of
/// simulated time, when simulated time is ahead, the runtime's only thread sleeps until real
/// time catches up. Blocking is the point: nothing runs meanwhile, so pacing changes when
/// things happen in real time and never what happens in simulated time.
async fn pace(clock: SimClock, speed: f64) {
    let started = Instant::now();
    loop {
        let ahead = clock.now_s() / speed - started.elapsed().as_secs_f64();
        if ahead > 0.0 {
            std::thread::sleep(Duration::from_secs_f64(ahead));
        }
        tokio::time::sleep(PACE_STEP).await;
    }
}

async fn session(config: &Config, opts: &DemoOptions) -> Result<DemoResult, SessionError> {
    let flash_dir = opts.output.join("flash");
    std::fs::create_dir_all(&flash_dir).map_err(|source| DaemonError::Io {
        what: format!("creating {}", flash_dir.display()),
        source,
    })?;
    let mut scenario = Scenario::paper();
    scenario.seed = opts.seed;
    // Long enough for collection, calibration and push; the hil is stopped when we are done.
    scenario.duration_s = scenario
        .duration_s
        .max(config.session.max_duration_s + 120.0);
    let mut config = config.clone();
    let provisioned = if config.push.authenticate {
        config.push.keys = exocal_dbc::auth::KeySet::derived(opts.seed);
        exocal_hil::flash::provision(&flash_dir, &config.push.keys).map(|_| ())
    } else {
        // Unauthenticated: the emulated nodes must not keep keys from an earlier demo here.
        NodeId::JOINTS.iter().try_for_each(|&n| {
            match std::fs::remove_file(exocal_hil::flash::key_path(&flash_dir, n)) {
                Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(e),
                _ => Ok(()),
            }
        })
    };
    provisioned.map_err(|source| DaemonError::Io {
        what: format!("setting up the demo keys in {}", flash_dir.display()),
        source,
    })?;
    let config = &config;
    let mut hil = Hil::new(scenario, &flash_dir).map_err(|e| DaemonError::Interface {
        name: "in-process hil".into(),
        reason: e.to_string(),
    })?;
    // Speed 1 on the paused runtime's virtual clock.
    let clock = SimClock::new(1.0).expect("a positive speed");
    let bus = InProcessBus::with_clock(InProcessBus::DEFAULT_CAPACITY, clock.bus_clock());
    let mut hil_end = bus.attach();
    let mut daemon_end = bus.attach();
    let hil_task = tokio::spawn(async move { hil.run(&mut hil_end, &clock).await });
    let pacer = tokio::spawn(pace(clock, opts.speed));
    // SIGTERM/SIGINT end the session like `calibrate`'s: the log is finished, nothing is lost.
    let shutdown = crate::shutdown::Shutdown::on_signals();
    let mut notifier = Notifier::disabled();
    let mut reporter = Reporter::detect(&notifier);
    let result = run_session(
        &mut daemon_end,
        &clock.bus_clock(),
        config,
        false,
        shutdown.wait(),
        &mut notifier,
        &mut reporter,
    )
    .await;
    pacer.abort();
    hil_task.abort();
    let _ = hil_task.await;
    let summary = result?;
    let flash_crc = NodeId::JOINTS
        .iter()
        .map(|&n| {
            let crc = exocal_hil::flash::read(&flash_dir, n)
                .ok()
                .flatten()
                .map(|img| img.table.crc());
            (n, crc)
        })
        .collect();
    Ok(DemoResult { summary, flash_crc })
}

/// Checks that every node's flash holds the table the daemon pushed to it.
pub fn check_flash(result: &DemoResult) -> Result<(), DaemonError> {
    let Some(push) = &result.summary.push else {
        return Err(DaemonError::Push("nothing was pushed".into()));
    };
    let mut wrong = Vec::new();
    for (report, (node, crc)) in push.nodes.iter().zip(&result.flash_crc) {
        if *crc != Some(report.new_crc) {
            wrong.push(format!(
                "{node}: flash holds {crc:?}, pushed {:#010x}",
                report.new_crc
            ));
        }
    }
    if wrong.is_empty() {
        Ok(())
    } else {
        Err(DaemonError::Push(wrong.join("; ")))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_paper_scenario_calibrates_pushes_and_persists() {
        let dir = std::env::temp_dir().join(format!("exocald-demo-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let opts = DemoOptions {
            seed: 2024,
            speed: 1e6,
            output: dir.clone(),
        };
        let config = demo_config(Config::default_config(), &dir, 1.0);
        let result = match run(&config, &opts).map_err(|e| *e) {
            Ok(r) => r,
            Err(SessionError { error, summary }) => panic!("{error}\n{summary:#?}"),
        };
        check_flash(&result).unwrap();
        let s = &result.summary;
        let v = &s.outcome.as_ref().unwrap().verdict;
        assert!(
            v.improvement >= 0.8,
            "held-out improvement {}",
            v.improvement
        );
        assert_eq!(s.frames.unknown + s.frames.malformed, 0);
        // The log reads back with every channel, and as many raw frames as ingest counted.
        let bytes = std::fs::read(&s.log_path).unwrap();
        let summary = mcap::Summary::read(&bytes).unwrap().unwrap();
        assert_eq!(summary.channels.len(), crate::mcaplog::Topic::ALL.len());
        let rx = s.log_counts.iter().find(|(t, _)| t == "/can/rx").unwrap().1;
        assert!(rx >= s.frames.received, "{rx} < {}", s.frames.received);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
