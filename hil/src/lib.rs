//! exocal-hil: emulates the suit's IMU nodes on a CAN interface.
//!
//! The emulated suit ([`sim::Suit`]) is a deterministic, seeded model of the true arm, seven
//! joint nodes and the end-effector reference node, with per-node clocks, table storage in
//! emulated flash files ([`flash`]) behind the `no_std` transfer state machine of `exocal-dbc`,
//! and injected faults, all described by a TOML [`Scenario`]. [`Hil`] plays it on any
//! [`exocal_bus::Transport`] (SocketCAN or the in-process bus) at `speed` × the tokio runtime's
//! time ([`exocal_bus::SimClock`]: real time, or virtual time on a paused runtime):
//!
//! ```no_run
//! # async fn demo() -> Result<(), exocal_hil::HilError> {
//! use exocal_bus::{InProcessBus, SimClock};
//! use exocal_hil::{Hil, Scenario};
//! let mut hil = Hil::new(Scenario::paper(), std::path::Path::new("/tmp/exocal-flash"))?;
//! // Simulated time starts with the clock: make it right before `run`.
//! let clock = SimClock::new(20.0).expect("positive speed");
//! let bus = InProcessBus::with_clock(InProcessBus::DEFAULT_CAPACITY, clock.bus_clock());
//! let mut hil_end = bus.attach();
//! let _daemon_end = bus.attach(); // give this one to the daemon
//! let report = hil.run(&mut hil_end, &clock).await?;
//! println!("{report}");
//! # Ok(()) }
//! ```
//!
//! The scenario's `duration_s` bounds the *motion*, not the nodes' lives: [`Hil::run`] returns
//! when the motion ends, and [`Hil::linger`] then keeps the nodes answering (heartbeats, table
//! transfers and their readback; no more samples) for a given simulated time or until a stop
//! future resolves — as a real suit at rest whose nodes stay powered. [`Hil::play`] is `run`
//! with a stop future.

#![warn(missing_docs)]

pub mod capture;
pub mod flash;
pub mod motion;
pub mod scenario;
pub mod sim;
pub mod stream_auth;
pub mod trial;
pub mod wearer;

pub use scenario::{Scenario, ScenarioError};
pub use sim::{Kind, Stats, Suit};
pub use wearer::{Voice, Wearer};

use exocal_bus::{BusError, SimClock, Transport};
use exocal_dbc::NodeId;
use std::future::Future;
use std::path::Path;
use std::time::{Duration, Instant};

/// Why the emulation could not start or stopped.
#[derive(Debug)]
pub enum HilError {
    /// Bad scenario.
    Scenario(ScenarioError),
    /// A flash file could not be read or written.
    Flash(flash::FlashError),
    /// The factory table does not fit the table format.
    Factory(NodeId, exocal_dbc::EncodeError),
    /// The bus failed.
    Bus(BusError),
}

impl std::fmt::Display for HilError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            HilError::Scenario(e) => e.fmt(f),
            HilError::Flash(e) => e.fmt(f),
            HilError::Factory(n, e) => write!(f, "factory table of {n}: {e}"),
            HilError::Bus(e) => e.fmt(f),
        }
    }
}

impl std::error::Error for HilError {}

/// What a run did.
#[derive(Clone, Debug)]
pub struct RunReport {
    /// Simulated seconds played, the motion and any lingering after it.
    pub simulated_s: f64,
    /// Simulated seconds of motion (at most the scenario's `duration_s`).
    pub motion_s: f64,
    /// Wall-clock time taken.
    pub wall: Duration,
    /// Frames received from the bus.
    pub received: u64,
    /// Frames the transport says it dropped on receive.
    pub rx_dropped: u64,
    /// The emulation's counters.
    pub stats: Stats,
    /// CRC-32 of the table each joint node holds at the end (index = joint, 0-based).
    pub held_crc: [Option<u32>; 7],
}

