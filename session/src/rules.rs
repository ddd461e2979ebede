//! What the data path needs to know of the suit and of the session's rules.
//!
//! Contract: [`Settings`] is plain data, validated by whoever built it (the daemon's
//! configuration parser checks every value and its upper limit, naming key and line). The
//! data path reads it and never a file: the node ids, the nominal table, the anatomical
//! bounds, the collection window's rules and the validation rules. [`Settings::suit_default`]
//! is the shipped configuration's values (the daemon's test checks its `exocald.toml` parses to
//! exactly this), for tests and examples that need a suit without a file.

use calib_core::{DhTable, JointRanges, ParamKind, RateBias};

use crate::JOINTS;

/// Anatomical bounds a table must respect to be pushed (SI units). [`Bounds::table`] turns
/// them into calib-core's per-parameter [`calib_core::Bounds`].
#[derive(Debug, Clone, PartialEq)]
pub struct Bounds {
    /// Allowed `a_i` (m), `(min, max)`.
    pub a: [(f64, f64); JOINTS],
    /// Allowed `d_i` (m), `(min, max)`.
    pub d: [(f64, f64); JOINTS],
    /// Largest |α_i − nominal α_i| (rad).
    pub alpha_deviation: f64,
    /// Largest |offset_i − nominal offset_i| (rad).
    pub offset_deviation: f64,
    /// Anatomical rotation range of each joint (rad).
    pub joint_range: JointRanges<JOINTS>,
}

impl Bounds {
    /// The per-parameter bounds of a table whose nominal is `nominal`: `a` and `d` as
    /// configured, `α` and the joint offset within their deviation of nominal (calib-core
    /// compares angles modulo 2π).
    pub fn table(&self, nominal: &DhTable<JOINTS>) -> calib_core::Bounds<JOINTS> {
        let mut b = calib_core::Bounds::none();
        for (j, row) in nominal.rows.iter().enumerate() {
            let around = |x: f64, dev: f64| Some((x - dev, x + dev));
            b.limits[ParamKind::A as usize][j] = Some(self.a[j]);
            b.limits[ParamKind::D as usize][j] = Some(self.d[j]);
            b.limits[ParamKind::Alpha as usize][j] = around(row.alpha, self.alpha_deviation);
            b.limits[ParamKind::Theta as usize][j] =
                around(row.theta_offset, self.offset_deviation);
        }
        b
    }
}

/// The collection window's rules (the configuration's `[session]`).
#[derive(Debug, Clone, PartialEq)]
pub struct WindowRules {
    /// Shortest collection window (s).
    pub min_duration_s: f64,
    /// Longest collection window (s): a session without enough data by then fails.
    pub max_duration_s: f64,
    /// Fraction (0, 1] of each joint's range the motion must visit.
    pub excitation_required: f64,
    /// Aligned samples (on the grid) needed before calibrating.
    pub min_samples: usize,
    /// Rate of the common time grid the streams are resampled onto (Hz).
    pub grid_hz: f64,
    /// A hole longer than this (s) in any stream is a gap: grid points inside it are excluded.
    pub max_gap_s: f64,
    /// Stop when good enough: `(mm, mrad)`. When set, the window closes as soon as (after
    /// `min_duration_s`, every joint covered, enough samples) the expected table error of the
    /// motion so far is within both, and at `max_duration_s` at the latest, calibrating what
    /// it has if the motion suffices. `None`: the window closes at `min_duration_s`.
    pub stop_at_expected_error: Option<(f64, f64)>,
}

/// What a calibration must satisfy to be pushed (the configuration's `[validation]`).
#[derive(Debug, Clone, PartialEq)]
pub struct ValidationRules {
    /// Largest condition number of the (column-scaled) identification problem.
    pub max_condition_number: f64,
    /// Fraction (0, 1) of the session, at its end, kept out of the fit.
    pub holdout_fraction: f64,
    /// Largest expected table error (1σ, RMS position over the session's poses, mm) a pushed
    /// table may have, from the drift EM's Cramér-Rao bound.
    pub max_expected_position_error_mm: f64,
    /// The same for rotation (mrad).
    pub max_expected_rotation_error_mrad: f64,
}

/// What the suit's angle sensors are known to do beyond the paper's model (the configuration's
/// optional `[sensors]`): a rate bias left after fusion, from the sensors' spec. The drift EM
/// then keeps a rate bias in every joint's model whatever one session's data say: a small
/// ramp over half a minute is too weak for the data alone to choose, yet shifts the joint
/// offsets by millimetres (calib-core's README, issue 30's field sweep).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct SensorSpec {
    /// The rate bias (none by default).
    pub rate_bias: RateBias,
}

/// Everything the data path reads: the suit and the session's rules.
#[derive(Debug, Clone, PartialEq)]
pub struct Settings {
    /// CAN node id of the node on joint `i + 1`.
    pub joint_nodes: [u8; JOINTS],
    /// The nominal D-H table the suit was built to.
    pub nominal: DhTable<JOINTS>,
    /// Anatomical bounds a pushed table must respect.
    pub bounds: Bounds,
    /// The collection window's rules.
    pub window: WindowRules,
    /// What a calibration must satisfy to be pushed.
    pub validation: ValidationRules,
    /// What the sensors are known to do beyond the paper's model.
    pub sensors: SensorSpec,
}

impl Settings {
    /// The shipped configuration's values (`daemon/exocald.toml`): the paper's Table 1 arm,
    /// Table 2 and 3 bounds, a minute's window on a 100 Hz grid.
    pub fn suit_default() -> Settings {
        let deg = f64::to_radians;
        let nominal = DhTable::paper_nominal();
        let range = [
            (-90.0, 90.0),
            (-120.0, 30.0),
            (-10.0, 100.0),
            (0.0, 150.0),
            (-20.0, 30.0),
            (-30.0, 40.0),
            (-90.0, 90.0),
        ];
        let small = (-0.05, 0.05);
        Settings {
            joint_nodes: core::array::from_fn(|i| i as u8 + 1),
            nominal,
            bounds: Bounds {
                a: [
                    (0.02, 0.06),
                    (0.02, 0.06),
                    (0.377, 0.485),
                    (0.211, 0.267),
                    small,
                    small,
                    small,
                ],
                d: [small; JOINTS],
                alpha_deviation: deg(10.0),
                offset_deviation: deg(15.0),
                joint_range: JointRanges {
                    limits: range.map(|(lo, hi)| (deg(lo), deg(hi))),
                },
            },
            window: WindowRules {
                min_duration_s: 60.0,
                max_duration_s: 180.0,
                excitation_required: 0.5,
                min_samples: 1000,
                grid_hz: 100.0,
                max_gap_s: 0.05,
                stop_at_expected_error: None,
            },
            validation: ValidationRules {
                max_condition_number: 1.0e4,
                holdout_fraction: 0.2,
                max_expected_position_error_mm: 3.0,
                max_expected_rotation_error_mrad: 10.0,
            },
            sensors: SensorSpec::default(),
        }
    }
}
