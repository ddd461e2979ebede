//! One calibration session on any transport: collect → align → calibrate → validate → push,
//! with the MCAP log written throughout.
//!
//! Contract:
//! - [`run_session`] owns the session's log: it is created first and finished on every path
//!   (success, refusal, error, shutdown), so a session always leaves a readable file;
//! - nothing is pushed unless the calibration passed validation, the session was not
//!   interrupted, and `dry_run` is off; a shutdown (the `shutdown` future completing) before the
//!   push starts ends the session with [`DaemonError::Interrupted`]; once started, the push runs
//!   to its end (it is bounded by the push policy, and every node transfer is atomic);
//! - session time (durations, push timeouts, log times) is `clock` — the wall clock on SocketCAN,
//!   a [`exocal_bus::SimClock`] on the in-process bus — so a simulated suit at any speed sees the
//!   same behaviour; the housekeeping tick and the push's wait for replies are tokio timers (on
//!   the demo's paused runtime they are simulated too, which makes the demo reproducible);
//!   the watchdog and the log's flush cadence use real time and never decide what is collected;
//! - the heavy calibration runs on a blocking thread while the loop keeps draining (and
//!   logging) the bus, feeding the watchdog and flushing the log.

use std::future::Future;
use std::pin::Pin;
use std::time::{Duration, Instant};

use exocal_bus::{Clock, Transport};
use exocal_log::write::Level;
use exocal_session::collect::Collected;
use exocal_session::estimate::Estimate;
use exocal_session::pipeline::{Calibrated, Outcome};
use exocal_session::window::{Phase, Shortfall};
use exocal_session::{CalibrationJob, Session};

use crate::config::Config;
use crate::exit::DaemonError;
use crate::live::LiveView;
use crate::log::records::ns;
use crate::log::records::{self, Observer};
use crate::push::{self, PushReport};
use crate::shell::html_report::{self, ReportFile};
use crate::shell::io::Io;
use crate::shell::lines;
use crate::shell::notify::{Notifier, Reporter};
use crate::shell::shutdown;
use crate::shell::stream_nonce::StreamNonces;
use crate::shell::summary::{Latency, SessionError, SessionSummary};

/// Real time between two turns of the housekeeping tick.
pub const TICK: Duration = Duration::from_millis(100);

/// Rate (Hz) at which the arm's frames are written to `/tf` for Foxglove.
pub const TF_HZ: f64 = 20.0;

/// Runs one session on `bus` (see the module docs). `clock` is the bus clock. With
/// `[live] enabled`, the live view serves the session (started here, stopped at its end).
pub async fn run_session<T: Transport>(
    bus: &mut T,
    clock: &Clock,
    config: &Config,
    dry_run: bool,
    shutdown: impl Future<Output = ()>,
    notifier: &mut Notifier,
    reporter: &mut Reporter,
) -> Result<SessionSummary, SessionError> {
    let live = LiveView::for_session(config).map_err(DaemonError::from)?;
    if let Some(live) = &live {
        reporter.message(&live.banner(config));
    }
    let observers: Vec<&dyn Observer> = live.iter().map(|l| l as &dyn Observer).collect();
    run_session_with(
        bus, clock, config, dry_run, shutdown, notifier, reporter, &observers,
    )
    .await
}

/// [`run_session`] with `observers` of its records besides its log (the live view, whoever
/// started it keeps it after the session).
#[allow(clippy::too_many_arguments)]
pub async fn run_session_with<T: Transport>(
    bus: &mut T,
    clock: &Clock,
    config: &Config,
    dry_run: bool,
    shutdown: impl Future<Output = ()>,
    notifier: &mut Notifier,
    reporter: &mut Reporter,
    observers: &[&dyn Observer],
) -> Result<SessionSummary, SessionError> {
    let start = clock.now();
    let (log_path, mut io) = Io::open(config, start, observers, notifier, reporter)?;
    let mut tick = tokio::time::interval(TICK);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut running = Running {
        bus,
        clock,
        config,
        io: &mut io,
        session: Session::new(&config.calibration),
        nonces: StreamNonces::new(&config.push),
        origin: Duration::ZERO,
        handed_off: false,
        tick,
        report: ReportFile::new(&log_path, start, config),
        summary: SessionSummary::new(log_path),
    };
    tokio::pin!(shutdown);
    let result = running.run(dry_run, start, shutdown).await;
    let mut summary = running.summary;
    summary.report_path = running.report.path;
    let (log_counts, result) = io.close(result, clock.now());
    summary.log_counts = log_counts;
    match result {
        Ok(()) => Ok(summary),
        Err(error) => Err(SessionError {
            error,
            summary: Some(summary),
        }),
    }
}

