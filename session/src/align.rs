//! Time alignment: per-node clock models and resampling onto one time grid.
//!
//! Every IMU node stamps its samples with its own free-running microsecond counter; the host
//! stamps each frame when it receives it. The two differ by an offset, a rate error (skew, up to
//! a few hundred ppm), one-sided receive jitter (queueing only delays), rare outliers (a frame
//! stuck behind a burst), counter rollover, and discontinuities (a node reboots and restarts
//! from zero, or its clock steps).
//!
//! Contract (all pure functions; time is always an argument, no clock is read here):
//! - [`Unwrapper`] turns a wrapping counter into a monotone tick count (a small backward step,
//!   from reordering, is not a wrap).
//! - [`fit_clock`] fits `host = host_ref + (1 + skew)·(node − node_ref)` robustly: a
//!   median-of-halves start, then least squares on the points within a MAD-based band,
//!   iterated; outliers do not move the fit.
//! - [`track_clock`] splits one node's stream (in arrival order) into segments wherever
//!   `host − node` jumps and stays jumped ([`AlignParams::jump_confirm`] consecutive samples
//!   agreeing), fits each segment, and maps any sample to host time through its segment.
//!   Isolated outliers stay in their segment (the robust fit ignores them). A segment with too
//!   few points maps nothing: its samples are excluded, never guessed.
//! - [`track_clocks`] tracks every node of a session and tells the receiver's stalls from the
//!   nodes' own discontinuities. A break that every sending node shows within
//!   [`STALL_WINDOW_S`] of host time, and across which every one of those nodes' counters runs
//!   on (node time neither steps back nor runs ahead of host time by more than the jump
//!   threshold), is a [`Stall`] of the receiver (or the bus, or a sender lagging for all
//!   nodes): frames arrived late, the node clocks did not move. Its segments are joined again
//!   and fitted on the earliest-arriving of them (receive delays are one-sided), so the late
//!   samples map through their node's clock and are kept. Anything else (one node rebooting,
//!   one clock stepping, all nodes power-cycling at once) stays a jump of that node.
//! - [`resample_scalar`] / [`resample_quat`] evaluate a time-sorted stream on a grid: linear
//!   interpolation for angles, slerp (shortest arc) for unit quaternions. A grid point is a gap
//!   (`None`) unless it is bracketed by two samples at most `max_gap` apart (or hits a sample).
//! - [`align`] puts the arm's joint streams and the pose stream on one grid and keeps only the
//!   grid points where every stream has a value; the others are counted as gaps. A kept point
//!   interpolated across readings that were lost (a hole in a stream shorter than `max_gap`)
//!   says how long its stream went unseen there ([`AlignedSample::unseen_s`], [`unseen`]): a
//!   fill is not a measurement, and the jump test judges it as it judges a gap.

use crate::MAX_JOINTS;
use calib_core::median;

/// Tuning of the clock tracker.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AlignParams {
    /// A change of `host − node` larger than this (s) is a clock jump candidate.
    pub jump_threshold_s: f64,
    /// Consecutive samples that must agree on a jump before a new segment starts.
    pub jump_confirm: usize,
    /// Recent in-segment samples whose median `host − node` is the reference.
    pub reference_window: usize,
    /// Fewest points a segment needs to be fitted (and its samples used).
    pub min_segment_points: usize,
    /// Smallest inlier band (s) of the robust fit, for (nearly) noise-free clocks.
    pub inlier_floor_s: f64,
}

impl Default for AlignParams {
    fn default() -> Self {
        AlignParams {
            // A loaded receiver or a lagging sender delays frames by tens of milliseconds in
            // bursts (seen in a TCG guest on a busy host: 4-17 ms RMS): those are one-sided
            // delays, not jumps, and must not split the clock into segments. A real jump or
            // reboot moves the clock by far more and stays moved.
            jump_threshold_s: 0.050,
            jump_confirm: 25,
            reference_window: 50,
            min_segment_points: 20,
            inlier_floor_s: 100e-6,
        }
    }
}

/// Unwraps a counter that rolls over at `modulus` ticks.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Unwrapper {
    modulus: u64,
    last: Option<u64>,
    base: u64,
}

impl Unwrapper {
    /// A counter of `modulus` distinct values (e.g. `1 << 32` for a u32 µs counter).
    pub fn new(modulus: u64) -> Unwrapper {
        Unwrapper {
            modulus: modulus.max(2),
            last: None,
            base: 0,
        }
    }

    /// The unwrapped value of raw counter reading `raw` (taken modulo the modulus).
    ///
    /// A backward step of more than half the range is a rollover; a smaller one (reordering,
    /// or a reboot) is returned as is, for the clock tracker to judge.
    pub fn unwrap(&mut self, raw: u64) -> u64 {
        let raw = raw % self.modulus;
        if let Some(last) = self.last {
            if last > raw && last - raw > self.modulus / 2 {
                self.base += self.modulus;
            } else if raw > last && raw - last > self.modulus / 2 && self.base >= self.modulus {
                // A frame from before the last rollover, arriving late.
                return self.base - self.modulus + raw;
            }
        }
        self.last = Some(raw);
        self.base + raw
    }
}

/// A fitted clock: `host = host_ref + (1 + skew)·(node − node_ref)`, times in seconds.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ClockFit {
    /// Node time of the reference point, the fit's first point (s).
    pub node_ref: f64,
    /// Host time the fit maps `node_ref` to (s).
    pub host_ref: f64,
    /// Rate error of the node clock relative to the host (+1e-4 = node runs 100 ppm slow).
    pub skew: f64,
    /// RMS residual of the inliers (s).
    pub residual_rms: f64,
    /// Points within the residual band: the ones the fit used.
    pub inliers: usize,
    /// Points outside the band, left out of the fit.
    pub outliers: usize,
}

impl ClockFit {
    /// Host time of node time `node` (s).
    pub fn to_host(&self, node: f64) -> f64 {
        self.host_ref + (1.0 + self.skew) * (node - self.node_ref)
    }
}

/// Robust fit of host time against node time over `(node_s, host_s)` points.
///
/// Returns `None` with fewer than 2 points, non-finite input, or no spread in node time.
pub fn fit_clock(points: &[(f64, f64)], params: &AlignParams) -> Option<ClockFit> {
    if points.len() < 2 || points.iter().any(|(n, h)| !n.is_finite() || !h.is_finite()) {
        return None;
    }
    let node_ref = points[0].0;
    let host_ref0 = points[0].1;
    // Centred coordinates keep the arithmetic well conditioned.
    let xs: Vec<f64> = points.iter().map(|p| p.0 - node_ref).collect();
    let ds: Vec<f64> = points
        .iter()
        .map(|p| (p.1 - host_ref0) - (p.0 - node_ref))
        .collect();

    // Start: median of d over each half of the node-time span gives skew and offset.
    let mut order: Vec<usize> = (0..xs.len()).collect();
    order.sort_by(|&a, &b| xs[a].total_cmp(&xs[b]));
    let half = order.len() / 2;
    let (lo, hi) = order.split_at(half.max(1));
    let med = |idx: &[usize], v: &[f64]| median(&mut idx.iter().map(|&i| v[i]).collect::<Vec<_>>());
    let (x_lo, x_hi) = (med(lo, &xs), med(hi, &xs));
    if x_hi - x_lo <= 0.0 {
        return None;
    }
    let mut skew = (med(hi, &ds) - med(lo, &ds)) / (x_hi - x_lo);
    let mut offset = median(
        &mut xs
            .iter()
            .zip(&ds)
            .map(|(x, d)| d - skew * x)
            .collect::<Vec<_>>(),
    );

    let mut inliers = Vec::with_capacity(xs.len());
    let mut rms = 0.0;
    for _ in 0..4 {
        let resid: Vec<f64> = xs
            .iter()
            .zip(&ds)
            .map(|(x, d)| d - offset - skew * x)
            .collect();
        let mad = median(&mut resid.iter().map(|r| r.abs()).collect::<Vec<_>>());
        let band = (4.0 * 1.4826 * mad).max(params.inlier_floor_s);
        inliers.clear();
        inliers.extend((0..xs.len()).filter(|&i| resid[i].abs() <= band));
        if inliers.len() < 2 {
            return None;
        }
        // Least squares of d on x over the inliers.
        let n = inliers.len() as f64;
        let mx = inliers.iter().map(|&i| xs[i]).sum::<f64>() / n;
        let md = inliers.iter().map(|&i| ds[i]).sum::<f64>() / n;
        let sxx: f64 = inliers.iter().map(|&i| (xs[i] - mx).powi(2)).sum();
        let sxd: f64 = inliers.iter().map(|&i| (xs[i] - mx) * (ds[i] - md)).sum();
        if sxx <= 0.0 {
            return None;
        }
        skew = sxd / sxx;
        offset = md - skew * mx;
        rms = (inliers
            .iter()
            .map(|&i| (ds[i] - offset - skew * xs[i]).powi(2))
            .sum::<f64>()
            / n)
            .sqrt();
    }
    Some(ClockFit {
        node_ref,
        host_ref: host_ref0 + offset,
        skew,
        residual_rms: rms,
        inliers: inliers.len(),
        outliers: xs.len() - inliers.len(),
    })
}

