//! An arm of `n` joints (1 ≤ n ≤ [`MAX_JOINTS`]) in the session's fixed-size arrays.
//!
//! Contract: the data path (ingest, alignment, the window, the samples, validation, the
//! report's detail) holds every per-joint quantity in a `[T; MAX_JOINTS]` array whose first
//! `n` entries are the arm's (`Settings::joints`) and whose rest are zero: a zero D-H row and
//! a zero reading make the identity link, so forward kinematics of the padded table equals the
//! `n`-joint arm's bit for bit (cos 0 = 1, sin 0 = 0). Parameter-indexed arrays follow
//! calib-core's order `kind·MAX_JOINTS + joint`, the padded joints' entries zero.
//!
//! What must not see the padding — calib-core's identification, drift EM, separation and
//! guidance, whose parameters of a padded joint would be unidentifiable — runs monomorphised
//! at the arm's own length: [`with_joints!`](crate::with_joints) picks `N` (and `P = 4N`) from
//! the runtime count, [`narrow`] takes an arm's entries out of a padded array and [`widen`]
//! puts them back.

use calib_core::{DhRow, DhTable, ParamKind, Sample};

use crate::{MAX_JOINTS, MAX_PARAMS};

/// Runs `$body` with the const items `$n` (the joint count `$count`, 1..=[`MAX_JOINTS`]) and
/// `$p` (`4 · $n`, its D-H parameters) in scope, for calling code generic over the arm's
/// length. A count out of range is taken as [`MAX_JOINTS`]: the configuration refuses one
/// (`Settings::joints` is checked where it is read).
#[macro_export]
macro_rules! with_joints {
    ($count:expr, |$n:ident| $body:expr) => {
        $crate::with_joints!($count, |$n, _P| $body)
    };
    ($count:expr, |$n:ident, $p:ident| $body:expr) => {
        match $count {
            1 => {
                const $n: usize = 1;
                const $p: usize = 4;
                $body
            }
            2 => {
                const $n: usize = 2;
                const $p: usize = 8;
                $body
            }
            3 => {
                const $n: usize = 3;
                const $p: usize = 12;
                $body
            }
            4 => {
                const $n: usize = 4;
                const $p: usize = 16;
                $body
            }
            5 => {
                const $n: usize = 5;
                const $p: usize = 20;
                $body
            }
            6 => {
                const $n: usize = 6;
                const $p: usize = 24;
                $body
            }
            _ => {
                const $n: usize = 7;
                const $p: usize = 28;
                $body
            }
        }
    };
}

// The macro's last arm is the longest arm.
const _: () = assert!(MAX_JOINTS == 7 && MAX_PARAMS == 4 * MAX_JOINTS);

/// The first `N` entries of a padded array.
pub fn narrow<T: Copy, const N: usize>(padded: &[T; MAX_JOINTS]) -> [T; N] {
    const { assert!(N <= MAX_JOINTS, "an arm of at most MAX_JOINTS joints") };
    core::array::from_fn(|j| padded[j])
}

/// An arm's `N` entries, padded with `fill` to [`MAX_JOINTS`].
pub fn widen<T: Copy, const N: usize>(arm: &[T; N], fill: T) -> [T; MAX_JOINTS] {
    const { assert!(N <= MAX_JOINTS, "an arm of at most MAX_JOINTS joints") };
    core::array::from_fn(|j| if j < N { arm[j] } else { fill })
}

/// The zero D-H row: the identity link padding a table.
pub const ZERO_ROW: DhRow = DhRow {
    a: 0.0,
    alpha: 0.0,
    d: 0.0,
    theta_offset: 0.0,
};

/// An `N`-joint table padded with zero rows.
pub fn widen_table<const N: usize>(table: &DhTable<N>) -> DhTable<MAX_JOINTS> {
    DhTable {
        rows: widen(&table.rows, ZERO_ROW),
    }
}

/// A padded sample as the `N`-joint arm's.
pub fn narrow_sample<const N: usize>(s: &Sample<MAX_JOINTS>) -> Sample<N> {
    Sample {
        joints: narrow(&s.joints),
        pose: s.pose,
    }
}

/// An `N`-joint sample padded with zero readings.
pub fn widen_sample<const N: usize>(s: &Sample<N>) -> Sample<MAX_JOINTS> {
    Sample {
        joints: widen(&s.joints, 0.0),
        pose: s.pose,
    }
}

/// Per-parameter values of an `N`-joint arm (calib-core's order `kind·N + joint`) in the
/// padded order `kind·MAX_JOINTS + joint`, the padded joints' entries `fill`.
pub fn widen_params<const N: usize>(arm: &[f64], fill: f64) -> [f64; MAX_PARAMS] {
    debug_assert_eq!(arm.len(), 4 * N, "one value per parameter of the arm");
    let mut out = [fill; MAX_PARAMS];
    for (p, &v) in arm.iter().enumerate().take(4 * N) {
        let (kind, joint) = ParamKind::of_index(p, N);
        out[kind.index(joint, MAX_JOINTS)] = v;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_padded_table_has_the_arms_kinematics_bit_for_bit() {
        let arm: DhTable<4> = DhTable::paper_nominal().first();
        let q = [0.3, -1.1, 0.7, 2.0];
        let padded = widen_table(&arm);
        let (a, b) = (arm.fk(&q), padded.fk(&widen(&q, 0.0)));
        assert_eq!(a, b);
        assert_eq!(narrow::<_, 4>(&padded.rows), arm.rows);
    }

    #[test]
    fn parameters_keep_their_kind_and_joint_when_padded() {
        let arm: [f64; 8] = core::array::from_fn(|p| p as f64 + 1.0);
        let padded = widen_params::<2>(&arm, 0.0);
        for (p, &v) in arm.iter().enumerate() {
            let (kind, joint) = ParamKind::of_index(p, 2);
            assert_eq!(padded[kind.index(joint, MAX_JOINTS)], v);
        }
        assert_eq!(padded.iter().filter(|&&v| v != 0.0).count(), 8);
    }

    #[test]
    fn the_macro_picks_the_arms_length() {
        for n in 1..=MAX_JOINTS {
            let (got_n, got_p) = with_joints!(n, |N, P| (N, P));
            assert_eq!((got_n, got_p), (n, 4 * n));
        }
    }
}
