//! Ingest: received frames → decoded messages → per-node timestamped streams.
//!
//! Contract:
//! - [`Ingest::on_frame`] never fails: every frame is counted ([`FrameStats`]) as decoded,
//!   unknown (an identifier the DBC does not define, extended or remote frames) or malformed
//!   (a known identifier with a bad length, multiplexer or value), and the caller gets an
//!   [`Event`] to log or act on. Invalid (NaN) angles are counted and kept out of the streams.
//! - A babbling node is named: a timestamped frame (joint state, IMU vector, pose page) that
//!   repeats its identifier's previous frame byte for byte is counted per node
//!   ([`FrameStats::repeats`]); [`FrameStats::babbling`] names the nodes that repeat far more
//!   than the others (bus-wide duplication spreads over every node and names none). A repeated
//!   joint state is kept out of the streams.
//! - Host time is the transport's receive timestamp (the kernel's on SocketCAN) truncated to
//!   whole µs ([`whole_micros`]), in seconds since the first frame of the session
//!   ([`Ingest::origin`]); node time is the node's µs
//!   counter, unwrapped across its 2^32 rollover.
//! - [`Ingest::align`] fits every node's clock ([`crate::align::track_clocks`]: a break every
//!   node shows at once is a receiver stall, reported once in [`StallReport`] and not as a
//!   jump of each node; a node's own reboot or clock step is its jump), maps every sample to
//!   host time and resamples all streams onto one grid ([`crate::align::align`]).

use std::time::Duration;

use embedded_can::Frame as _;
use exocal_dbc::pose::PoseAssembler;
use exocal_dbc::Received;
use exocal_dbc::{DecodeError, Message, NodeId};
use serde::Serialize;

use crate::align::{self, AlignParams, Aligned, Pose, Stall, Unwrapper};
use crate::stream::{angle, stream_of, Column, Source, POSE, STREAMS};
use crate::MAX_JOINTS;
use exocal_dbc::spec::Kind;

/// Node clocks are 32-bit microsecond counters.
pub const NODE_CLOCK_MODULUS: u64 = 1 << 32;
/// IMU vectors carry the low 16 bits of their node's clock.
pub const IMU_CLOCK_MODULUS: u64 = 1 << 16;

/// `t` truncated to whole microseconds: the resolution of receive times in ingest.
///
/// Sub-µs digits are noise against CAN's frame times (≥ 47 µs at 1 Mbit/s) and receive jitter,
/// and µs is what `candump -L` logs and `SO_TIMESTAMP` delivers: a candump log of a session
/// then replays through `exocald offline` to exactly the live result.
pub fn whole_micros(t: Duration) -> Duration {
    Duration::new(t.as_secs(), t.subsec_micros() * 1_000)
}

/// Frame counters of a session.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize)]
pub struct FrameStats {
    /// Every frame taken.
    pub received: u64,
    /// Frames the DBC decoded.
    pub decoded: u64,
    /// Identifiers the DBC does not define (and extended or remote frames).
    pub unknown: u64,
    /// Known identifiers with a bad DLC, multiplexer or value.
    pub malformed: u64,
    /// Joint angles marked invalid (NaN) by their node.
    pub invalid_angles: u64,
    /// Poses refused (quaternion not of unit norm).
    pub bad_poses: u64,
    /// Joint-state frames per joint.
    pub joint_frames: [u64; MAX_JOINTS],
    /// Complete end-effector poses.
    pub poses: u64,
    /// Heartbeats per node id 1..=8 (index 0 unused).
    pub heartbeats: [u64; 9],
    /// Joint-state frames from joint nodes that are not on the configured arm, per node id
    /// 1..=8 (index 0 unused): a suit with more joints than its configuration, or a recording
    /// of another arm. Not calibrated on.
    pub off_arm: [u64; 9],
    /// Timestamped frames identical to the previous frame of their identifier, per node id
    /// 1..=8 (index 0 unused): a genuine one carries a new timestamp or sequence number.
    pub repeats: [u64; 9],
}

/// Fewest repeated frames for a node to be called babbling.
pub const BABBLE_MIN_REPEATS: u64 = 100;
/// A babbling node repeats at least this many times more frames than the median node.
pub const BABBLE_FACTOR: u64 = 5;

impl FrameStats {
    /// Nodes whose repeated frames ([`FrameStats::repeats`]) number at least
    /// [`BABBLE_MIN_REPEATS`] and [`BABBLE_FACTOR`] × the median over the eight nodes, with
    /// their count.
    pub fn babbling(&self) -> Vec<(NodeId, u64)> {
        let mut counts: Vec<u64> = self.repeats[1..].to_vec();
        counts.sort_unstable();
        let median = counts[counts.len() / 2];
        let bar = BABBLE_MIN_REPEATS.max(median.saturating_mul(BABBLE_FACTOR));
        NodeId::ALL
            .iter()
            .filter_map(|&n| {
                let r = self.repeats[usize::from(n.raw()).min(8)];
                (r >= bar).then_some((n, r))
            })
            .collect()
    }
}