/// One stretch of a node's stream with a single clock model.
#[derive(Debug, Clone, PartialEq)]
pub struct ClockSegment {
    /// Range of sample indices (arrival order) in this segment.
    pub start: usize,
    /// One past the segment's last sample index.
    pub end: usize,
    /// `None` when the segment is too short to fit: its samples are excluded.
    pub fit: Option<ClockFit>,
}

/// A node's clock over a whole session: segments separated by detected jumps/reboots.
#[derive(Debug, Clone, PartialEq)]
pub struct ClockTrack {
    /// The segments, in arrival order.
    pub segments: Vec<ClockSegment>,
    /// A sample whose receive time disagrees with its segment's fit by more than this (s) has a
    /// timestamp that cannot be trusted (a glitch too short to be a jump): it maps to nothing.
    pub reject_s: f64,
    /// How late (s) a frame may arrive after its fitted send time and still be used:
    /// [`LATE_LIMIT_S`], or longer across a receiver stall whose lateness the node's counter
    /// vouches for.
    pub late_limit_s: f64,
}

impl ClockTrack {
    /// Number of detected discontinuities (reboots or clock jumps).
    pub fn jumps(&self) -> usize {
        self.segments.len().saturating_sub(1)
    }

    /// Host time of sample `index` with node time `node_s`, or `None` if its segment is unfitted.
    pub fn to_host(&self, index: usize, node_s: f64) -> Option<f64> {
        let seg = self
            .segments
            .iter()
            .find(|s| s.start <= index && index < s.end)?;
        seg.fit.map(|f| f.to_host(node_s))
    }

    /// Maps all samples; `None` for those in unfitted segments and for timestamp glitches: a
    /// frame received more than `reject_s` before its fitted send time (impossible) or more than
    /// `late_limit_s` after it (late frames are normal, a second late is not, unless a stall
    /// explains it).
    pub fn map_all(&self, points: &[(f64, f64)]) -> Vec<Option<f64>> {
        points
            .iter()
            .enumerate()
            .map(|(i, p)| {
                self.to_host(i, p.0)
                    .filter(|&h| (-self.reject_s..=self.late_limit_s).contains(&(p.1 - h)))
            })
            .collect()
    }
}

/// The last `capacity` values in arrival order, kept sorted too, so that their median costs no
/// copy and no sort per point (it is the same value as [`median`] of them).
struct Window {
    capacity: usize,
    arrival: std::collections::VecDeque<f64>,
    sorted: Vec<f64>,
}

impl Window {
    fn new(capacity: usize) -> Self {
        Window {
            capacity,
            arrival: std::collections::VecDeque::with_capacity(capacity),
            sorted: Vec::with_capacity(capacity),
        }
    }

    fn is_empty(&self) -> bool {
        self.arrival.is_empty()
    }

    fn clear(&mut self) {
        self.arrival.clear();
        self.sorted.clear();
    }

    /// Adds `x`, dropping the oldest value when full.
    fn push(&mut self, x: f64) {
        if self.arrival.len() == self.capacity {
            if let Some(old) = self.arrival.pop_front() {
                let at = self.sorted.partition_point(|v| v.total_cmp(&old).is_lt());
                self.sorted.remove(at);
            }
        }
        self.arrival.push_back(x);
        let at = self.sorted.partition_point(|v| v.total_cmp(&x).is_lt());
        self.sorted.insert(at, x);
    }

    fn median(&self) -> f64 {
        let (v, n) = (&self.sorted, self.sorted.len());
        if n % 2 == 1 {
            v[n / 2]
        } else {
            0.5 * (v[n / 2 - 1] + v[n / 2])
        }
    }
}

/// How late (s) a frame may arrive after its fitted send time and still be used.
pub const LATE_LIMIT_S: f64 = 1.0;

/// Splits `points` (`(node_s, host_s)` in arrival order) into clock segments and fits each.
pub fn track_clock(points: &[(f64, f64)], params: &AlignParams) -> ClockTrack {
    let d = |i: usize| points[i].1 - points[i].0;
    let mut boundaries = vec![0usize];
    let mut recent = Window::new(params.reference_window.max(1));
    let mut pending: Vec<usize> = Vec::new();
    for i in 0..points.len() {
        let di = d(i);
        if !di.is_finite() {
            continue;
        }
        if recent.is_empty() {
            recent.push(di);
            continue;
        }
        let reference = recent.median();
        if (di - reference).abs() <= params.jump_threshold_s {
            pending.clear();
            recent.push(di);
            continue;
        }
        pending.push(i);
        // A jump is confirmed when enough off-reference samples agree with each other (with
        // their median): isolated outliers and glitches among them do not reset the count.
        let mut offs: Vec<f64> = pending.iter().map(|&j| d(j)).collect();
        let centre = median(&mut offs);
        let agreeing: Vec<usize> = pending
            .iter()
            .copied()
            .filter(|&j| (d(j) - centre).abs() <= params.jump_threshold_s)
            .collect();
        if agreeing.len() >= params.jump_confirm.max(1) {
            boundaries.push(agreeing[0]);
            recent.clear();
            let keep = agreeing
                .len()
                .saturating_sub(params.reference_window.max(1));
            for &j in &agreeing[keep..] {
                recent.push(d(j));
            }
            pending.clear();
        }
    }
    boundaries.push(points.len());
    let segments = boundaries
        .windows(2)
        .filter(|w| w[1] > w[0])
        .map(|w| {
            let fit = if w[1] - w[0] >= params.min_segment_points {
                fit_clock(&points[w[0]..w[1]], params)
            } else {
                None
            };
            ClockSegment {
                start: w[0],
                end: w[1],
                fit,
            }
        })
        .collect();
    ClockTrack {
        segments,
        reject_s: params.jump_threshold_s,
        late_limit_s: LATE_LIMIT_S,
    }
}

/// Host-time window (s) within which every sending node's clock must break for the break to be
/// the receiver's stall rather than the nodes' own: a few ms, the spread of one burst of late
/// frames (with samples at 100 Hz, the first late frame of each node arrives within 10 ms).
pub const STALL_WINDOW_S: f64 = 0.020;

/// Fewest nodes that must break together for a stall: one node alone is that node's jump.
pub const STALL_MIN_NODES: usize = 2;

/// Samples either side of a break whose median `host − node` gives the break's step (the
/// samples nearest it: a late step is confirmed by more than these).
const STEP_WINDOW: usize = 25;

/// A stall of the receiver (or the bus, or of a sender common to all nodes): every sending
/// node's frames arrived late together, then on time again, while the node clocks ran on.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Stall {
    /// Host time (s) of the first late frame.
    pub at_s: f64,
    /// How late the frames arrived (s): the largest step of `host − node` over the episode.
    pub late_s: f64,
}

