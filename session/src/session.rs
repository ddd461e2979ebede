//! One session's collection, driven like smoltcp's `Interface::poll`: frames and ticks in,
//! what to show and what to compute out, the computations' results fed back. Time is always an
//! argument.
//!
//! Contract:
//! - [`Session::take`] takes every received frame (through the stream gate, once
//!   [`Session::authenticate`]d) and hands back each [`Event`] ingest made of the frames it
//!   passed, for the log;
//! - [`Session::on_tick`] says where the collection stands at `elapsed_s` on the caller's
//!   monotonic clock: its [`Progress`], its [`Phase`] under the window's rules and the stream
//!   gate's (a collection the gate speaks against — a second sender, heavy loss — is refused
//!   with the reasons), and, when one is due and none is running, an [`EstimateJob`] to run off
//!   the caller's loop; [`Session::estimated`] takes its result;
//! - [`Session::at_end`] judges a recording by the same rules at its end: the live session
//!   and `exocald offline` refuse the same collections for the same reasons;
//! - [`Session::into_calibration`] ends the collection: it aligns what was gathered (see
//!   `collect`) and hands out the [`CalibrationJob`], which calibrates it
//!   ([`crate::pipeline::run`]) off the caller's loop.
//!
//! The caller owns I/O and time: the daemon's loop reads the bus and the clock, writes the log,
//! runs the jobs on a blocking thread and feeds the watchdog; a replay feeds recorded frames
//! with their recorded times.

use std::time::Duration;

use exocal_dbc::Received;

use crate::collect::{Collected, Collector};
use crate::estimate::{Estimate, EstimateJob};
use crate::gate::{Dropped, StreamGate};
use crate::ingest::{Event, FrameStats};
use crate::pipeline::{CalibrateError, Calibrated};
use crate::window::{Phase, Progress, Shortfall};
use crate::Settings;

/// One session's collection (see the module docs).
#[derive(Debug, Clone)]
pub struct Session {
    settings: Settings,
    collector: Collector,
    /// `elapsed_s` of the last estimate handed out.
    last_estimate_s: f64,
    /// An estimate was handed out and its result is not back yet.
    estimating: bool,
}

/// The calibration of what a session collected ([`Session::into_calibration`]): the aligned
/// collection and the settings, to calibrate off the caller's loop. It owns the collection, so
/// a long session is never copied to be calibrated.
#[derive(Debug, Clone)]
pub struct CalibrationJob {
    collected: Collected,
    settings: Settings,
}

impl CalibrationJob {
    /// The calibration of `collected` under `settings` (samples that needed no session: a
    /// CSV's; a session hands out its own, [`Session::into_calibration`]).
    pub fn new(collected: Collected, settings: Settings) -> CalibrationJob {
        CalibrationJob {
            collected,
            settings,
        }
    }

    /// What the session collected, aligned.
    pub fn collected(&self) -> &Collected {
        &self.collected
    }

    /// The settings the session ran with.
    pub fn settings(&self) -> &Settings {
        &self.settings
    }

    /// Calibrates the collection: least squares, the EM and validation ([`crate::pipeline::run`]).
    pub fn run(&self) -> Result<Calibrated, CalibrateError> {
        crate::pipeline::run(&self.collected.samples, &self.settings)
    }
}

/// Where the collection stands at a tick.
#[derive(Debug)]
pub struct Tick {
    /// Coverage, samples and the estimates so far, to show and log.
    pub progress: Progress,
    /// Keep collecting, calibrate now, or refused (with every reason).
    pub phase: Phase,
    /// An estimate to run now (at most one at a time; `None` unless collecting).
    pub estimate: Option<EstimateJob>,
}

impl Session {
    /// An empty collection under `settings`, without stream authentication.
    pub fn new(settings: &Settings) -> Session {
        Session {
            settings: settings.clone(),
            collector: Collector::new(settings),
            last_estimate_s: 0.0,
            estimating: false,
        }
    }

    /// The settings the session runs with.
    pub fn settings(&self) -> &Settings {
        &self.settings
    }

    /// From now on, data frames reach ingest only through `gate`.
    pub fn authenticate(&mut self, gate: StreamGate) {
        self.collector.gate = Some(gate);
    }

    /// Takes one received frame (see the module docs): `each` sees every frame ingest takes
    /// now with its [`Event`]; returns the spans the gate dropped.
    pub fn take(&mut self, rx: &Received, each: impl FnMut(&Received, Event)) -> Vec<Dropped> {
        self.collector.take(rx, each)
    }

    /// Where the collection stands `elapsed_s` into it (see the module docs).
    pub fn on_tick(&mut self, elapsed_s: f64) -> Tick {
        let window = &self.collector.window;
        let progress = window.progress(elapsed_s);
        let phase = match window.phase(elapsed_s) {
            Phase::Ready => match self.collector.unverified(false) {
                why if why.is_empty() => Phase::Ready,
                why => Phase::Failed(why),
            },
            Phase::Failed(mut why) => {
                // The gate's reasons, where the window's do not already name them.
                if !why.iter().any(|w| {
                    matches!(
                        w,
                        Shortfall::Unverified { .. } | Shortfall::SecondSender { .. }
                    )
                }) {
                    why.extend(self.collector.unverified(true));
                }
                Phase::Failed(why)
            }
            Phase::Collecting => Phase::Collecting,
        };
        let every = EstimateJob::every_s(&self.settings);
        // An estimate only while collecting: one started on the tick the window closes would
        // run beside the calibration for nothing.
        let estimate = (matches!(phase, Phase::Collecting)
            && !self.estimating
            && elapsed_s - self.last_estimate_s >= every)
            .then(|| {
                self.last_estimate_s = elapsed_s;
                self.estimating = true;
                EstimateJob::of(&self.collector, &self.settings)
            });
        Tick {
            progress,
            phase,
            estimate,
        }
    }

