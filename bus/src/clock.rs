//! Time: the wall clock, or simulated time.
//!
//! Contract: [`Clock::now`] is the time frames are stamped with and sessions are timed by, as a
//! [`Duration`] since an epoch. [`Clock::Wall`] is the host's wall clock (the UNIX epoch, as
//! SocketCAN's kernel timestamps). [`SimClock`] is simulated time: 0 when the clock is made,
//! advancing `speed` times faster than the tokio runtime's clock; its epoch is the wall clock
//! at that moment in whole µs (so log names stay unique, while the receive times a session
//! works with — µs since its first frame — are the same from run to run). On a running
//! runtime that is `speed` × real time; on a paused runtime (`start_paused`) it is virtual: it
//! stands still while any task can run or a blocking task is busy, and jumps to the next timer
//! otherwise, so a session on the in-process bus gives the same frames, timestamps and results
//! on every run.

use std::time::{Duration, SystemTime, UNIX_EPOCH};

/// The time a bus stamps frames with and a session is timed by.
#[derive(Clone, Copy, Debug)]
pub enum Clock {
    /// The host's wall clock (time since the UNIX epoch).
    Wall,
    /// Simulated time.
    Simulated(SimClock),
}

impl Clock {
    /// Now, since the clock's epoch: what frames and log records are stamped with.
    pub fn now(&self) -> Duration {
        match self {
            Clock::Wall => SystemTime::now()
                .duration_since(UNIX_EPOCH)
                .unwrap_or_default(),
            Clock::Simulated(c) => c.epoch + Duration::from_secs_f64(c.now_s()),
        }
    }

    /// A monotonic reading, for timeouts, deadlines and elapsed times: never goes back when
    /// the host's wall clock is stepped (NTP, a manual `date`, an RTC read at boot). For
    /// [`Clock::Wall`] it is the time since the first call in this process
    /// ([`std::time::Instant`], `CLOCK_MONOTONIC`); simulated time is monotonic already and
    /// is returned as seconds since its start. Only differences of two readings mean anything.
    pub fn monotonic(&self) -> Duration {
        match self {
            Clock::Wall => {
                static ANCHOR: std::sync::OnceLock<std::time::Instant> = std::sync::OnceLock::new();
                ANCHOR.get_or_init(std::time::Instant::now).elapsed()
            }
            Clock::Simulated(c) => Duration::from_secs_f64(c.now_s()),
        }
    }
}

/// Simulated time running `speed` times faster than the tokio runtime's clock.
#[derive(Clone, Copy, Debug)]
pub struct SimClock {
    start: tokio::time::Instant,
    epoch: Duration,
    speed: f64,
}

impl SimClock {
    /// Starts now. `speed` must be finite and positive.
    pub fn new(speed: f64) -> Option<SimClock> {
        let wall = Clock::Wall.now();
        (speed.is_finite() && speed > 0.0).then(|| SimClock {
            start: tokio::time::Instant::now(),
            epoch: Duration::from_micros(wall.as_micros() as u64),
            speed,
        })
    }

    /// The speed factor.
    pub fn speed(&self) -> f64 {
        self.speed
    }

    /// Simulated seconds since start.
    pub fn now_s(&self) -> f64 {
        self.start.elapsed().as_secs_f64() * self.speed
    }

    /// Sleeps until simulated time `t_s`.
    pub async fn sleep_until(&self, t_s: f64) {
        let after = Duration::from_secs_f64((t_s / self.speed).clamp(0.0, 1e9));
        tokio::time::sleep_until(self.start + after).await
    }

    /// This clock as a [`Clock`] (for the in-process bus and the daemon).
    pub fn bus_clock(&self) -> Clock {
        Clock::Simulated(*self)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_monotonic_reading_never_goes_back() {
        let c = Clock::Wall;
        let mut last = c.monotonic();
        for _ in 0..1000 {
            let now = c.monotonic();
            assert!(now >= last);
            last = now;
        }
    }

    #[tokio::test(start_paused = true)]
    async fn runs_speed_times_faster_than_the_runtime() {
        let c = SimClock::new(50.0).unwrap();
        let t0 = c.bus_clock().now();
        assert_eq!(t0.subsec_nanos() % 1000, 0, "the epoch is whole µs");
        c.sleep_until(2.0).await;
        assert_eq!(c.now_s(), 2.0);
        assert_eq!(c.bus_clock().now() - t0, Duration::from_secs(2));
        assert!(SimClock::new(0.0).is_none() && SimClock::new(f64::NAN).is_none());
    }
}