/// Every node's clock track over a session, and the receiver stalls found among them.
#[derive(Debug, Clone, PartialEq)]
pub struct SessionClocks {
    /// One track per stream, in the order given; stalls are not counted as their jumps.
    pub tracks: Vec<ClockTrack>,
    /// Stall episodes in host-time order (a late step and the step back on time are one).
    pub stalls: Vec<Stall>,
}

impl SessionClocks {
    /// The longest stall's lateness (s), if any.
    pub fn longest_stall_s(&self) -> Option<f64> {
        self.stalls.iter().map(|s| s.late_s).reduce(f64::max)
    }
}

/// One break of one stream: `segment` starts at sample `start`, received at `host_s`; the
/// sample before it was received at `before_s`.
#[derive(Debug, Clone, Copy)]
struct Break {
    stream: usize,
    segment: usize,
    start: usize,
    before_s: f64,
    host_s: f64,
}

impl Break {
    /// Whether the two breaks happened together: their receive intervals (from the sample
    /// before to the break's first) overlap, give or take [`STALL_WINDOW_S`].
    fn together(&self, other: &Break) -> bool {
        self.before_s - STALL_WINDOW_S <= other.host_s
            && other.before_s - STALL_WINDOW_S <= self.host_s
    }
}

/// Median `host − node` of (up to) [`STEP_WINDOW`] finite points of `points[range]`, taken from
/// its start (`from_end` false) or its end.
fn level(points: &[(f64, f64)], range: std::ops::Range<usize>, from_end: bool) -> Option<f64> {
    let d = |p: &(f64, f64)| p.1 - p.0;
    let mut v: Vec<f64> = if from_end {
        points[range]
            .iter()
            .rev()
            .map(d)
            .filter(|x| x.is_finite())
            .take(STEP_WINDOW)
            .collect()
    } else {
        points[range]
            .iter()
            .map(d)
            .filter(|x| x.is_finite())
            .take(STEP_WINDOW)
            .collect()
    };
    (!v.is_empty()).then(|| median(&mut v))
}

/// The step of `host − node` at the start of segment `k ≥ 1` of `track`: between the medians
/// of the [`STEP_WINDOW`] samples either side of the break.
fn step_at(points: &[(f64, f64)], track: &ClockTrack, k: usize) -> Option<f64> {
    let (prev, seg) = (&track.segments[k - 1], &track.segments[k]);
    let before = level(points, prev.start..prev.end, true)?;
    let after = level(points, seg.start..seg.end, false)?;
    Some(after - before)
}

/// Samples before a break of which one must lead on to it for the counter to run on (a
/// reordered frame may come between).
const RUN_ON_NEIGHBOURS: usize = 3;

/// Whether the node's counter runs on across the break at sample `b` (`b ≥ 1`): from one of the
/// [`RUN_ON_NEIGHBOURS`] samples before it to the break's first, node time does not step back
/// beyond `tolerance` (s), and advances by no more than host time did plus the time the stream
/// has been received (frames lost in a stall are at most that late). A reboot restarts the
/// counter (back, or far forward once unwrapped); late frames only move host time.
fn counter_runs_on(points: &[(f64, f64)], b: usize, tolerance: f64) -> bool {
    let at = points[b];
    let received_s = at.1 - points[0].1;
    points[b.saturating_sub(RUN_ON_NEIGHBOURS)..b]
        .iter()
        .any(|before| {
            let (dn, dh) = (at.0 - before.0, at.1 - before.1);
            dn.is_finite()
                && dh.is_finite()
                && dn >= -tolerance
                && dn <= dh + received_s + tolerance
        })
}

/// Tracks every stream's clock ([`track_clock`]) and finds the breaks that are receiver stalls:
/// every sending stream breaks at the same time (at least [`STALL_MIN_NODES`] of them; the
/// intervals between each break's first sample and the one before overlap, give or take
/// [`STALL_WINDOW_S`]), each with its counter running on. A stream is sending at a break when
/// it has samples received more than the window before and after it. Those breaks are undone:
/// the segments they separated are one again, fitted on the points of the segments that
/// arrived earliest (within the jump threshold), and the track's late limit covers the
/// longest stall. A stall episode opens with a step of `host − node` up and ends with the
/// next step down.
pub fn track_clocks(streams: &[&[(f64, f64)]], params: &AlignParams) -> SessionClocks {
    let mut tracks: Vec<ClockTrack> = streams.iter().map(|s| track_clock(s, params)).collect();
    let spans: Vec<Option<(f64, f64)>> = streams
        .iter()
        .map(|s| {
            let mut hosts = s.iter().map(|p| p.1).filter(|h| h.is_finite());
            let first = hosts.next()?;
            Some(hosts.fold((first, first), |(lo, hi), h| (lo.min(h), hi.max(h))))
        })
        .collect();
    let mut breaks: Vec<Break> = tracks
        .iter()
        .enumerate()
        .flat_map(|(i, t)| {
            t.segments
                .iter()
                .enumerate()
                .skip(1)
                .map(move |(k, seg)| Break {
                    stream: i,
                    segment: k,
                    start: seg.start,
                    before_s: streams[i][seg.start - 1].1,
                    host_s: streams[i][seg.start].1,
                })
        })
        .filter(|b| b.host_s.is_finite() && b.before_s.is_finite())
        .collect();
    breaks.sort_by(|a, b| a.host_s.total_cmp(&b.host_s));

    // Clusters of breaks that are stalls: (host time, step of host − node per stream).
    let mut used = vec![false; breaks.len()];
    let mut stall_breaks: Vec<Vec<Break>> = Vec::new();
    let mut steps: Vec<(f64, f64)> = Vec::new();
    for first in 0..breaks.len() {
        if used[first] {
            continue;
        }
        let reference = breaks[first];
        let h = reference.host_s;
        let sending: Vec<usize> = (0..streams.len())
            .filter(|&j| {
                spans[j].is_some_and(|(lo, hi)| {
                    lo < reference.before_s - STALL_WINDOW_S && hi > h + STALL_WINDOW_S
                })
            })
            .collect();
        if sending.len() < STALL_MIN_NODES {
            continue;
        }
        // For each sending stream, its first unused break at the same time.
        let members: Option<Vec<usize>> = sending
            .iter()
            .map(|&j| {
                (0..breaks.len())
                    .find(|&k| !used[k] && breaks[k].stream == j && breaks[k].together(&reference))
            })
            .collect();
        let Some(members) = members else { continue };
        let runs_on = members.iter().all(|&k| {
            let b = breaks[k];
            counter_runs_on(streams[b.stream], b.start, params.jump_threshold_s)
        });
        if !runs_on {
            continue;
        }
        let mut node_steps: Vec<f64> = members
            .iter()
            .filter_map(|&k| {
                let b = breaks[k];
                step_at(streams[b.stream], &tracks[b.stream], b.segment)
            })
            .collect();
        if node_steps.is_empty() {
            continue;
        }
        for &k in &members {
            used[k] = true;
        }
        steps.push((h, median(&mut node_steps)));
        stall_breaks.push(members.iter().map(|&k| breaks[k]).collect());
    }

    // Episodes: steps up (later still, while one is open) until a step down; a step down with
    // no episode open ends a stall that began before the session.
    let mut stalls: Vec<Stall> = Vec::new();
    let mut lateness: Option<f64> = None;
    for &(h, step) in &steps {
        match (lateness, stalls.last_mut()) {
            (Some(late), Some(last)) if step > 0.0 => {
                last.late_s = last.late_s.max(late + step);
                lateness = Some(late + step);
            }
            (Some(_), Some(_)) => lateness = None,
            _ => {
                stalls.push(Stall {
                    at_s: h,
                    late_s: step.abs(),
                });
                lateness = (step > 0.0).then_some(step);
            }
        }
    }
    let late_limit_s = stalls
        .iter()
        .map(|s| s.late_s + params.jump_threshold_s)
        .fold(LATE_LIMIT_S, f64::max);

    // Undo the stall breaks, stream by stream.
    for (i, track) in tracks.iter_mut().enumerate() {
        let mut joined_at: Vec<usize> = stall_breaks
            .iter()
            .flatten()
            .filter(|b| b.stream == i)
            .map(|b| b.segment)
            .collect();
        if joined_at.is_empty() {
            continue;
        }
        joined_at.sort_unstable();
        *track = join_segments(streams[i], track, &joined_at, params);
        track.late_limit_s = late_limit_s;
    }
    SessionClocks { tracks, stalls }
}