/// One live session in progress: the bus, the log and what was collected so far. Its steps
/// run in order — [`Running::collect`], [`Running::align`], [`Running::calibrate`],
/// [`Running::push`] —
/// and each keeps the bus drained, the log flushed and the watchdog fed while it waits.
struct Running<'a, 'io, T> {
    bus: &'a mut T,
    clock: &'a Clock,
    config: &'a Config,
    io: &'a mut Io<'io>,
    session: Session,
    /// The stream nonces sent to the nodes.
    nonces: StreamNonces<'a>,
    /// Bus time of the collection's first frame: aligned sample times are relative to it.
    origin: Duration,
    /// Whether the collection was handed over ([`Running::end_collection`]).
    handed_off: bool,
    tick: tokio::time::Interval,
    summary: SessionSummary,
    /// The session's report file.
    report: ReportFile,
}

impl<T: Transport> Running<'_, '_, T> {
    /// The whole session after the log is open; `start` is its bus-clock start.
    async fn run<S: Future<Output = ()>>(
        &mut self,
        dry_run: bool,
        start: Duration,
        mut shutdown: Pin<&mut S>,
    ) -> Result<(), DaemonError> {
        if let Err(e) = self.collect(shutdown.as_mut()).await {
            // Until the collection is handed over; a refused one was summed up with its report.
            if !self.handed_off {
                self.summary.frames = self.session.stats().clone();
            }
            if matches!(e, DaemonError::Interrupted) {
                self.interrupted_report(start);
            }
            return Err(e);
        }
        let window_closed = (Instant::now(), self.clock.monotonic());
        let job = self.align(shutdown.as_mut()).await?;
        self.summary.collected(job.collected());
        let (job, calibrated) = self.calibrate(job, shutdown.as_mut()).await?;
        self.log_result(job.collected(), &calibrated);
        let accepted = calibrated.outcome.verdict.accepted();
        let reasons = calibrated.outcome.verdict.reasons.clone();
        self.summary.outcome = Some(calibrated.outcome);
        if !accepted {
            return Err(DaemonError::Validation(reasons));
        }
        if dry_run {
            self.io
                .event(self.clock.now(), Level::Info, "dry run: nothing pushed");
            return Ok(());
        }
        self.io.log_failed()?;
        // Last chance to stop before touching the nodes.
        if shutdown::is_done(&mut shutdown) {
            return Err(DaemonError::Interrupted);
        }
        let pushed = self.push(start).await;
        if pushed.is_ok() {
            self.summary.latency = Some(Latency {
                real: window_closed.0.elapsed(),
                session: self.clock.monotonic().saturating_sub(window_closed.1),
                simulated: matches!(self.clock, Clock::Simulated(_)),
            });
        }
        let push = self.summary.push.as_ref().map(records::push_records);
        if let Some(line) = push.and_then(|push| self.report.with_push(&push)) {
            self.io.lines(self.clock.now(), vec![line]);
        }
        pushed?;
        Ok(())
    }

    /// Step 1: collects until the session rules are met (or cannot be). The tick goes before
    /// the bus so a saturated bus cannot starve the watchdog.
    async fn collect<S: Future<Output = ()>>(
        &mut self,
        mut shutdown: Pin<&mut S>,
    ) -> Result<(), DaemonError> {
        // The window is timed on the clock's monotonic reading: a step of the host's wall clock
        // (NTP at boot) neither stretches nor cuts it.
        let started = self.clock.monotonic();
        self.authenticate_streams().await?;
        let required = self.config.calibration.window.excitation_required;
        let mut estimate_job: Option<tokio::task::JoinHandle<Option<Estimate>>> = None;
        loop {
            tokio::select! {
                biased;
                () = &mut shutdown => return Err(DaemonError::Interrupted),
                _ = self.tick.tick() => {
                    self.io.housekeeping();
                    let elapsed = self.clock.monotonic().saturating_sub(started).as_secs_f64();
                    let tick = self.session.on_tick(elapsed);
                    self.io.reporter.update(&tick.progress, required, self.io.notifier);
                    let r = self.io.log.progress(ns(self.clock.now()), &tick.progress);
                    self.io.check(r);
                    if let Some(job) = tick.estimate {
                        estimate_job = Some(tokio::task::spawn_blocking(|| job.run()));
                    }
                    match tick.phase {
                        Phase::Collecting => {}
                        Phase::Ready => {
                            self.io.reporter.closed(&tick.progress, required);
                            break;
                        }
                        Phase::Failed(why) => {
                            self.summary.stream = self.session.gate().map(|g| g.stats().clone());
                            if let Some(job) = estimate_job.take() {
                                job.abort();
                            }
                            self.summary.frames = self.session.stats().clone();
                            self.session_report(&why, shutdown.as_mut()).await?;
                            return Err(DaemonError::Session(why));
                        }
                    }
                }
                done = async { estimate_job.as_mut().expect("guarded").await }, if estimate_job.is_some() => {
                    estimate_job = None;
                    self.session.estimated(done.ok().flatten());
                }
                rx = self.bus.recv() => {
                    let rx = rx.map_err(|source| DaemonError::Bus { what: "receiving CAN".into(), source })?;
                    self.io.take_frame(&rx, &mut self.session);
                    // A node rebooted (it lost the nonce with its RAM), or another sender set
                    // one: every node gets a new one.
                    if self.session.nonce_wanted() {
                        self.send_stream_nonce().await?;
                    }
                }
            }
            self.io.log_failed()?;
        }
        let now = self.clock.now();
        let end = records::collection_end(&self.session, self.bus.dropped(), ns(now));
        let (s, gate) = (self.session.stats(), self.session.gate());
        let lines = lines::collection_end(s, gate.map(|g| g.stats()), end.dropped);
        self.summary.stream = gate.map(|g| g.stats().clone());
        let r = self.io.log.collection_end(&end);
        self.io.check(r);
        self.io.lines(now, lines);
        // An estimate still running: a blocking task cannot be aborted, and left to run it
        // would hold its copy of the collection and a core beside the calibration (the peak
        // memory, and the latency on a one-core controller, would depend on when it ends).
        // Its result is of no use any more; it is waited for as any step off the loop is.
        if let Some(job) = estimate_job {
            let _ = self
                .wait_off_loop("last estimate", shutdown.as_mut(), job)
                .await?;
        }
        Ok(())
    }

