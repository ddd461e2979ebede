//! What a session gathers before it calibrates, live or replayed: frames in, aligned samples
//! and their data quality out.
//!
//! Contract:
//! - `Collector::on_frame` is the one place a received frame is taken: decoded by
//!   [`Ingest`], and each joint angle and pose counted by the [`Window`]. The live
//!   session feeds it from the bus (and logs the [`Event`] it returns); `exocald offline`
//!   feeds it the frames of a recording. The same frames give the same [`Collected`], bit for
//!   bit;
//! - [`Collector::collected`] aligns what was gathered: every node's clock fitted, all streams
//!   resampled onto the `window.grid_hz` grid (at most [`crate::WindowRules::max_samples`]
//!   points: bounded by the rules, not by the frames' timestamps), gaps longer than
//!   `window.max_gap_s` excluded, and the data-quality summary the report shows;
//! - [`Collected::from_samples`] is the same for samples that need no alignment (a CSV file):
//!   no frames, no clocks.

use crate::detail::{Quality, StreamQuality};
use exocal_dbc::Received;

use crate::align::{AlignParams, AlignedSample};
use crate::gate::{Dropped, StreamGate};
use crate::ingest::{ClockReport, Event, FrameStats, Ingest, Reading, StallReport};
use crate::stream::{Column, STREAMS};
use crate::window::{Shortfall, Window};
use crate::{Settings, MAX_JOINTS};

/// A session's frames so far: the decoded streams, the collection window and the stream gate.
/// Fed only by a [`crate::Session`] (`Session::take`), which is what callers drive; outside the
/// crate it is the copy an `EstimateJob` works on.
#[derive(Debug, Clone)]
pub struct Collector {
    /// The decoded streams and the frame counters.
    pub(crate) ingest: Ingest,
    /// The collection window: coverage, sample counts, ready/failed.
    pub(crate) window: Window,
    /// The stream gate, when the sensor streams are authenticated: frames reach
    /// [`Collector::on_frame`] only through it ([`Collector::take`]).
    pub(crate) gate: Option<StreamGate>,
    /// Frames taken through [`Collector::take`] (the received frames, before the gate).
    pub(crate) taken: u64,
}

impl Collector {
    /// An empty collection under `config`'s node ids, session rules and joint ranges.
    pub fn new(settings: &Settings) -> Collector {
        let ingest = Ingest::new(&settings.joint_nodes[..settings.joints.min(MAX_JOINTS)]);
        Collector {
            // The gyro at rest needs the joint gyros where some joint is unaided: about each
            // joint's axis, `z_{j−1}` seen from link `j`, `R_x(α_j)ᵀ ẑ`.
            ingest: match settings.sensors.unaided.iter().any(|&u| u) {
                true => ingest.with_joint_gyros(
                    settings
                        .nominal
                        .rows
                        .map(|r| [0.0, r.alpha.sin(), r.alpha.cos()]),
                ),
                false => ingest,
            },
            window: Window::new(
                settings.window.clone(),
                settings.bounds.joint_range,
                settings.joints,
            ),
            gate: None,
            taken: 0,
        }
    }

    /// Takes one received frame through the stream gate, if there is one: `each` sees every
    /// frame ingest takes now with its [`Event`]; returns the spans the gate dropped.
    pub(crate) fn take(
        &mut self,
        rx: &Received,
        mut each: impl FnMut(&Received, Event),
    ) -> Vec<Dropped> {
        self.taken += 1;
        let Some(gate) = self.gate.as_mut() else {
            let event = self.on_frame(rx);
            each(rx, event);
            return Vec::new();
        };
        let mut pass = Vec::new();
        let dropped = gate.on_frame(rx, &mut pass);
        for r in &pass {
            let event = self.on_frame(r);
            each(r, event);
        }
        dropped
    }