/// `track` with the breaks before the segments numbered in `joined_at` (sorted, ≥ 1) undone:
/// each run of joined segments is one, fitted on the points of those of its segments whose
/// median `host − node` is within the jump threshold of the lowest (the others arrived late).
fn join_segments(
    points: &[(f64, f64)],
    track: &ClockTrack,
    joined_at: &[usize],
    params: &AlignParams,
) -> ClockTrack {
    let mut groups: Vec<Vec<usize>> = Vec::new();
    for k in 0..track.segments.len() {
        match groups.last_mut() {
            Some(g) if joined_at.binary_search(&k).is_ok() => g.push(k),
            _ => groups.push(vec![k]),
        }
    }
    let segments = groups
        .iter()
        .map(|g| {
            if g.len() == 1 {
                return track.segments[g[0]].clone();
            }
            let (start, end) = (
                track.segments[g[0]].start,
                track.segments[g[g.len() - 1]].end,
            );
            let levels: Vec<(usize, f64)> = g
                .iter()
                .filter_map(|&k| {
                    let s = &track.segments[k];
                    let mut d: Vec<f64> = points[s.start..s.end]
                        .iter()
                        .map(|p| p.1 - p.0)
                        .filter(|d| d.is_finite())
                        .collect();
                    (!d.is_empty()).then(|| (k, median(&mut d)))
                })
                .collect();
            let fit = levels.iter().map(|l| l.1).reduce(f64::min).and_then(|low| {
                let on_time: Vec<(f64, f64)> = levels
                    .iter()
                    .filter(|l| l.1 - low <= params.jump_threshold_s)
                    .flat_map(|&(k, _)| {
                        let s = &track.segments[k];
                        points[s.start..s.end].iter().copied()
                    })
                    .collect();
                if on_time.len() >= params.min_segment_points {
                    fit_clock(&on_time, params)
                } else {
                    None
                }
            });
            ClockSegment { start, end, fit }
        })
        .collect();
    ClockTrack {
        segments,
        reject_s: track.reject_s,
        late_limit_s: track.late_limit_s,
    }
}

/// Index of the last sample with time ≤ `t` in a sorted stream, by binary search.
fn bracket<T>(stream: &[(f64, T)], t: f64) -> Option<usize> {
    let after = stream.partition_point(|s| s.0 <= t);
    after.checked_sub(1)
}

/// Bracketing pair for grid time `t`: `(i, i + 1, fraction)` or an exact hit `(i, i, 0)`.
fn interval<T>(stream: &[(f64, T)], t: f64, max_gap: f64) -> Option<(usize, usize, f64)> {
    let i = bracket(stream, t)?;
    if stream[i].0 == t {
        return Some((i, i, 0.0));
    }
    let j = i + 1;
    let (t0, t1) = (stream[i].0, stream.get(j)?.0);
    if t1 - t0 > max_gap {
        return None;
    }
    Some((i, j, (t - t0) / (t1 - t0)))
}

/// Linear interpolation of a time-sorted scalar stream at each grid time; `None` in gaps.
pub fn resample_scalar(stream: &[(f64, f64)], grid: &[f64], max_gap: f64) -> Vec<Option<f64>> {
    grid.iter()
        .map(|&t| {
            let (i, j, u) = interval(stream, t, max_gap)?;
            Some(stream[i].1 + u * (stream[j].1 - stream[i].1))
        })
        .collect()
}

/// A unit quaternion `[w, x, y, z]`.
pub type Quat = [f64; 4];

/// Spherical linear interpolation from `a` to `b` by `u ∈ [0, 1]`, along the shortest arc.
pub fn slerp(a: Quat, b: Quat, u: f64) -> Quat {
    let mut dot: f64 = a.iter().zip(&b).map(|(x, y)| x * y).sum();
    let b = if dot < 0.0 {
        dot = -dot;
        b.map(|x| -x)
    } else {
        b
    };
    let (wa, wb) = if dot > 0.9995 {
        (1.0 - u, u)
    } else {
        let theta = dot.min(1.0).acos();
        let s = theta.sin();
        (((1.0 - u) * theta).sin() / s, (u * theta).sin() / s)
    };
    let q: Vec<f64> = a.iter().zip(&b).map(|(x, y)| wa * x + wb * y).collect();
    let norm = q.iter().map(|x| x * x).sum::<f64>().sqrt();
    [q[0] / norm, q[1] / norm, q[2] / norm, q[3] / norm]
}

/// A pose: position (m) and unit quaternion `[w, x, y, z]`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose {
    /// Position (m).
    pub position: [f64; 3],
    /// Orientation, unit quaternion `[w, x, y, z]`.
    pub orientation: Quat,
}

/// Interpolation of a time-sorted pose stream: linear position, slerp orientation.
pub fn resample_pose(stream: &[(f64, Pose)], grid: &[f64], max_gap: f64) -> Vec<Option<Pose>> {
    grid.iter()
        .map(|&t| {
            let (i, j, u) = interval(stream, t, max_gap)?;
            let (a, b) = (&stream[i].1, &stream[j].1);
            let mut position = [0.0; 3];
            for (k, p) in position.iter_mut().enumerate() {
                *p = a.position[k] + u * (b.position[k] - a.position[k]);
            }
            Some(Pose {
                position,
                orientation: slerp(a.orientation, b.orientation, u),
            })
        })
        .collect()
}

/// Orientation-only variant of [`resample_pose`].
pub fn resample_quat(stream: &[(f64, Quat)], grid: &[f64], max_gap: f64) -> Vec<Option<Quat>> {
    grid.iter()
        .map(|&t| {
            let (i, j, u) = interval(stream, t, max_gap)?;
            Some(slerp(stream[i].1, stream[j].1, u))
        })
        .collect()
}

/// Sorts a stream by time and drops exact duplicate times (keeping the first) and non-finite
/// times.
pub fn sort_stream<T>(stream: &mut Vec<(f64, T)>) {
    stream.retain(|s| s.0.is_finite());
    stream.sort_by(|a, b| a.0.total_cmp(&b.0));
    stream.dedup_by(|b, a| a.0 == b.0);
}

/// The grid `start, start + 1/hz, …` up to and including `end`, at most `max_points` of it
/// (from `start`): its size is bounded by the caller's rules, never by the times it is given.
pub fn grid(start: f64, end: f64, hz: f64, max_points: usize) -> Vec<f64> {
    if !(start.is_finite() && end.is_finite() && hz.is_finite() && hz > 0.0) || end < start {
        return Vec::new();
    }
    // Saturating: a span of 1e300 s is as many points as fit, then cut to `max_points`.
    let n = (((end - start) * hz + 1e-9).floor() as usize).saturating_add(1);
    (0..n.min(max_points))
        .map(|k| start + k as f64 / hz)
        .collect()
}

/// One aligned sample: every joint angle (rad) and the end-effector pose at time `t` (host s).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AlignedSample {
    /// Time of the grid point (host s).
    pub t: f64,
    /// Joint angles (rad), joint 1 first.
    pub joints: [f64; MAX_JOINTS],
    /// Each joint node's gyro about its joint's axis (rad/s; [`crate::ingest::Ingest::with_joint_gyros`]);
    /// NaN where not kept (by default, and a CSV) or not interpolated at `t`.
    pub rates: [f64; MAX_JOINTS],
    /// Measured end-effector pose at `t`.
    pub pose: Pose,
    /// How long the stream with the longest hole around `t` went unseen beyond its usual
    /// interval (s): 0 when every stream was interpolated between consecutive readings, 0.03 s
    /// across three lost readings at 100 Hz. Samples that do not come from [`align`] are 0.
    pub unseen_s: f64,
}