    /// The result of the last [`Tick::estimate`] (`None`: too little data, or the job was
    /// lost): the window shows it, and stops when good enough by it.
    pub fn estimated(&mut self, estimate: Option<Estimate>) {
        self.estimating = false;
        let Some(e) = estimate else { return };
        let window = &mut self.collector.window;
        window.set_condition_number(e.condition);
        if let Some(x) = e.expected {
            window.set_expected(x);
        }
        if let Some(g) = e.guidance {
            window.set_guidance(g);
        }
    }

    /// The rules a recording `duration_s` long does not meet (see the module docs): empty when
    /// the live session would have calibrated it.
    pub fn at_end(&self, duration_s: f64) -> Vec<Shortfall> {
        let mut why = self.collector.window.at_end(duration_s);
        let failed = !why.is_empty();
        why.extend(self.collector.unverified(failed));
        why
    }

    /// What was gathered, aligned (see the module docs).
    fn collected(&self) -> Collected {
        self.collector.collected(&self.settings)
    }

    /// Ends the collection: aligns what was gathered (seconds of CPU on a slow controller, so
    /// the caller runs this off its loop too) into the [`CalibrationJob`].
    pub fn into_calibration(self) -> CalibrationJob {
        CalibrationJob {
            collected: self.collected(),
            settings: self.settings,
        }
    }

    /// Frame counters so far.
    pub fn stats(&self) -> &FrameStats {
        self.collector.ingest.stats()
    }

    /// Receive time of the first frame taken (the samples' time origin).
    pub fn origin(&self) -> Option<Duration> {
        self.collector.ingest.origin()
    }

    /// The stream gate, once authenticated.
    pub fn gate(&self) -> Option<&StreamGate> {
        self.collector.gate.as_ref()
    }

    /// Whether every node needs a new stream nonce (a node rebooted, or another sender set
    /// one); see [`StreamGate::nonce_wanted`].
    pub fn nonce_wanted(&mut self) -> bool {
        self.collector
            .gate
            .as_mut()
            .is_some_and(StreamGate::nonce_wanted)
    }

    /// Gives the stream gate the nonce just sent to the nodes; `false` without a gate.
    pub fn renonce(&mut self, nonce: u32) -> bool {
        let Some(gate) = self.collector.gate.as_mut() else {
            return false;
        };
        gate.renonce(nonce);
        true
    }

    /// The frames a replay of the session's log calibrates on (the log's collection end):
    /// those received, through the gate or not.
    pub fn frames_received(&self) -> u64 {
        match self.collector.gate {
            Some(_) => self.collector.taken,
            None => self.stats().received,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn estimate(condition: f64) -> Estimate {
        Estimate {
            condition,
            expected: None,
            guidance: None,
        }
    }

    #[test]
    fn estimates_are_handed_out_one_at_a_time_and_their_results_are_shown() {
        let settings = Settings::suit_default();
        let every = EstimateJob::every_s(&settings);
        let mut session = Session::new(&settings);
        assert!(
            session.on_tick(0.5 * every).estimate.is_none(),
            "not due yet"
        );
        let tick = session.on_tick(every);
        assert_eq!(tick.phase, Phase::Collecting);
        assert!(tick.estimate.is_some(), "due");
        assert!(
            session.on_tick(2.5 * every).estimate.is_none(),
            "one still running"
        );
        session.estimated(Some(estimate(42.0)));
        let tick = session.on_tick(2.5 * every);
        assert_eq!(tick.progress.condition_number, Some(42.0));
        assert!(tick.estimate.is_some(), "due again once the last is back");
        // A lost job frees the slot too.
        session.estimated(None);
        assert!(session.on_tick(3.5 * every).estimate.is_some());
    }

    #[test]
    fn a_window_that_runs_out_is_refused_live_and_replayed_for_the_same_reasons() {
        let settings = Settings::suit_default();
        let mut session = Session::new(&settings);
        let end = settings.window.max_duration_s;
        let tick = session.on_tick(end + 1.0);
        let Phase::Failed(why) = tick.phase else {
            panic!("{:?}", tick.phase)
        };
        assert!(!why.is_empty());
        assert!(tick.estimate.is_none(), "no estimate once refused");
        assert_eq!(session.at_end(end + 1.0), why);
        assert_eq!(session.frames_received(), 0);
        assert!(!session.renonce(7), "no gate to give a nonce");
    }

    #[test]
    fn the_calibration_job_holds_what_was_collected_and_judges_it_by_the_settings() {
        let mut settings = Settings::suit_default();
        settings.window.min_samples = 17;
        let job = Session::new(&settings).into_calibration();
        assert!(job.collected().samples.is_empty());
        assert_eq!(job.settings().window.min_samples, 17);
        match job.run() {
            Err(CalibrateError::TooFewSamples { have: 0, need: 17 }) => {}
            other => panic!("{other:?}"),
        }
    }
}
