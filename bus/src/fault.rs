//! Seeded faults on a CAN wire, in the manner of smoltcp's `phy::FaultInjector`.
//!
//! Contract: a [`FaultConfig`] (plain `Copy` data: probabilities per frame and two hold-back
//! times) and a seed decide, frame by frame, what the wire does to it: lose it (alone or in a
//! burst), corrupt one bit of its payload, hold it back (a fixed delay, or a random one up to a
//! bound so that later frames overtake it), and send it twice. The decision is [`Faults::fate`]:
//! pure, with the time passed in and never read from a clock, so the same seed, configuration
//! and frame sequence give the same fates on every run and at every speed. Probabilities
//! that are 0 draw nothing, so switching one fault off leaves the others' draws unchanged.
//!
//! Two users: the emulated suit (exocal-hil) draws each frame's fate in simulated time and keeps
//! its own wire queue; [`FaultInjector`] wraps any [`Transport`]: frames it is given to send go
//! through [`Faults::fate`] at the time last passed to [`FaultInjector::advance`] and wait in a
//! queue (at most [`FaultInjector::HELD_MAX`] frames) until `advance` reaches their time;
//! frames it receives are lost or corrupted with the same probabilities, at their receive
//! timestamp (holding back and duplicating act on the sending side, where the wire's order is
//! made).

use std::cmp::Reverse;
use std::collections::BinaryHeap;
use std::time::Duration;

use crate::{BusError, Frame, Received, Transport};
use embedded_can::Frame as _;

/// What the wire does to frames: probabilities per frame (0 = never) and hold-back times.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct FaultConfig {
    /// A frame is lost.
    pub drop: f64,
    /// A loss burst starts at this frame (the frame is lost, and `burst_len - 1` after it).
    pub burst_start: f64,
    /// Frames lost per burst.
    pub burst_len: u32,
    /// One bit of the payload is flipped (frames with a payload only).
    pub corrupt: f64,
    /// The frame is held back by `delay_by`.
    pub delay: f64,
    /// How long a delayed frame is held back.
    pub delay_by: Duration,
    /// The frame is held back by a uniform time up to `reorder_max`, so later frames overtake it.
    pub reorder: f64,
    /// Bound of the reordering hold-back.
    pub reorder_max: Duration,
    /// A second copy of the frame follows it [`DUPLICATE_GAP`] later.
    pub duplicate: f64,
    /// After this many sends the transport fails every send (`ENOBUFS`: a transmit queue that
    /// stays full, a bus-off controller); `None`: never.
    pub fail_sends_after: Option<u64>,
}

/// Time between a frame and its duplicate (a little more than one classic frame at 1 Mbit/s).
pub const DUPLICATE_GAP: Duration = Duration::from_micros(20);

/// A probability that is not in `[0, 1]`, or a non-finite one, in a [`FaultConfig`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct BadProbability(pub &'static str);

impl std::fmt::Display for BadProbability {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "fault probability `{}` must be in [0, 1]", self.0)
    }
}

impl std::error::Error for BadProbability {}

impl FaultConfig {
    /// Checks that every probability is in `[0, 1]`; names the first that is not.
    pub fn check(&self) -> Result<(), BadProbability> {
        for (name, p) in [
            ("drop", self.drop),
            ("burst_start", self.burst_start),
            ("corrupt", self.corrupt),
            ("delay", self.delay),
            ("reorder", self.reorder),
            ("duplicate", self.duplicate),
        ] {
            if !(0.0..=1.0).contains(&p) {
                return Err(BadProbability(name));
            }
        }
        Ok(())
    }
}

/// What the faults did so far.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct FaultStats {
    /// Frames lost, alone or in bursts.
    pub dropped: u64,
    /// Frames with a bit flipped.
    pub corrupted: u64,
    /// Frames held back (delayed or reordered).
    pub delayed: u64,
    /// Extra copies.
    pub duplicated: u64,
}

/// A frame's fate on the wire.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Fate {
    /// Lost.
    Dropped,
    /// `frame` (corrupted or not) reaches the bus at `at`, and again at `again` if duplicated.
    Deliver {
        /// The frame as it arrives (one payload bit flipped if corrupted).
        frame: Frame,
        /// When it reaches the bus.
        at: Duration,
        /// When its duplicate follows, if it is duplicated.
        again: Option<Duration>,
    },
}