/// What one frame was.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Event {
    /// A sample of stream `stream` (an index of [`STREAMS`]).
    Sample {
        /// The stream, an index of [`STREAMS`].
        stream: usize,
        /// Node clock at sampling (µs; the low 16 bits for IMU vectors).
        node_timestamp_us: u32,
        /// What was sampled.
        reading: Reading,
    },
    /// Any other decoded message (heartbeats, IMU vectors no stream takes, table replies,
    /// triggers, …).
    Message(Message),
    /// Not a frame of the DBC.
    Unknown(DecodeError),
    /// A DBC frame that does not decode.
    Malformed(DecodeError),
    /// A pose page that did not complete a pose (or completed a bad one).
    Partial,
}

/// One sample of a stream, as its message carried it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Reading {
    /// A joint reading (rad; NaN when the node marked it invalid) and its rate (rad/s).
    Angle {
        /// Joint angle (rad).
        angle: f64,
        /// Joint rate (rad/s).
        rate: f64,
    },
    /// A complete end-effector pose.
    Pose(exocal_dbc::pose::Pose),
    /// A raw IMU vector in the sensor's frame, in its message's unit ([`Column::Vector`]).
    Vector([f64; 3]),
}

/// One stream's samples in arrival order: node clock and host time, and its values
/// ([`Column::width`] of them per sample, flat).
#[derive(Debug, Clone)]
struct Series {
    unwrap: Unwrapper,
    /// `(node_s, host_s)` per sample, arrival order.
    clock: Vec<(f64, f64)>,
    values: Vec<f64>,
    width: usize,
}

impl Series {
    fn new(column: Column, clock_modulus: u64) -> Self {
        Series {
            unwrap: Unwrapper::new(clock_modulus),
            clock: Vec::new(),
            values: Vec::new(),
            width: column.width(),
        }
    }

    fn push(&mut self, node_us: u32, host_s: f64, value: &[f64]) {
        debug_assert_eq!(value.len(), self.width);
        let node_s = self.unwrap.unwrap(u64::from(node_us)) as f64 * 1e-6;
        self.clock.push((node_s, host_s));
        self.values.extend_from_slice(value);
    }

    fn len(&self) -> usize {
        self.clock.len()
    }

    fn value(&self, k: usize) -> &[f64] {
        &self.values[k * self.width..(k + 1) * self.width]
    }

    /// Samples mapped to host time through `track` (this stream's), each read by `read`, sorted.
    fn mapped<T>(&self, track: &align::ClockTrack, read: impl Fn(&[f64]) -> T) -> Vec<(f64, T)> {
        let mut out: Vec<(f64, T)> = track
            .map_all(&self.clock)
            .into_iter()
            .enumerate()
            .filter_map(|(k, t)| t.map(|t| (t, read(self.value(k)))))
            .collect();
        align::sort_stream(&mut out);
        out
    }
}

fn pose_of(v: &[f64]) -> Pose {
    Pose {
        position: [v[0], v[1], v[2]],
        orientation: [v[3], v[4], v[5], v[6]],
    }
}

/// The receiver's stalls over a session: breaks every node's clock showed together, which
/// are not counted as any node's jump ([`crate::align::track_clocks`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct StallReport {
    /// Stall episodes.
    pub count: usize,
    /// Lateness of the longest (ms), if any.
    pub longest_ms: Option<f64>,
}

impl StallReport {
    /// The report of `stalls`.
    pub fn of(stalls: &[Stall]) -> StallReport {
        StallReport {
            count: stalls.len(),
            longest_ms: stalls.iter().map(|s| s.late_s * 1e3).reduce(f64::max),
        }
    }
}

impl std::fmt::Display for StallReport {
    /// `receiver stalled N times (longest X ms)`.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let times = if self.count == 1 { "time" } else { "times" };
        write!(f, "receiver stalled {} {times}", self.count)?;
        if let Some(ms) = self.longest_ms {
            write!(f, " (longest {ms:.0} ms)")?;
        }
        Ok(())
    }
}

/// How one node's clock looked over the session.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ClockReport {
    /// The stream's name ([`STREAMS`]: `Joint1`…`Joint7`, `EndEffector`).
    pub node: String,
    /// Samples in the node's stream.
    pub samples: usize,
    /// Samples in segments too short to fit (excluded).
    pub unmapped: usize,
    /// The node's own reboots or clock jumps detected (a receiver stall is none of these).
    pub jumps: usize,
    /// Skew of the longest segment (ppm).
    pub skew_ppm: Option<f64>,
    /// RMS residual of the longest segment's fit (µs).
    pub residual_rms_us: Option<f64>,
    /// Receive-time outliers of all segments.
    pub outliers: usize,
}

fn clock_report(
    name: &str,
    samples: usize,
    mapped: usize,
    track: &align::ClockTrack,
) -> ClockReport {
    let longest = track
        .segments
        .iter()
        .filter(|s| s.fit.is_some())
        .max_by_key(|s| s.end - s.start)
        .and_then(|s| s.fit);
    ClockReport {
        node: name.to_string(),
        samples,
        unmapped: samples - mapped.min(samples),
        jumps: track.jumps(),
        skew_ppm: longest.map(|f| f.skew * 1e6),
        residual_rms_us: longest.map(|f| f.residual_rms * 1e6),
        outliers: track
            .segments
            .iter()
            .filter_map(|s| s.fit)
            .map(|f| f.outliers)
            .sum(),
    }
}

