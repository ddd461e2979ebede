//! The wearer: how much of each joint's range their free motion uses, and how they follow
//! guidance ("move joint 7") — a stated, imperfect compliance model, so that what guidance gains
//! is measured, not assumed.
//!
//! Contract: the wearer considers the advice they are given at most once per `follow_s`
//! seconds ([`Attention::heed`]). Each time, with probability `compliance` (seeded: the same
//! scenario and advice give the same choices), they follow it: `reaction_s` later, the advised
//! joint blends from its free motion into sweeps of its whole range ([`SWEEP_HZ`]) for
//! `follow_s` seconds and back, over [`RAMP_S`] each way ([`crate::motion::Motion::sweep`]);
//! the other joints keep their free motion. Otherwise they ignore it until they next consider
//! advice. With `compliance = 0` (the default) and a `reach` of 1 the suit moves as if no one
//! spoke to it. Who speaks: [`Voice`], which `exocald demo` fills from its session's progress;
//! the `exocal-hil` binary on a CAN bus hears no one (only `reach` applies there).

use std::sync::{Arc, Mutex};

use calib_core::Rng;
use serde::{Deserialize, Serialize};

use crate::motion::Motion;
pub use crate::motion::{RAMP_S, SWEEP_HZ};

/// How the wearer moves and listens (a scenario's `[wearer]` table).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Wearer {
    /// Fraction (0, 1] of each joint's range the free motion uses, about the range's middle.
    pub reach: [f64; 7],
    /// Probability in [0, 1] that the wearer follows a piece of advice they consider.
    pub compliance: f64,
    /// Seconds from considering advice to moving as told.
    pub reaction_s: f64,
    /// Seconds the wearer moves the advised joint, and between two considerations of advice
    /// (at least `2 ·` [`RAMP_S`]).
    pub follow_s: f64,
    /// Seconds the wearer stands still at power-up before moving (0: moves at once).
    pub still_s: f64,
}

impl Default for Wearer {
    fn default() -> Self {
        Wearer {
            reach: [1.0; 7],
            compliance: 0.0,
            reaction_s: 2.0,
            follow_s: 10.0,
            still_s: 0.0,
        }
    }
}

/// The wearer's attention: when they next consider advice, and their choices.
#[derive(Clone, Debug)]
pub struct Attention {
    wearer: Wearer,
    rng: Rng,
    /// Simulated time (s) before which advice goes unheard.
    busy_until: f64,
    /// Pieces of advice considered.
    pub considered: u32,
    /// Pieces of advice followed.
    pub followed: u32,
}

impl Attention {
    /// A wearer as `wearer` says, drawing their choices from `rng`.
    pub fn new(wearer: Wearer, rng: Rng) -> Attention {
        Attention {
            wearer,
            rng,
            busy_until: f64::NEG_INFINITY,
            considered: 0,
            followed: 0,
        }
    }

    /// The wearer is told at simulated time `t_s` to move `joint` (0-based); `motion` is theirs,
    /// evaluated so far up to `t_s` at most (the advice changes it only from `t_s` on).
    pub fn heed(&mut self, joint: usize, t_s: f64, motion: &mut Motion) {
        if t_s < self.busy_until || joint >= 7 || self.wearer.compliance <= 0.0 {
            return;
        }
        self.considered += 1;
        self.busy_until = t_s + self.wearer.follow_s;
        if self.rng.uniform() < self.wearer.compliance {
            self.followed += 1;
            let from = t_s + self.wearer.reaction_s;
            let phase = std::f64::consts::TAU * self.rng.uniform();
            motion.sweep(joint, from, from + self.wearer.follow_s, phase);
            self.busy_until = from + self.wearer.follow_s;
        }
    }
}

/// What the wearer is told: the joint (0-based) to move now, or nothing. Whoever speaks (the
/// demo's listener to the daemon's progress) and the emulator playing the suit
/// ([`crate::Hil::listening`]) each hold a clone.
#[derive(Clone, Debug, Default)]
pub struct Voice(Arc<Mutex<Option<usize>>>);

impl Voice {
    /// Says `joint` (0-based) is the one to move, or (`None`) nothing.
    pub fn say(&self, joint: Option<usize>) {
        *self.0.lock().unwrap_or_else(|e| e.into_inner()) = joint;
    }

    /// What is being said.
    pub fn heard(&self) -> Option<usize> {
        *self.0.lock().unwrap_or_else(|e| e.into_inner())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use calib_core::JointRanges;

    fn motion() -> Motion {
        Motion::random(&JointRanges::paper(), &mut Rng::new(3))
    }

    #[test]
    fn a_compliant_wearer_moves_the_advised_joint_after_reacting_and_listens_again_after() {
        let free = motion();
        let mut m = free.clone();
        let wearer = Wearer {
            compliance: 1.0,
            ..Wearer::default()
        };
        let mut a = Attention::new(wearer, Rng::new(1));
        a.heed(6, 5.0, &mut m);
        // Busy: the same or other advice goes unheard until the sweep (7 s to 17 s) ends.
        a.heed(2, 6.0, &mut m);
        a.heed(2, 16.9, &mut m);
        assert_eq!((a.considered, a.followed), (1, 1));
        assert_eq!(m.joint(6, 6.9), free.joint(6, 6.9));
        assert_ne!(m.joint(6, 8.0), free.joint(6, 8.0));
        assert_eq!(m.joint(2, 18.0), free.joint(2, 18.0));
        a.heed(2, 17.0, &mut m);
        assert_eq!((a.considered, a.followed), (2, 2));
        assert_ne!(m.joint(2, 20.0), free.joint(2, 20.0));
    }

    #[test]
    fn compliance_is_the_share_of_advice_followed_and_none_changes_nothing() {
        let mut m = motion();
        let wearer = Wearer {
            compliance: 0.6,
            ..Wearer::default()
        };
        let mut a = Attention::new(wearer.clone(), Rng::new(2));
        for k in 0..1000 {
            a.heed(k % 7, 20.0 * k as f64, &mut m);
        }
        assert_eq!(a.considered, 1000);
        assert!(
            (a.followed as f64 / 1000.0 - 0.6).abs() < 0.05,
            "{}",
            a.followed
        );

        let free = motion();
        let mut m = free.clone();
        let mut deaf = Attention::new(Wearer::default(), Rng::new(2));
        for k in 0..100 {
            deaf.heed(k % 7, k as f64, &mut m);
        }
        assert_eq!((deaf.considered, deaf.followed), (0, 0));
        assert_eq!(m, free);
    }
}