    /// What the stream gate says against calibrating on this collection (empty without a
    /// gate): a [`Shortfall::SecondSender`] for every node on whose identifiers frames it did
    /// not sign arrived, and [`Shortfall::Unverified`] when spans were dropped and either the
    /// window `failed` or they exceed [`crate::gate::MAX_DROPPED_FRACTION`] of all spans. A
    /// session with any of these is refused: its data were attacked or too much is missing.
    pub(crate) fn unverified(&self, failed: bool) -> Vec<Shortfall> {
        let Some(s) = self.gate.as_ref().map(StreamGate::stats) else {
            return Vec::new();
        };
        let mut why: Vec<Shortfall> = s
            .second_senders()
            .map(|(node, spans)| Shortfall::SecondSender { node, spans })
            .collect();
        if s.dropped_spans > 0 && (failed || s.heavy_loss()) {
            why.push(Shortfall::Unverified {
                spans: s.dropped_spans,
                frames: s.dropped_frames,
                seconds: s.dropped_s,
                of: s.dropped_spans + s.verified_spans,
            });
        }
        why
    }

    /// Takes one received frame (see the module docs); returns what ingest made of it.
    pub(crate) fn on_frame(&mut self, rx: &Received) -> Event {
        let event = self.ingest.on_frame(rx);
        if let Event::Sample {
            stream, reading, ..
        } = event
        {
            match (STREAMS[stream].column, reading) {
                (Column::Angle(j), Reading::Angle { angle, .. }) => {
                    self.window.joint_sample(j, angle)
                }
                (Column::Pose, _) => self.window.pose_sample(),
                _ => {}
            }
        }
        event
    }

    /// Aligns what was gathered (see the module docs).
    pub fn collected(&self, settings: &Settings) -> Collected {
        let (aligned, clocks) = self.ingest.align(
            &AlignParams::default(),
            settings.window.grid_hz,
            settings.window.max_gap_s,
            settings.window.max_samples(),
        );
        let stalls = StallReport::of(&aligned.stalls);
        let quality = frame_quality(
            settings,
            &self.ingest,
            &clocks,
            stalls,
            &aligned.samples,
            aligned.gaps,
        );
        Collected {
            frames: self.ingest.stats().clone(),
            clocks,
            stalls,
            samples: aligned.samples,
            gaps: aligned.gaps,
            quality,
        }
    }
}

/// What a session gathered, aligned: the calibration's input and its data quality.
#[derive(Debug, Clone, Default)]
pub struct Collected {
    /// Frame counters of the collection window.
    pub frames: FrameStats,
    /// One report per node clock (joints, then the end effector).
    pub clocks: Vec<ClockReport>,
    /// Receiver stalls (not counted in any node's clock jumps).
    pub stalls: StallReport,
    /// The samples on the grid, time-ordered.
    pub samples: Vec<AlignedSample>,
    /// Grid points excluded as gaps.
    pub gaps: usize,
    /// The data-quality summary the report shows.
    pub quality: Quality,
}

impl Collected {
    /// Samples that need no alignment (CSV), with their data quality.
    pub fn from_samples(samples: Vec<AlignedSample>, settings: &Settings) -> Collected {
        Collected {
            quality: sample_quality(settings, &samples),
            samples,
            ..Collected::default()
        }
    }
}

/// The arm's joint ranges.
fn ranges(settings: &Settings) -> Vec<(f64, f64)> {
    settings.bounds.joint_range.limits[..settings.joints].to_vec()
}

fn duration(samples: &[AlignedSample]) -> f64 {
    match (samples.first(), samples.last()) {
        (Some(a), Some(b)) => b.t - a.t,
        _ => 0.0,
    }
}

