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
use std::io::{BufWriter, Write};
use std::path::PathBuf;
use std::time::{Duration, Instant};

use exocal_bus::{Clock, Frame, Received, Transport};
use exocal_dbc::table::Table;
use exocal_dbc::NodeId;
use serde::Serialize;

use crate::align::{AlignParams, Aligned};
use crate::calibrate::{self, Outcome};
use crate::config::{Config, JOINTS};
use crate::exit::DaemonError;
use crate::ingest::{ClockReport, Event, FrameStats, Ingest, StallReport};
use crate::mcaplog::{
    CanFrameRecord, CollectionEnd, Counts, Level, LogError, SessionLog, Transform,
};
use crate::push::{push_tables, PushObserver, PushReport};
use crate::report::{Notifier, Reporter};
use crate::session::{Phase, Session};

/// Real time between two turns of the housekeeping tick.
pub const TICK: Duration = Duration::from_millis(100);
/// A clock fit whose residual exceeds this (µs RMS) is reported as unreliable. Receive jitter
/// averages out in the fit (an in-process bus whose hil sends frames in ~10 ms batches sees ~5 ms
/// RMS and still aligns well); tens of ms mean the timestamps cannot be trusted.
pub const CLOCK_RESIDUAL_WARN_US: f64 = 20_000.0;
/// Bus-clock seconds between two estimates of the condition number during collection.
pub const CONDITION_EVERY_S: f64 = 10.0;
/// Samples (at most) the in-collection condition estimate runs LS on.
pub const CONDITION_SAMPLES: usize = 600;

/// Condition number of the identification problem on the data so far: the streams aligned,
/// subsampled to at most [`CONDITION_SAMPLES`], one LS from nominal. `None` if too little data.
pub fn condition_estimate(ingest: &Ingest, config: &Config) -> Option<f64> {
    let (aligned, _) = align_session(ingest, config);
    let n = aligned.samples.len();
    if n < 50 {
        return None;
    }
    let step = n.div_ceil(CONDITION_SAMPLES);
    let samples: Vec<calib_core::Sample<JOINTS>> = aligned
        .samples
        .iter()
        .step_by(step)
        .map(calibrate::to_sample)
        .collect();
    let nominal = crate::validate::table_from_rows(&config.nominal);
    let opts = calib_core::LsOptions::new();
    calib_core::identify_ls::<JOINTS, { calib_core::SUIT_PARAMS }>(&nominal, &samples, &opts)
        .ok()
        .map(|r| r.condition)
}

/// Aligns a session's streams for calibration: every node's clock fitted, all streams
/// resampled onto the `session.grid_hz` grid, gaps longer than `session.max_gap_s` excluded.
/// The live session and `exocald offline` both align through here.
pub fn align_session(ingest: &Ingest, config: &Config) -> (Aligned, Vec<ClockReport>) {
    ingest.align(
        &AlignParams::default(),
        config.session.grid_hz,
        config.session.max_gap_s,
    )
}

/// Rate (Hz) at which the arm's frames are written to `/tf` for Foxglove.
pub const TF_HZ: f64 = 20.0;

/// What a session did (also when it failed: see [`SessionError`]).
#[derive(Debug, Clone, Serialize)]
pub struct SessionSummary {
    pub log_path: PathBuf,
    pub log_counts: Vec<(String, u64)>,
    /// Frames received in the collection window: those the calibration used (frames that
    /// arrive while calibrating and pushing are not counted), as an offline replay of the log
    /// counts them.
    pub frames: FrameStats,
    pub clocks: Vec<ClockReport>,
    /// Receiver stalls (not counted in any node's clock jumps).
    pub stalls: StallReport,
    pub aligned_samples: usize,
    pub gaps: usize,
    pub outcome: Option<Outcome>,
    pub push: Option<PushReport>,
    /// The HTML calibration report, once written (next to the log for a live session).
    pub report_path: Option<PathBuf>,
}

/// A failed session: why, and what it did up to then (the log is finished).
#[derive(Debug)]
pub struct SessionError {
    pub error: DaemonError,
    pub summary: Option<SessionSummary>,
}

impl From<DaemonError> for SessionError {
    fn from(error: DaemonError) -> Self {
        SessionError {
            error,
            summary: None,
        }
    }
}

