//! Seeded push trials: a quiet suit whose transfer path is faulty, and a new table per joint
//! node to push to it — what the atomic-push tests draw, on the in-process bus and on vcan.
//!
//! Contract: [`TransferMix::scenario`] and [`new_tables`] are pure functions of their seed
//! (calib-core's [`Rng`]), so a failing trial is replayed from its seed alone.

use calib_core::Rng;
use exocal_dbc::table::{Field, Table};
use exocal_dbc::NodeId;

use crate::scenario::{Reboot, Scenario, TransferBehaviour, TransferFault};
use crate::Suit;

/// The bounds a trial's faults are drawn within.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TransferMix {
    /// Uniform loss: one of these, equally likely.
    pub losses: &'static [f64],
    /// Probability of a loss burst per frame (drawn in three trials out of ten, 1–8 frames).
    pub burst_start: f64,
    /// Duplication and reordering probabilities are uniform in `[0, max_fraction)`, delay in
    /// half that.
    pub max_fraction: f64,
    /// Reordering hold-back bound, ms: uniform in `[1, reorder_max_ms)`.
    pub reorder_max_ms: f64,
    /// Delay, ms: uniform in `[1, delay_max_ms)`.
    pub delay_max_ms: f64,
    /// Node reboots: up to `reboots - 1`, each starting uniformly in `[push_at_s,
    /// push_at_s + reboot_window_s)` and down for a time uniform in `down_s`.
    pub reboots: u64,
    /// When the push starts (simulated seconds).
    pub push_at_s: f64,
    /// See `reboots`.
    pub reboot_window_s: f64,
    /// See `reboots`.
    pub down_s: (f64, f64),
    /// Probability that one node refuses every transfer: NACK or silence (silence only
    /// without `nack`).
    pub refusal: f64,
    /// Whether a refusing node may NACK.
    pub nack: bool,
}

impl TransferMix {
    /// The scenario of trial `seed`: the paper's suit with 1 Hz streams (the bus is left to the
    /// transfer), running long enough for any push, with this mix's faults.
    pub fn scenario(&self, seed: u64) -> Scenario {
        let mut rng = Rng::new(seed);
        let mut range = |lo: f64, hi: f64| lo + (hi - lo) * rng.uniform();
        let mut s = Scenario::paper();
        s.seed = seed;
        s.duration_s = 600.0;
        s.rates.joint_state_hz = 1.0;
        s.rates.imu_hz = 1.0;
        s.rates.pose_hz = 1.0;
        let f = &mut s.faults;
        f.loss =
            self.losses[(range(0.0, self.losses.len() as f64) as usize).min(self.losses.len() - 1)];
        if range(0.0, 1.0) < 0.3 {
            f.burst_start = self.burst_start;
        }
        f.burst_len = 1 + range(0.0, 8.0) as u32;
        f.duplicate = range(0.0, self.max_fraction);
        f.reorder = range(0.0, self.max_fraction);
        f.reorder_max_ms = range(1.0, self.reorder_max_ms);
        f.delay = range(0.0, self.max_fraction / 2.0);
        f.delay_ms = range(1.0, self.delay_max_ms);
        for _ in 0..range(0.0, self.reboots as f64) as u64 {
            f.reboots.push(Reboot {
                node: 1 + range(0.0, 7.0) as u8,
                at_s: self.push_at_s + range(0.0, self.reboot_window_s),
                down_s: range(self.down_s.0, self.down_s.1),
            });
        }
        if range(0.0, 1.0) < self.refusal {
            let behaviour = if self.nack && range(0.0, 1.0) < 0.5 {
                TransferBehaviour::Nack
            } else {
                TransferBehaviour::Silent
            };
            f.transfer.push(TransferFault {
                node: 1 + range(0.0, 7.0) as u8,
                behaviour,
            });
        }
        s
    }
}

/// Per joint node: the table it holds, and a new one near it (every field moved up by 1–500 raw
/// units, kept in bounds), drawn from `seed`.
pub fn new_tables(suit: &Suit, seed: u64) -> Vec<(NodeId, Table, Table)> {
    let mut rng = Rng::new(seed);
    NodeId::JOINTS
        .iter()
        .map(|&n| {
            let old = suit.held_table(n).expect("every joint node holds a table");
            let mut raw = old.raw_values();
            for f in Field::ALL {
                let (lo, hi) = f.raw_bounds();
                let k = f.seq() as usize;
                raw[k] = (raw[k] + 1 + (rng.next_u64() % 500) as i64).clamp(lo, hi);
            }
            (n, old, Table::from_raw(raw).expect("clamped into bounds"))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    const MIX: TransferMix = TransferMix {
        losses: &[0.0, 0.1, 0.4],
        burst_start: 0.02,
        max_fraction: 0.2,
        reorder_max_ms: 200.0,
        delay_max_ms: 300.0,
        reboots: 4,
        push_at_s: 0.5,
        reboot_window_s: 2.0,
        down_s: (0.01, 1.5),
        refusal: 0.2,
        nack: true,
    };

    #[test]
    fn trials_are_seeded_valid_and_within_their_bounds() {
        let mut refusing = 0;
        for seed in 0..200 {
            let s = MIX.scenario(seed);
            assert_eq!(s, MIX.scenario(seed));
            s.validate().unwrap();
            let f = &s.faults;
            assert!(MIX.losses.contains(&f.loss));
            assert!(f.duplicate < 0.2 && f.reorder < 0.2 && f.delay < 0.1);
            assert!(f.reboots.len() < 4);
            for r in &f.reboots {
                assert!((0.5..2.5).contains(&r.at_s) && (0.01..1.5).contains(&r.down_s));
            }
            refusing += f.transfer.len();
        }
        assert!((20..60).contains(&refusing), "{refusing} of 200 refuse");
    }

    #[test]
    fn new_tables_differ_from_the_old_and_are_seeded() {
        let dir = crate::sim::tests::temp_dir("trial");
        let suit = Suit::new(MIX.scenario(1), &dir).unwrap();
        let a = new_tables(&suit, 9);
        assert_eq!(a.len(), 7);
        assert!(a.iter().all(|(_, old, new)| old.crc() != new.crc()));
        assert_eq!(
            a.iter().map(|t| t.2.crc()).collect::<Vec<_>>(),
            new_tables(&suit, 9)
                .iter()
                .map(|t| t.2.crc())
                .collect::<Vec<_>>()
        );
        let _ = std::fs::remove_dir_all(&dir);
    }
}