/// The session's incoming data.
#[derive(Debug, Clone)]
pub struct Ingest {
    origin: Option<Duration>,
    /// Joint index of each node id (1..=7 → 0..7), from the configuration.
    joint_of_node: [Option<usize>; 9],
    /// Joints of the arm: the streams of joints past them are never waited for.
    joints: usize,
    /// One per [`STREAMS`] entry.
    streams: Vec<Series>,
    assembler: PoseAssembler,
    stats: FrameStats,
    /// The last payload seen per standard identifier (for [`FrameStats::repeats`]).
    last_payload: std::collections::HashMap<u32, ([u8; 8], usize)>,
    /// The joint nodes' gyros about their joints' axes, where asked for
    /// ([`Ingest::with_joint_gyros`]).
    joint_gyros: Option<JointGyros>,
}

/// Keep a joint gyro reading only this long after the last one kept (s): a node that floods
/// its gyro frames grows the series no faster than 250 readings a second.
pub const JOINT_GYRO_MIN_INTERVAL_S: f64 = 0.004;

/// Each joint node's gyro about its joint's axis: `(host s, rad/s)` in receive order, on the
/// host's receive time (their 16-bit node stamps are not fitted; the gyro at rest needs no
/// better than the frames' latency).
#[derive(Debug, Clone)]
struct JointGyros {
    /// Joint `j`'s axis in its node's frame (unit).
    axes: [[f64; 3]; MAX_JOINTS],
    series: [Vec<(f64, f64)>; MAX_JOINTS],
}

impl Ingest {
    /// A new session of the arm whose joint `i` is on node `joint_nodes[i]` (at most
    /// [`MAX_JOINTS`]; the nodes of joints past the arm's send nothing it waits for).
    pub fn new(joint_nodes: &[u8]) -> Ingest {
        let mut joint_of_node = [None; 9];
        let joint_nodes = &joint_nodes[..joint_nodes.len().min(MAX_JOINTS)];
        for (i, &id) in joint_nodes.iter().enumerate() {
            if let Some(slot) = joint_of_node.get_mut(usize::from(id)) {
                *slot = Some(i);
            }
        }
        let streams = STREAMS
            .iter()
            .map(|s| {
                let modulus = match s.message {
                    // IMU vectors carry the low 16 bits of the node clock.
                    Kind::ImuGyro | Kind::ImuAccel | Kind::ImuMag => IMU_CLOCK_MODULUS,
                    _ => NODE_CLOCK_MODULUS,
                };
                Series::new(s.column, modulus)
            })
            .collect();
        Ingest {
            origin: None,
            joint_of_node,
            joints: joint_nodes.len(),
            streams,
            assembler: PoseAssembler::new(),
            stats: FrameStats::default(),
            last_payload: std::collections::HashMap::new(),
            joint_gyros: None,
        }
    }

    /// This session keeping, beside its streams, each joint node's gyro reading about its
    /// joint's axis (`axes[j]`, a unit vector in the node's frame), which alignment resamples
    /// into [`crate::align::AlignedSample::rates`] (for the gyro at rest; they are not a
    /// stream of their own: their frames are in the log's `/can/rx`).
    pub fn with_joint_gyros(mut self, axes: [[f64; 3]; MAX_JOINTS]) -> Ingest {
        self.joint_gyros = Some(JointGyros {
            axes,
            series: Default::default(),
        });
        self
    }

    /// Receive time of the session's first frame (transport clock).
    pub fn origin(&self) -> Option<Duration> {
        self.origin
    }

    /// Counters so far.
    pub fn stats(&self) -> &FrameStats {
        &self.stats
    }

    /// Seconds of `t` since the origin (negative if earlier).
    pub fn host_s(&self, t: Duration) -> f64 {
        match self.origin {
            None => 0.0,
            Some(o) if t >= o => (t - o).as_secs_f64(),
            Some(o) => -(o - t).as_secs_f64(),
        }
    }