impl From<DaemonError> for Box<SessionError> {
    fn from(error: DaemonError) -> Self {
        Box::new(SessionError::from(error))
    }
}

fn io_err(what: &str, e: LogError) -> DaemonError {
    DaemonError::Log {
        what: what.to_string(),
        source: e,
    }
}

fn ns(d: Duration) -> u64 {
    d.as_nanos().min(u128::from(u64::MAX)) as u64
}

fn record(frame: &Frame, t: Duration) -> CanFrameRecord {
    use exocal_bus::embedded_can::Frame as _;
    CanFrameRecord {
        id: frame.raw_id(),
        extended: frame.is_extended(),
        dlc: frame.dlc() as u8,
        data: frame.data().to_vec(),
        host_ns: ns(t),
        kernel_ns: Some(ns(t)),
    }
}

/// The log, the notifier and the reporter, and the real-time start, bundled for the loop.
struct Io<'a> {
    log: SessionLog<BufWriter<std::fs::File>>,
    notifier: &'a mut Notifier,
    reporter: &'a mut Reporter,
    started: Instant,
    log_error: Option<LogError>,
}

impl Io<'_> {
    /// Remembers the first log error (the session then ends with it) and carries on.
    fn check(&mut self, r: Result<(), LogError>) {
        if let Err(e) = r {
            self.log_error.get_or_insert(e);
        }
    }

    fn housekeeping(&mut self) {
        let now = self.started.elapsed();
        let r = self.log.tick(ns(now)).map(|_| ());
        self.check(r);
        self.notifier.watchdog(now);
    }

    fn event(&mut self, t: Duration, level: Level, message: &str) {
        if level >= Level::Warning {
            self.reporter.message(message);
        }
        let r = self.log.event(ns(t), level, message);
        self.check(r);
    }

    fn frame(&mut self, sent: bool, frame: &Frame, t: Duration) {
        let r = self.log.can_frame(sent, &record(frame, t));
        self.check(r);
    }
}

impl PushObserver for Io<'_> {
    fn frame(&mut self, sent: bool, frame: &Frame, t: Duration) {
        Io::frame(self, sent, frame, t);
    }

    fn tick(&mut self) {
        self.housekeeping();
    }
}

/// Logs one received frame and feeds it to ingest and the session.
fn take_frame(rx: &Received, ingest: &mut Ingest, session: &mut Session, io: &mut Io<'_>) {
    io.frame(false, &rx.frame, rx.timestamp);
    let t = ns(rx.timestamp);
    match ingest.on_frame(rx) {
        Event::Joint {
            joint,
            node_timestamp_us,
            angle,
            rate,
        } => {
            session.joint_sample(joint, angle);
            let r = io
                .log
                .joint_state(t, joint + 1, node_timestamp_us, angle, rate);
            io.check(r);
        }
        Event::Pose(p) => {
            session.pose_sample();
            let pose = Transform {
                translation: p.position,
                rotation_wxyz: p.quat,
            };
            let r = io.log.ee_pose(t, &pose);
            io.check(r);
        }
        Event::Unknown(e) | Event::Malformed(e) => {
            // The first few are worth a line each; the counters carry the rest.
            let s = ingest.stats();
            if s.unknown + s.malformed <= 10 {
                io.event(rx.timestamp, Level::Warning, &format!("bad frame: {e}"));
            }
        }
        Event::Message(_) | Event::Partial => {}
    }
}

/// The report of a session that ends without a calibration (`why`: the session rules it did
/// not meet), next to its log as a calibrated session's would be: what the motion lacked.
fn session_report(
    ingest: &Ingest,
    config: &Config,
    why: &[String],
    io: &mut Io<'_>,
    clock: &Clock,
    summary: &mut SessionSummary,
) {
    let (aligned, clocks) = align_session(ingest, config);
    let quality = crate::calreport::frame_quality(
        config,
        ingest.stats(),
        &clocks,
        StallReport::of(&aligned.stalls),
        &ingest.stream_rates(),
        &aligned.samples,
        aligned.gaps,
    );
    let name = summary
        .log_path
        .file_name()
        .map_or_else(String::new, |n| n.to_string_lossy().into_owned());
    let input = crate::calreport::session_input(
        format!("exocald session — {name}"),
        format!(
            "live session on {}, logged to {}",
            config.interface,
            summary.log_path.display()
        ),
        &aligned.samples,
        why.to_vec(),
        quality,
    );
    let path = crate::calreport::report_path_for_log(&summary.log_path);
    match std::fs::write(&path, exocal_report::html::render_session(&input)) {
        Ok(()) => {
            io.event(
                clock.now(),
                Level::Info,
                &format!("session report: {}", path.display()),
            );
            summary.report_path = Some(path);
        }
        Err(e) => io.event(
            clock.now(),
            Level::Warning,
            &format!("cannot write the report {}: {e}", path.display()),
        ),
    }
    summary.clocks = clocks;
    summary.aligned_samples = aligned.samples.len();
    summary.gaps = aligned.gaps;
}

