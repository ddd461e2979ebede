//! What the data path needs to know of the suit and of the session's rules.
//!
//! Contract: [`Settings`] is plain data, validated by whoever built it (the daemon's
//! configuration parser checks every value and its upper limit, naming key and line). The
//! data path reads it and never a file: the node ids, the nominal table, the anatomical
//! bounds, the collection window's rules and the validation rules. [`Settings::suit_default`]
//! is the shipped configuration's values (the daemon's test checks its `exocald.toml` parses to
//! exactly this), for tests and examples that need a suit without a file.

use std::fmt;

use calib_core::{DhTable, JointRanges, ParamKind, RateBias};

use crate::MAX_JOINTS;

/// How much a recording's span may differ from the window's and still count as that long: a
/// live window runs from the daemon's start to the tick that ends it, a recording from its
/// first to its last frame (`crate::window::Window::at_end` lets a recording be this much
/// shorter than `min_duration_s`; a [`Budget`] lets it be this much longer than
/// `max_duration_s`).
pub const DURATION_SLACK_S: f64 = 1.0;

/// Most frames a 1 Mbit/s CAN bus carries in a second: the shortest frame (11-bit identifier,
/// no data) with its interframe space is 47 bits.
pub const MAX_BUS_FRAMES_PER_S: f64 = 1.0e6 / 47.0;

/// Anatomical bounds a table must respect to be pushed (SI units). [`Bounds::table`] turns
/// them into calib-core's per-parameter [`calib_core::Bounds`].
#[derive(Debug, Clone, PartialEq)]
pub struct Bounds {
    /// Allowed `a_i` (m), `(min, max)`.
    pub a: [(f64, f64); MAX_JOINTS],
    /// Allowed `d_i` (m), `(min, max)`.
    pub d: [(f64, f64); MAX_JOINTS],
    /// Largest |α_i − nominal α_i| (rad).
    pub alpha_deviation: f64,
    /// Largest |offset_i − nominal offset_i| (rad).
    pub offset_deviation: f64,
    /// Anatomical rotation range of each joint (rad).
    pub joint_range: JointRanges<MAX_JOINTS>,
}

impl Bounds {
    /// The per-parameter bounds of a table whose nominal is `nominal`: `a` and `d` as
    /// configured, `α` and the joint offset within their deviation of nominal (calib-core
    /// compares angles modulo 2π), for the first `joints` rows (the arm's; the padding is
    /// unbounded, [`crate::arm`]).
    pub fn table(
        &self,
        nominal: &DhTable<MAX_JOINTS>,
        joints: usize,
    ) -> calib_core::Bounds<MAX_JOINTS> {
        let mut b = calib_core::Bounds::none();
        for (j, row) in nominal.rows.iter().enumerate().take(joints) {
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

impl WindowRules {
    /// The longest span a recording of one session may have (s): `max_duration_s` plus
    /// [`DURATION_SLACK_S`].
    pub fn max_span_s(&self) -> f64 {
        self.max_duration_s + DURATION_SLACK_S
    }

    /// Most received frames a session can hold: [`WindowRules::max_span_s`] of a saturated
    /// 1 Mbit/s bus ([`MAX_BUS_FRAMES_PER_S`]).
    pub fn max_frames(&self) -> usize {
        (self.max_span_s() * MAX_BUS_FRAMES_PER_S).ceil() as usize
    }

    /// Most points of a session's alignment grid, hence most samples it calibrates on:
    /// ⌊[`WindowRules::max_span_s`] × `grid_hz`⌋ + 1.
    pub fn max_samples(&self) -> usize {
        (self.max_span_s() * self.grid_hz).floor() as usize + 1
    }
}

/// What a recording is counted in.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Item {
    /// Received frames (a session log, a candump log).
    Frame,
    /// Samples (CSV).
    Sample,
}

impl fmt::Display for Item {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Item::Frame => "frame",
            Item::Sample => "sample",
        })
    }
}

