//! `exocald run`: waiting for triggers, and which ones start a session.
//!
//! Contract:
//! - a session starts on SIGUSR1 (local: only root can send it) or on a `Trigger` frame asking
//!   `StartCalibration` that passes the [`TriggerGate`]. With `push.authenticate` (the default)
//!   its MAC must verify with the trigger key for a counter above the last one accepted
//!   ([`exocal_dbc::auth::next_counter`]); in every case at least `trigger.cooldown_s` must have
//!   passed since the last session started, whatever started it. A flood of Trigger frames
//!   therefore starts at most one session per cooldown, and forged or replayed ones none;
//! - a valid trigger inside the cooldown is consumed: its counter can never start a session
//!   later. The last accepted counter persists in the state directory's `trigger-counter`
//!   ([`crate::state`], fsynced; not in `output.directory`, which `--output` changes), so a
//!   restart does not reopen old triggers to replay;
//! - refused frames are counted and reported at most once per cooldown (a flood must not
//!   flood the journal either);
//! - time is the bus clock's monotonic reading, passed in: the gate never reads a clock.

use std::path::PathBuf;
use std::time::Duration;

use exocal_bus::{Clock, Transport};
use exocal_dbc::auth::{next_counter, previous_counter, verify_trigger, Key};
use exocal_dbc::{Message, Trigger, TriggerCommand};

use crate::config::Config;
use crate::exit::DaemonError;
use crate::shell::notify::{Notifier, Reporter};
use crate::shell::runner::{run_session, TICK};
use crate::shell::shutdown::Shutdown;
use crate::shell::throttle::Throttle;

/// What the gate makes of a start request.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Verdict {
    /// Start a session now.
    Start,
    /// Authentic, but the last session started less than a cooldown ago: this much remains.
    Cooldown(Duration),
    /// The MAC does not verify (no key, or a guess).
    Forged,
    /// The MAC verifies for a counter already used: a replay or a stale sender.
    Replayed,
    /// Authentic, but not a start (`Abort`: sessions are stopped with SIGTERM).
    NotAStart,
}

/// Which start requests start a session (see the module docs).
#[derive(Debug, Clone)]
pub struct TriggerGate {
    /// The trigger key; `None` when authentication is off.
    key: Option<Key>,
    counter: u32,
    cooldown: Duration,
    last_start: Option<Duration>,
}

impl TriggerGate {
    /// A gate checking MACs with `key` (none: authentication off), the last accepted counter
    /// being `counter`, letting a session start at most every `cooldown`.
    pub fn new(key: Option<Key>, counter: u32, cooldown: Duration) -> Self {
        TriggerGate {
            key,
            counter,
            cooldown,
            last_start: None,
        }
    }

    /// The last accepted trigger counter (to persist).
    pub fn counter(&self) -> u32 {
        self.counter
    }

    /// Judges a `Trigger` frame received at `now` (monotonic).
    pub fn trigger(&mut self, t: &Trigger, now: Duration) -> Verdict {
        if let Some(key) = &self.key {
            let verifies = |c: Option<u32>| c.filter(|&c| verify_trigger(key, t.command, c, t.mac));
            match verifies(next_counter(self.counter, t.counter_lo)) {
                Some(c) => self.counter = c,
                None if verifies(previous_counter(self.counter, t.counter_lo)).is_some() => {
                    return Verdict::Replayed
                }
                None => return Verdict::Forged,
            }
        }
        match t.command {
            TriggerCommand::StartCalibration => self.start(now),
            TriggerCommand::Abort => Verdict::NotAStart,
        }
    }

    /// A start asked for at `now` (an authentic trigger, or SIGUSR1): only the cooldown applies.
    pub fn start(&mut self, now: Duration) -> Verdict {
        if let Some(last) = self.last_start {
            let next = last.saturating_add(self.cooldown);
            if now < next {
                return Verdict::Cooldown(next - now);
            }
        }
        self.last_start = Some(now);
        Verdict::Start
    }
}