/// splitmix64: small, seeded, the same stream on every platform.
#[derive(Clone, Copy, Debug)]
struct SplitMix64(u64);

impl SplitMix64 {
    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// Uniform in `[0, 1)`.
    fn unit(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    /// True with probability `p`; draws nothing when `p` is 0.
    fn chance(&mut self, p: f64) -> bool {
        p > 0.0 && self.unit() < p
    }
}

/// The seeded decision of each frame's fate (time passed in; see the module docs).
#[derive(Clone, Debug)]
pub struct Faults {
    config: FaultConfig,
    rng: SplitMix64,
    burst_left: u32,
    stats: FaultStats,
}

impl Faults {
    /// Faults of `config`, drawn from `seed`.
    pub fn new(config: FaultConfig, seed: u64) -> Faults {
        Faults {
            config,
            rng: SplitMix64(seed),
            burst_left: 0,
            stats: FaultStats::default(),
        }
    }

    /// The configuration.
    pub fn config(&self) -> &FaultConfig {
        &self.config
    }

    /// What happened so far.
    pub fn stats(&self) -> FaultStats {
        self.stats
    }

    /// The fate of `frame`, put on the wire at `now`.
    pub fn fate(&mut self, now: Duration, frame: Frame) -> Fate {
        if self.lost() {
            return Fate::Dropped;
        }
        let c = self.config;
        let frame = self.maybe_corrupt(frame);
        let mut at = now;
        if self.rng.chance(c.delay) {
            at += c.delay_by;
            self.stats.delayed += 1;
        }
        if self.rng.chance(c.reorder) {
            at += c.reorder_max.mul_f64(self.rng.unit());
            self.stats.delayed += 1;
        }
        let again = self.rng.chance(c.duplicate).then(|| {
            self.stats.duplicated += 1;
            at + DUPLICATE_GAP
        });
        Fate::Deliver { frame, at, again }
    }

    /// Whether the next frame is lost (bursts, then uniform loss); counts it.
    pub fn lost(&mut self) -> bool {
        let c = self.config;
        let lost = if self.burst_left > 0 {
            self.burst_left -= 1;
            true
        } else if self.rng.chance(c.burst_start) {
            self.burst_left = c.burst_len.saturating_sub(1);
            true
        } else {
            self.rng.chance(c.drop)
        };
        self.stats.dropped += u64::from(lost);
        lost
    }

    fn maybe_corrupt(&mut self, frame: Frame) -> Frame {
        let len = frame.data().len() as u64;
        if frame.is_remote_frame() || len == 0 || !self.rng.chance(self.config.corrupt) {
            return frame;
        }
        let bit = self.rng.next_u64() % (len * 8);
        let mut out = frame;
        out.flip_bit(bit as u32);
        self.stats.corrupted += 1;
        out
    }
}

/// A frame waiting for its time, ordered by time and then by when it was offered.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
struct Held {
    at: Duration,
    order: u64,
    frame: FrameKey,
}

/// [`Frame`] with a total order, only so that [`Held`] can sit in a heap (the order never
/// decides: `order` is unique).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct FrameKey(Frame);

impl PartialOrd for FrameKey {
    fn partial_cmp(&self, other: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(other))
    }
}

impl Ord for FrameKey {
    fn cmp(&self, _: &Self) -> std::cmp::Ordering {
        std::cmp::Ordering::Equal
    }
}

/// A [`Transport`] whose wire drops, corrupts, delays, reorders and duplicates frames (see the
/// module docs). Time is what [`FaultInjector::advance`] was last given.
pub struct FaultInjector<T: Transport> {
    inner: T,
    faults: Faults,
    held: BinaryHeap<Reverse<Held>>,
    order: u64,
    now: Duration,
    sent: u64,
}

impl<T: Transport> FaultInjector<T> {
    /// Frames held back at most; a frame offered beyond that is dropped (and counted).
    pub const HELD_MAX: usize = 4096;