    /// Opens the collection's stream authentication ([`StreamNonces::open`]).
    async fn authenticate_streams(&mut self) -> Result<(), DaemonError> {
        let on = self.config.push.authenticate && self.config.verify_streams;
        if !self.nonces.open(on, &mut self.session) {
            let line = "sensor streams are not authenticated ([push] authenticate = false, or no \
                        keys): any sender on the bus can steer the calibration";
            self.io.event(self.clock.now(), Level::Warning, line);
            return Ok(());
        }
        self.send_stream_nonce().await
    }

    /// Sends every keyed node a fresh nonce ([`StreamNonces::next`]) and logs it.
    async fn send_stream_nonce(&mut self) -> Result<(), DaemonError> {
        for frame in self.nonces.next(&mut self.session)? {
            let sent = self.bus.send(&frame.1).await;
            sent.map_err(|source| DaemonError::Bus {
                what: format!("sending {} its stream nonce", frame.0),
                source,
            })?;
            self.io.frame(true, &frame.1, self.clock.now());
        }
        Ok(())
    }

    /// Step 2: ends the collection and aligns it on a blocking thread (the clock fits and the
    /// resampling are seconds of CPU on a slow controller); logs the aligned samples and what
    /// the clocks showed. The collection moves to the job (no copy of a long session); a fresh
    /// one decodes, for the log, what arrives afterwards.
    async fn align<S: Future<Output = ()>>(
        &mut self,
        shutdown: Pin<&mut S>,
    ) -> Result<CalibrationJob, DaemonError> {
        let session = self.end_collection();
        let job = (self.off_loop("aligning", shutdown, move || session.into_calibration())).await?;
        let now = self.clock.now();
        // The warnings first, the samples, then the grid they are on.
        let mut lines = lines::aligned(job.collected(), self.config.calibration.window.grid_hz);
        let grid = lines.pop();
        self.io.lines(now, lines);
        for (i, s) in job.collected().samples.iter().enumerate() {
            let joints = self.config.calibration.joints;
            let r = self.io.log.aligned(self.log_time(s.t), s, joints);
            self.io.check(r);
            self.io.between_records(i);
        }
        self.io.lines(now, grid.into_iter().collect());
        Ok(job)
    }

    /// Hands the collection over (the aligned samples' times are relative to its first frame)
    /// and starts a fresh one, which decodes for the log what arrives afterwards.
    fn end_collection(&mut self) -> Session {
        self.origin = self.session.origin().unwrap_or_default();
        self.handed_off = true;
        std::mem::replace(&mut self.session, Session::new(&self.config.calibration))
    }