impl AlignedSample {
    /// The sample at `t` of calib-core's `sample` (its rotation as a unit quaternion).
    pub fn of(t: f64, sample: &calib_core::Sample<MAX_JOINTS>) -> AlignedSample {
        let q = nalgebra::UnitQuaternion::from_matrix(&sample.pose.r);
        AlignedSample {
            t,
            joints: sample.joints,
            rates: [f64::NAN; MAX_JOINTS],
            pose: Pose {
                position: sample.pose.p.into(),
                orientation: [q.w, q.i, q.j, q.k],
            },
            unseen_s: 0.0,
        }
    }

    /// As calib-core takes it (quaternion normalised): the inverse of [`AlignedSample::of`].
    pub fn sample(&self) -> calib_core::Sample<MAX_JOINTS> {
        let [w, x, y, z] = self.pose.orientation;
        let q = nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(w, x, y, z));
        calib_core::Sample {
            joints: self.joints,
            pose: calib_core::Frame {
                r: q.to_rotation_matrix().into_inner(),
                p: nalgebra::Vector3::from(self.pose.position),
            },
        }
    }
}

/// Per grid time, how long a time-sorted stream went unseen around it beyond its usual
/// interval (its median): a grid time between two readings `h` apart, where `h` is more than
/// 1.5 usual intervals `p`, is `h − p` unseen (0.03 s across three lost readings at 100 Hz);
/// everywhere else 0. Whether the point is interpolated at all is [`resample_scalar`]'s call
/// (`max_gap`); this says what the interpolation bridged.
pub fn unseen(times: &[f64], grid: &[f64]) -> Vec<f64> {
    let mut out = vec![0.0; grid.len()];
    let mut steps: Vec<f64> = times.windows(2).map(|w| w[1] - w[0]).collect();
    let usual = median(&mut steps);
    if usual.is_nan() || usual <= 0.0 {
        return out;
    }
    for w in times.windows(2) {
        let (t0, t1) = (w[0], w[1]);
        if t1 - t0 <= 1.5 * usual {
            continue;
        }
        let from = grid.partition_point(|&t| t <= t0);
        let to = grid.partition_point(|&t| t < t1);
        for u in &mut out[from..to.max(from)] {
            *u = u.max(t1 - t0 - usual);
        }
    }
    out
}

/// The result of [`align`].
#[derive(Debug, Clone, PartialEq)]
pub struct Aligned {
    /// The aligned samples, time-ordered.
    pub samples: Vec<AlignedSample>,
    /// Grid points covered by all streams' time spans.
    pub grid_points: usize,
    /// Of those, points excluded because some stream had a gap there.
    pub gaps: usize,
    /// Receiver stalls found while mapping the streams to host time ([`track_clocks`]; empty
    /// from [`align`] itself, which gets host times).
    pub stalls: Vec<Stall>,
}