/// Data quality of a frame-level session: counters; per stream of [`STREAMS`] its samples,
/// rate and loss, and for those aligned ([`Column::calibrates`]) their clock (`clocks`, by
/// name); the alignment's gaps.
fn frame_quality(
    settings: &Settings,
    ingest: &Ingest,
    clocks: &[ClockReport],
    stalls: StallReport,
    samples: &[AlignedSample],
    gaps: usize,
) -> Quality {
    let stats = ingest.stats();
    let counters = [
        ("received", stats.received),
        ("decoded", stats.decoded),
        ("unknown", stats.unknown),
        ("malformed", stats.malformed),
        ("invalid angles", stats.invalid_angles),
        ("bad poses", stats.bad_poses),
        ("poses", stats.poses),
    ]
    .into_iter()
    .map(|(k, v)| (k.to_string(), v))
    .collect();
    let streams = (STREAMS.iter().enumerate())
        .zip(ingest.stream_rates())
        // The streams of joints past the arm's are not the session's.
        .filter(|((_, s), _)| !matches!(s.column, Column::Angle(j) if j >= settings.joints))
        .map(|((i, s), (rate, loss))| {
            let clock = clocks.iter().find(|c| c.node == s.name);
            StreamQuality {
                name: s.name.to_string(),
                samples: ingest.stream_samples(i),
                rate_hz: rate.unwrap_or(0.0),
                loss,
                excluded: clock.map_or(0, |c| c.unmapped),
                jumps: clock.map_or(0, |c| c.jumps),
                skew_ppm: clock.and_then(|c| c.skew_ppm),
                jitter_us: clock.and_then(|c| c.residual_rms_us),
            }
        })
        .collect();
    Quality {
        duration_s: duration(samples),
        grid_hz: settings.window.grid_hz,
        gaps,
        counters,
        streams,
        joint_ranges: ranges(settings),
        excitation_required: Some(settings.window.excitation_required),
        receiver_stalls: stalls.count,
        longest_stall_ms: stalls.longest_ms,
    }
}

/// Data quality of plain samples (CSV): span, the grid rate they were calibrated at, no
/// frame counters or clocks.
fn sample_quality(settings: &Settings, samples: &[AlignedSample]) -> Quality {
    let span = duration(samples);
    let rate = if span > 0.0 {
        (samples.len() - 1) as f64 / span
    } else {
        0.0
    };
    Quality {
        duration_s: span,
        grid_hz: settings.window.grid_hz,
        gaps: 0,
        counters: Vec::new(),
        streams: vec![StreamQuality {
            name: "CSV samples".into(),
            samples: samples.len(),
            rate_hz: rate,
            loss: None,
            excluded: 0,
            jumps: 0,
            skew_ppm: None,
            jitter_us: None,
        }],
        joint_ranges: ranges(settings),
        excitation_required: Some(settings.window.excitation_required),
        receiver_stalls: 0,
        longest_stall_ms: None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use exocal_dbc::message::{JointState, Message};
    use exocal_dbc::Frame;
    use exocal_dbc::NodeId;
    use std::time::Duration;

    #[test]
    fn a_frame_reaches_ingest_and_the_window_and_its_event_comes_back() {
        let config = Settings::suit_default();
        let mut c = Collector::new(&config);
        for k in 0..3u32 {
            let msg = Message::JointState(JointState {
                node: NodeId::new(3).unwrap(),
                timestamp_us: 10_000 * (k + 1),
                angle: 0.25,
                rate: 0.0,
            });
            let event = c.on_frame(&Received {
                frame: msg.to_frame::<Frame>().unwrap(),
                timestamp: Duration::from_millis(10 * u64::from(k)),
            });
            assert!(
                matches!(
                    event,
                    Event::Sample {
                        stream: 2,
                        reading: Reading::Angle { .. },
                        ..
                    }
                ),
                "{event:?}"
            );
        }
        assert_eq!(c.ingest.stats().received, 3);
        assert_eq!(c.ingest.joint_samples(2), 3);
        // Three samples in one bin of joint 3's range: that bin counts as visited.
        let coverage = c.window.progress(0.0).coverage;
        assert!((coverage[2] - 1.0 / 36.0).abs() < 1e-12, "{coverage:?}");
        assert_eq!(coverage[0], 0.0);
    }
}
