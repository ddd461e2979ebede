//! A recorded session replayed through the live data path.
//!
//! Contract:
//! - recorded frames are taken in file order, with their recorded receive times, by a
//!   [`Session`] as the live one: the live code path minus the bus, so the same frames give the
//!   same samples (and, through [`crate::pipeline::run`], the same table) bit for bit;
//! - recorded samples (a CSV file) bypass alignment; the EM then steps at the recording's
//!   median sample interval (`window.grid_hz` when the two agree to [`CSV_RATE_TOLERANCE`]);
//! - the recording is judged by the live session's rules at its end ([`Session::at_end`]: the
//!   window's and the stream gate's): one the live daemon would not have calibrated has
//!   [`Replay::shortfalls`] saying why.

use exocal_dbc::Received;

use crate::align::AlignedSample;
use crate::collect::Collected;
use crate::detail::TimedSample;
use crate::window::{Shortfall, Window};
use crate::{CalibrationJob, Session, Settings};

/// Relative difference between a recording's sample rate and `window.grid_hz` below which the
/// configured rate is kept (a CSV `t` column's decimal rounding, not a different rate).
pub const CSV_RATE_TOLERANCE: f64 = 1e-6;

/// A recorded session.
#[derive(Debug, Clone)]
pub enum Recording {
    /// Frames to replay (for a session log, cut at its collection end).
    Frames(Vec<Received>),
    /// Samples that bypass alignment.
    Samples(Vec<TimedSample>),
}

/// The recording as the live session would have collected it, before calibrating.
#[derive(Debug, Clone)]
pub struct Replay {
    /// What the live session would have gathered (for samples: unaligned), with the settings
    /// the calibration runs with (for samples, `window.grid_hz` is theirs): the calibration
    /// the live session would have run.
    pub job: CalibrationJob,
    /// First to last frame (or sample), seconds.
    pub duration_s: f64,
    /// The window rules the recording does not meet: empty when the live daemon would have
    /// calibrated it.
    pub shortfalls: Vec<Shortfall>,
}

/// Replays `recording` under `settings` (see the module docs).
pub fn replay(recording: &Recording, settings: &Settings) -> Replay {
    replay_gated(recording, settings, None)
}

/// [`replay`] with the live session's stream gate re-applied to the frames
/// ([`crate::gate::StreamGate::replaying`]): the frames the live session's gate passed, and
/// only those, reach ingest.
pub fn replay_gated(
    recording: &Recording,
    settings: &Settings,
    gate: Option<crate::gate::StreamGate>,
) -> Replay {
    let mut settings = settings.clone();
    match recording {
        Recording::Frames(frames) => {
            let mut session = Session::new(&settings);
            if let Some(gate) = gate {
                session.authenticate(gate);
            }
            for rx in frames {
                session.take(rx, |_, _| {});
            }
            let duration_s = match (frames.first(), frames.last()) {
                (Some(a), Some(b)) => b.timestamp.saturating_sub(a.timestamp).as_secs_f64(),
                _ => 0.0,
            };
            Replay {
                shortfalls: session.at_end(duration_s),
                job: session.into_calibration(),
                duration_s,
            }
        }
        Recording::Samples(samples) => {
            let mut steps: Vec<f64> = samples.windows(2).map(|w| w[1].t - w[0].t).collect();
            steps.sort_by(f64::total_cmp);
            if let Some(&median) = steps.get(steps.len() / 2) {
                let hz = 1.0 / median;
                if (hz / settings.window.grid_hz - 1.0).abs() > CSV_RATE_TOLERANCE {
                    settings.window.grid_hz = hz;
                }
            }
            let mut window = Window::new(
                settings.window.clone(),
                settings.bounds.joint_range,
                settings.joints,
            );
            for s in samples {
                for (j, &q) in s.sample.joints.iter().enumerate() {
                    window.joint_sample(j, q);
                }
                window.pose_sample();
            }
            let duration_s = match (samples.first(), samples.last()) {
                (Some(a), Some(b)) => (b.t - a.t).max(0.0),
                _ => 0.0,
            };
            let aligned: Vec<AlignedSample> = samples
                .iter()
                .map(|s| AlignedSample::of(s.t, &s.sample))
                .collect();
            let collected = Collected::from_samples(aligned, &settings);
            Replay {
                job: CalibrationJob::new(collected, settings),
                shortfalls: window.at_end(duration_s),
                duration_s,
            }
        }
    }
}