/// What the serve loop did.
#[derive(Debug, Default, Clone, PartialEq, Eq)]
pub struct ServeStats {
    /// Sessions started.
    pub sessions: u64,
    /// Authentic start requests inside a cooldown.
    pub cooled: u64,
    /// Trigger frames refused (forged or replayed).
    pub refused: u64,
}

/// Serves on `bus` until `shutdown`: a session per start request the gate lets through
/// (`local` receives SIGUSR1's requests). Returns what it did; a session's failure is reported
/// and the loop goes on; an interruption during a session ends it.
#[allow(clippy::too_many_arguments)]
pub async fn serve<T: Transport>(
    bus: &mut T,
    clock: &Clock,
    config: &Config,
    dry_run: bool,
    shutdown: &Shutdown,
    local: &mut tokio::sync::mpsc::Receiver<()>,
    notifier: &mut Notifier,
    reporter: &mut Reporter,
) -> Result<ServeStats, DaemonError> {
    const IDLE: &str = "idle: waiting for a trigger (CAN Trigger frame or SIGUSR1)";
    let state = config.push.state_dir.clone();
    let key = if config.push.authenticate {
        config.push.keys.trigger().cloned()
    } else {
        None
    };
    if config.push.authenticate && key.is_none() {
        return Err(DaemonError::Keys(crate::keys::KeyError::NoKey {
            path: PathBuf::from(crate::keys::CREDENTIAL),
            name: "Trigger",
        }));
    }
    let cooldown = Duration::from_secs_f64(config.trigger.cooldown_s);
    let counter = match &state {
        Some(dir) => crate::state::load_trigger_counter(dir)?,
        None => 0,
    };
    let mut gate = TriggerGate::new(key, counter, cooldown);
    let mut stats = ServeStats::default();
    let mut refused_since_note = 0u64;
    let mut last_note: Option<Duration> = None;
    // Valid triggers during one cooldown ([`Throttle`]: a line each for the first few only).
    let mut cooled_lines = Throttle::default();
    let started = std::time::Instant::now();
    let mut tick = tokio::time::interval(TICK);
    notifier.ready(IDLE);
    reporter.message(IDLE);
    let stop = shutdown.wait();
    tokio::pin!(stop);
    let mut local_open = true;
    loop {
        let (by, verdict) = tokio::select! {
            () = &mut stop => return Ok(stats),
            asked = local.recv(), if local_open => match asked {
                Some(()) => ("SIGUSR1", gate.start(clock.monotonic())),
                None => {
                    local_open = false;
                    continue;
                }
            },
            rx = bus.recv() => {
                let rx = rx.map_err(|source| DaemonError::Bus {
                    what: "receiving CAN".into(),
                    source,
                })?;
                let Ok(Message::Trigger(t)) = exocal_dbc::decode_frame(&rx.frame) else {
                    continue;
                };
                let before = gate.counter();
                let v = gate.trigger(&t, clock.monotonic());
                if let (Some(dir), true) = (&state, gate.counter() != before) {
                    crate::state::save_trigger_counter(dir, gate.counter())?;
                }
                ("CAN Trigger frame", v)
            }
            _ = tick.tick() => {
                notifier.watchdog(started.elapsed());
                continue;
            }
        };
        let now = clock.monotonic();
        match verdict {
            Verdict::Start => cooled_lines = Throttle::default(),
            Verdict::NotAStart => continue,
            Verdict::Cooldown(left) => {
                stats.cooled += 1;
                if let Some(n) = cooled_lines.occur() {
                    reporter.message(&Throttle::line(
                        &format!(
                            "trigger ignored ({by}): the last session started less than \
                             trigger.cooldown_s = {} s ago ({:.0} s to go)",
                            config.trigger.cooldown_s,
                            left.as_secs_f64()
                        ),
                        n,
                    ));
                }
                continue;
            }
            Verdict::Forged | Verdict::Replayed => {
                stats.refused += 1;
                refused_since_note += 1;
                if last_note.is_none_or(|t| now.saturating_sub(t) >= cooldown) {
                    reporter.message(&format!(
                        "{refused_since_note} Trigger frame(s) refused: bad MAC or a replayed \
                         counter (last: {verdict:?}); reported at most once per cooldown"
                    ));
                    last_note = Some(now);
                    refused_since_note = 0;
                }
                continue;
            }
        }
        stats.sessions += 1;
        reporter.message(&format!("trigger received ({by}): starting a session"));
        // SIGUSR1 during the session is drained here, so it does not start another one after
        // it (a Trigger frame during the session goes to the session, which logs it).
        let result = {
            let session = run_session(
                bus,
                clock,
                config,
                dry_run,
                shutdown.wait(),
                notifier,
                reporter,
            );
            tokio::pin!(session);
            loop {
                tokio::select! {
                    result = &mut session => break result,
                    Some(()) = local.recv(), if local_open => {
                        eprintln!("exocald: trigger ignored (SIGUSR1): a session is running");
                    }
                }
            }
        };
        match crate::shell::summary::finish(result, crate::shell::summary::Output::Text) {
            Ok(()) => {}
            Err(DaemonError::Interrupted) => return Err(DaemonError::Interrupted),
            Err(e) => reporter.message(&format!("session failed: {e}")),
        }
        notifier.status(IDLE);
        reporter.message(IDLE);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use exocal_dbc::auth::{trigger, KeySet};

    const COOLDOWN: Duration = Duration::from_secs(60);

    fn s(x: f64) -> Duration {
        Duration::from_secs_f64(x)
    }

    #[test]
    fn only_fresh_authentic_starts_pass_and_at_most_one_per_cooldown() {
        let keys = KeySet::derived(1);
        let key = keys.trigger().unwrap();
        let mut gate = TriggerGate::new(Some(key.clone()), 100, COOLDOWN);
        let start = |c| trigger(key, TriggerCommand::StartCalibration, c);
        assert_eq!(gate.trigger(&start(101), s(0.0)), Verdict::Start);
        // Its replay, an older counter, a forged MAC, another key's MAC.
        assert_eq!(gate.trigger(&start(101), s(61.0)), Verdict::Replayed);
        assert_eq!(gate.trigger(&start(50), s(62.0)), Verdict::Replayed);
        let mut forged = start(102);
        forged.mac ^= 0x8000;
        assert_eq!(gate.trigger(&forged, s(63.0)), Verdict::Forged);
        let other = KeySet::derived(2);
        let foreign = trigger(
            other.trigger().unwrap(),
            TriggerCommand::StartCalibration,
            102,
        );
        assert_eq!(gate.trigger(&foreign, s(64.0)), Verdict::Forged);
        assert_eq!(gate.counter(), 101);
        // Authentic and fresh, inside the cooldown: consumed, not started.
        let mut gate = TriggerGate::new(Some(key.clone()), 0, COOLDOWN);
        assert_eq!(gate.trigger(&start(1), s(10.0)), Verdict::Start);
        assert_eq!(gate.trigger(&start(2), s(40.0)), Verdict::Cooldown(s(30.0)));
        assert_eq!(gate.trigger(&start(2), s(75.0)), Verdict::Replayed);
        assert_eq!(gate.trigger(&start(3), s(70.0)), Verdict::Start);
        // SIGUSR1 obeys the cooldown too; an authentic Abort starts nothing.
        assert_eq!(gate.start(s(100.0)), Verdict::Cooldown(s(30.0)));
        let abort = trigger(key, TriggerCommand::Abort, 4);
        assert_eq!(gate.trigger(&abort, s(200.0)), Verdict::NotAStart);
        assert_eq!(gate.counter(), 4);
    }

    /// A flood: every 10 ms for ten minutes of monotonic time, an authentic fresh trigger, its
    /// replay and a forgery. Sessions start exactly once per cooldown; without a key (authenticate
    /// = false) the cooldown alone bounds them the same way.
    #[test]
    fn a_flood_starts_one_session_per_cooldown() {
        let keys = KeySet::derived(3);
        let key = keys.trigger().unwrap();
        for authenticated in [true, false] {
            let mut gate = TriggerGate::new(authenticated.then(|| key.clone()), 0, COOLDOWN);
            let mut starts = Vec::new();
            let mut refused = 0u64;
            for i in 0..60_000u32 {
                let now = Duration::from_millis(10 * u64::from(i));
                let fresh = trigger(key, TriggerCommand::StartCalibration, i + 1);
                let mut forged = fresh;
                forged.mac = forged.mac.wrapping_add(i | 1);
                for t in [fresh, fresh, forged] {
                    match gate.trigger(&t, now) {
                        Verdict::Start => starts.push(now),
                        Verdict::Forged | Verdict::Replayed => refused += 1,
                        _ => {}
                    }
                }
            }
            assert_eq!(starts.len(), 10, "one per minute for ten minutes");
            assert!(starts.windows(2).all(|w| w[1] - w[0] >= COOLDOWN));
            if authenticated {
                assert_eq!(refused, 2 * 60_000);
            }
        }
    }

    /// The serve loop itself on the in-process bus, on virtual time: for 150 s, every 50 ms,
    /// an authentic fresh trigger, its replay and a forgery, with a 60 s cooldown. Exactly
    /// three sessions start (at 0, 60 and 120 s; each fails for want of motion: no suit is
    /// on this bus), and the counter file holds the last accepted counter — in the state
    /// directory, not in the output directory.
    #[tokio::test(start_paused = true)]
    async fn the_serve_loop_under_a_trigger_flood_starts_one_session_per_cooldown() {
        use exocal_bus::{InProcessBus, SimClock};
        let dir = std::env::temp_dir().join(format!("exocald-flood-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let mut config = Config::default_config();
        config.output.directory = dir.clone();
        let state = dir.with_extension("state");
        let _ = std::fs::remove_dir_all(&state);
        config.push.state_dir = Some(state.clone());
        config.calibration.window.min_duration_s = 1.0;
        config.calibration.window.max_duration_s = 2.0;
        config.calibration.window.min_samples = 10;
        config.trigger.cooldown_s = 60.0;
        config.push.keys = KeySet::derived(4);
        let key = config.push.keys.trigger().unwrap().clone();
        let clock = SimClock::new(1.0).unwrap();
        let bus = InProcessBus::with_clock(InProcessBus::DEFAULT_CAPACITY, clock.bus_clock());
        let mut daemon = bus.attach();
        let flood = bus.attach();
        let (stop, shutdown) = Shutdown::manual();
        let flooder = tokio::spawn(async move {
            for i in 0..3000u32 {
                let fresh = trigger(&key, TriggerCommand::StartCalibration, i + 1);
                let mut forged = fresh;
                forged.mac ^= 1;
                for t in [fresh, fresh, forged] {
                    flood.send_now(&Message::Trigger(t).to_frame().unwrap());
                }
                tokio::time::sleep(Duration::from_millis(50)).await;
            }
            let _ = stop.send(true);
        });
        let (_keep, mut local) = tokio::sync::mpsc::channel(1);
        let mut notifier = Notifier::disabled();
        let mut reporter = Reporter::Plain { last_line: None };
        let stats = serve(
            &mut daemon,
            &clock.bus_clock(),
            &config,
            true,
            &shutdown,
            &mut local,
            &mut notifier,
            &mut reporter,
        )
        .await
        .unwrap();
        flooder.await.unwrap();
        let logs = std::fs::read_dir(&dir)
            .unwrap()
            .filter(|e| {
                e.as_ref()
                    .is_ok_and(|e| e.path().extension().is_some_and(|x| x == "mcap"))
            })
            .count();
        let counter = crate::state::load_trigger_counter(&state).unwrap();
        assert!(!dir.join(crate::state::TRIGGER_COUNTER).exists());
        let _ = std::fs::remove_dir_all(&dir);
        let _ = std::fs::remove_dir_all(&state);
        assert_eq!((stats.sessions, logs), (3, 3), "{stats:?}");
        assert!(stats.refused > 1000 && stats.cooled > 500, "{stats:?}");
        // The last authentic trigger came while idle, at 150 s.
        assert!((2990..=3000).contains(&counter), "{counter}");
    }
}
