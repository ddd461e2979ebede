//! The loop's outputs, bundled: the session's log (and its other observers, through the
//! [`Recorder`]), systemd's notifier, the console reporter, and the real-time start.
//!
//! Contract:
//! - a log error does not stop the loop where it happens: the first is kept
//!   ([`Io::check`]) and ends the session at the next step ([`Io::log_failed`]), and
//!   [`Io::close`] finishes the file on every path;
//! - [`Io::housekeeping`] feeds the watchdog first, then lets the log flush: it is called on
//!   every tick, after every frame and every [`RECORDS_PER_TURN`] records written in one go, so
//!   no burst of work starves systemd's watchdog;
//! - warnings go to the console too; a flood of the same warning is a few lines and a count
//!   ([`Throttle`]).

use std::io::BufWriter;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use exocal_bus::{Frame, Received};
use exocal_log::write::{Level, LogError, SessionLog};
use exocal_session::ingest::Event;
use exocal_session::Session;

use crate::config::Config;
use crate::exit::DaemonError;
use crate::log::records::{self, ns, Observer};
use crate::push::PushObserver;
use crate::shell::notify::{Notifier, Reporter};
use crate::shell::tee::Recorder;
use crate::shell::throttle::Throttle;

/// Records written in one go between two housekeeping turns (the log's flush, the watchdog).
pub const RECORDS_PER_TURN: usize = 256;

/// A log error as the session's, `what` the log was doing.
pub fn io_err(what: &str, e: LogError) -> DaemonError {
    DaemonError::Log {
        what: what.to_string(),
        source: e,
    }
}

/// The log (and the session's other observers), the notifier and the reporter, and the
/// real-time start, bundled for the loop.
pub struct Io<'a> {
    pub(crate) log: Recorder<'a, BufWriter<std::fs::File>>,
    pub(crate) notifier: &'a mut Notifier,
    pub(crate) reporter: &'a mut Reporter,
    started: Instant,
    log_error: Option<LogError>,
    /// Trigger frames during the session ([`Throttle`]: a flood is not a line each).
    ignored_triggers: Throttle,
    /// `StreamNonce` frames another sender put on the bus.
    foreign_nonces: Throttle,
}