    /// Runs `job` on tokio's blocking pool while this thread keeps the bus drained (and
    /// logged), the log flushed and the watchdog fed: no CPU-bound step runs on the loop's
    /// thread, so none can starve the watchdog however slow or busy the controller.
    async fn off_loop<R: Send + 'static, S: Future<Output = ()>>(
        &mut self,
        what: &str,
        shutdown: Pin<&mut S>,
        job: impl FnOnce() -> R + Send + 'static,
    ) -> Result<R, DaemonError> {
        let job = tokio::task::spawn_blocking(job);
        self.wait_off_loop(what, shutdown, job).await
    }

    /// Waits for `job`, on tokio's blocking pool, as [`Self::off_loop`] does.
    async fn wait_off_loop<R: Send + 'static, S: Future<Output = ()>>(
        &mut self,
        what: &str,
        mut shutdown: Pin<&mut S>,
        job: tokio::task::JoinHandle<R>,
    ) -> Result<R, DaemonError> {
        tokio::pin!(job);
        let done = loop {
            tokio::select! {
                biased;
                () = &mut shutdown => return Err(DaemonError::Interrupted),
                done = &mut job => break done,
                _ = self.tick.tick() => self.io.housekeeping(),
                rx = self.bus.recv() => {
                    if let Ok(rx) = rx {
                        self.io.take_frame(&rx, &mut self.session);
                    }
                }
            }
        };
        done.map_err(|e| DaemonError::Internal {
            what: format!("in the {what} task"),
            source: Box::new(e),
        })
    }

    /// Step 3: runs the pipeline and renders the report on a blocking thread, the bus drained
    /// and the watchdog fed meanwhile; writes the report next to the log.
    async fn calibrate<S: Future<Output = ()>>(
        &mut self,
        job: CalibrationJob,
        shutdown: Pin<&mut S>,
    ) -> Result<(CalibrationJob, Calibrated), DaemonError> {
        self.io.notifier.status("calibrating");
        self.io
            .reporter
            .phase("calibrating", "least squares, then EM");
        let (calibration, source) = self.report.titles("calibration");
        let (session, _) = self.report.titles("session");
        // The report is rendered on the blocking thread too: it is a few hundred ms of SVG.
        let (job, calibrated, html) = self
            .off_loop("calibration", shutdown, move || {
                let calibrated = job.run();
                let (title, reasons) = match &calibrated {
                    Err(e) => (session, vec![e.to_string()]),
                    Ok(_) => (calibration, Vec::new()),
                };
                let result = calibrated.as_ref().map_err(|_| reasons.as_slice());
                let (settings, collected) = (job.settings(), job.collected());
                let html = html_report::render(title, source, settings, collected, result);
                (job, calibrated, html)
            })
            .await?;
        // The samples would not calibrate: the report says why, as for a session that ran out
        // of time.
        let line = self.report.write_calibration(html);
        self.io.lines(self.clock.now(), vec![line]);
        Ok((job, calibrated?))
    }

    /// The calibration's record, its line and the arm on the calibrated table, into the log.
    fn log_result(&mut self, collected: &Collected, calibrated: &Calibrated) {
        let table = calibrated.outcome.table();
        let joints = self.config.calibration.joints;
        let step = ((self.config.calibration.window.grid_hz / TF_HZ).round() as usize).max(1);
        for (i, s) in collected.samples.iter().step_by(step).enumerate() {
            let links = records::arm_transforms(&table, &s.joints, joints);
            let r = self.io.log.arm_transforms(self.log_time(s.t), &links);
            self.io.check(r);
            self.io.between_records(i);
        }
        let now = self.clock.now();
        self.log_calibration(now, &calibrated.outcome, None);
        let limits = &self.config.calibration.bounds.joint_range.limits;
        if let Ok(urdf) = records::urdf(&table, limits, joints) {
            let r = self.io.log.robot_description(ns(now), &urdf);
            self.io.check(r);
        }
        self.io.lines(now, lines::calibrated(&calibrated.outcome));
    }

    /// The calibration's record at `now`, with the push's `report` once there is one.
    fn log_calibration(&mut self, now: Duration, outcome: &Outcome, report: Option<&PushReport>) {
        let s = &self.summary;
        let (clocks, samples, gaps) = (&s.clocks, s.aligned_samples, s.gaps);
        let record = records::calibration_record(outcome, clocks, samples, gaps, report);
        let r = self.io.log.calibration(ns(now), &record);
        self.io.check(r);
    }

    /// Step 4: pushes the validated table to every node with CRC readback, and logs what each
    /// node holds afterwards (also when the push fails).
    async fn push(&mut self, start: Duration) -> Result<(), DaemonError> {
        let outcome = (self.summary.outcome.clone()).ok_or(DaemonError::Interrupted)?;
        let tables = push::node_tables(&outcome, self.config).map_err(DaemonError::Unpushable)?;
        self.io.notifier.status("pushing tables");
        self.io.reporter.phase("pushing", "the tables to the nodes");
        let first_session = (ns(start) / 1_000_000 % 251) as u8;
        let (bus, clock, policy) = (&mut *self.bus, self.clock, &self.config.push);
        let pushed = push::push_calibration(bus, clock, &tables, policy, first_session, self.io);
        let (report, result) = pushed.await;
        let now = self.clock.now();
        for line in report.lines() {
            self.io.event(now, Level::Info, &line);
        }
        self.log_calibration(now, &outcome, Some(&report));
        self.summary.push = Some(report);
        result?;
        let line = "every node holds its new table (CRC read back)";
        self.io.event(self.clock.now(), Level::Info, line);
        Ok(())
    }

    /// The report of a session that ends without a calibration (`why`: the session rules it
    /// did not meet), next to its log as a calibrated session's would be: what the motion lacked.
    async fn session_report<S: Future<Output = ()>>(
        &mut self,
        why: &[Shortfall],
        shutdown: Pin<&mut S>,
    ) -> Result<(), DaemonError> {
        let (title, source) = self.report.titles("session");
        let session = self.end_collection();
        let why: Vec<String> = why.iter().map(Shortfall::to_string).collect();
        let (job, html) = self
            .off_loop("session report", shutdown, move || {
                let job = session.into_calibration();
                let (settings, collected) = (job.settings(), job.collected());
                let html = html_report::render(title, source, settings, collected, Err(&why));
                (job, html)
            })
            .await?;
        let line = self.report.write(&html, "session report");
        self.io.lines(self.clock.now(), vec![line]);
        self.summary.collected(job.collected());
        Ok(())
    }

    /// The report of a session stopped during collection ([`html_report::interrupted`]).
    fn interrupted_report(&mut self, start: Duration) {
        let (title, source) = self.report.titles("session");
        let seconds = self.clock.now().saturating_sub(start).as_secs_f64();
        let settings = &self.config.calibration;
        let html = html_report::interrupted(title, source, &self.summary.frames, seconds, settings);
        let line = self.report.write(&html, "session report");
        self.io.lines(self.clock.now(), vec![line]);
    }

    /// Log time of the aligned sample at `t` s of the session.
    fn log_time(&self, t: f64) -> u64 {
        ns(self.origin + Duration::from_secs_f64(t.max(0.0)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    use crate::shell::shutdown::Shutdown;
    use exocal_bus::SimClock;
    use exocal_bus::{Frame, InProcessBus};
    use exocal_dbc::table::Table;
    use exocal_dbc::NodeId;
    use exocal_hil::{Hil, Scenario};
    use exocal_session::validate::Refusal;
    use std::path::PathBuf;

    fn temp_dir(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("exocald-runner-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        d
    }

    /// Runs one session against the paper hil, on the test runtime's paused clock (virtual time,
    /// as the demo runs: the outcome does not depend on the machine's load); `stop_after_s`
    /// raises the shutdown flag after that much simulated time. Returns the result and the
    /// flash CRCs before and after.
    async fn session(
        config: Config,
        dir: &std::path::Path,
        stop_after_s: Option<f64>,
    ) -> (
        Result<SessionSummary, SessionError>,
        Vec<Option<u32>>,
        Vec<Option<u32>>,
    ) {
        session_on(config, dir, stop_after_s, Scenario::paper()).await
    }

    /// [`session`] against the hil playing `scenario` (for 400 s at most).
    async fn session_on(
        config: Config,
        dir: &std::path::Path,
        stop_after_s: Option<f64>,
        mut scenario: Scenario,
    ) -> (
        Result<SessionSummary, SessionError>,
        Vec<Option<u32>>,
        Vec<Option<u32>>,
    ) {
        let flash = dir.join("flash");
        std::fs::create_dir_all(&flash).unwrap();
        exocal_hil::flash::provision(&flash, &config.push.keys).unwrap();
        scenario.duration_s = 400.0;
        let hil = Hil::new(scenario, &flash).unwrap();
        let crcs = |flash: &std::path::Path| -> Vec<Option<u32>> {
            NodeId::JOINTS
                .iter()
                .map(|&n| {
                    exocal_hil::flash::read(flash, n)
                        .unwrap()
                        .map(|i| i.table.crc())
                })
                .collect()
        };
        let before = crcs(&flash);
        let ([mut daemon_end], clock, hil_task) = play(hil);
        let (stop, shutdown) = Shutdown::manual();
        if let Some(s) = stop_after_s {
            tokio::spawn(async move {
                tokio::time::sleep(Duration::from_secs_f64(s)).await;
                let _ = stop.send(true);
            });
        }
        let result = run_plain(&mut daemon_end, &clock, &config, shutdown.wait()).await;
        hil_task.abort();
        let _ = hil_task.await;
        (result, before, crcs(&flash))
    }

    /// `hil` playing on a new in-process bus stamped with its simulated clock (the test
    /// runtime's): `N` endpoints on it (attached before the hil starts), the clock and the
    /// hil's task.
    fn play<const N: usize>(
        mut hil: Hil,
    ) -> (
        [exocal_bus::Endpoint; N],
        SimClock,
        tokio::task::JoinHandle<Result<exocal_hil::RunReport, exocal_hil::HilError>>,
    ) {
        let clock = SimClock::new(1.0).unwrap();
        let bus = InProcessBus::with_clock(InProcessBus::DEFAULT_CAPACITY, clock.bus_clock());
        let mut hil_end = bus.attach();
        let ends = std::array::from_fn(|_| bus.attach());
        let task = tokio::spawn(async move { hil.run(&mut hil_end, &clock).await });
        (ends, clock, task)
    }

    /// [`run_session`] on `clock`'s time without notifications, its progress in plain lines.
    async fn run_plain(
        daemon_end: &mut exocal_bus::Endpoint,
        clock: &SimClock,
        config: &Config,
        shutdown: impl Future<Output = ()>,
    ) -> Result<SessionSummary, SessionError> {
        let mut notifier = Notifier::disabled();
        let mut reporter = Reporter::Plain { last_line: None };
        let bus_clock = clock.bus_clock();
        run_session(
            daemon_end,
            &bus_clock,
            config,
            false,
            shutdown,
            &mut notifier,
            &mut reporter,
        )
        .await
    }

    fn config(dir: &std::path::Path) -> Config {
        let mut c = Config::default_config();
        c.output.directory = dir.to_path_buf();
        c.calibration.window.min_duration_s = 15.0;
        c.push.timeout_ms = 400;
        // Authenticated, as on a suit: the hil's nodes are provisioned with these keys.
        c.push.keys = exocal_dbc::auth::KeySet::derived(31);
        c
    }

    /// [`config`] whose validation refuses every table: no minute of motion gives one to a
    /// micrometre.
    fn refusing_config(dir: &std::path::Path) -> Config {
        let mut c = config(dir);
        c.calibration.validation.max_expected_position_error_mm = 1e-3;
        c
    }

    fn topic_count(summary: &SessionSummary, topic: &str) -> u64 {
        summary
            .log_counts
            .iter()
            .find(|(t, _)| t == topic)
            .map_or(0, |c| c.1)
    }

    /// The file must be finished: a summary section with every channel.
    fn assert_finished(path: &std::path::Path) -> mcap::Summary {
        let bytes = std::fs::read(path).unwrap();
        let summary = mcap::Summary::read(&bytes)
            .unwrap()
            .expect("a finished file");
        assert_eq!(summary.channels.len(), exocal_log::write::Topic::ALL.len());
        summary
    }

    #[tokio::test(start_paused = true)]
    async fn shutdown_during_collection_finishes_the_log_and_pushes_nothing() {
        let dir = temp_dir("sigterm");
        // Mid-collection (the minimum is 15 s).
        let (result, before, after) = session(config(&dir), &dir, Some(8.0)).await;
        let err = result.unwrap_err();
        assert!(
            matches!(err.error, DaemonError::Interrupted),
            "{}",
            err.error
        );
        assert_eq!(err.error.exit_code(), crate::exit::code::TEMPFAIL);
        let summary = err.summary.unwrap();
        assert!(summary.push.is_none());
        // The report says it was stopped, when, and that the log has the frames.
        let report =
            std::fs::read_to_string(summary.report_path.as_ref().expect("a report")).unwrap();
        assert!(
            report.contains("Stopped before calibrating")
                && report.contains("into the collection, with"),
            "{report}"
        );
        // Sent: the collection's stream nonce (one frame per node), nothing else.
        assert_eq!(topic_count(&summary, "/can/tx"), NodeId::ALL.len() as u64);
        assert!(topic_count(&summary, "/can/rx") > 1000);
        // The file holds what the summary counts: a message per record, a batch of frames per
        // message on /can/*.
        let file = assert_finished(&summary.log_path);
        let stats = file.stats.unwrap();
        for (topic, records) in &summary.log_counts {
            let id = file
                .channels
                .values()
                .find(|c| &c.topic == topic)
                .unwrap()
                .id;
            let messages = stats.channel_message_counts.get(&id).copied().unwrap_or(0);
            if topic.starts_with("/can/") {
                assert!(
                    messages <= *records && (messages == 0) == (*records == 0),
                    "{topic}"
                );
            } else {
                assert_eq!(messages, *records, "{topic}");
            }
        }
        assert_eq!(before, after, "no node's table changed");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[tokio::test(start_paused = true)]
    async fn a_refused_calibration_pushes_nothing_and_says_why() {
        let dir = temp_dir("refused");
        let (result, before, after) = session(refusing_config(&dir), &dir, None).await;
        let err = result.unwrap_err();
        match &err.error {
            DaemonError::Validation(reasons) => {
                assert!(
                    reasons.iter().any(|r| matches!(
                        r,
                        Refusal::ExpectedPosition { max, .. } if *max == 1e-3
                    )),
                    "{reasons:?}"
                );
            }
            other => panic!("{other}"),
        }
        assert_eq!(err.error.exit_code(), crate::exit::code::DATAERR);
        let summary = err.summary.unwrap();
        assert!(summary.outcome.is_some() && summary.push.is_none());
        assert!(summary.latency.is_none(), "nothing was verified");
        // Sent: the collection's stream nonce (one frame per node), no table command.
        assert_eq!(topic_count(&summary, "/can/tx"), NodeId::ALL.len() as u64);
        assert_eq!(topic_count(&summary, "/calibration"), 1);
        assert_finished(&summary.log_path);
        assert_eq!(before, after);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[tokio::test(start_paused = true)]
    async fn a_session_that_stops_when_good_enough_ends_early_and_reaches_its_limits() {
        let dir = temp_dir("good-enough");
        let mut c = config(&dir);
        c.calibration.window.stop_at_expected_error = Some((2.0, 6.0));
        let (result, before, after) = session(c, &dir, None).await;
        let summary = result.expect("the session pushes");
        // The paper's scenario is within ±2.0 mm, ±6.0 mrad at STOP_GUARD estimates in a row
        // (5 s apart) before its minute (±1.3 mm at 60 s).
        assert!(
            summary.aligned_samples < 6_000,
            "stopped after {} samples",
            summary.aligned_samples
        );
        let e = summary.outcome.as_ref().unwrap().verdict.expected.unwrap();
        assert!(e.position_mm <= 2.0 && e.rotation_mrad <= 6.0, "{e}");
        assert!(summary.push.as_ref().unwrap().complete());
        assert_ne!(before, after, "the nodes hold the new tables");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[tokio::test(start_paused = true)]
    async fn a_session_without_enough_motion_fails_at_the_maximum_duration() {
        let dir = temp_dir("short");
        let mut c = config(&dir);
        c.calibration.window.min_samples = 1_000_000;
        c.calibration.window.max_duration_s = 16.0;
        let (result, _, _) = session(c, &dir, None).await;
        let err = result.unwrap_err();
        assert!(
            matches!(err.error, DaemonError::Session(_)),
            "{}",
            err.error
        );
        assert!(
            err.error.to_string().contains("1000000 required"),
            "{}",
            err.error
        );
        assert_eq!(err.error.exit_code(), crate::exit::code::NOINPUT);
        let summary = err.summary.unwrap();
        assert_finished(&summary.log_path);
        // The report says why and shows the data the session had.
        let report = summary
            .report_path
            .expect("a report for the failed session");
        let html = std::fs::read_to_string(&report).unwrap();
        assert!(html.contains("Not calibrated"), "{html}");
        assert!(html.contains("1000000 required"));
        assert!(
            summary.aligned_samples > 1000,
            "{}",
            summary.aligned_samples
        );
        assert!(html.contains(&format!("<td>{}</td>", summary.aligned_samples)));
        // The frames counted are the collection's (16 s of eight nodes at 100 Hz and more), not
        // those that arrived while its report was rendered.
        assert!(summary.frames.received > 16 * 800, "{:?}", summary.frames);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[tokio::test(start_paused = true)]
    async fn a_bus_stall_is_a_receiver_stall_and_a_reboot_is_that_nodes_jump() {
        use exocal_hil::scenario::{BusStall, Reboot};
        let dir = temp_dir("stall");
        // Refused: the alignment is what this test is about.
        let c = refusing_config(&dir);
        let mut scenario = Scenario::paper();
        // Every node's frames 400 ms late for 3 s, then Joint4 reboots.
        scenario.faults.bus_stalls.push(BusStall {
            from_s: 5.0,
            to_s: 8.0,
            late_ms: 400.0,
        });
        scenario.faults.reboots.push(Reboot {
            node: 4,
            at_s: 11.0,
            down_s: 0.5,
        });
        let (result, _, _) = session_on(c, &dir, None, scenario).await;
        let summary = match result {
            Ok(s) => s,
            Err(e) => e.summary.expect("a summary"),
        };
        assert_eq!(summary.stalls.count, 1, "{:?}", summary.stalls);
        assert!(
            summary
                .stalls
                .longest_ms
                .is_some_and(|ms| (300.0..500.0).contains(&ms)),
            "{:?}",
            summary.stalls
        );
        for c in &summary.clocks {
            let want = usize::from(c.node == "Joint4");
            assert_eq!(c.jumps, want, "{c:?}; streams {:?}", summary.stream);
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// One authenticated session (the hil's nodes hold the keys the daemon has) against the
    /// paper hil, with a rogue on the bus when `rogue`: during bursts (~0.3 s every 10 s) it
    /// sends a biased copy of each Joint3 angle (+0.03 rad) and each pose's position page
    /// (x + 2 cm); with `Rogue::Nonces`, every 10 s an unsigned `StreamNonce` for every node
    /// (a nonce far above the daemon's) and a replay of each nonce frame the daemon sent.
    /// Returns the result, and the joint nodes' flash tables before and after.
    async fn authenticated_session(
        name: &str,
        rogue: Rogue,
    ) -> (Result<SessionSummary, SessionError>, Vec<Table>, Vec<Table>) {
        use exocal_dbc::{JointState, Message, PosePage};
        let dir = temp_dir(name);
        let flash = dir.join("flash");
        std::fs::create_dir_all(&flash).unwrap();
        let keys = exocal_dbc::auth::KeySet::derived(21);
        exocal_hil::flash::provision(&flash, &keys).unwrap();
        // The demo's window (the fixed minute): a 15-s session is refused on this suit.
        let mut config = Config::default_config();
        // A fixed window: the stream gate is judged over a whole minute.
        config.calibration.window.min_duration_s = 60.0;
        config.calibration.window.stop_at_expected_error = None;
        config.output.directory = dir.clone();
        config.push.timeout_ms = 400;
        config.push.authenticate = true;
        config.push.keys = keys;
        let mut scenario = Scenario::paper();
        scenario.duration_s = 400.0;
        let hil = Hil::new(scenario, &flash).unwrap();
        let tables = |flash: &std::path::Path| -> Vec<Table> {
            NodeId::JOINTS
                .iter()
                .map(|&n| exocal_hil::flash::read(flash, n).unwrap().unwrap().table)
                .collect()
        };
        let before = tables(&flash);
        let ([mut daemon_end, mut rogue_end], clock, hil_task) = play(hil);
        let rogue_task = tokio::spawn(async move {
            let mut seen = 0u64;
            let mut recorded: Vec<Frame> = Vec::new();
            while let Ok(rx) = rogue_end.recv().await {
                seen += 1;
                if rogue == Rogue::Nonces {
                    match exocal_dbc::decode_frame(&rx.frame) {
                        Ok(Message::StreamNonce(_)) => recorded.push(rx.frame),
                        _ if seen.is_multiple_of(35_000) => {
                            for node in NodeId::ALL {
                                let forged = Message::StreamNonce(exocal_dbc::StreamNonce {
                                    node,
                                    nonce: u32::MAX - 7,
                                    mac: 0x0BAD_F00D,
                                });
                                let _ = rogue_end.send(&forged.to_frame::<Frame>().unwrap()).await;
                            }
                            for f in &recorded {
                                let _ = rogue_end.send(f).await;
                            }
                        }
                        _ => {}
                    }
                    continue;
                }
                if rogue == Rogue::None {
                    continue;
                }
                // Bursts of ~0.3 s every 10 s (the suit sends ~3,500 frames/s).
                if seen % 35_000 >= 1_000 {
                    continue;
                }
                let biased = match exocal_dbc::decode_frame(&rx.frame) {
                    Ok(Message::JointState(j)) if j.node == NodeId::JOINTS[2] => {
                        Message::JointState(JointState {
                            angle: j.angle + 0.03,
                            ..j
                        })
                    }
                    Ok(Message::EePose(mut p)) => match p.page {
                        PosePage::TimePosX { timestamp_us, x } => {
                            p.page = PosePage::TimePosX {
                                timestamp_us,
                                x: x + 0.02,
                            };
                            Message::EePose(p)
                        }
                        _ => continue,
                    },
                    _ => continue,
                };
                let _ = rogue_end.send(&biased.to_frame::<Frame>().unwrap()).await;
            }
        });
        let (_stop, shutdown) = Shutdown::manual();
        let result = run_plain(&mut daemon_end, &clock, &config, shutdown.wait()).await;
        hil_task.abort();
        rogue_task.abort();
        (result, before, tables(&flash))
    }

    #[derive(Clone, Copy, PartialEq, Eq)]
    enum Rogue {
        None,
        /// Biased data frames.
        Injector,
        /// Forged and replayed `StreamNonce` frames.
        Nonces,
    }

    /// Forged `StreamNonce` frames for every node (unsigned, a nonce far ahead) and replays of
    /// the daemon's own, every 10 s. A node that obeyed an unsigned nonce would verify none of
    /// the 40 later spans and the session would fail authentication, the frame never named. No
    /// node takes them: no span is lost, the session validates and pushes, and the summary
    /// counts the frames from another sender.
    #[tokio::test(start_paused = true)]
    async fn spoofed_nonces_on_the_bus_change_nothing_and_are_counted() {
        let (result, _, _) = authenticated_session("stream-nonces", Rogue::Nonces).await;
        let s = result.unwrap_or_else(|e| panic!("session: {}", e.error));
        let g = s.stream.clone().expect("streams verified");
        assert!(g.foreign_nonces >= 5 * 16, "{g:?}");
        assert_eq!((g.dropped_spans, g.renonces), (0, 0), "{g:?}");
        assert!(s.push.as_ref().is_some_and(|p| p.complete()));
    }

    /// A rogue injecting biased JointState and EePose frames during an authenticated session
    /// steers nothing: every span its frames land in is dropped, the session is refused naming
    /// Joint3 and the end effector as nodes with a second sender on their identifiers (exit
    /// 65), nothing is pushed and every node keeps its table. The same session without the
    /// rogue verifies every span past the start and pushes.
    #[tokio::test(start_paused = true)]
    async fn a_rogue_injecting_biased_frames_is_named_and_the_session_refused() {
        let (clean, _, _) = authenticated_session("stream-clean", Rogue::None).await;
        let clean = clean.unwrap_or_else(|e| panic!("clean session: {}", e.error));
        let c = clean.stream.clone().expect("streams verified");
        assert_eq!(
            (c.dropped_spans, c.second_senders().count()),
            (0, 0),
            "{c:?}"
        );
        assert!(c.verified_spans > 4000, "{c:?}");
        assert!(clean.push.as_ref().is_some_and(|p| p.complete()));

        let (attacked, before, after) =
            authenticated_session("stream-rogue", Rogue::Injector).await;
        let summary = match &attacked {
            Ok(s) => s.clone(),
            Err(e) => e.summary.clone().expect("a summary"),
        };
        let g = summary.stream.clone().expect("streams verified");
        assert!(g.dropped_spans > 0 && g.dropped_frames > 0, "{g:?}");
        let named: Vec<NodeId> = g.second_senders().map(|(n, _)| n).collect();
        assert_eq!(named, [NodeId::JOINTS[2], NodeId::END_EFFECTOR], "{g:?}");
        let e = attacked.expect_err("refused");
        let DaemonError::Session(why) = &e.error else {
            panic!("{}", e.error);
        };
        let refused: Vec<NodeId> = why
            .iter()
            .filter_map(|w| match *w {
                Shortfall::SecondSender { node, spans } if spans > 0 => Some(node),
                _ => None,
            })
            .collect();
        assert_eq!(refused, named, "{why:?}");
        assert!(
            e.error
                .to_string()
                .contains("a second sender on Joint3's identifiers"),
            "{}",
            e.error
        );
        assert_eq!(e.error.exit_code(), crate::exit::code::DATAERR);
        assert!(summary.push.is_none(), "nothing pushed");
        assert_eq!(after, before, "the nodes keep their tables");
    }
}