/// Why a recording is more than one session under the rules could be.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Beyond {
    /// More items than the session could hold.
    Count {
        /// What is counted.
        item: Item,
        /// The most it could hold.
        max: usize,
        /// [`WindowRules::max_span_s`].
        max_span_s: f64,
        /// For samples, `grid_hz`.
        grid_hz: f64,
    },
    /// Items further apart in time than the session could be long.
    Span {
        /// What is counted.
        item: Item,
        /// From the earliest to the latest item so far (s).
        span_s: f64,
        /// [`WindowRules::max_span_s`].
        max_span_s: f64,
    },
}

impl fmt::Display for Beyond {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            Beyond::Count {
                item: Item::Frame,
                max,
                max_span_s,
                ..
            } => write!(
                f,
                "more than {max} frames, more than a 1 Mbit/s bus carries ({MAX_BUS_FRAMES_PER_S:.0} \
                 frames/s) in the longest session this configuration collects ({max_span_s} s: \
                 session.max_duration_s + {DURATION_SLACK_S} s)"
            ),
            Beyond::Count {
                item: Item::Sample,
                max,
                max_span_s,
                grid_hz,
            } => write!(
                f,
                "more than {max} samples, more than the longest session this configuration \
                 collects holds ({max_span_s} s: session.max_duration_s + {DURATION_SLACK_S} s, \
                 on the session.grid_hz = {grid_hz} Hz grid)"
            ),
            Beyond::Span {
                item,
                span_s,
                max_span_s,
            } => write!(
                f,
                "this {item} is {span_s:.6} s away from another: the recording spans more than the \
                 longest session this configuration collects ({max_span_s} s: \
                 session.max_duration_s + {DURATION_SLACK_S} s)"
            ),
        }
    }
}

impl std::error::Error for Beyond {}

/// The most a recording may hold under the window's rules — what one live session could have
/// collected — checked item by item as the recording is read, so that a reader refuses a
/// longer one at its first item too many, with bounded memory, instead of after reading it.
#[derive(Debug, Clone)]
pub struct Budget {
    item: Item,
    max: usize,
    max_span_s: f64,
    grid_hz: f64,
    count: usize,
    /// Earliest and latest time so far.
    span: Option<(f64, f64)>,
}

impl Budget {
    /// For received frames: at most [`WindowRules::max_frames`], within
    /// [`WindowRules::max_span_s`] of each other.
    pub fn frames(rules: &WindowRules) -> Budget {
        Budget::new(Item::Frame, rules.max_frames(), rules)
    }

    /// For samples: at most [`WindowRules::max_samples`], within [`WindowRules::max_span_s`]
    /// of each other.
    pub fn samples(rules: &WindowRules) -> Budget {
        Budget::new(Item::Sample, rules.max_samples(), rules)
    }

    fn new(item: Item, max: usize, rules: &WindowRules) -> Budget {
        Budget {
            item,
            max,
            max_span_s: rules.max_span_s(),
            grid_hz: rules.grid_hz,
            count: 0,
            span: None,
        }
    }

    /// Counts one item at time `t_s` (s; a time that is not finite is not a time and counts
    /// only as an item), or says why it is one too many.
    pub fn admit(&mut self, t_s: f64) -> Result<(), Beyond> {
        if self.count >= self.max {
            return Err(Beyond::Count {
                item: self.item,
                max: self.max,
                max_span_s: self.max_span_s,
                grid_hz: self.grid_hz,
            });
        }
        if t_s.is_finite() {
            let (lo, hi) = self
                .span
                .map_or((t_s, t_s), |(a, b)| (a.min(t_s), b.max(t_s)));
            if hi - lo > self.max_span_s {
                return Err(Beyond::Span {
                    item: self.item,
                    span_s: hi - lo,
                    max_span_s: self.max_span_s,
                });
            }
            self.span = Some((lo, hi));
        }
        self.count += 1;
        Ok(())
    }
}

/// What a calibration must satisfy to be pushed (the configuration's `[validation]`).
#[derive(Debug, Clone, PartialEq)]
pub struct ValidationRules {
    /// Largest condition number of the (column-scaled) identification problem.
    pub max_condition_number: f64,
    /// Fraction (0, 1) of the session, at its end, kept out of the fit.
    pub holdout_fraction: f64,
    /// Largest expected table error (1σ, RMS position over the joint ranges, mm) a pushed
    /// table may have, from the drift EM's Cramér-Rao bound.
    pub max_expected_position_error_mm: f64,
    /// The same for rotation (mrad).
    pub max_expected_rotation_error_mrad: f64,
}