/// The arm's link frames for Foxglove, from `table` at joint angles `q`.
fn arm_transforms(table: &calib_core::DhTable<JOINTS>, q: &[f64; JOINTS]) -> Vec<Transform> {
    table
        .rows
        .iter()
        .zip(q)
        .map(|(row, &qi)| {
            let f = row.transform(qi);
            let rot = nalgebra::UnitQuaternion::from_rotation_matrix(
                &nalgebra::Rotation3::from_matrix(&f.r),
            );
            Transform {
                translation: [f.p.x, f.p.y, f.p.z],
                rotation_wxyz: [rot.w, rot.i, rot.j, rot.k],
            }
        })
        .collect()
}

/// Node tables to push, from the calibrated rows.
pub fn node_tables(outcome: &Outcome, config: &Config) -> Result<Vec<(NodeId, Table)>, String> {
    outcome
        .node_rows
        .iter()
        .enumerate()
        .map(|(i, r)| {
            let node = NodeId::new(config.joint_nodes[i])
                .ok_or_else(|| format!("joint {}: no node id", i + 1))?;
            let table = Table::from_si(r.a, r.alpha, r.d, r.theta_offset, r.tau, r.sigma)
                .map_err(|e| format!("{node}: the table does not fit the DBC: {e}"))?;
            Ok((node, table))
        })
        .collect()
}

/// Runs one session on `bus` (see the module docs). `clock` is the bus clock.
pub async fn run_session<T: Transport>(
    bus: &mut T,
    clock: &Clock,
    config: &Config,
    dry_run: bool,
    shutdown: impl Future<Output = ()>,
    notifier: &mut Notifier,
    reporter: &mut Reporter,
) -> Result<SessionSummary, SessionError> {
    let start = clock.now();
    let flush_ns = (config.output.flush_interval_s * 1e9) as u64;
    let (log_path, log) = SessionLog::create_in(&config.output.directory, ns(start), flush_ns)
        .map_err(|e| {
            io_err(
                &format!("creating the log in {}", config.output.directory.display()),
                e,
            )
        })?;
    let mut io = Io {
        log,
        notifier,
        reporter,
        started: Instant::now(),
        log_error: None,
    };
    io.reporter
        .message(&format!("logging to {}", log_path.display()));
    io.event(
        start,
        Level::Info,
        &format!("session started on {}", config.interface),
    );
    io.notifier.ready("collecting free motion");
    io.housekeeping();

    let mut summary = SessionSummary {
        log_path,
        log_counts: Vec::new(),
        frames: FrameStats::default(),
        clocks: Vec::new(),
        stalls: StallReport::default(),
        aligned_samples: 0,
        gaps: 0,
        outcome: None,
        push: None,
        report_path: None,
    };
    let result = session_body(
        bus,
        clock,
        config,
        dry_run,
        shutdown,
        &mut io,
        &mut summary,
        start,
    )
    .await;
    io.reporter.finish();
    if let Err(e) = &result {
        // Into the log only: the caller reports the error (the binary prints it once).
        let r = io.log.event(ns(clock.now()), Level::Error, &e.to_string());
        io.check(r);
    }
    io.notifier.stopping();
    let counts: Counts = io.log.counts();
    let log_error = io.log_error.take();
    let finished = io.log.finish();
    summary.log_counts = counts
        .iter()
        .map(|(t, n)| (t.name().to_string(), *n))
        .collect();
    let result = match (result, log_error, finished) {
        (Err(e), _, _) => Err(e),
        (Ok(()), Some(e), _) | (Ok(()), None, Err(e)) => Err(io_err("writing the log", e)),
        (Ok(()), None, Ok(_)) => Ok(()),
    };
    match result {
        Ok(()) => Ok(summary),
        Err(error) => Err(SessionError {
            error,
            summary: Some(summary),
        }),
    }
}