impl std::fmt::Display for RunReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let s = &self.stats;
        writeln!(
            f,
            "simulated {:.3} s in {:.3} s wall ({:.1}x); frames sent {}, received {}, rx dropped {}",
            self.simulated_s,
            self.wall.as_secs_f64(),
            self.simulated_s / self.wall.as_secs_f64().max(1e-9),
            s.frames_sent,
            self.received,
            self.rx_dropped,
        )?;
        if self.simulated_s > self.motion_s {
            writeln!(
                f,
                "motion {:.3} s, then the nodes answered for {:.3} s",
                self.motion_s,
                self.simulated_s - self.motion_s
            )?;
        }
        writeln!(
            f,
            "faults: lost {}, duplicated {}, delayed {}, malformed {}, babbled {}, NaN {}, reboots {}; \
             table commands {}, replies {}, refused as unauthenticated {}, corrupt flash {}, \
             boots without a readable key or counter (installing nothing) {}",
            s.lost, s.duplicated, s.delayed, s.malformed, s.babbled, s.nans, s.reboots, s.commands, s.replies,
            s.refused_unauthenticated, s.flash_corrupt, s.locked
        )?;
        for node in NodeId::ALL {
            let c = s.samples[usize::from(node.raw())];
            write!(f, "{node}:")?;
            for k in Kind::ALL {
                if c[k as usize] > 0 {
                    write!(f, " {k:?}={}", c[k as usize])?;
                }
            }
            if let Some(Some(crc)) = node.joint_index().map(|j| self.held_crc[j]) {
                write!(f, " table_crc={crc:#010x}")?;
            }
            writeln!(f)?;
        }
        Ok(())
    }
}

/// How long the nodes keep answering once the motion has ended ([`Hil::linger`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Linger {
    /// Until the stop future resolves.
    UntilStopped,
    /// For this many simulated seconds after the end of the motion (or until stopped first).
    For(f64),
}

/// How a phase of the emulation ended.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Ended {
    /// Its simulated time ran out.
    Elapsed,
    /// The stop future resolved first.
    Stopped,
}

/// The emulator driving a transport.
pub struct Hil {
    suit: Suit,
    /// When the first phase started (wall clock).
    started: Option<Instant>,
    /// Frames received from the bus over all phases.
    received: u64,
    /// What the wearer is told, when anyone speaks to them.
    voice: Option<Voice>,
}

impl Hil {
    /// Powers the suit of `scenario` up, with node flash files in `flash_dir`.
    pub fn new(scenario: Scenario, flash_dir: &Path) -> Result<Hil, HilError> {
        Ok(Hil {
            suit: Suit::new(scenario, flash_dir)?,
            started: None,
            received: 0,
            voice: None,
        })
    }

    /// The wearer hears `voice` while the suit plays: what it says, they may follow
    /// ([`wearer`]: the scenario's `[wearer]` says how).
    pub fn listening(mut self, voice: Voice) -> Hil {
        self.voice = Some(voice);
        self
    }

    /// The emulated suit (truth, held tables, counters).
    pub fn suit(&self) -> &Suit {
        &self.suit
    }

    /// Plays the scenario's motion on `bus` until `scenario.duration_s` of simulated time has
    /// passed on `clock`, answering table transfers as they come, and reports. Frames go out in
    /// simulated-time order at `clock.speed()` × real time. Timers have about 1 ms of wall-clock
    /// resolution, so a node answers a command within about `speed` ms of simulated time: scale
    /// transfer timeouts. The nodes fall silent when it returns: [`Hil::linger`] keeps them up.
    pub async fn run<T: Transport>(
        &mut self,
        bus: &mut T,
        clock: &SimClock,
    ) -> Result<RunReport, HilError> {
        self.play(bus, clock, std::future::pending()).await?;
        Ok(self.report(bus))
    }

    /// [`Hil::run`] without the report, ending early when `stop` resolves.
    pub async fn play<T: Transport, F: Future<Output = ()>>(
        &mut self,
        bus: &mut T,
        clock: &SimClock,
        stop: F,
    ) -> Result<Ended, HilError> {
        let end = self.suit.scenario().duration_s;
        self.serve_until(bus, clock, end, stop).await
    }