    /// Takes one received frame.
    pub fn on_frame(&mut self, rx: &Received) -> Event {
        let t = whole_micros(rx.timestamp);
        self.origin.get_or_insert(t);
        let host_s = self.host_s(t);
        self.stats.received += 1;
        let frame = &rx.frame;
        let decoded = exocal_dbc::decode_frame(frame);
        let message = match decoded {
            Ok(m) => m,
            Err(e @ (DecodeError::UnknownId(_) | DecodeError::Remote(_))) => {
                self.stats.unknown += 1;
                return Event::Unknown(e);
            }
            Err(e) => {
                self.stats.malformed += 1;
                return Event::Malformed(e);
            }
        };
        debug_assert!(!frame.is_extended());
        self.stats.decoded += 1;
        let repeated = self.count_repeat(frame, &message);
        match message {
            Message::JointState(js) => {
                let Some(joint) = self.joint_of_node[usize::from(js.node.raw())] else {
                    if let Some(n) = self.stats.off_arm.get_mut(usize::from(js.node.raw())) {
                        *n += 1;
                    }
                    return Event::Message(message);
                };
                if repeated {
                    // Carries nothing new; kept out of the streams (and the clock fit).
                    return Event::Message(message);
                }
                let Some(stream) = stream_of(Source::Joint(joint), Kind::JointState) else {
                    return Event::Message(message);
                };
                self.stats.joint_frames[joint] += 1;
                if js.angle.is_nan() {
                    self.stats.invalid_angles += 1;
                } else {
                    self.streams[stream].push(js.timestamp_us, host_s, &[js.angle]);
                }
                Event::Sample {
                    stream,
                    node_timestamp_us: js.timestamp_us,
                    reading: Reading::Angle {
                        angle: js.angle,
                        rate: js.rate,
                    },
                }
            }
            Message::EePose(page) => match self.assembler.push(page) {
                Some(Ok(p)) => {
                    self.stats.poses += 1;
                    let stream = stream_of(Source::EndEffector, Kind::EePose).unwrap_or(POSE);
                    let [x, y, z] = p.position;
                    let [qw, qx, qy, qz] = p.quat;
                    self.streams[stream].push(p.timestamp_us, host_s, &[x, y, z, qw, qx, qy, qz]);
                    Event::Sample {
                        stream,
                        node_timestamp_us: p.timestamp_us,
                        reading: Reading::Pose(p),
                    }
                }
                Some(Err(_)) => {
                    self.stats.bad_poses += 1;
                    Event::Partial
                }
                None => Event::Partial,
            },
            Message::ImuGyro(v) | Message::ImuAccel(v) | Message::ImuMag(v) if !repeated => {
                let source = self.source(v.node);
                if let (Message::ImuGyro(_), Some(Source::Joint(j)), Some(g)) =
                    (message, source, self.joint_gyros.as_mut())
                {
                    let series = &mut g.series[j];
                    if series
                        .last()
                        .is_none_or(|&(t, _)| host_s >= t + JOINT_GYRO_MIN_INTERVAL_S)
                    {
                        let a = g.axes[j];
                        series.push((host_s, v.xyz[0] * a[0] + v.xyz[1] * a[1] + v.xyz[2] * a[2]));
                    }
                }
                let Some(stream) = source.and_then(|source| stream_of(source, message.kind()))
                else {
                    return Event::Message(message);
                };
                let ts = u32::from(v.timestamp_lo);
                self.streams[stream].push(ts, host_s, &v.xyz);
                Event::Sample {
                    stream,
                    node_timestamp_us: ts,
                    reading: Reading::Vector(v.xyz),
                }
            }
            Message::Heartbeat(hb) => {
                self.stats.heartbeats[usize::from(hb.node.raw()).min(8)] += 1;
                Event::Message(message)
            }
            other => Event::Message(other),
        }
    }

    /// The role of `node` on the suit, if it has one.
    fn source(&self, node: NodeId) -> Option<Source> {
        if node == NodeId::END_EFFECTOR {
            return Some(Source::EndEffector);
        }
        self.joint_of_node[usize::from(node.raw()).min(8)].map(Source::Joint)
    }

    /// Counts `frame` in [`FrameStats::repeats`] if it repeats its identifier's previous frame;
    /// returns whether it did.
    fn count_repeat(&mut self, frame: &exocal_dbc::Frame, message: &Message) -> bool {
        let timestamped = matches!(
            message,
            Message::JointState(_)
                | Message::ImuGyro(_)
                | Message::ImuAccel(_)
                | Message::ImuMag(_)
                | Message::EePose(_)
        );
        let (Some(node), true) = (message.node(), timestamped) else {
            return false;
        };
        let id = frame.raw_id();
        let data = frame.data();
        let mut payload = [0u8; 8];
        let len = data.len().min(8);
        payload[..len].copy_from_slice(&data[..len]);
        let repeated = self.last_payload.insert(id, (payload, len)) == Some((payload, len));
        if repeated {
            self.stats.repeats[usize::from(node.raw()).min(8)] += 1;
        }
        repeated
    }

    /// Joint samples received for joint `joint` (valid angles).
    pub fn joint_samples(&self, joint: usize) -> usize {
        if joint < MAX_JOINTS {
            self.streams[angle(joint)].len()
        } else {
            0
        }
    }

    /// Samples received on stream `stream` (an index of [`STREAMS`]).
    pub fn stream_samples(&self, stream: usize) -> usize {
        self.streams.get(stream).map_or(0, Series::len)
    }

    /// Up to `n` arm configurations spread evenly over the session so far: at each of `n`
    /// receive instants from the first one at which every joint has reported to the last
    /// reading, every joint's latest angle by then. No clock model and no interpolation: for
    /// figures that depend on where the arm went and not on when, such as the condition number
    /// of the identification problem. Empty until every joint of the arm has reported; the
    /// joints past it read 0 ([`crate::arm`]).
    pub fn joint_snapshot(&self, n: usize) -> Vec<[f64; MAX_JOINTS]> {
        let joints = &self.streams[angle(0)..angle(0) + self.joints];
        let span = joints.iter().try_fold((f64::MIN, f64::MIN), |(lo, hi), s| {
            let first = s.clock.first()?.1;
            let last = s.clock.last()?.1;
            Some((lo.max(first), hi.max(last)))
        });
        let Some((start, end)) = span.filter(|(lo, hi)| lo <= hi) else {
            return Vec::new();
        };
        let n = n.max(1);
        (0..n)
            .map(|i| {
                let t = if n == 1 {
                    end
                } else {
                    start + (end - start) * i as f64 / (n - 1) as f64
                };
                std::array::from_fn(|j| {
                    let Some(s) = joints.get(j) else { return 0.0 };
                    // Arrival order: host times ascend (a stepped clock only blurs the pick).
                    let k = s.clock.partition_point(|c| c.1 <= t).max(1);
                    s.value(k - 1)[0]
                })
            })
            .collect()
    }

