//! Simulated time: how fast the emulation runs against the wall clock.
//!
//! Contract: simulated time starts at 0 when the [`SimClock`] is made and advances `speed`
//! times faster than the monotonic wall clock. [`SimClock::bus_clock`] turns it into bus receive
//! timestamps (wall-clock time at start plus simulated time), so an in-process bus stamps frames
//! in the same time base the nodes were simulated in, at any speed.

use std::sync::Arc;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

/// Simulated time running `speed` times faster than the wall clock.
#[derive(Clone, Copy, Debug)]
pub struct SimClock {
    start: Instant,
    epoch: Duration,
    speed: f64,
}

impl SimClock {
    /// Starts now. `speed` must be finite and positive.
    pub fn new(speed: f64) -> Option<SimClock> {
        (speed.is_finite() && speed > 0.0).then(|| SimClock {
            start: Instant::now(),
            epoch: SystemTime::now()
                .duration_since(UNIX_EPOCH)
                .unwrap_or_default(),
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

    /// The wall-clock instant at which simulated time reaches `t_s`.
    pub fn instant_at(&self, t_s: f64) -> Instant {
        self.start + Duration::from_secs_f64((t_s / self.speed).clamp(0.0, 1e9))
    }

    /// Sleeps until simulated time `t_s`.
    pub async fn sleep_until(&self, t_s: f64) {
        tokio::time::sleep_until(self.instant_at(t_s).into()).await
    }

    /// A clock for [`exocal_bus::InProcessBus::with_clock`]: wall time at start + simulated time.
    pub fn bus_clock(&self) -> exocal_bus::Clock {
        let c = *self;
        Arc::new(move || c.epoch + Duration::from_secs_f64(c.now_s()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn runs_speed_times_faster() {
        let c = SimClock::new(50.0).unwrap();
        std::thread::sleep(Duration::from_millis(20));
        let t = c.now_s();
        assert!((1.0..2.0).contains(&t), "{t}");
        assert!(SimClock::new(0.0).is_none() && SimClock::new(f64::NAN).is_none());
        let stamp = (c.bus_clock())();
        assert!(stamp >= c.epoch + Duration::from_secs(1));
    }
}