    /// `inner` behind faults of `config` drawn from `seed`, at time 0.
    pub fn new(inner: T, config: FaultConfig, seed: u64) -> Self {
        FaultInjector {
            inner,
            faults: Faults::new(config, seed),
            held: BinaryHeap::new(),
            order: 0,
            now: Duration::ZERO,
            sent: 0,
        }
    }

    /// What the faults did so far.
    pub fn stats(&self) -> FaultStats {
        self.faults.stats()
    }

    /// The wrapped transport.
    pub fn inner(&self) -> &T {
        &self.inner
    }

    /// When the next held-back frame is due, if any.
    pub fn next_due(&self) -> Option<Duration> {
        self.held.peek().map(|h| h.0.at)
    }

    /// Moves time to `now` (never back) and sends every held frame due by then, in order.
    pub async fn advance(&mut self, now: Duration) -> Result<(), BusError> {
        self.now = self.now.max(now);
        let mut due = Vec::new();
        while self.held.peek().is_some_and(|h| h.0.at <= self.now) {
            due.push(self.held.pop().expect("peeked").0.frame.0);
        }
        if due.is_empty() {
            Ok(())
        } else {
            self.inner.send_all(&due).await
        }
    }

    fn hold(&mut self, at: Duration, frame: Frame) {
        if self.held.len() >= Self::HELD_MAX {
            self.faults.stats.dropped += 1;
            return;
        }
        self.order += 1;
        self.held.push(Reverse(Held {
            at,
            order: self.order,
            frame: FrameKey(frame),
        }));
    }
}

impl<T: Transport> Transport for FaultInjector<T> {
    async fn send(&mut self, frame: &Frame) -> Result<(), BusError> {
        if self
            .faults
            .config()
            .fail_sends_after
            .is_some_and(|n| self.sent >= n)
        {
            return Err(BusError::Io(std::io::Error::from_raw_os_error(105))); // ENOBUFS
        }
        self.sent += 1;
        if let Fate::Deliver { frame, at, again } = self.faults.fate(self.now, *frame) {
            self.hold(at, frame);
            if let Some(again) = again {
                self.hold(again, frame);
            }
        }
        let now = self.now;
        self.advance(now).await
    }

    async fn recv(&mut self) -> Result<Received, BusError> {
        loop {
            let r = self.inner.recv().await?;
            if self.faults.lost() {
                continue;
            }
            let frame = self.faults.maybe_corrupt(r.frame);
            return Ok(Received { frame, ..r });
        }
    }