    /// Poses received.
    pub fn pose_samples(&self) -> usize {
        self.streams[POSE].len()
    }

    /// Receive-side rate of each stream of [`STREAMS`], in its order: the mean rate (Hz) over
    /// the stream's span, and the estimated fraction lost (1 − samples / (span / median
    /// interval + 1), at least 0), both `None` with fewer than 3 samples.
    pub fn stream_rates(&self) -> Vec<(Option<f64>, Option<f64>)> {
        let host = |clock: &[(f64, f64)]| -> (Option<f64>, Option<f64>) {
            let n = clock.len();
            if n < 3 {
                return (None, None);
            }
            let mut times: Vec<f64> = clock.iter().map(|c| c.1).collect();
            times.sort_by(f64::total_cmp);
            let span = times[n - 1] - times[0];
            let mut steps: Vec<f64> = times.windows(2).map(|w| w[1] - w[0]).collect();
            steps.sort_by(f64::total_cmp);
            let median = steps[steps.len() / 2];
            let rate = (span > 0.0).then(|| (n - 1) as f64 / span);
            let loss = (median > 0.0).then(|| (1.0 - n as f64 / (span / median + 1.0)).max(0.0));
            (rate, loss)
        };
        self.streams.iter().map(|s| host(&s.clock)).collect()
    }