    /// After the motion ([`Hil::play`] returned [`Ended::Elapsed`]): the nodes stay up, sending
    /// their heartbeats and answering table transfers (readback included), until simulated time
    /// `duration_s + s` for [`Linger::For`]`(s)`, or until `stop` resolves. Called before the
    /// motion has ended, it plays the rest of the motion first.
    pub async fn linger<T: Transport, F: Future<Output = ()>>(
        &mut self,
        bus: &mut T,
        clock: &SimClock,
        linger: Linger,
        stop: F,
    ) -> Result<Ended, HilError> {
        let end = match linger {
            Linger::UntilStopped => f64::INFINITY,
            Linger::For(s) => self.suit.scenario().duration_s + s.max(0.0),
        };
        self.serve_until(bus, clock, end, stop).await
    }

    /// What the emulation did so far; `bus` is the transport it played on (for its drop count).
    pub fn report<T: Transport>(&self, bus: &T) -> RunReport {
        let simulated_s = self.suit.now_s();
        RunReport {
            simulated_s,
            motion_s: simulated_s.min(self.suit.scenario().duration_s),
            wall: self.started.map_or(Duration::ZERO, |s| s.elapsed()),
            received: self.received,
            rx_dropped: bus.dropped(),
            stats: self.suit.stats().clone(),
            held_crc: std::array::from_fn(|j| {
                self.suit.held_table(NodeId::JOINTS[j]).map(|t| t.crc())
            }),
        }
    }