#[allow(clippy::too_many_arguments)]
async fn session_body<T: Transport>(
    bus: &mut T,
    clock: &Clock,
    config: &Config,
    dry_run: bool,
    shutdown: impl Future<Output = ()>,
    io: &mut Io<'_>,
    summary: &mut SessionSummary,
    start: Duration,
) -> Result<(), DaemonError> {
    tokio::pin!(shutdown);
    // The window is timed on the clock's monotonic reading: a step of the host's wall clock
    // (NTP at boot) neither stretches nor cuts it.
    let started = clock.monotonic();
    let mut ingest = Ingest::new(config.joint_nodes);
    let mut session = Session::new(config.session.clone(), config.bounds.joint_range);
    let mut tick = tokio::time::interval(TICK);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let required = config.session.excitation_required;

    // 1. Collect. The tick goes before the bus so a saturated bus cannot starve the watchdog.
    let mut condition_job: Option<tokio::task::JoinHandle<Option<f64>>> = None;
    let mut last_condition_s = 0.0;
    loop {
        tokio::select! {
            biased;
            () = &mut shutdown => {
                summary.frames = ingest.stats().clone();
                return Err(DaemonError::Interrupted);
            }
            _ = tick.tick() => {
                io.housekeeping();
                let elapsed = clock.monotonic().saturating_sub(started).as_secs_f64();
                if condition_job.is_none() && elapsed - last_condition_s >= CONDITION_EVERY_S {
                    last_condition_s = elapsed;
                    let (snapshot, cfg) = (ingest.clone(), config.clone());
                    condition_job = Some(tokio::task::spawn_blocking(move || {
                        condition_estimate(&snapshot, &cfg)
                    }));
                }
                let progress = session.progress(elapsed);
                io.reporter.update(&progress, required, io.notifier);
                let r = io.log.write(crate::mcaplog::Topic::Progress, ns(clock.now()), &progress);
                io.check(r);
                match session.phase(elapsed) {
                    Phase::Collecting => {}
                    Phase::Ready => break,
                    Phase::Failed(why) => {
                        summary.frames = ingest.stats().clone();
                        session_report(&ingest, config, &why, io, clock, summary);
                        return Err(DaemonError::Session(why.join("; ")));
                    }
                }
            }
            done = async { condition_job.as_mut().expect("guarded").await }, if condition_job.is_some() => {
                condition_job = None;
                if let Ok(Some(k)) = done {
                    session.set_condition_number(k);
                }
            }
            rx = bus.recv() => {
                let rx = rx.map_err(|source| DaemonError::Bus { what: "receiving CAN".into(), source })?;
                take_frame(&rx, &mut ingest, &mut session, io);
            }
        }
        if let Some(e) = io.log_error.take() {
            return Err(io_err("writing the log", e));
        }
    }
    if let Some(job) = condition_job {
        job.abort();
    }
    summary.frames = ingest.stats().clone();
    let s = ingest.stats();
    // The record `exocald offline` honours: a replay of this log calibrates on the first
    // `frames` frames of /can/rx, as this session did.
    let end = CollectionEnd {
        frames: s.received,
        window_end_ns: ns(clock.now()),
        unknown: s.unknown,
        malformed: s.malformed,
        invalid_angles: s.invalid_angles,
        dropped: bus.dropped(),
    };
    let r = io.log.collection_end(&end);
    io.check(r);
    io.event(
        clock.now(),
        Level::Info,
        &format!(
            "collection done: {} frames ({} unknown, {} malformed, {} invalid angles, {} dropped by the receiver)",
            s.received,
            s.unknown,
            s.malformed,
            s.invalid_angles,
            bus.dropped()
        ),
    );
    for (node, repeats) in s.babbling() {
        io.event(
            clock.now(),
            Level::Warning,
            &format!("{node} is babbling: {repeats} frames repeated verbatim"),
        );
    }

    // 2. Align.
    let (aligned, clocks) = align_session(&ingest, config);
    summary.clocks = clocks;
    summary.stalls = StallReport::of(&aligned.stalls);
    summary.aligned_samples = aligned.samples.len();
    summary.gaps = aligned.gaps;
    if summary.stalls.count > 0 {
        let line = format!(
            "{}: every node's frames arrived late together while their clocks ran on; their \
             samples are kept on the nodes' clocks (not clock jumps)",
            summary.stalls
        );
        io.event(clock.now(), Level::Warning, &line);
    }
    for c in &summary.clocks {
        if c.residual_rms_us
            .is_some_and(|r| r > CLOCK_RESIDUAL_WARN_US)
        {
            let line = format!(
                "{}: receive-time residual {:.0} µs RMS: timestamps are unreliable (a lagging \
                 sender or a loaded receiver); expect a poor alignment",
                c.node,
                c.residual_rms_us.unwrap_or(f64::NAN)
            );
            io.event(clock.now(), Level::Warning, &line);
        }
        if c.jumps > 0 || c.unmapped > 0 {
            let line = format!(
                "{}: {} clock jump(s)/reboot(s), {} samples excluded",
                c.node, c.jumps, c.unmapped
            );
            io.event(clock.now(), Level::Warning, &line);
        }
    }
    let origin = ingest.origin().unwrap_or(start);
    for s in &aligned.samples {
        let t = ns(origin + Duration::from_secs_f64(s.t.max(0.0)));
        let r = io.log.aligned(t, s);
        io.check(r);
    }
    io.event(
        clock.now(),
        Level::Info,
        &format!(
            "aligned {} samples on a {} Hz grid, {} grid points excluded as gaps",
            aligned.samples.len(),
            config.session.grid_hz,
            aligned.gaps
        ),
    );

    // 3. Calibrate on a blocking thread; keep the bus drained and the watchdog fed.
    io.notifier.status("calibrating");
    io.reporter.message("calibrating (least squares, then EM)");
    let samples = aligned.samples.clone();
    let cfg = config.clone();
    let quality = crate::calreport::frame_quality(
        config,
        ingest.stats(),
        &summary.clocks,
        summary.stalls,
        &ingest.stream_rates(),
        &aligned.samples,
        aligned.gaps,
    );
    let log_name = summary
        .log_path
        .file_name()
        .map_or_else(String::new, |n| n.to_string_lossy().into_owned());
    let title = format!("exocald calibration — {log_name}");
    let source = format!(
        "live session on {}, logged to {}",
        config.interface,
        summary.log_path.display()
    );
    // The report is rendered on the blocking thread too: it is a few hundred ms of SVG.
    let job = tokio::task::spawn_blocking(move || {
        calibrate::run_detailed(&samples, &cfg).map(|(outcome, detail)| {
            let input = crate::calreport::report_input(
                title, source, &cfg, &samples, &outcome, detail, quality,
            );
            let html = exocal_report::html::render(&input);
            (outcome, html)
        })
    });
    tokio::pin!(job);
    let outcome = loop {
        tokio::select! {
            biased;
            () = &mut shutdown => return Err(DaemonError::Interrupted),
            done = &mut job => break done,
            _ = tick.tick() => io.housekeeping(),
            rx = bus.recv() => {
                if let Ok(rx) = rx {
                    take_frame(&rx, &mut ingest, &mut session, io);
                }
            }
        }
    };
    let outcome = outcome.map_err(|e| DaemonError::Internal {
        what: "in the calibration task".into(),
        source: Box::new(e),
    })?;
    let (outcome, html) = match outcome {
        Ok(done) => done,
        Err(e) => {
            // The samples would not calibrate: the report says why, as for a session that ran
            // out of time.
            session_report(&ingest, config, &[e.to_string()], io, clock, summary);
            return Err(e.into());
        }
    };
    let report_path = crate::calreport::report_path_for_log(&summary.log_path);
    match std::fs::write(&report_path, html) {
        Ok(()) => {
            io.event(
                clock.now(),
                Level::Info,
                &format!("calibration report: {}", report_path.display()),
            );
            summary.report_path = Some(report_path);
        }
        Err(e) => io.event(
            clock.now(),
            Level::Warning,
            &format!("cannot write the report {}: {e}", report_path.display()),
        ),
    }

    // The arm for Foxglove, on the calibrated table.
    let calibrated = calib_core::DhTable {
        rows: std::array::from_fn(|i| {
            let r = outcome.node_rows[i];
            calib_core::DhRow {
                a: r.a,
                alpha: r.alpha,
                d: r.d,
                theta_offset: r.theta_offset,
            }
        }),
    };
    let step = ((config.session.grid_hz / TF_HZ).round() as usize).max(1);
    for s in aligned.samples.iter().step_by(step) {
        let t = ns(origin + Duration::from_secs_f64(s.t.max(0.0)));
        let r = io
            .log
            .arm_transforms(t, &arm_transforms(&calibrated, &s.joints));
        io.check(r);
    }
    let report = serde_json::json!({
        "outcome": &outcome,
        "frames": &summary.frames,
        "clocks": &summary.clocks,
        "aligned_samples": summary.aligned_samples,
        "gaps": summary.gaps,
    });
    let r = io
        .log
        .write(crate::mcaplog::Topic::Calibration, ns(clock.now()), &report);
    io.check(r);
    let v = &outcome.verdict;
    io.event(
        clock.now(),
        Level::Info,
        &format!(
            "expected table error {}; held-out pose error {:.3e} → {:.3e} ({:.1}% better than nominal, paired t {:.1}), condition number {:.3e}",
            v.expected
                .map_or_else(|| "unknown".to_string(), |e| e.to_string()),
            v.nominal.mean_error,
            v.candidate.mean_error,
            v.improvement * 100.0,
            v.heldout_t,
            v.condition_number
        ),
    );
    let accepted = v.accepted();
    let reasons = v.reasons.clone();
    summary.outcome = Some(outcome);
    if !accepted {
        return Err(DaemonError::Validation(reasons));
    }
    if dry_run {
        io.event(clock.now(), Level::Info, "dry run: nothing pushed");
        return Ok(());
    }
    if let Some(e) = io.log_error.take() {
        return Err(io_err("writing the log", e));
    }
    // Last chance to stop before touching the nodes.
    if futures_ready(&mut shutdown) {
        return Err(DaemonError::Interrupted);
    }

    // 4. Push.
    let outcome = summary.outcome.as_ref().ok_or(DaemonError::Interrupted)?;
    let tables = node_tables(outcome, config).map_err(|e| DaemonError::Validation(vec![e]))?;
    io.notifier.status("pushing tables");
    io.reporter.message("pushing the tables to the nodes");
    let first_session = (ns(start) / 1_000_000 % 251) as u8;
    let report = push_tables(bus, clock, &tables, &config.push, first_session, io)
        .await
        .map_err(|source| DaemonError::Bus {
            what: "pushing tables".into(),
            source,
        })?;
    for line in report.lines() {
        io.event(clock.now(), Level::Info, &line);
    }
    let r = io
        .log
        .write(crate::mcaplog::Topic::Calibration, ns(clock.now()), &report);
    io.check(r);
    let complete = report.complete();
    let failed: Vec<String> = report
        .lines()
        .into_iter()
        .zip(&report.nodes)
        .filter(|(_, n)| n.holds != crate::push::Holds::New)
        .map(|(l, _)| l)
        .collect();
    summary.push = Some(report);
    if !complete {
        return Err(DaemonError::Push(failed.join("; ")));
    }
    io.event(
        clock.now(),
        Level::Info,
        "every node holds its new table (CRC read back)",
    );
    Ok(())
}