    /// Fits the clocks of the streams that calibrate ([`Column::calibrates`]) and resamples
    /// them onto one grid at `hz` (host s since origin), of at most `max_points`
    /// ([`crate::align::align`]); the receiver stalls found are in [`Aligned::stalls`]. The
    /// clock reports are theirs, in [`STREAMS`] order.
    pub fn align(
        &self,
        params: &AlignParams,
        hz: f64,
        max_gap: f64,
        max_points: usize,
    ) -> (Aligned, Vec<ClockReport>) {
        // The arm's streams: a joint past it has no node on the bus.
        let calibrating: Vec<usize> = (0..STREAMS.len())
            .filter(|&i| STREAMS[i].column.calibrates())
            .filter(|&i| !matches!(STREAMS[i].column, Column::Angle(j) if j >= self.joints))
            .collect();
        let clocks: Vec<&[(f64, f64)]> = calibrating
            .iter()
            .map(|&i| self.streams[i].clock.as_slice())
            .collect();
        let session = align::track_clocks(&clocks, params);
        let mut reports = Vec::with_capacity(calibrating.len());
        let mut joints: [Vec<(f64, f64)>; MAX_JOINTS] = Default::default();
        let mut rates = self
            .joint_gyros
            .as_ref()
            .map(|g| g.series.clone())
            .unwrap_or_default();
        for r in &mut rates {
            align::sort_stream(r);
        }
        let mut poses = Vec::new();
        for (&i, track) in calibrating.iter().zip(&session.tracks) {
            let series = &self.streams[i];
            let mapped = match STREAMS[i].column {
                Column::Angle(j) => {
                    joints[j] = series.mapped(track, |v| v[0]);
                    joints[j].len()
                }
                Column::Pose => {
                    poses = series.mapped(track, pose_of);
                    poses.len()
                }
                Column::Vector => 0,
            };
            reports.push(clock_report(STREAMS[i].name, series.len(), mapped, track));
        }
        let arm = &joints[..self.joints];
        let mut aligned = align::align(arm, &rates, &poses, hz, max_gap, max_points);
        aligned.stalls = session.stalls;
        (aligned, reports)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use exocal_dbc::pose::Pose as DbcPose;
    use exocal_dbc::Frame;
    use exocal_dbc::JointState;

    fn rx(frame: Frame, t_s: f64) -> Received {
        Received {
            frame,
            timestamp: Duration::from_secs(1_700_000_000) + Duration::from_secs_f64(t_s),
        }
    }

    fn joint_frame(node: u8, ts_us: u32, angle: f64) -> Frame {
        Message::JointState(JointState {
            node: NodeId::new(node).unwrap(),
            timestamp_us: ts_us,
            angle,
            rate: 0.0,
        })
        .to_frame()
        .unwrap()
    }

    /// Asked for, a joint node's gyro is kept about its joint's axis on the receive time, at
    /// most one reading per [`JOINT_GYRO_MIN_INTERVAL_S`] (a flood is thinned, not stored);
    /// not asked for, nothing is kept.
    #[test]
    fn joint_gyros_are_kept_about_the_axis_and_a_flood_is_thinned() {
        let gyro = |k: u16| {
            Message::ImuGyro(exocal_dbc::ImuVector {
                node: NodeId::new(3).unwrap(),
                xyz: [0.25, 0.5, 1.0],
                timestamp_lo: k,
            })
            .to_frame::<Frame>()
            .unwrap()
        };
        let s = std::f64::consts::FRAC_1_SQRT_2;
        let mut axes = [[0.0, 0.0, 1.0]; MAX_JOINTS];
        axes[2] = [0.0, s, s];
        let mut asked = Ingest::new(&[1, 2, 3, 4, 5, 6, 7]).with_joint_gyros(axes);
        let mut plain = Ingest::new(&[1, 2, 3, 4, 5, 6, 7]);
        // 1000 frames in 0.1 s, then 10 at 100 Hz.
        let times = (0..1000)
            .map(|k| k as f64 * 1e-4)
            .chain((1..=10).map(|k| 0.1 + k as f64 * 0.01));
        for (k, t) in times.enumerate() {
            asked.on_frame(&rx(gyro(k as u16), t));
            plain.on_frame(&rx(gyro(k as u16), t));
        }
        let kept = &asked.joint_gyros.as_ref().unwrap().series[2];
        assert_eq!(kept.len(), 25 + 10, "{kept:?}");
        assert!(
            kept.iter().all(|&(_, r)| (r - 1.5 * s).abs() < 1e-3),
            "{kept:?}"
        );
        assert!(plain.joint_gyros.is_none());
    }

    #[test]
    fn the_end_effectors_gyro_and_magnetometer_are_streams_and_a_joints_gyro_is_not() {
        // STREAMS takes the end effector's IMU rate, not a joint node's: the table decides.
        let mut ing = Ingest::new(&[1, 2, 3, 4, 5, 6, 7]);
        let gyro = |node: NodeId, lo: u16, z: f64| {
            Message::ImuGyro(exocal_dbc::ImuVector {
                node,
                xyz: [0.0, 0.5, z],
                timestamp_lo: lo,
            })
            .to_frame::<Frame>()
            .unwrap()
        };
        let ee = crate::stream::stream_of(Source::EndEffector, Kind::ImuGyro).unwrap();
        for k in 0..5u16 {
            let e = ing.on_frame(&rx(
                gyro(NodeId::END_EFFECTOR, k * 10_000, f64::from(k)),
                0.01 * f64::from(k),
            ));
            assert!(
                matches!(e, Event::Sample { stream, reading: Reading::Vector([_, _, z]), .. } if stream == ee && z == f64::from(k)),
                "{e:?}"
            );
        }
        assert_eq!(ing.stream_samples(ee), 5);
        let e = ing.on_frame(&rx(gyro(NodeId::new(3).unwrap(), 7, 1.0), 0.1));
        assert!(matches!(e, Event::Message(Message::ImuGyro(_))), "{e:?}");
        // Its rate is measured like every stream's; it is not aligned (no clock report).
        assert!(ing.stream_rates()[ee].0.is_some());
        let (_, clocks) = ing.align(&AlignParams::default(), 100.0, 0.05, usize::MAX);
        assert!(clocks.iter().all(|c| c.node != STREAMS[ee].name));
        // Any IMU vector the table names is a stream of its own; one it does not, a message.
        let mag = crate::stream::stream_of(Source::EndEffector, Kind::ImuMag).unwrap();
        let imu = |m: fn(exocal_dbc::ImuVector) -> Message| {
            m(exocal_dbc::ImuVector {
                node: NodeId::END_EFFECTOR,
                xyz: [20.0, -5.0, 43.0],
                timestamp_lo: 99,
            })
            .to_frame::<Frame>()
            .unwrap()
        };
        let e = ing.on_frame(&rx(imu(Message::ImuMag), 0.2));
        assert!(
            matches!(e, Event::Sample { stream, reading: Reading::Vector([20.0, -5.0, 43.0]), .. } if stream == mag),
            "{e:?}"
        );
        assert_eq!(ing.stream_samples(mag), 1);
        let e = ing.on_frame(&rx(imu(Message::ImuAccel), 0.2));
        assert!(matches!(e, Event::Message(Message::ImuAccel(_))), "{e:?}");
    }

    #[test]
    fn the_joint_snapshot_takes_every_joints_latest_angle_once_all_have_reported() {
        let mut ing = Ingest::new(&[1, 2, 3, 4, 5, 6, 7]);
        // Joints 1-6 report from t = 0 s; joint 7 only from t = 1 s: nothing until then.
        for k in 0..=20u32 {
            let t = 0.1 * f64::from(k);
            for node in 1..=7u8 {
                if node == 7 && k < 10 {
                    continue;
                }
                // The angle encodes joint and time: node/10 + t/100 (within the DBC's range).
                let angle = f64::from(node) / 10.0 + t / 100.0;
                ing.on_frame(&rx(joint_frame(node, 100_000 * k + 1, angle), t));
            }
            if k == 9 {
                assert!(ing.joint_snapshot(5).is_empty());
            }
        }
        let snap = ing.joint_snapshot(3);
        // At 1.0 s, 1.5 s and 2.0 s (receive time), each joint's reading of that instant.
        assert_eq!(snap.len(), 3);
        for (row, t) in snap.iter().zip([1.0, 1.5, 2.0]) {
            for (j, a) in row.iter().enumerate() {
                let want = (j + 1) as f64 / 10.0 + t / 100.0;
                assert!(
                    (a - want).abs() < 1e-4,
                    "joint {} at {t}: {a} != {want}",
                    j + 1
                );
            }
        }
    }

    #[test]
    fn frames_are_counted_and_never_fatal() {
        let mut ing = Ingest::new(&[1, 2, 3, 4, 5, 6, 7]);
        let e = ing.on_frame(&rx(joint_frame(3, 1000, 0.5), 0.0));
        assert!(matches!(
            e,
            Event::Sample {
                stream: 2,
                reading: Reading::Angle { .. },
                ..
            }
        ));
        // Unknown identifier, wrong DLC on a known identifier, extended id, NaN angle.
        let unknown = Frame::new(embedded_can_id(0x7ff), &[0; 8]).unwrap();
        assert!(matches!(ing.on_frame(&rx(unknown, 0.1)), Event::Unknown(_)));
        let short = Frame::new(embedded_can_id(0x103), &[0; 3]).unwrap();
        assert!(matches!(ing.on_frame(&rx(short, 0.2)), Event::Malformed(_)));
        let ext = Frame::new(embedded_can::ExtendedId::new(0x103).unwrap(), &[0; 8]).unwrap();
        assert!(matches!(ing.on_frame(&rx(ext, 0.3)), Event::Unknown(_)));
        ing.on_frame(&rx(joint_frame(3, 2000, f64::NAN), 0.4));
        let s = ing.stats();
        assert_eq!(
            (
                s.received,
                s.decoded,
                s.unknown,
                s.malformed,
                s.invalid_angles
            ),
            (5, 2, 2, 1, 1)
        );
        assert_eq!(s.joint_frames[2], 2);
        assert_eq!(ing.joint_samples(2), 1);
    }

    #[test]
    fn a_node_repeating_its_frames_is_named_babbling_and_duplication_names_none() {
        let mut ing = Ingest::new(&[1, 2, 3, 4, 5, 6, 7]);
        let mut t = 0.0;
        // Every joint sends fresh frames; every 20th frame is duplicated on the bus.
        for k in 0..400u32 {
            for node in 1..=7u8 {
                let f = joint_frame(node, 1000 * k, 0.1);
                t += 1e-4;
                ing.on_frame(&rx(f, t));
                if k % 20 == 0 {
                    ing.on_frame(&rx(f, t));
                }
            }
        }
        assert!(ing.stats().repeats[1..=7].iter().all(|&r| r == 20));
        assert_eq!(ing.stats().babbling(), vec![]);
        // Repeats carry nothing new: only the 400 genuine samples per joint are kept.
        assert!((0..7).all(|j| ing.joint_samples(j) == 400));
        // Node 6 repeats its last frame 500 times.
        let last = joint_frame(6, 1000 * 399, 0.1);
        for _ in 0..500 {
            t += 1e-4;
            ing.on_frame(&rx(last, t));
        }
        assert_eq!(ing.stats().babbling(), vec![(NodeId::JOINTS[5], 520)]);
    }

    fn embedded_can_id(id: u16) -> embedded_can::StandardId {
        embedded_can::StandardId::new(id).unwrap()
    }

    #[test]
    fn a_wiring_permutation_maps_nodes_to_joints() {
        let mut ing = Ingest::new(&[7, 6, 5, 4, 3, 2, 1]);
        let e = ing.on_frame(&rx(joint_frame(7, 10, 0.25), 0.0));
        assert!(matches!(
            e,
            Event::Sample {
                stream: 0,
                reading: Reading::Angle { .. },
                ..
            }
        ));
    }

    /// Seven joints at 100 Hz and poses at 50 Hz, each node with its own clock offset and
    /// skew, a node-clock rollover on joint 5, reordered arrival; the aligned result follows
    /// the true signals.
    #[test]
    fn streams_align_through_skewed_clocks_and_rollover() {
        let mut ing = Ingest::new(&[1, 2, 3, 4, 5, 6, 7]);
        let angle = |j: usize, t: f64| 0.3 * (t * (0.5 + 0.1 * j as f64)).sin();
        let skew = |node: usize| (node as f64 - 4.0) * 50e-6; // −150 .. +200 ppm
        let offset_us = |node: usize| {
            if node == 5 {
                (1u64 << 32) - 3_000_000 // rolls over 3 s into the session
            } else {
                node as u64 * 1_234_567
            }
        };
        let node_us = |node: usize, t: f64| {
            ((offset_us(node) as f64 + t * (1.0 - skew(node)) * 1e6).round() as u64 % (1 << 32))
                as u32
        };
        let mut frames = Vec::new();
        for k in 0..1000 {
            let t = k as f64 * 0.01;
            for j in 0..MAX_JOINTS {
                let node = j + 1;
                let f = joint_frame(node as u8, node_us(node, t), angle(j, t));
                // receive latency 0.3 ms + up to 0.4 ms, deterministic
                let lat = 3e-4 + 4e-4 * (((k * 7 + j * 13) % 17) as f64 / 17.0);
                frames.push((t + lat, f));
            }
            if k % 2 == 0 {
                let p = DbcPose {
                    seq: ((k / 2) % 64) as u8,
                    timestamp_us: node_us(8, t),
                    position: [0.1, 0.2, 0.3 + 0.1 * (t * 0.7).sin()],
                    quat: [1.0, 0.0, 0.0, 0.0],
                };
                for (i, page) in p.pages().iter().enumerate() {
                    let f: Frame = Message::EePose(*page).to_frame().unwrap();
                    frames.push((t + 5e-4 + i as f64 * 1e-4, f));
                }
            }
        }
        // Arrival order by receive time: interleaved nodes.
        frames.sort_by(|a, b| a.0.total_cmp(&b.0));
        for (t, f) in &frames {
            ing.on_frame(&rx(*f, *t));
        }
        assert_eq!(ing.stats().poses, 500);
        let (aligned, reports) = ing.align(&AlignParams::default(), 100.0, 0.05, usize::MAX);
        assert_eq!(reports.len(), 8);
        for (node, r) in reports.iter().enumerate() {
            assert_eq!(r.jumps, 0, "{r:?}");
            assert_eq!(r.unmapped, 0, "{r:?}");
            let want = skew(node + 1) * 1e6;
            assert!((r.skew_ppm.unwrap() - want).abs() < 5.0, "{r:?} vs {want}");
        }
        assert!(aligned.samples.len() > 950, "{}", aligned.samples.len());
        assert_eq!(aligned.gaps, 0);
        // Host time origin = first frame ≈ true t + 0.3 ms; the mapped times carry the mean
        // latency, so the signals agree to within ~1 ms of motion (≤ 0.3 rad/s · 1 ms).
        for s in &aligned.samples {
            for (j, q) in s.joints.iter().enumerate() {
                let want = angle(j, s.t);
                assert!(
                    (q - want).abs() < 1e-3,
                    "joint {j} at {}: {q} vs {want}",
                    s.t
                );
            }
        }
    }

    /// Seven joints and the end-effector at 100 Hz for 30 s through [`Ingest`], each node with
    /// its own clock offset and skew; `late(t)` is added to the receive time of every frame sent
    /// at `t`; node `reboot`, if any, goes silent at 15 s and restarts its clock 0.5 s later.
    fn ingest_session(late: impl Fn(f64) -> f64, reboot: Option<usize>) -> Ingest {
        let mut ing = Ingest::new(&[1, 2, 3, 4, 5, 6, 7]);
        let node_us = |node: usize, t: f64| {
            let us = if reboot == Some(node) && t >= 15.5 {
                (t - 15.5) * 1e6 + 500.0
            } else {
                node as f64 * 7_654_321.0 + t * (1.0 + (node as f64 - 4.0) * 30e-6) * 1e6
            };
            (us.round() as u64 % (1 << 32)) as u32
        };
        let mut frames: Vec<(f64, Frame)> = Vec::new();
        for k in 0..3000 {
            for node in 1..=8usize {
                let t = k as f64 * 0.01 + node as f64 * 1e-4;
                if reboot == Some(node) && (15.0..15.5).contains(&t) {
                    continue;
                }
                let rx = t + 3e-4 + late(t);
                if node <= MAX_JOINTS {
                    let f = joint_frame(node as u8, node_us(node, t), (0.3 * t).sin());
                    frames.push((rx, f));
                } else {
                    let p = DbcPose {
                        seq: (k % 64) as u8,
                        timestamp_us: node_us(node, t),
                        position: [0.1, 0.2, 0.3],
                        quat: [1.0, 0.0, 0.0, 0.0],
                    };
                    for page in p.pages() {
                        let f: Frame = Message::EePose(page).to_frame().unwrap();
                        frames.push((rx, f));
                    }
                }
            }
        }
        // One FIFO receive path: arrival order is send order (a stable sort by receive time).
        frames.sort_by(|a, b| a.0.total_cmp(&b.0));
        for (t, f) in &frames {
            ing.on_frame(&rx(*f, *t));
        }
        ing
    }

    #[test]
    fn a_receiver_stall_is_reported_once_and_its_samples_kept() {
        // Every frame sent from 10 s on arrives 400 ms late, until the backlog goes out at 13 s.
        let late = |t: f64| match t {
            t if (10.0..12.6).contains(&t) => 0.4,
            t if (12.6..13.0).contains(&t) => 13.0 - t,
            _ => 0.0,
        };
        let ing = ingest_session(late, None);
        let (aligned, reports) = ing.align(&AlignParams::default(), 100.0, 0.05, usize::MAX);
        let stalls = StallReport::of(&aligned.stalls);
        assert_eq!(stalls.count, 1, "{:?}", aligned.stalls);
        assert!(stalls
            .longest_ms
            .is_some_and(|ms| (ms - 400.0).abs() < 20.0));
        assert!(
            stalls
                .to_string()
                .starts_with("receiver stalled 1 time (longest "),
            "{stalls}"
        );
        for r in &reports {
            assert_eq!((r.jumps, r.unmapped), (0, 0), "{r:?}");
        }
        assert_eq!(aligned.gaps, 0);
    }

    #[test]
    fn one_node_rebooting_is_its_own_jump_not_a_stall() {
        let ing = ingest_session(|_| 0.0, Some(3));
        let (aligned, reports) = ing.align(&AlignParams::default(), 100.0, 0.05, usize::MAX);
        assert!(aligned.stalls.is_empty(), "{:?}", aligned.stalls);
        for r in &reports {
            assert_eq!(r.jumps, usize::from(r.node == "Joint3"), "{r:?}");
        }
    }
}