impl<'a> Io<'a> {
    /// Opens the session's log in the configured directory (named by `start`, the bus time)
    /// and says so; logs the arm as built, for Foxglove's 3D panel until the calibrated one
    /// follows; tells systemd the session is collecting.
    pub fn open(
        config: &Config,
        start: Duration,
        observers: &'a [&'a dyn Observer],
        notifier: &'a mut Notifier,
        reporter: &'a mut Reporter,
    ) -> Result<(PathBuf, Io<'a>), DaemonError> {
        let flush_ns = (config.output.flush_interval_s * 1e9) as u64;
        let dir = &config.output.directory;
        let (log_path, log) = SessionLog::create_in(dir, ns(start), flush_ns)
            .map_err(|e| io_err(&format!("creating the log in {}", dir.display()), e))?;
        let mut io = Io {
            log: Recorder::new(log, observers),
            notifier,
            reporter,
            started: Instant::now(),
            log_error: None,
            ignored_triggers: Throttle::default(),
            foreign_nonces: Throttle::default(),
        };
        io.reporter
            .message(&format!("logging to {}", log_path.display()));
        let unaided = exocal_session::rules::joint_list(&config.calibration.sensors.unaided);
        if !unaided.is_empty() {
            io.reporter.message(&format!(
                "stand still for a few seconds before moving: the gyro bias of joints {unaided} \
                 is measured then"
            ));
        }
        let started = format!("session started on {}", config.interface);
        io.event(start, Level::Info, &started);
        let limits = &config.calibration.bounds.joint_range.limits;
        let joints = config.calibration.joints;
        if let Ok(urdf) = records::urdf(&config.calibration.nominal, limits, joints) {
            let r = io.log.robot_description(ns(start), &urdf);
            io.check(r);
        }
        io.notifier.ready("collecting free motion");
        io.housekeeping();
        Ok((log_path, io))
    }

    /// Ends the session's log on every path: `result` (how the session ended) goes into it as
    /// an error line, systemd hears the session is stopping, and the file is finished. Returns
    /// the messages written per topic and the session's result, which a log error turns into a
    /// failure.
    pub fn close(
        mut self,
        result: Result<(), DaemonError>,
        now: Duration,
    ) -> (Vec<(String, u64)>, Result<(), DaemonError>) {
        self.reporter.finish();
        if let Err(e) = &result {
            // Into the log only: the caller reports the error (the binary prints it once).
            let r = self.log.event(ns(now), Level::Error, &e.to_string());
            self.check(r);
        }
        self.notifier.stopping();
        let counts = (self.log.counts().iter())
            .map(|(t, n)| (t.name().to_string(), *n))
            .collect();
        let log_error = self.log_error.take();
        let result = match (result, log_error, self.log.finish()) {
            (Err(e), _, _) => Err(e),
            (Ok(()), Some(e), _) | (Ok(()), None, Err(e)) => Err(io_err("writing the log", e)),
            (Ok(()), None, Ok(_)) => Ok(()),
        };
        (counts, result)
    }

    /// Remembers the first log error (the session then ends with it) and carries on.
    pub fn check(&mut self, r: Result<(), LogError>) {
        if let Err(e) = r {
            self.log_error.get_or_insert(e);
        }
    }

    /// The first log error, if any, as the session's error.
    pub fn log_failed(&mut self) -> Result<(), DaemonError> {
        match self.log_error.take() {
            Some(e) => Err(io_err("writing the log", e)),
            None => Ok(()),
        }
    }

    /// The watchdog first: the log's flush writes a chunk (its sync runs on the log's own
    /// thread, `exocal_log::write`).
    pub fn housekeeping(&mut self) {
        let now = self.started.elapsed();
        self.notifier.watchdog(now);
        let r = self.log.tick(ns(now)).map(|_| ());
        self.check(r);
    }

    /// Between two of many records written in one go (a session's aligned samples, its arm
    /// on the calibrated table): every [`RECORDS_PER_TURN`] records, the housekeeping turn
    /// (flush, watchdog), so a long session's log writing cannot starve the watchdog.
    pub fn between_records(&mut self, written: usize) {
        if written % RECORDS_PER_TURN == RECORDS_PER_TURN - 1 {
            self.housekeeping();
        }
    }

    /// Logs `message` at `t`; a warning or worse goes to the console too.
    pub fn event(&mut self, t: Duration, level: Level, message: &str) {
        if level >= Level::Warning {
            self.reporter.message(message);
        }
        let r = self.log.event(ns(t), level, message);
        self.check(r);
    }

    /// Writes `lines` at `t`, as [`Io::event`] does each.
    pub fn lines(&mut self, t: Duration, lines: Vec<crate::shell::lines::Line>) {
        for (level, line) in lines {
            self.event(t, level, &line);
        }
    }

    /// Logs a frame sent (`sent`) or received at bus time `t`.
    pub fn frame(&mut self, sent: bool, frame: &Frame, t: Duration) {
        let r = self.log.can_frame(sent, &records::frame_record(frame, t));
        self.check(r);
    }

    /// Logs one received frame and feeds it to the collection through the stream gate (the
    /// frames it passes now; a warning for each of the first spans it drops).
    pub fn take_frame(&mut self, rx: &Received, session: &mut Session) {
        self.frame(false, &rx.frame, rx.timestamp);
        let mut events = Vec::new();
        let dropped = session.take(rx, |rx, event| events.push((rx.timestamp, event)));
        for (at, event) in events {
            self.take_event(at, event, session);
        }
        for d in dropped {
            let spans = session.gate().map_or(0, |g| g.stats().dropped_spans);
            if spans <= 10 {
                self.event(rx.timestamp, Level::Warning, &format!("stream span {d}"));
            }
        }
        // The housekeeping turn (time-gated: a clock read when nothing is due) after every frame
        // as well as on the tick: with a backlog of frames the socket is always ready, and tokio
        // fires timers only when the task yields and the runtime turns its driver (after its
        // co-operative budget, every few thousand frames): on a starved controller that can be
        // seconds, longer than systemd's watchdog allows.
        self.housekeeping();
    }

    fn take_event(&mut self, at: Duration, event: Event, session: &Session) {
        let t = ns(at);
        match event {
            Event::Sample {
                stream,
                node_timestamp_us,
                reading,
            } => {
                let r = self.log.sample(t, stream, node_timestamp_us, reading);
                self.check(r);
            }
            Event::Unknown(e) | Event::Malformed(e) => {
                // The first few are worth a line each; the counters carry the rest.
                let s = session.stats();
                if s.unknown + s.malformed <= 10 {
                    self.event(at, Level::Warning, &format!("bad frame: {e}"));
                }
            }
            Event::Message(exocal_dbc::Message::Trigger(t))
                if t.command == exocal_dbc::TriggerCommand::StartCalibration =>
            {
                // Anyone on the bus can send these: a line each for the first few only.
                if let Some(n) = self.ignored_triggers.occur() {
                    let line = Throttle::line(
                        "trigger ignored (CAN Trigger frame): a session is running",
                        n,
                    );
                    self.event(at, Level::Warning, &line);
                }
            }
            Event::Message(exocal_dbc::Message::StreamNonce(n)) => {
                // Never ours (a socket does not receive its own frames): forged or replayed,
                // and the node takes neither (exocal_session::gate).
                if let Some(k) = self.foreign_nonces.occur() {
                    let line = Throttle::line(
                        &format!(
                            "a StreamNonce frame for {} this controller did not send (nonce {}): \
                             another sender on the bus, forging or replaying; the node keeps its \
                             nonce",
                            n.node, n.nonce
                        ),
                        k,
                    );
                    self.event(at, Level::Warning, &line);
                }
            }
            Event::Message(_) | Event::Partial => {}
        }
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