/// The rate bias weighed when the sensors' spec is not configured (°/s, a ramp): what one this
/// size, too small for a session to show, would add to the table error is stated beside the
/// expected error (calib-core's `DriftEmOptions::consider`); it scales linearly with the size.
pub const UNCONFIGURED_RATE_BIAS_DEG_S: f64 = 0.01;

/// What the suit's angle sensors are known to do beyond the paper's model (the configuration's
/// optional `[sensors]`): a rate bias left after fusion, from the sensors' spec. The drift EM
/// then keeps a rate bias in every joint's model whatever one session's data say: a small
/// ramp over half a minute is too weak for the data alone to choose, yet shifts the joint
/// offsets by millimetres (calib-core's README, the field sweep).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct SensorSpec {
    /// The rate bias (none by default).
    pub rate_bias: RateBias,
    /// The joints whose reading integrates the node's gyro with nothing to correct its heading
    /// (no gravity reference about a vertical axis, no magnetometer): where the suit holds
    /// still, their rates measure the gyro's bias, which is then taken out of their readings
    /// (`pipeline::gyro_at_rest`). None by default.
    pub unaided: [bool; MAX_JOINTS],
}

/// The joints of `set` as people number them, `1, 3, 5` (the configuration's, the summary's and
/// the refusals' form); empty for none.
pub fn joint_list(set: &[bool]) -> String {
    let names: Vec<String> = (0..set.len())
        .filter(|&j| set[j])
        .map(|j| (j + 1).to_string())
        .collect();
    names.join(", ")
}

/// Everything the data path reads: the suit and the session's rules.
#[derive(Debug, Clone, PartialEq)]
pub struct Settings {
    /// Joints of the arm (1..=[`MAX_JOINTS`]): every per-joint array's first `joints` entries
    /// are the arm's, the rest zero ([`crate::arm`]).
    pub joints: usize,
    /// CAN node id of the node on joint `i + 1`.
    pub joint_nodes: [u8; MAX_JOINTS],
    /// The nominal D-H table the suit was built to.
    pub nominal: DhTable<MAX_JOINTS>,
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
    /// The same suit's arm of its first `joints` joints (at most [`Settings::joints`]): the
    /// rows, ranges, node ids and unaided joints past them cleared ([`crate::arm`]).
    pub fn first(&self, joints: usize) -> Settings {
        let joints = joints.clamp(1, self.joints.clamp(1, MAX_JOINTS));
        let mut s = self.clone();
        s.joints = joints;
        for j in joints..MAX_JOINTS {
            s.joint_nodes[j] = 0;
            s.nominal.rows[j] = crate::arm::ZERO_ROW;
            s.bounds.a[j] = (0.0, 0.0);
            s.bounds.d[j] = (0.0, 0.0);
            s.bounds.joint_range.limits[j] = (0.0, 0.0);
            s.sensors.unaided[j] = false;
        }
        s
    }

    /// The shipped configuration's values (`daemon/exocald.toml`): the paper's Table 1 arm,
    /// Table 2 and 3 bounds, a minute's window on a 100 Hz grid.
    pub fn suit_default() -> Settings {
        let deg = f64::to_radians;
        let nominal = DhTable::paper_nominal();
        let small = (-0.05, 0.05);
        Settings {
            joints: MAX_JOINTS,
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
                d: [small; MAX_JOINTS],
                alpha_deviation: deg(10.0),
                offset_deviation: deg(15.0),
                joint_range: JointRanges::paper(),
            },
            window: WindowRules {
                min_duration_s: 20.0,
                max_duration_s: 180.0,
                excitation_required: 0.5,
                min_samples: 1000,
                grid_hz: 100.0,
                max_gap_s: 0.05,
                stop_at_expected_error: Some((2.0, 6.0)),
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