    /// Runs the suit on `bus` until simulated time `end` (may be infinite) or until `stop`.
    async fn serve_until<T: Transport, F: Future<Output = ()>>(
        &mut self,
        bus: &mut T,
        clock: &SimClock,
        end: f64,
        stop: F,
    ) -> Result<Ended, HilError> {
        self.started.get_or_insert_with(Instant::now);
        let mut stop = std::pin::pin!(stop);
        loop {
            let now = clock.now_s().min(end);
            let frames = self.suit.advance(now);
            if let Some(joint) = self.voice.as_ref().and_then(Voice::heard) {
                self.suit.heed(joint);
            }
            if !frames.is_empty() {
                bus.send_all(&frames).await.map_err(HilError::Bus)?;
            }
            if now >= end {
                return Ok(Ended::Elapsed);
            }
            // Heartbeats never stop, so the next event is finite; `sleep_until` caps it anyway.
            let next = self.suit.next_event_s().min(end);
            // Biased: a stop goes first; when the sender lags behind the clock, received commands
            // still go before it catches up.
            tokio::select! {
                biased;
                _ = stop.as_mut() => return Ok(Ended::Stopped),
                r = bus.recv() => {
                    let r = r.map_err(HilError::Bus)?;
                    self.received += 1;
                    self.suit.receive(&r.frame, clock.now_s());
                }
                _ = clock.sleep_until(next) => {}
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use exocal_bus::{Endpoint, InProcessBus};
    use exocal_dbc::transfer::{RetryPolicy, Upload, UploadError};
    use exocal_dbc::{decode_frame, CmdCode, Message, NackReason, Table};
    use scenario::{TransferBehaviour, TransferFault};

    fn temp_dir(name: &str) -> std::path::PathBuf {
        let d = std::env::temp_dir().join(format!("exocal-hil-run-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        d
    }

    /// The keys the tests provision their nodes with.
    fn keys() -> exocal_dbc::auth::KeySet {
        exocal_dbc::auth::KeySet::derived(5)
    }

    /// An authenticated upload of `table` to `node` (keys from [`keys`]).
    fn upload(node: NodeId, session: u8, table: Table) -> Upload {
        let key = keys().node(node).unwrap().clone();
        Upload::authenticated(node, session, table, policy(), key)
    }

    /// Pushes `table` to `node` from a controller endpoint while the hil runs (nodes
    /// provisioned with [`keys`]); returns the upload outcome and every frame the controller
    /// saw.
    async fn push(
        scenario: Scenario,
        dir: &Path,
        node: NodeId,
        table: Table,
    ) -> (Option<Result<u32, UploadError>>, Vec<Message>, RunReport) {
        flash::provision(dir, &keys()).unwrap();
        let mut hil = Hil::new(scenario, dir).unwrap();
        // Slow enough that a loaded CI machine keeps up (timeouts are in simulated time).
        let clock = SimClock::new(10.0).unwrap();
        let bus = InProcessBus::with_clock(InProcessBus::DEFAULT_CAPACITY, clock.bus_clock());
        let mut hil_end = bus.attach();
        let mut ctrl: Endpoint = bus.attach();
        let hil_task = tokio::spawn(async move { hil.run(&mut hil_end, &clock).await.unwrap() });
        let mut up = upload(node, 42, table);
        let mut seen = Vec::new();
        // Let the nodes run for a simulated second before pushing.
        while clock.now_s() < 1.0 {
            if let Some(r) = ctrl.try_recv() {
                seen.push(decode_frame(&r.frame).unwrap());
            } else {
                tokio::time::sleep(Duration::from_millis(1)).await;
            }
        }
        drive(&mut up, &mut ctrl, &clock, &mut seen).await;
        // Keep listening until the hil stops, for the heartbeats after the push.
        while !hil_task.is_finished() {
            while let Some(r) = ctrl.try_recv() {
                seen.push(decode_frame(&r.frame).unwrap());
            }
            tokio::time::sleep(Duration::from_millis(1)).await;
        }
        while let Some(r) = ctrl.try_recv() {
            seen.push(decode_frame(&r.frame).unwrap());
        }
        let report = hil_task.await.unwrap();
        (up.outcome(), seen, report)
    }

    /// Drives `up` from `ctrl` until it has an outcome (a hang guard stops it after 20 s of
    /// wall-clock time); every frame `ctrl` receives meanwhile goes to `seen`. The exchange is
    /// printed when the upload does not succeed.
    async fn drive(
        up: &mut Upload,
        ctrl: &mut Endpoint,
        clock: &SimClock,
        seen: &mut Vec<Message>,
    ) {
        let mut log = Vec::new();
        let t0 = std::time::Instant::now();
        while up.outcome().is_none() && t0.elapsed() < Duration::from_secs(20) {
            let now_us = (clock.now_s() * 1e6) as u64;
            if let Some(cmd) = up.poll(now_us) {
                log.push(format!("{:.3} send {:?}", clock.now_s(), cmd.cmd));
                ctrl.send_now(&Message::TableCmd(cmd).to_frame().unwrap());
            }
            let mut idle = true;
            while let Some(r) = ctrl.try_recv() {
                idle = false;
                let m = decode_frame(&r.frame).unwrap();
                if let Message::TableReply(rep) = m {
                    log.push(format!("{:.3} got {:?}", clock.now_s(), rep.reply));
                    up.on_reply(&rep);
                }
                seen.push(m);
            }
            if idle {
                tokio::time::sleep(Duration::from_millis(1)).await;
            }
        }
        if !matches!(up.outcome(), Some(Ok(_))) {
            eprintln!("upload log:\n{}", log.join("\n"));
        }
    }

    fn policy() -> RetryPolicy {
        RetryPolicy {
            timeout_us: 500_000,
            max_attempts: 4,
            max_restarts: 2,
        }
    }

    fn short_paper() -> Scenario {
        let mut s = Scenario::paper();
        s.duration_s = 12.0;
        s
    }

    fn new_table() -> Table {
        Table::from_si(0.0301, -1.5, 0.0299, 0.01, 1.2, 0.9).unwrap()
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_pushed_table_is_installed_persisted_and_reported() {
        let dir = temp_dir("push");
        let node = NodeId::JOINTS[0];
        let (outcome, seen, report) = push(short_paper(), &dir, node, new_table()).await;
        let replies: Vec<_> = seen
            .iter()
            .filter(|m| matches!(m, Message::TableReply(_)))
            .collect();
        assert_eq!(
            outcome,
            Some(Ok(new_table().crc())),
            "{report}\n{replies:?}"
        );
        assert_eq!(
            flash::read(&dir, node).unwrap().map(|i| i.table),
            Some(new_table())
        );
        // Later heartbeats carry the new CRC.
        let last_hb = seen.iter().rev().find_map(|m| match m {
            Message::Heartbeat(h) if h.node == node => Some(h.table_crc),
            _ => None,
        });
        assert_eq!(last_hb, Some(new_table().crc()));
        assert!(
            report.stats.commands >= 9 && report.received >= 9,
            "{report}"
        );
        // Other nodes still hold their factory tables.
        let factory = flash::read(&dir, NodeId::JOINTS[1]).unwrap().unwrap().table;
        assert_ne!(factory, new_table());
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn nacking_and_silent_nodes_keep_their_table_and_the_upload_fails() {
        for (behaviour, want) in [
            (
                TransferBehaviour::Nack,
                UploadError::Nacked(CmdCode::Begin, NackReason::FlashError),
            ),
            (
                TransferBehaviour::Silent,
                UploadError::Timeout(CmdCode::Begin),
            ),
        ] {
            let dir = temp_dir(&format!("{behaviour:?}"));
            let node = NodeId::JOINTS[4];
            let mut s = short_paper();
            s.faults.transfer.push(TransferFault { node: 5, behaviour });
            let (outcome, _, _) = push(s, &dir, node, new_table()).await;
            assert_eq!(outcome, Some(Err(want)));
            let held = flash::read(&dir, node).unwrap().unwrap().table;
            assert_ne!(held, new_table());
            let _ = std::fs::remove_dir_all(&dir);
        }
    }

    /// Nodes with a provisioned key refuse an unauthenticated transfer (correct CRC, no
    /// CommitAuth) and take an authenticated one, storing its counter with the table.
    #[tokio::test(start_paused = true)]
    async fn keyed_nodes_take_only_authenticated_tables() {
        let dir = temp_dir("keyed");
        let keys = keys();
        flash::provision(&dir, &keys).unwrap();
        let mut s = Scenario::paper();
        s.duration_s = 30.0;
        let mut hil = Hil::new(s, &dir).unwrap();
        let clock = SimClock::new(1.0).unwrap();
        let bus = InProcessBus::with_clock(InProcessBus::DEFAULT_CAPACITY, clock.bus_clock());
        let mut hil_end = bus.attach();
        let mut ctrl = bus.attach();
        let hil_task = tokio::spawn(async move { hil.run(&mut hil_end, &clock).await.unwrap() });
        let node = NodeId::JOINTS[2];
        let factory = flash::read(&dir, node).unwrap().unwrap();
        let mut seen = Vec::new();
        let mut up = Upload::new(node, 1, new_table(), policy());
        drive(&mut up, &mut ctrl, &clock, &mut seen).await;
        assert_eq!(
            up.outcome(),
            Some(Err(UploadError::Nacked(
                CmdCode::Commit,
                NackReason::BadMac
            )))
        );
        assert_eq!(
            flash::read(&dir, node).unwrap().unwrap().table,
            factory.table
        );
        let key = keys.node(node).unwrap().clone();
        let mut up = Upload::authenticated(node, 2, new_table(), policy(), key);
        drive(&mut up, &mut ctrl, &clock, &mut seen).await;
        assert_eq!(up.outcome(), Some(Ok(new_table().crc())));
        let image = flash::read(&dir, node).unwrap().unwrap();
        assert_eq!(
            (image.table, image.counter),
            (new_table(), factory.counter + 1)
        );
        hil_task.abort();
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// On tokio's paused clock (virtual time, as the demo runs): the schedule is checked exactly,
    /// whatever the load of the machine running the test.
    #[tokio::test(start_paused = true)]
    async fn run_plays_the_scenario_in_time_at_speed() {
        let dir = temp_dir("speed");
        let mut s = Scenario::paper();
        s.duration_s = 8.0;
        let mut hil = Hil::new(s, &dir).unwrap();
        let clock = SimClock::new(40.0).unwrap();
        let bus = InProcessBus::with_clock(InProcessBus::DEFAULT_CAPACITY, clock.bus_clock());
        let mut hil_end = bus.attach();
        let mut rx = bus.attach();
        let t0 = tokio::time::Instant::now();
        let report = hil.run(&mut hil_end, &clock).await.unwrap();
        // 8 simulated s at 40x: 0.2 s of the runtime's (virtual) time, to a timer tick.
        let took = t0.elapsed().as_secs_f64();
        assert!((took - 0.2).abs() < 0.005, "8 s at 40x took {took} s");
        let mut n = 0u64;
        let mut last = Duration::ZERO;
        let first = rx.try_recv().unwrap().timestamp;
        while let Some(r) = rx.try_recv() {
            assert!(r.timestamp >= last);
            last = r.timestamp;
            n += 1;
        }
        assert_eq!(n + 1, report.stats.frames_sent);
        // Frames are stamped in simulated time when they reach the bus: the span is the
        // scenario's 8 s, to a tick of the runtime's timers (1 ms, 40 ms simulated at 40x).
        let span = (last - first).as_secs_f64();
        assert!(
            (span - 8.0).abs() <= 0.04 + 1e-9,
            "bus timestamps span {span} simulated s"
        );
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// Every frame `rx` holds now.
    fn drain(rx: &mut Endpoint) -> Vec<Message> {
        std::iter::from_fn(|| rx.try_recv())
            .map(|r| decode_frame(&r.frame).unwrap())
            .collect()
    }

    // On a paused runtime: simulated time is the runtime's virtual time, so phases end exactly.
    #[tokio::test(start_paused = true)]
    async fn linger_for_keeps_only_the_heartbeats_for_that_much_simulated_time() {
        let dir = temp_dir("linger-for");
        let mut s = Scenario::paper();
        s.duration_s = 2.0;
        let mut hil = Hil::new(s, &dir).unwrap();
        let clock = SimClock::new(5.0).unwrap();
        let bus = InProcessBus::with_clock(InProcessBus::DEFAULT_CAPACITY, clock.bus_clock());
        let mut hil_end = bus.attach();
        let mut rx = bus.attach();
        let ended = hil.play(&mut hil_end, &clock, std::future::pending());
        assert_eq!(ended.await.unwrap(), Ended::Elapsed);
        let motion = hil.report(&hil_end);
        assert_eq!((motion.motion_s, motion.simulated_s), (2.0, 2.0));
        let moving = drain(&mut rx);
        assert!(moving.iter().any(|m| matches!(m, Message::JointState(_))));
        // `--linger 0`: nothing more.
        let ended = hil.linger(
            &mut hil_end,
            &clock,
            Linger::For(0.0),
            std::future::pending(),
        );
        assert_eq!(ended.await.unwrap(), Ended::Elapsed);
        assert_eq!(hil.report(&hil_end).simulated_s, 2.0);
        assert!(drain(&mut rx).is_empty());
        let ended = hil.linger(
            &mut hil_end,
            &clock,
            Linger::For(10.0),
            std::future::pending(),
        );
        assert_eq!(ended.await.unwrap(), Ended::Elapsed);
        let report = hil.report(&hil_end);
        assert_eq!((report.motion_s, report.simulated_s), (2.0, 12.0));
        assert!(report
            .to_string()
            .contains("then the nodes answered for 10.000 s"));
        let rest = drain(&mut rx);
        assert_eq!(
            rest.len() as u64,
            report.stats.frames_sent - motion.stats.frames_sent
        );
        // No sample taken after the motion; heartbeats (1 Hz in this scenario) go on.
        for node in NodeId::ALL {
            let (before, after) = (
                motion.stats.samples[usize::from(node.raw())],
                report.stats.samples[usize::from(node.raw())],
            );
            for k in [Kind::JointState, Kind::Imu, Kind::Pose] {
                assert_eq!(before[k as usize], after[k as usize], "{node} {k:?}");
            }
            let beats = rest
                .iter()
                .filter(|m| matches!(m, Message::Heartbeat(h) if h.node == node))
                .count();
            assert!(
                (9..=11).contains(&beats),
                "{node}: {beats} heartbeats in 10 s"
            );
        }
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[tokio::test(start_paused = true)]
    async fn after_the_motion_the_nodes_take_a_push_and_answer_until_stopped() {
        let dir = temp_dir("linger-push");
        flash::provision(&dir, &keys()).unwrap();
        let mut s = Scenario::paper();
        s.duration_s = 2.0;
        let mut hil = Hil::new(s, &dir).unwrap();
        let clock = SimClock::new(1.0).unwrap();
        let bus = InProcessBus::with_clock(InProcessBus::DEFAULT_CAPACITY, clock.bus_clock());
        let mut hil_end = bus.attach();
        let mut ctrl = bus.attach();
        let (motion_tx, motion_rx) = tokio::sync::oneshot::channel();
        let (stop_tx, stop_rx) = tokio::sync::oneshot::channel::<()>();
        let hil_task = tokio::spawn(async move {
            let motion = hil.play(&mut hil_end, &clock, std::future::pending());
            let motion = motion.await.unwrap();
            motion_tx.send(hil.report(&hil_end)).unwrap();
            let stop = async {
                let _ = stop_rx.await;
            };
            let rest = hil.linger(&mut hil_end, &clock, Linger::UntilStopped, stop);
            (motion, rest.await.unwrap(), hil.report(&hil_end))
        });
        let at_motion_end = motion_rx.await.unwrap();
        drain(&mut ctrl);
        let node = NodeId::JOINTS[3];
        let mut up = upload(node, 7, new_table());
        let mut seen = Vec::new();
        drive(&mut up, &mut ctrl, &clock, &mut seen).await;
        assert_eq!(up.outcome(), Some(Ok(new_table().crc())));
        // Three simulated seconds later, still answering: heartbeats announce the new table.
        let until = clock.now_s() + 3.0;
        clock.sleep_until(until).await;
        seen.extend(drain(&mut ctrl));
        stop_tx.send(()).unwrap();
        let (motion, rest, report) = hil_task.await.unwrap();
        assert_eq!((motion, rest), (Ended::Elapsed, Ended::Stopped));
        assert_eq!(at_motion_end.motion_s, 2.0);
        // The suit advances at its events: the last heartbeat was at most a second before.
        assert!(report.simulated_s > until - 1.5, "{report}");
        assert_eq!(report.motion_s, 2.0);
        assert!(
            report.stats.commands > at_motion_end.stats.commands
                && report.stats.replies > at_motion_end.stats.replies,
            "{report}"
        );
        assert_eq!(
            flash::read(&dir, node).unwrap().map(|i| i.table),
            Some(new_table())
        );
        for node in NodeId::ALL {
            let i = usize::from(node.raw());
            let (before, after) = (at_motion_end.stats.samples[i], report.stats.samples[i]);
            assert_eq!(
                before[..3],
                after[..3],
                "{node}: no samples after the motion"
            );
        }
        let last_hb = seen.iter().rev().find_map(|m| match m {
            Message::Heartbeat(h) if h.node == node => Some(h.table_crc),
            _ => None,
        });
        assert_eq!(last_hb, Some(new_table().crc()));
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[tokio::test(start_paused = true)]
    async fn a_stop_during_the_motion_ends_it_there() {
        let dir = temp_dir("stop");
        let mut s = Scenario::paper();
        s.duration_s = 5.0;
        let mut hil = Hil::new(s, &dir).unwrap();
        let clock = SimClock::new(2.0).unwrap();
        let bus = InProcessBus::with_clock(InProcessBus::DEFAULT_CAPACITY, clock.bus_clock());
        let mut hil_end = bus.attach();
        let _rx = bus.attach();
        let stop = tokio::time::sleep(Duration::from_millis(500));
        assert_eq!(
            hil.play(&mut hil_end, &clock, stop).await.unwrap(),
            Ended::Stopped
        );
        let report = hil.report(&hil_end);
        assert!(
            report.motion_s < 5.0 && report.simulated_s == report.motion_s,
            "{report}"
        );
        assert!(report.stats.frames_sent > 0);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