    fn dropped(&self) -> u64 {
        self.inner.dropped()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::InProcessBus;
    use embedded_can::StandardId;

    fn frame(i: u16) -> Frame {
        Frame::new(StandardId::new(i & 0x7FF).unwrap(), &i.to_le_bytes()).unwrap()
    }

    fn ms(n: u64) -> Duration {
        Duration::from_millis(n)
    }

    #[test]
    fn no_faults_deliver_every_frame_at_once_and_draw_nothing() {
        let mut f = Faults::new(FaultConfig::default(), 1);
        for i in 0..100 {
            assert_eq!(
                f.fate(ms(i.into()), frame(i)),
                Fate::Deliver {
                    frame: frame(i),
                    at: ms(i.into()),
                    again: None
                }
            );
        }
        assert_eq!(f.stats(), FaultStats::default());
        assert_eq!(f.rng.0, 1, "no draw was made");
    }

    #[test]
    fn the_same_seed_gives_the_same_fates_and_rates_follow_the_config() {
        let config = FaultConfig {
            drop: 0.1,
            corrupt: 0.05,
            delay: 0.1,
            delay_by: ms(50),
            reorder: 0.1,
            reorder_max: ms(20),
            duplicate: 0.05,
            ..FaultConfig::default()
        };
        config.check().unwrap();
        let run = |seed| {
            let mut f = Faults::new(config, seed);
            let fates: Vec<Fate> = (0..20_000)
                .map(|i| f.fate(ms(i), frame(i as u16)))
                .collect();
            (fates, f.stats())
        };
        let (a, sa) = run(7);
        assert_eq!(a, run(7).0);
        assert_ne!(a, run(8).0);
        let rate = |n: u64| n as f64 / 20_000.0;
        assert!((rate(sa.dropped) - 0.1).abs() < 0.01, "{sa:?}");
        let delivered = 20_000.0 * 0.9;
        assert!(
            (sa.corrupted as f64 / delivered - 0.05).abs() < 0.01,
            "{sa:?}"
        );
        assert!(
            (sa.delayed as f64 / delivered - 0.19).abs() < 0.02,
            "{sa:?}"
        );
        assert!(
            (sa.duplicated as f64 / delivered - 0.05).abs() < 0.01,
            "{sa:?}"
        );
        for (i, fate) in a.iter().enumerate() {
            if let Fate::Deliver {
                frame: f,
                at,
                again,
            } = *fate
            {
                let sent = ms(i as u64);
                assert!(at >= sent && at <= sent + ms(70), "{at:?}");
                assert_eq!(again.map(|t| t - at), again.map(|_| DUPLICATE_GAP));
                let diff = f
                    .data()
                    .iter()
                    .zip(frame(i as u16).data())
                    .map(|(x, y)| (x ^ y).count_ones())
                    .sum::<u32>();
                assert!(diff <= 1, "at most one bit flipped");
                assert_eq!(f.raw_id(), frame(i as u16).raw_id());
            }
        }
    }

    #[test]
    fn a_burst_loses_burst_len_frames_in_a_row() {
        let mut f = Faults::new(
            FaultConfig {
                burst_start: 1.0,
                burst_len: 5,
                ..FaultConfig::default()
            },
            3,
        );
        assert!((0..5).all(|_| f.lost()));
        assert_eq!(f.stats().dropped, 5);
        assert!(FaultConfig {
            drop: 1.5,
            ..FaultConfig::default()
        }
        .check()
        .is_err_and(|e| e.0 == "drop"));
    }

    #[tokio::test(start_paused = true)]
    async fn the_injector_holds_frames_back_until_their_time_and_duplicates() {
        let bus = InProcessBus::new();
        let mut rx = bus.attach();
        let config = FaultConfig {
            delay: 1.0,
            delay_by: ms(10),
            duplicate: 1.0,
            ..FaultConfig::default()
        };
        let mut tx = FaultInjector::new(bus.attach(), config, 5);
        tx.advance(ms(100)).await.unwrap();
        tx.send(&frame(1)).await.unwrap();
        assert!(rx.try_recv().is_none(), "held back");
        assert_eq!(tx.next_due(), Some(ms(110)));
        tx.advance(ms(109)).await.unwrap();
        assert!(rx.try_recv().is_none());
        tx.advance(ms(110)).await.unwrap();
        assert_eq!(rx.try_recv().unwrap().frame, frame(1));
        assert!(rx.try_recv().is_none(), "the copy is 20 µs later");
        tx.advance(ms(111)).await.unwrap();
        assert_eq!(rx.try_recv().unwrap().frame, frame(1));
        assert_eq!(tx.next_due(), None);
        assert_eq!(tx.stats().duplicated, 1);
    }

    #[tokio::test(start_paused = true)]
    async fn reordered_frames_are_overtaken_and_received_frames_are_lost() {
        let bus = InProcessBus::new();
        let mut rx = FaultInjector::new(
            bus.attach(),
            FaultConfig {
                drop: 0.5,
                ..FaultConfig::default()
            },
            9,
        );
        let mut tx = FaultInjector::new(
            bus.attach(),
            FaultConfig {
                reorder: 0.5,
                reorder_max: ms(50),
                ..FaultConfig::default()
            },
            11,
        );
        for i in 0..200u16 {
            tx.advance(ms(u64::from(i))).await.unwrap();
            tx.send(&frame(i)).await.unwrap();
        }
        tx.advance(ms(1000)).await.unwrap();
        let mut got = Vec::new();
        while let Ok(Ok(r)) = tokio::time::timeout(Duration::from_millis(1), rx.recv()).await {
            got.push(r.frame.raw_id());
        }
        assert!(got.len() > 60 && got.len() < 140, "{}", got.len());
        assert!(got.windows(2).any(|w| w[0] > w[1]), "some overtaken");
        assert_eq!(rx.stats().dropped + got.len() as u64, 200);
        assert!(tx.stats().delayed > 60);
    }
}