/// Whether a pinned future is already complete (polled once, without waiting).
fn futures_ready<F: Future<Output = ()>>(f: &mut std::pin::Pin<&mut F>) -> bool {
    let waker = std::task::Waker::noop();
    let mut cx = std::task::Context::from_waker(waker);
    f.as_mut().poll(&mut cx).is_ready()
}

/// Writes `summary` as pretty JSON to `out` (for `--report`).
pub fn write_summary(summary: &SessionSummary, out: &mut impl Write) -> std::io::Result<()> {
    serde_json::to_writer_pretty(&mut *out, summary)?;
    writeln!(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::shutdown::Shutdown;
    use exocal_bus::InProcessBus;
    use exocal_bus::SimClock;
    use exocal_hil::{Hil, Scenario};

    fn temp_dir(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("exocald-runner-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        d
    }

    /// Runs one session against the paper hil; `stop_after_s` raises the shutdown flag after
    /// that much real time. Returns the result and the flash CRCs before and after.
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
        scenario.duration_s = 400.0;
        let mut hil = Hil::new(scenario, &flash).unwrap();
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
        let clock = SimClock::new(20.0).unwrap();
        let bus = InProcessBus::with_clock(InProcessBus::DEFAULT_CAPACITY, clock.bus_clock());
        let mut hil_end = bus.attach();
        let mut daemon_end = bus.attach();
        let hil_task = tokio::spawn(async move { hil.run(&mut hil_end, &clock).await });
        let (stop, shutdown) = Shutdown::manual();
        if let Some(s) = stop_after_s {
            tokio::spawn(async move {
                tokio::time::sleep(Duration::from_secs_f64(s)).await;
                let _ = stop.send(true);
            });
        }
        let mut notifier = Notifier::disabled();
        let mut reporter = Reporter::Plain { last_line: None };
        let result = run_session(
            &mut daemon_end,
            &clock.bus_clock(),
            &config,
            false,
            shutdown.wait(),
            &mut notifier,
            &mut reporter,
        )
        .await;
        hil_task.abort();
        let _ = hil_task.await;
        (result, before, crcs(&flash))
    }

    fn config(dir: &std::path::Path) -> Config {
        let mut c = Config::default_config();
        c.output.directory = dir.to_path_buf();
        c.session.min_duration_s = 15.0;
        c.push.timeout_ms = 400;
        // The hil's nodes here hold no keys (authenticated pushes: push.rs, demo, atomic_push).
        c.push.authenticate = false;
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
        assert_eq!(summary.channels.len(), crate::mcaplog::Topic::ALL.len());
        summary
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn shutdown_during_collection_finishes_the_log_and_pushes_nothing() {
        let dir = temp_dir("sigterm");
        // 0.4 s real = ~8 s simulated: mid-collection (the minimum is 15 s).
        let (result, before, after) = session(config(&dir), &dir, Some(0.4)).await;
        let err = result.unwrap_err();
        assert!(
            matches!(err.error, DaemonError::Interrupted),
            "{}",
            err.error
        );
        assert_eq!(err.error.exit_code(), crate::exit::code::TEMPFAIL);
        let summary = err.summary.unwrap();
        assert!(summary.push.is_none());
        assert_eq!(topic_count(&summary, "/can/tx"), 0);
        assert!(topic_count(&summary, "/can/rx") > 1000);
        let stats = assert_finished(&summary.log_path).stats.unwrap();
        assert_eq!(
            stats.message_count,
            summary.log_counts.iter().map(|c| c.1).sum::<u64>()
        );
        assert_eq!(before, after, "no node's table changed");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_refused_calibration_pushes_nothing_and_says_why() {
        let dir = temp_dir("refused");
        let mut c = config(&dir);
        // No minute of motion gives a table to a micrometre: validation must refuse.
        c.validation.max_expected_position_error_mm = 1e-3;
        let (result, before, after) = session(c, &dir, None).await;
        let err = result.unwrap_err();
        match &err.error {
            DaemonError::Validation(reasons) => {
                assert!(
                    reasons
                        .iter()
                        .any(|r| r.contains("mm (1σ) above the 0.001 mm allowed")),
                    "{reasons:?}"
                );
            }
            other => panic!("{other}"),
        }
        assert_eq!(err.error.exit_code(), crate::exit::code::DATAERR);
        let summary = err.summary.unwrap();
        assert!(summary.outcome.is_some() && summary.push.is_none());
        assert_eq!(topic_count(&summary, "/can/tx"), 0);
        assert_eq!(topic_count(&summary, "/calibration"), 1);
        assert_finished(&summary.log_path);
        assert_eq!(before, after);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_session_without_enough_motion_fails_at_the_maximum_duration() {
        let dir = temp_dir("short");
        let mut c = config(&dir);
        c.session.min_samples = 1_000_000;
        c.session.max_duration_s = 16.0;
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
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_bus_stall_is_a_receiver_stall_and_a_reboot_is_that_nodes_jump() {
        use exocal_hil::scenario::{BusStall, Reboot};
        let dir = temp_dir("stall");
        let mut c = config(&dir);
        // Refused (no table is good to a micrometre): the alignment is what this test is about.
        c.validation.max_expected_position_error_mm = 1e-3;
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
        // A loaded machine may stall the in-process bus too: those are stalls as well.
        assert!(summary.stalls.count >= 1, "{:?}", summary.stalls);
        // Receive stamps carry the emulator's ~1 ms real (20 ms simulated) send jitter.
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
            assert_eq!(c.jumps, want, "{c:?}");
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