/// Resamples the joint streams of the arm (`joints`, at most [`MAX_JOINTS`]; the samples'
/// readings past them are 0, [`crate::arm`]) and the pose stream (host time, sorted) onto one
/// grid at `hz` over the span common to all streams, at most `max_points` of it from the
/// span's start (the session's rules bound it: [`crate::WindowRules::max_samples`]); grid
/// points where any stream has a gap are excluded.
pub fn align(
    joints: &[Vec<(f64, f64)>],
    rates: &[Vec<(f64, f64)>; MAX_JOINTS],
    pose: &[(f64, Pose)],
    hz: f64,
    max_gap: f64,
    max_points: usize,
) -> Aligned {
    let span = |first: Option<f64>, last: Option<f64>| first.zip(last);
    let mut spans: Vec<Option<(f64, f64)>> = joints
        .iter()
        .map(|s| span(s.first().map(|x| x.0), s.last().map(|x| x.0)))
        .collect();
    spans.push(span(pose.first().map(|x| x.0), pose.last().map(|x| x.0)));
    let Some(spans) = spans.into_iter().collect::<Option<Vec<_>>>() else {
        return Aligned {
            samples: Vec::new(),
            grid_points: 0,
            gaps: 0,
            stalls: Vec::new(),
        };
    };
    let start = spans.iter().map(|s| s.0).fold(f64::NEG_INFINITY, f64::max);
    let end = spans.iter().map(|s| s.1).fold(f64::INFINITY, f64::min);
    // Start on a multiple of the grid period so that grids of different sessions line up.
    let start = (start * hz).ceil() / hz;
    let g = grid(start, end, hz, max_points);
    let per_joint: Vec<Vec<Option<f64>>> = joints
        .iter()
        .map(|s| resample_scalar(s, &g, max_gap))
        .collect();
    let per_rate: Vec<Vec<Option<f64>>> = rates
        .iter()
        .map(|s| resample_scalar(s, &g, max_gap))
        .collect();
    let poses = resample_pose(pose, &g, max_gap);
    let pose_times: Vec<f64> = pose.iter().map(|s| s.0).collect();
    let mut unseen_s = unseen(&pose_times, &g);
    for s in joints {
        let times: Vec<f64> = s.iter().map(|s| s.0).collect();
        for (u, v) in unseen_s.iter_mut().zip(unseen(&times, &g)) {
            *u = u.max(v);
        }
    }
    let mut samples = Vec::with_capacity(g.len());
    for (k, &t) in g.iter().enumerate() {
        let Some(p) = poses[k] else { continue };
        let mut q = [0.0; MAX_JOINTS];
        if per_joint
            .iter()
            .zip(q.iter_mut())
            .all(|(col, out)| col[k].map(|v| *out = v).is_some())
        {
            samples.push(AlignedSample {
                t,
                joints: q,
                rates: std::array::from_fn(|j| per_rate[j][k].unwrap_or(f64::NAN)),
                pose: p,
                unseen_s: unseen_s[k],
            });
        }
    }
    Aligned {
        grid_points: g.len(),
        gaps: g.len() - samples.len(),
        samples,
        stalls: Vec::new(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// SplitMix64: a small deterministic generator for the synthetic clocks.
    struct Rng(u64);
    impl Rng {
        fn next_u64(&mut self) -> u64 {
            self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = self.0;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            z ^ (z >> 31)
        }
        fn uniform(&mut self) -> f64 {
            (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
        }
        /// Exponential with the given mean: one-sided receive latency.
        fn exp(&mut self, mean: f64) -> f64 {
            -mean * (1.0 - self.uniform()).ln()
        }
    }

    /// A synthetic node: true host send times every `period`, node clock with `skew` and
    /// `offset`, receive latency 200 µs + Exp(`jitter`), and a fraction of `outlier` frames
    /// delayed by 20–80 ms. Returns `(node_s, host_rx_s)` and the true send host times.
    fn synth(
        seed: u64,
        n: usize,
        period: f64,
        skew: f64,
        offset: f64,
        jitter: f64,
        outlier: f64,
    ) -> (Vec<(f64, f64)>, Vec<f64>) {
        let mut rng = Rng(seed);
        let mut pts = Vec::new();
        let mut truth = Vec::new();
        for k in 0..n {
            let host_send = 5.0 + k as f64 * period;
            let node = offset + host_send / (1.0 + skew);
            let mut rx = host_send + 200e-6 + rng.exp(jitter);
            if rng.uniform() < outlier {
                rx += 0.020 + 0.060 * rng.uniform();
            }
            pts.push((node, rx));
            truth.push(host_send);
        }
        (pts, truth)
    }

    /// The running window's median is the median of its last values, duplicates included.
    #[test]
    fn the_running_median_is_the_median_of_the_window() {
        let mut w = Window::new(7);
        let mut all = Vec::new();
        let mut x = 0.3_f64;
        for i in 0..500 {
            x = (x * 3.7 + 0.1).fract();
            let v = if i % 5 == 0 {
                0.25
            } else {
                (x * 20.0).round() / 20.0 - 0.5
            };
            w.push(v);
            all.push(v);
            let mut last: Vec<f64> = all[all.len().saturating_sub(7)..].to_vec();
            assert_eq!(
                w.median().to_bits(),
                median(&mut last).to_bits(),
                "after {i}"
            );
        }
        w.clear();
        assert!(w.is_empty());
    }

    #[test]
    fn unwrapper_handles_rollover_and_small_reordering() {
        let mut u = Unwrapper::new(1 << 16);
        assert_eq!(u.unwrap(65_000), 65_000);
        assert_eq!(u.unwrap(65_500), 65_500);
        assert_eq!(u.unwrap(100), 65_536 + 100); // rolled over
        assert_eq!(u.unwrap(65_530), 65_530); // a late frame from before the rollover
        assert_eq!(u.unwrap(200), 65_536 + 200);
        assert_eq!(u.unwrap(150), 65_536 + 150); // reordered: a small step back is no wrap
        for k in 1..=10u64 {
            // ten more rollovers, 1000 ticks a step
            let _ = u.unwrap((200 + k * 1000) % 65_536);
        }
        assert_eq!(u.unwrap(11_200), 65_536 + 11_200);
    }

    #[test]
    fn unwrapped_u32_microseconds_span_many_rollovers() {
        let m = 1u64 << 32;
        let mut u = Unwrapper::new(m);
        let mut t = m - 5_000_000; // 5 s before the first wrap
        for _ in 0..3 * 4300 {
            // 3 × 4300 s in 1 s steps: three rollovers
            assert_eq!(u.unwrap(t % m), t);
            t += 1_000_000;
        }
    }

    #[test]
    fn fit_recovers_skew_and_offset_under_jitter_and_outliers() {
        for (seed, skew) in [(1, 200e-6), (2, -200e-6), (3, 37e-6), (4, 0.0)] {
            let (pts, truth) = synth(seed, 6000, 0.01, skew, 1234.5, 300e-6, 0.02);
            let fit = fit_clock(&pts, &AlignParams::default()).unwrap();
            assert!(
                (fit.skew - skew).abs() < 2e-6,
                "skew {} vs {skew}",
                fit.skew
            );
            assert!(fit.outliers >= 100, "outliers {}", fit.outliers);
            // Mapped times follow the true send times up to the mean latency (≈ 0.5 ms),
            // the same for every node on the bus: the spread is what matters.
            let errs: Vec<f64> = pts
                .iter()
                .zip(&truth)
                .map(|(p, t)| fit.to_host(p.0) - t)
                .collect();
            let mean = errs.iter().sum::<f64>() / errs.len() as f64;
            let worst = errs.iter().map(|e| (e - mean).abs()).fold(0.0, f64::max);
            assert!(mean > 0.0 && mean < 1e-3, "bias {mean}");
            assert!(worst < 50e-6, "worst deviation {worst}");
        }
    }

    #[test]
    fn plain_least_squares_would_be_pulled_by_the_outliers() {
        // Guards the test above: the synthetic outliers are strong enough to matter.
        let (pts, _) = synth(9, 3000, 0.01, 150e-6, 0.0, 300e-6, 0.05);
        let n = pts.len() as f64;
        let mx = pts.iter().map(|p| p.0).sum::<f64>() / n;
        let my = pts.iter().map(|p| p.1).sum::<f64>() / n;
        let sxx: f64 = pts.iter().map(|p| (p.0 - mx).powi(2)).sum();
        let sxy: f64 = pts.iter().map(|p| (p.0 - mx) * (p.1 - my)).sum();
        let ls_resid_max = pts
            .iter()
            .map(|p| (p.1 - my - sxy / sxx * (p.0 - mx)).abs())
            .fold(0.0, f64::max);
        let robust = fit_clock(&pts, &AlignParams::default()).unwrap();
        assert!(robust.residual_rms < 1e-3);
        assert!(ls_resid_max > 0.02);
        assert!((robust.skew - 150e-6).abs() < 3e-6);
    }

    #[test]
    fn fit_rejects_degenerate_input() {
        let p = AlignParams::default();
        assert_eq!(fit_clock(&[], &p), None);
        assert_eq!(fit_clock(&[(1.0, 2.0)], &p), None);
        assert_eq!(fit_clock(&[(1.0, 2.0), (1.0, 3.0), (1.0, 4.0)], &p), None);
        assert_eq!(fit_clock(&[(1.0, 2.0), (f64::NAN, 3.0)], &p), None);
        let exact: Vec<(f64, f64)> = (0..100).map(|k| (k as f64, 10.0 + k as f64)).collect();
        let f = fit_clock(&exact, &p).unwrap();
        assert!(f.skew.abs() < 1e-12 && (f.to_host(50.0) - 60.0).abs() < 1e-9);
        assert_eq!(f.outliers, 0);
    }

    #[test]
    fn a_reboot_starts_a_new_segment_and_both_are_mapped() {
        // 30 s of a node, then it reboots (its clock restarts at 0) and runs 30 s more.
        let (mut pts, mut truth) = synth(11, 3000, 0.01, 120e-6, 700.0, 200e-6, 0.01);
        let (b, bt) = synth(12, 3000, 0.01, 120e-6, 0.0, 200e-6, 0.01);
        // Shift the second part in host time to follow the first, with a 0.5 s boot gap.
        let shift = 30.5;
        pts.extend(b.iter().map(|&(n, h)| (n, h + shift)));
        truth.extend(bt.iter().map(|t| t + shift));
        let track = track_clock(&pts, &AlignParams::default());
        assert_eq!(track.jumps(), 1, "{:?}", track.segments);
        assert_eq!(track.segments[1].start, 3000);
        let mapped = track.map_all(&pts);
        for (k, (m, t)) in mapped.iter().zip(&truth).enumerate() {
            let e = m.unwrap() - t;
            assert!(e > 0.0 && e < 1.5e-3, "sample {k}: error {e}");
        }
    }

    #[test]
    fn a_clock_step_is_a_jump_but_isolated_outliers_are_not() {
        let (mut pts, _) = synth(21, 4000, 0.01, -180e-6, 50.0, 300e-6, 0.03);
        // The node's clock steps forward by 80 ms at sample 2500.
        for p in &mut pts[2500..] {
            p.0 += 0.080;
        }
        let track = track_clock(&pts, &AlignParams::default());
        assert_eq!(track.jumps(), 1, "{:?}", track.segments);
        let boundary = track.segments[1].start;
        assert!((2500..2505).contains(&boundary), "boundary {boundary}");
        for s in &track.segments {
            let f = s.fit.unwrap();
            assert!((f.skew + 180e-6).abs() < 5e-6, "skew {}", f.skew);
        }

        let (clean, _) = synth(22, 4000, 0.01, 90e-6, 50.0, 300e-6, 0.05);
        assert_eq!(track_clock(&clean, &AlignParams::default()).jumps(), 0);
    }

    /// Per node: `(node_s, host_rx_s)` points in arrival order, and their true send times.
    type Session = (Vec<Vec<(f64, f64)>>, Vec<Vec<f64>>);

    /// Eight nodes (own skew, offset and phase) sampling every 10 ms from host time 5 s, with
    /// `late(node, host_send)` added to every receive time.
    fn session(n: usize, late: impl Fn(usize, f64) -> f64) -> Session {
        let mut rng = Rng(77);
        let mut streams = Vec::new();
        let mut truths = Vec::new();
        for node in 0..8 {
            let skew = (node as f64 - 3.5) * 40e-6;
            let offset = 100.0 + 517.0 * node as f64;
            // A FIFO receive path: a frame is never received before the one sent ahead of it.
            let mut last_rx = f64::NEG_INFINITY;
            let s: Vec<(f64, f64, f64)> = (0..n)
                .map(|k| {
                    let send = 5.0 + k as f64 * 0.01 + node as f64 * 1.1e-3;
                    let rx = send + 200e-6 + rng.exp(200e-6) + late(node, send);
                    last_rx = last_rx.max(rx);
                    (offset + send / (1.0 + skew), last_rx, send)
                })
                .collect();
            streams.push(s.iter().map(|p| (p.0, p.1)).collect());
            truths.push(s.iter().map(|p| p.2).collect());
        }
        (streams, truths)
    }

    /// A sender lagging `lag` s for every node from host time `from` and catching up in one
    /// burst at `to`: frames are `lag` late, then received together at `to`, then on time.
    fn lagging(from: f64, to: f64, lag: f64) -> impl Fn(f64) -> f64 {
        move |send| {
            if send < from || send >= to {
                0.0
            } else if send < to - lag {
                lag
            } else {
                to - send
            }
        }
    }

    fn refs(streams: &[Vec<(f64, f64)>]) -> Vec<&[(f64, f64)]> {
        streams.iter().map(Vec::as_slice).collect()
    }

    #[test]
    fn every_node_late_together_is_one_stall_and_every_sample_is_kept_on_its_node_clock() {
        let lag = lagging(20.0, 23.0, 0.3);
        let (streams, truths) = session(4000, |_, t| lag(t));
        let p = AlignParams::default();
        // Node by node, the lag reads as two jumps (late, then back on time); all nodes
        // together, it is one stall.
        for s in &streams {
            assert_eq!(track_clock(s, &p).jumps(), 2);
        }
        let clocks = track_clocks(&refs(&streams), &p);
        assert_eq!(clocks.stalls.len(), 1, "{:?}", clocks.stalls);
        let stall = clocks.stalls[0];
        // Its first late frame arrived 0.3 s after the lag began.
        assert!((stall.at_s - 20.3).abs() < 0.02, "{stall:?}");
        assert!((stall.late_s - 0.3).abs() < 0.02, "{stall:?}");
        assert_eq!(clocks.longest_stall_s(), Some(stall.late_s));
        for ((track, s), truth) in clocks.tracks.iter().zip(&streams).zip(&truths) {
            assert_eq!(track.jumps(), 0, "{:?}", track.segments);
            for (k, (m, t)) in track.map_all(s).iter().zip(truth).enumerate() {
                let e = m.map(|m| m - t);
                assert!(
                    e.is_some_and(|e| e > 0.0 && e < 1.5e-3),
                    "sample {k}: {e:?}"
                );
            }
        }
    }

    #[test]
    fn a_stall_longer_than_the_late_limit_keeps_its_samples_too() {
        let lag = lagging(20.0, 26.0, 2.5);
        let (streams, _) = session(4000, |_, t| lag(t));
        let clocks = track_clocks(&refs(&streams), &AlignParams::default());
        assert_eq!(clocks.stalls.len(), 1, "{:?}", clocks.stalls);
        assert!(
            (clocks.stalls[0].late_s - 2.5).abs() < 0.02,
            "{:?}",
            clocks.stalls
        );
        for (track, s) in clocks.tracks.iter().zip(&streams) {
            assert_eq!(track.jumps(), 0);
            assert!(track.map_all(s).iter().all(Option::is_some));
        }
    }

    /// Node `node`'s clock restarts from (about) zero at host time `at`, after `down` s silent.
    fn reboot(streams: &mut [Vec<(f64, f64)>], node: usize, at: f64, down: f64) {
        let s = &mut streams[node];
        let restart = s.iter().find(|p| p.1 >= at + down).map(|p| p.0);
        let first_after = restart.expect("samples after the reboot");
        s.retain(|p| p.1 < at || p.1 >= at + down);
        for p in s.iter_mut().filter(|p| p.1 >= at + down) {
            p.0 -= first_after - 0.0005;
        }
    }

    #[test]
    fn one_node_rebooting_is_that_nodes_jump_stall_or_not() {
        let p = AlignParams::default();
        for stalled in [false, true] {
            let lag = lagging(12.0, 14.0, 0.3);
            let (mut streams, _) = session(4000, |_, t| if stalled { lag(t) } else { 0.0 });
            reboot(&mut streams, 2, 30.0, 0.5);
            let clocks = track_clocks(&refs(&streams), &p);
            assert_eq!(
                clocks.stalls.len(),
                usize::from(stalled),
                "{:?}",
                clocks.stalls
            );
            for (node, track) in clocks.tracks.iter().enumerate() {
                let segments = &track.segments;
                assert_eq!(
                    track.jumps(),
                    usize::from(node == 2),
                    "node {node}: {segments:?}"
                );
            }
        }
    }

    #[test]
    fn every_node_rebooting_at_once_is_no_stall() {
        let (mut streams, _) = session(4000, |_, _| 0.0);
        for node in 0..8 {
            reboot(&mut streams, node, 30.0, 0.5);
        }
        let clocks = track_clocks(&refs(&streams), &AlignParams::default());
        assert!(clocks.stalls.is_empty(), "{:?}", clocks.stalls);
        assert!(clocks.tracks.iter().all(|t| t.jumps() == 1));
    }

    #[test]
    fn a_lag_that_spares_one_sending_node_is_no_stall() {
        let lag = lagging(20.0, 23.0, 0.3);
        let (streams, _) = session(4000, |node, t| if node == 5 { 0.0 } else { lag(t) });
        let clocks = track_clocks(&refs(&streams), &AlignParams::default());
        assert!(clocks.stalls.is_empty(), "{:?}", clocks.stalls);
        for (node, track) in clocks.tracks.iter().enumerate() {
            assert_eq!(track.jumps(), if node == 5 { 0 } else { 2 }, "node {node}");
        }
    }

    #[test]
    fn a_too_short_glitch_maps_nothing() {
        let (mut pts, _) = synth(31, 1000, 0.01, 0.0, 0.0, 100e-6, 0.0);
        // 10 samples (fewer than min_segment_points) with a stepped clock, then back.
        for p in &mut pts[500..510] {
            p.0 -= 5.0;
        }
        let track = track_clock(&pts, &AlignParams::default());
        // Shorter than `jump_confirm`: a glitch, not a jump; its samples map to nothing.
        assert_eq!(track.jumps(), 0);
        let mapped = track.map_all(&pts);
        assert!(mapped[500..510].iter().all(Option::is_none));
        assert!(mapped[..500]
            .iter()
            .chain(&mapped[510..])
            .all(Option::is_some));
    }

    #[test]
    fn two_skewed_nodes_align_to_within_the_jitter() {
        // Two nodes sampling the same sine at 100 Hz, clocks ±200 ppm, different offsets,
        // receive jitter and outliers. After mapping and resampling they agree.
        let signal = |t: f64| (2.0 * std::f64::consts::PI * 0.5 * t).sin();
        let mut streams = Vec::new();
        for (seed, skew, off) in [(41, 200e-6, 10.0), (42, -200e-6, 3000.0)] {
            let (pts, truth) = synth(seed, 6000, 0.01, skew, off, 400e-6, 0.02);
            let track = track_clock(&pts, &AlignParams::default());
            assert_eq!(track.jumps(), 0);
            let mapped = track.map_all(&pts);
            let mut s: Vec<(f64, f64)> = mapped
                .iter()
                .zip(&truth)
                .map(|(m, t)| (m.unwrap(), signal(*t)))
                .collect();
            sort_stream(&mut s);
            streams.push(s);
        }
        let g = grid(6.0, 64.0, 100.0, usize::MAX);
        let a = resample_scalar(&streams[0], &g, 0.05);
        let b = resample_scalar(&streams[1], &g, 0.05);
        let worst = a
            .iter()
            .zip(&b)
            .map(|(x, y)| (x.unwrap() - y.unwrap()).abs())
            .fold(0.0, f64::max);
        // Signal slope ≤ π rad/s: 50 µs of misalignment is ≤ 1.6e-4.
        assert!(worst < 2e-4, "worst disagreement {worst}");
        // Without the skew correction the nodes drift apart by 24 ms over 60 s.
        let drift = 400e-6 * 60.0;
        assert!(drift * std::f64::consts::PI > 10.0 * worst);
    }

    #[test]
    fn linear_interpolation_and_gaps() {
        let s = vec![
            (0.0, 0.0),
            (1.0, 10.0),
            (2.0, 20.0),
            (5.0, 50.0),
            (5.04, 50.4),
        ];
        let g = [-0.5, 0.0, 0.25, 1.0, 1.5, 3.0, 5.02, 5.04, 6.0];
        let r = resample_scalar(&s, &g, 1.5);
        assert_eq!(r[0], None); // before the stream
        assert_eq!(r[1], Some(0.0));
        assert_eq!(r[2], Some(2.5));
        assert_eq!(r[3], Some(10.0));
        assert_eq!(r[4], Some(15.0));
        assert_eq!(r[5], None); // inside the 3 s hole
        assert!((r[6].unwrap() - 50.2).abs() < 1e-9);
        assert_eq!(r[7], Some(50.4)); // the last sample, hit exactly
        assert_eq!(r[8], None); // after the stream
    }

    #[test]
    fn a_fill_across_lost_readings_says_how_long_its_stream_was_unseen() {
        // 100 Hz readings at 3 ms phase; readings 10, 11 and 12 lost.
        let times: Vec<f64> = (0..30)
            .filter(|k| !(10..13).contains(k))
            .map(|k| 0.003 + k as f64 * 0.01)
            .collect();
        let g: Vec<f64> = (0..30).map(|k| k as f64 * 0.01).collect();
        let u = unseen(&times, &g);
        for (k, &v) in u.iter().enumerate() {
            // Readings 9 (0.093 s) and 13 (0.133 s) bracket grid points 10..=13.
            let want = if (10..=13).contains(&k) { 0.03 } else { 0.0 };
            assert!((v - want).abs() < 1e-9, "grid point {k}: {v}");
        }
        // Through align: the fills are kept (40 ms < max_gap) and marked.
        let joints: [Vec<(f64, f64)>; MAX_JOINTS] = core::array::from_fn(|j| {
            (0..32)
                .map(|k| (0.001 * j as f64 + k as f64 * 0.01, 0.0))
                .collect()
        });
        let pose: Vec<(f64, Pose)> = times
            .iter()
            .map(|&t| {
                let p = Pose {
                    position: [t, 0.0, 0.0],
                    orientation: [1.0, 0.0, 0.0, 0.0],
                };
                (t, p)
            })
            .collect();
        let a = align(&joints, &Default::default(), &pose, 100.0, 0.05, usize::MAX);
        assert_eq!(a.gaps, 0);
        let marked: Vec<f64> = a
            .samples
            .iter()
            .filter(|s| s.unseen_s > 0.0)
            .map(|s| s.t)
            .collect();
        assert_eq!(marked.len(), 4, "{marked:?}");
        assert!(a
            .samples
            .iter()
            .all(|s| s.unseen_s == 0.0 || (s.unseen_s - 0.03).abs() < 1e-9));
        // A steady stream is never unseen, whatever its phase or jitter.
        let jittered: Vec<f64> = (0..50)
            .map(|k| k as f64 * 0.01 + 0.002 * ((k * 7) % 3) as f64)
            .collect();
        assert!(unseen(&jittered, &g).iter().all(|&v| v == 0.0));
    }

    fn quat_about_z(angle: f64) -> Quat {
        [(angle / 2.0).cos(), 0.0, 0.0, (angle / 2.0).sin()]
    }

    #[test]
    fn slerp_follows_the_shortest_arc_at_constant_rate() {
        let a = quat_about_z(0.2);
        let b = quat_about_z(1.4);
        for u in [0.0, 0.1, 0.5, 0.9, 1.0] {
            let q = slerp(a, b, u);
            let want = quat_about_z(0.2 + u * 1.2);
            for k in 0..4 {
                assert!((q[k] - want[k]).abs() < 1e-12, "u {u}: {q:?} vs {want:?}");
            }
        }
        // The same rotation written with the opposite sign: the arc stays short.
        let b_neg = b.map(|x| -x);
        let q = slerp(a, b_neg, 0.5);
        let want = quat_about_z(0.8);
        let same = (0..4).all(|k| (q[k] - want[k]).abs() < 1e-12)
            || (0..4).all(|k| (q[k] + want[k]).abs() < 1e-12);
        assert!(same, "{q:?}");
        // Nearly equal quaternions: the linear branch stays unit-norm.
        let q = slerp(a, quat_about_z(0.2 + 1e-6), 0.5);
        assert!((q.iter().map(|x| x * x).sum::<f64>() - 1.0).abs() < 1e-12);
    }

    #[test]
    fn sort_stream_orders_and_dedups() {
        let mut s = vec![
            (2.0, 'c'),
            (1.0, 'a'),
            (f64::NAN, 'x'),
            (2.0, 'd'),
            (1.5, 'b'),
        ];
        sort_stream(&mut s);
        assert_eq!(s, vec![(1.0, 'a'), (1.5, 'b'), (2.0, 'c')]);
    }

    #[test]
    fn grid_is_inclusive_and_rejects_nonsense() {
        assert_eq!(grid(0.0, 0.03, 100.0, 100).len(), 4);
        assert!(grid(1.0, 0.0, 100.0, 100).is_empty());
        assert!(grid(0.0, 1.0, 0.0, 100).is_empty());
        assert!(grid(f64::NAN, 1.0, 10.0, 100).is_empty());
        // A span of 1.7e9 s (a recording whose first frames are at time 0) is not 1.7e11
        // points: the caller's bound is.
        let g = grid(0.0, 1.7e9, 100.0, 18_101);
        assert_eq!((g.len(), g[18_100]), (18_101, 181.0));
        assert_eq!(grid(0.0, f64::MAX, 1000.0, 3).len(), 3);
    }

    #[test]
    fn align_keeps_only_points_where_every_stream_has_data() {
        let hz = 100.0;
        let mut joints: [Vec<(f64, f64)>; MAX_JOINTS] = Default::default();
        for (j, s) in joints.iter_mut().enumerate() {
            // joint j: 1 kHz-ish samples from 10.0 s to 12.0 s, offset by j/7 ms
            *s = (0..2000)
                .map(|k| {
                    let t = 10.0 + k as f64 * 0.001 + j as f64 * 1e-4;
                    (t, j as f64 + t)
                })
                .collect();
        }
        // joint 3 loses 0.2 s in the middle
        joints[3].retain(|(t, _)| !(11.0..11.2).contains(t));
        let pose: Vec<(f64, Pose)> = (0..=250)
            .map(|k| {
                let t = 9.9 + k as f64 * 0.01;
                let pose = Pose {
                    position: [t, 0.0, 0.0],
                    orientation: quat_about_z(t),
                };
                (t, pose)
            })
            .collect();
        let a = align(&joints, &Default::default(), &pose, hz, 0.05, usize::MAX);
        // Common span: 10.0006 .. 11.999 → grid 10.01 .. 11.99: 199 points.
        assert_eq!(a.grid_points, 199);
        // Joint 3's hole runs from its sample at 10.9993 to the one at 11.2003 (0.201 s > max
        // gap): the grid points 11.00 ..= 11.20 inside it are gaps.
        assert_eq!(a.gaps, 21);
        assert_eq!(a.samples.len(), 178);
        for s in &a.samples {
            assert!(!(11.0..11.2).contains(&s.t));
            for (j, q) in s.joints.iter().enumerate() {
                assert!((q - (j as f64 + s.t)).abs() < 1e-9);
            }
            assert!((s.pose.position[0] - s.t).abs() < 1e-9);
            let want = quat_about_z(s.t);
            assert!((s.pose.orientation[3] - want[3]).abs() < 1e-9);
        }
        // A missing stream gives nothing, not a panic.
        let mut empty = joints.clone();
        empty[6].clear();
        assert_eq!(
            align(&empty, &Default::default(), &pose, hz, 0.05, usize::MAX)
                .samples
                .len(),
            0
        );
    }
}
