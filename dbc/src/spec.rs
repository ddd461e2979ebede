//! Signal and message layouts, written out by hand from `exocal.dbc`.
//!
//! Contract: every frame is classic CAN, DLC 8, every signal little-endian (Intel). These tables
//! are what the codec in [`crate::message`] reads and writes; the test `tests/dbc_file.rs` parses
//! the `.dbc` with the `can-dbc` crate and checks every entry here against it (id, DLC, start
//! bit, length, signedness, factor, offset, min, max, unit, multiplexing), so the DBC file stays
//! the single source of truth.

use crate::{DecodeError, EncodeError};

/// How a signal takes part in multiplexing.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MuxRole {
    /// Present in every frame of the message.
    Plain,
    /// The multiplexer switch itself (`M` in the DBC).
    Switch,
    /// Present only when the switch has this value (`m<value>` in the DBC).
    Case(u8),
}

/// One signal as the DBC declares it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SignalSpec {
    /// Signal name, unique within its message.
    pub name: &'static str,
    /// Start bit (little-endian numbering, bit 0 = LSB of byte 0).
    pub start: u8,
    /// Length in bits.
    pub len: u8,
    /// Two's complement signed raw value.
    pub signed: bool,
    /// physical = raw * factor + offset.
    pub factor: f64,
    /// physical = raw * factor + offset.
    pub offset: f64,
    /// Smallest valid physical value.
    pub min: f64,
    /// Largest valid physical value.
    pub max: f64,
    /// Unit string of the DBC.
    pub unit: &'static str,
    /// Multiplexing role.
    pub mux: MuxRole,
    /// Raw value that means "invalid" (decoded as NaN), listed in the DBC's `VAL_` table.
    pub invalid_raw: Option<i64>,
}

const fn sig(name: &'static str, start: u8, len: u8, signed: bool) -> SignalSpec {
    let max = if signed {
        ((1u64 << (len - 1)) - 1) as f64
    } else {
        ((1u128 << len) - 1) as f64
    };
    SignalSpec {
        name,
        start,
        len,
        signed,
        factor: 1.0,
        offset: 0.0,
        min: if signed { -max } else { 0.0 },
        max,
        unit: "",
        mux: MuxRole::Plain,
        invalid_raw: None,
    }
}

impl SignalSpec {
    const fn scaled(mut self, factor: f64, min: f64, max: f64, unit: &'static str) -> Self {
        self.factor = factor;
        self.min = min;
        self.max = max;
        self.unit = unit;
        self
    }
    const fn range(mut self, min: f64, max: f64) -> Self {
        self.min = min;
        self.max = max;
        self
    }
    const fn case(mut self, value: u8) -> Self {
        self.mux = MuxRole::Case(value);
        self
    }
    const fn switch(mut self) -> Self {
        self.mux = MuxRole::Switch;
        self
    }
    /// The most negative raw value marks "invalid" (NaN).
    const fn nan_at_min(mut self) -> Self {
        self.invalid_raw = Some(-(1i64 << (self.len - 1)));
        self
    }

    fn mask(&self) -> u64 {
        if self.len >= 64 {
            u64::MAX
        } else {
            (1u64 << self.len) - 1
        }
    }

    /// The raw value as stored in `data`, sign-extended, without any range check.
    pub fn raw(&self, data: &[u8; 8]) -> i64 {
        let bits = (u64::from_le_bytes(*data) >> self.start) & self.mask();
        if self.signed && self.len < 64 && bits >> (self.len - 1) & 1 == 1 {
            (bits | !self.mask()) as i64
        } else {
            bits as i64
        }
    }

    /// Writes `raw` into `data` (two's complement, truncated to the signal length).
    pub fn put_raw(&self, data: &mut [u8; 8], raw: i64) {
        let word = u64::from_le_bytes(*data) & !(self.mask() << self.start);
        *data = (word | ((raw as u64) & self.mask()) << self.start).to_le_bytes();
    }

    /// Valid raw range, from the DBC's physical min/max.
    pub fn raw_bounds(&self) -> (i64, i64) {
        (
            round((self.min - self.offset) / self.factor),
            round((self.max - self.offset) / self.factor),
        )
    }

    /// Raw value, checked against the valid range. The invalid marker is not accepted here.
    pub fn decode_raw(&self, id: u16, data: &[u8; 8]) -> Result<i64, DecodeError> {
        let raw = self.raw(data);
        let (lo, hi) = self.raw_bounds();
        if raw < lo || raw > hi {
            return Err(DecodeError::OutOfRange {
                id,
                signal: self.name,
            });
        }
        Ok(raw)
    }

    /// Physical value; the invalid marker decodes to NaN.
    pub fn decode(&self, id: u16, data: &[u8; 8]) -> Result<f64, DecodeError> {
        if self.invalid_raw.is_some() && self.invalid_raw == Some(self.raw(data)) {
            return Ok(f64::NAN);
        }
        let raw = self.decode_raw(id, data)?;
        Ok(raw as f64 * self.factor + self.offset)
    }

    /// Writes a raw value after checking it against the valid range.
    pub fn encode_raw(&self, data: &mut [u8; 8], raw: i64) -> Result<(), EncodeError> {
        let (lo, hi) = self.raw_bounds();
        if raw < lo || raw > hi {
            return Err(EncodeError::OutOfRange { signal: self.name });
        }
        self.put_raw(data, raw);
        Ok(())
    }

    /// Writes a physical value, rounded to the nearest raw step. NaN becomes the invalid marker
    /// where the signal has one; infinities and out-of-range values are errors.
    pub fn encode(&self, data: &mut [u8; 8], value: f64) -> Result<(), EncodeError> {
        if value.is_nan() {
            return match self.invalid_raw {
                Some(raw) => {
                    self.put_raw(data, raw);
                    Ok(())
                }
                None => Err(EncodeError::NotFinite { signal: self.name }),
            };
        }
        if value.is_infinite() {
            return Err(EncodeError::NotFinite { signal: self.name });
        }
        let scaled = (value - self.offset) / self.factor;
        let (lo, hi) = self.raw_bounds();
        if scaled < lo as f64 - 0.5 || scaled > hi as f64 + 0.5 {
            return Err(EncodeError::OutOfRange { signal: self.name });
        }
        self.encode_raw(data, round(scaled))
    }
}

/// Rounds half away from zero (no `std` needed). Only called on values already range-checked.
pub(crate) fn round(x: f64) -> i64 {
    if x >= 0.0 {
        (x + 0.5) as i64
    } else {
        (x - 0.5) as i64
    }
}

/// One message family: the same layout sent by (or to) each node in `nodes`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MessageSpec {
    /// DBC name prefix; the DBC message is `<name>_<NodeName>` (or `<name>` when `nodes` is empty).
    pub name: &'static str,
    /// Identifier base; the node id is OR-ed into the low 4 bits.
    pub base_id: u16,
    /// Node ids this family exists for (empty: one message, no node in the id).
    pub nodes: &'static [u8],
    /// Signals in DBC order.
    pub signals: &'static [SignalSpec],
}

impl MessageSpec {
    /// The identifier of this message for `node` (ignored when the family has no nodes).
    pub fn id(&self, node: u8) -> u16 {
        if self.nodes.is_empty() {
            self.base_id
        } else {
            self.base_id | u16::from(node)
        }
    }

    /// Looks a signal up by name.
    pub fn signal(&self, name: &str) -> Option<&'static SignalSpec> {
        self.signals.iter().find(|s| s.name == name)
    }
}

/// Every frame is 8 bytes.
pub const DLC: u8 = 8;

const JOINTS: &[u8] = &[1, 2, 3, 4, 5, 6, 7];
const ALL_NODES: &[u8] = &[1, 2, 3, 4, 5, 6, 7, 8];
const EE: &[u8] = &[8];

/// 2π rounded down to the DBC's 1 µrad grid (so it is not `TAU`).
#[allow(clippy::approx_constant)]
const TWO_PI: f64 = 6.283185;
/// Largest u32 raw value at a 1e-6 factor.
const U32_MICRO: f64 = 4294.967295;

pub(crate) mod s {
    use super::*;
    pub const JS_TIMESTAMP: SignalSpec =
        sig("Timestamp", 0, 32, false).scaled(1.0, 0.0, 4294967295.0, "us");
    pub const JS_ANGLE: SignalSpec = sig("Angle", 32, 20, true)
        .scaled(1e-5, -5.24287, 5.24287, "rad")
        .nan_at_min();
    pub const JS_RATE: SignalSpec = sig("Rate", 52, 12, true)
        .scaled(0.01, -20.47, 20.47, "rad/s")
        .nan_at_min();

    pub const EE_PAGE: SignalSpec = sig("Page", 0, 2, false).switch();
    pub const EE_SEQ: SignalSpec = sig("Seq", 2, 6, false);
    pub const EE_TIMESTAMP: SignalSpec = sig("Timestamp", 8, 32, false)
        .scaled(1.0, 0.0, 4294967295.0, "us")
        .case(0);
    pub const EE_POS_X: SignalSpec = sig("PosX", 40, 24, true)
        .scaled(1e-6, -2.0, 2.0, "m")
        .case(0);
    pub const EE_POS_Y: SignalSpec = sig("PosY", 8, 24, true)
        .scaled(1e-6, -2.0, 2.0, "m")
        .case(1);
    pub const EE_POS_Z: SignalSpec = sig("PosZ", 32, 24, true)
        .scaled(1e-6, -2.0, 2.0, "m")
        .case(1);
    pub const EE_QUAT_W: SignalSpec = sig("QuatW", 8, 24, true)
        .scaled(1e-6, -1.0, 1.0, "")
        .case(2);
    pub const EE_QUAT_X: SignalSpec = sig("QuatX", 32, 24, true)
        .scaled(1e-6, -1.0, 1.0, "")
        .case(2);
    pub const EE_QUAT_Y: SignalSpec = sig("QuatY", 8, 24, true)
        .scaled(1e-6, -1.0, 1.0, "")
        .case(3);
    pub const EE_QUAT_Z: SignalSpec = sig("QuatZ", 32, 24, true)
        .scaled(1e-6, -1.0, 1.0, "")
        .case(3);

    pub const fn imu(
        name: &'static str,
        start: u8,
        factor: f64,
        max: f64,
        unit: &'static str,
    ) -> SignalSpec {
        sig(name, start, 16, true)
            .scaled(factor, -max, max, unit)
            .nan_at_min()
    }
    pub const IMU_TIMESTAMP_LO: SignalSpec =
        sig("TimestampLo", 48, 16, false).scaled(1.0, 0.0, 65535.0, "us");
    pub const GYRO: [SignalSpec; 3] = [
        imu("X", 0, 0.001, 32.767, "rad/s"),
        imu("Y", 16, 0.001, 32.767, "rad/s"),
        imu("Z", 32, 0.001, 32.767, "rad/s"),
    ];
    pub const ACCEL: [SignalSpec; 3] = [
        imu("X", 0, 0.002, 65.534, "m/s^2"),
        imu("Y", 16, 0.002, 65.534, "m/s^2"),
        imu("Z", 32, 0.002, 65.534, "m/s^2"),
    ];
    pub const MAG: [SignalSpec; 3] = [
        imu("X", 0, 0.01, 327.67, "uT"),
        imu("Y", 16, 0.01, 327.67, "uT"),
        imu("Z", 32, 0.01, 327.67, "uT"),
    ];

    pub const HB_STATE: SignalSpec = sig("State", 0, 4, false).range(0.0, 3.0);
    pub const HB_BOOT_COUNT: SignalSpec = sig("BootCount", 4, 4, false);
    pub const HB_TX_ERRORS: SignalSpec = sig("TxErrors", 8, 8, false);
    pub const HB_RX_ERRORS: SignalSpec = sig("RxErrors", 16, 8, false);
    pub const HB_TABLE_CRC: SignalSpec = sig("TableCrc", 24, 32, false);
    pub const HB_FW_MAJOR: SignalSpec = sig("FwMajor", 56, 4, false);
    pub const HB_FW_MINOR: SignalSpec = sig("FwMinor", 60, 4, false);

    pub const CMD: SignalSpec = sig("Cmd", 0, 8, false).switch();
    pub const CMD_SESSION: SignalSpec = sig("Session", 8, 8, false);
    pub const CMD_SEGMENT_COUNT: SignalSpec =
        sig("SegmentCount", 16, 8, false).range(6.0, 6.0).case(1);
    pub const CMD_TABLE_CRC: SignalSpec = sig("TableCrc", 16, 32, false).case(32);
    pub const CMD_COUNTER_LO: SignalSpec = sig("CounterLo", 16, 16, false).case(33);
    pub const CMD_COMMIT_MAC: SignalSpec = sig("CommitMac", 32, 32, false).case(33);
    pub const CMD_NONCE: SignalSpec = sig("Nonce", 16, 32, false).case(48);

    const fn seg(
        name: &'static str,
        code: u8,
        signed: bool,
        unit: &'static str,
        min: f64,
        max: f64,
    ) -> SignalSpec {
        sig(name, 16, 32, signed)
            .scaled(1e-6, min, max, unit)
            .case(code)
    }
    /// Table segments in sequence order (commands 16..21).
    pub const SEGMENTS: [SignalSpec; 6] = [
        seg("SegA", 16, true, "m", -1.0, 1.0),
        seg("SegAlpha", 17, true, "rad", -TWO_PI, TWO_PI),
        seg("SegD", 18, true, "m", -1.0, 1.0),
        seg("SegThetaOffset", 19, true, "rad", -TWO_PI, TWO_PI),
        seg("SegTau", 20, false, "s", 1e-6, U32_MICRO),
        seg("SegSigma", 21, false, "rad/s", 0.0, U32_MICRO),
    ];

    pub const REPLY: SignalSpec = sig("Reply", 0, 8, false).switch();
    pub const REPLY_SESSION: SignalSpec = sig("Session", 8, 8, false);
    pub const ACKED_CMD: SignalSpec = sig("AckedCmd", 16, 8, false).case(0);
    pub const HELD_CRC: SignalSpec = sig("HeldCrc", 24, 32, false).case(0);
    pub const NACKED_CMD: SignalSpec = sig("NackedCmd", 16, 8, false).case(1);
    pub const NACK_HELD_CRC: SignalSpec = sig("NackHeldCrc", 24, 32, false).case(1);
    pub const NACK_REASON: SignalSpec = sig("NackReason", 56, 8, false).range(1.0, 11.0).case(1);
    pub const NODE_COUNTER: SignalSpec = sig("NodeCounter", 16, 32, false).case(2);
    pub const RB_MAC: SignalSpec = sig("RbMac", 16, 32, false).case(3);
    /// Readback segments in sequence order (replies 16..21).
    pub const READBACK: [SignalSpec; 6] = [
        seg("RbA", 16, true, "m", -1.0, 1.0),
        seg("RbAlpha", 17, true, "rad", -TWO_PI, TWO_PI),
        seg("RbD", 18, true, "m", -1.0, 1.0),
        seg("RbThetaOffset", 19, true, "rad", -TWO_PI, TWO_PI),
        seg("RbTau", 20, false, "s", 1e-6, U32_MICRO),
        seg("RbSigma", 21, false, "rad/s", 0.0, U32_MICRO),
    ];

    pub const TRIGGER_COMMAND: SignalSpec = sig("Command", 0, 8, false).range(1.0, 2.0);
    pub const TRIGGER_COUNTER_LO: SignalSpec = sig("CounterLo", 16, 16, false);
    pub const TRIGGER_MAC: SignalSpec = sig("Mac", 32, 32, false);
}

use s::*;

/// `JointState_<node>`: fused joint angle, rate and node timestamp.
pub static JOINT_STATE: MessageSpec = MessageSpec {
    name: "JointState",
    base_id: 0x100,
    nodes: JOINTS,
    signals: &[JS_TIMESTAMP, JS_ANGLE, JS_RATE],
};
/// `EePose_EndEffector`: the four pages of an end-effector pose.
pub static EE_POSE: MessageSpec = MessageSpec {
    name: "EePose",
    base_id: 0x140,
    nodes: EE,
    signals: &[
        EE_PAGE,
        EE_SEQ,
        EE_TIMESTAMP,
        EE_POS_X,
        EE_POS_Y,
        EE_POS_Z,
        EE_QUAT_W,
        EE_QUAT_X,
        EE_QUAT_Y,
        EE_QUAT_Z,
    ],
};
/// `ImuGyro_<node>`.
pub static IMU_GYRO: MessageSpec = MessageSpec {
    name: "ImuGyro",
    base_id: 0x200,
    nodes: ALL_NODES,
    signals: &[GYRO[0], GYRO[1], GYRO[2], IMU_TIMESTAMP_LO],
};
/// `ImuAccel_<node>`.
pub static IMU_ACCEL: MessageSpec = MessageSpec {
    name: "ImuAccel",
    base_id: 0x210,
    nodes: ALL_NODES,
    signals: &[ACCEL[0], ACCEL[1], ACCEL[2], IMU_TIMESTAMP_LO],
};
/// `ImuMag_<node>`.
pub static IMU_MAG: MessageSpec = MessageSpec {
    name: "ImuMag",
    base_id: 0x220,
    nodes: ALL_NODES,
    signals: &[MAG[0], MAG[1], MAG[2], IMU_TIMESTAMP_LO],
};
/// `TableReply_<node>`: node → controller.
pub static TABLE_REPLY: MessageSpec = MessageSpec {
    name: "TableReply",
    base_id: 0x580,
    nodes: JOINTS,
    signals: &[
        REPLY,
        REPLY_SESSION,
        ACKED_CMD,
        HELD_CRC,
        NACKED_CMD,
        NACK_HELD_CRC,
        NACK_REASON,
        NODE_COUNTER,
        RB_MAC,
        READBACK[0],
        READBACK[1],
        READBACK[2],
        READBACK[3],
        READBACK[4],
        READBACK[5],
    ],
};
/// `TableCmd_<node>`: controller → node.
pub static TABLE_CMD: MessageSpec = MessageSpec {
    name: "TableCmd",
    base_id: 0x600,
    nodes: JOINTS,
    signals: &[
        CMD,
        CMD_SESSION,
        CMD_SEGMENT_COUNT,
        SEGMENTS[0],
        SEGMENTS[1],
        SEGMENTS[2],
        SEGMENTS[3],
        SEGMENTS[4],
        SEGMENTS[5],
        CMD_TABLE_CRC,
        CMD_COUNTER_LO,
        CMD_COMMIT_MAC,
        CMD_NONCE,
    ],
};
/// `Heartbeat_<node>`.
pub static HEARTBEAT: MessageSpec = MessageSpec {
    name: "Heartbeat",
    base_id: 0x700,
    nodes: ALL_NODES,
    signals: &[
        HB_STATE,
        HB_BOOT_COUNT,
        HB_TX_ERRORS,
        HB_RX_ERRORS,
        HB_TABLE_CRC,
        HB_FW_MAJOR,
        HB_FW_MINOR,
    ],
};
/// `Trigger`: operator request, no node in the id.
pub static TRIGGER: MessageSpec = MessageSpec {
    name: "Trigger",
    base_id: 0x020,
    nodes: &[],
    signals: &[TRIGGER_COMMAND, TRIGGER_COUNTER_LO, TRIGGER_MAC],
};

/// Every message family of the protocol.
pub static ALL: [&MessageSpec; 9] = [
    &JOINT_STATE,
    &EE_POSE,
    &IMU_GYRO,
    &IMU_ACCEL,
    &IMU_MAG,
    &TABLE_REPLY,
    &TABLE_CMD,
    &HEARTBEAT,
    &TRIGGER,
];

/// DBC node names by node id (index 0 unused).
pub const NODE_NAMES: [&str; 9] = [
    "Controller",
    "Joint1",
    "Joint2",
    "Joint3",
    "Joint4",
    "Joint5",
    "Joint6",
    "Joint7",
    "EndEffector",
];

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn raw_bits_round_trip_signed_and_unsigned() {
        let mut d = [0u8; 8];
        JS_ANGLE.put_raw(&mut d, -3);
        assert_eq!(JS_ANGLE.raw(&d), -3);
        JS_RATE.put_raw(&mut d, 2047);
        assert_eq!(JS_RATE.raw(&d), 2047);
        assert_eq!(JS_ANGLE.raw(&d), -3, "neighbouring signal untouched");
        JS_TIMESTAMP.put_raw(&mut d, u32::MAX as i64);
        assert_eq!(JS_TIMESTAMP.raw(&d), u32::MAX as i64);
    }

    #[test]
    fn encode_rejects_out_of_range_and_infinity_and_maps_nan() {
        let mut d = [0u8; 8];
        assert_eq!(
            JS_ANGLE.encode(&mut d, 5.3),
            Err(EncodeError::OutOfRange { signal: "Angle" })
        );
        assert_eq!(
            JS_ANGLE.encode(&mut d, f64::INFINITY),
            Err(EncodeError::NotFinite { signal: "Angle" })
        );
        JS_ANGLE.encode(&mut d, f64::NAN).unwrap();
        assert!(JS_ANGLE.decode(0x101, &d).unwrap().is_nan());
        assert_eq!(
            SEGMENTS[4].encode(&mut d, f64::NAN),
            Err(EncodeError::NotFinite { signal: "SegTau" })
        );
        JS_ANGLE.encode(&mut d, -1.234566).unwrap();
        assert!((JS_ANGLE.decode(0x101, &d).unwrap() + 1.23457).abs() < 1e-12);
    }

    #[test]
    fn raw_bounds_follow_the_physical_range() {
        assert_eq!(JS_ANGLE.raw_bounds(), (-524287, 524287));
        assert_eq!(SEGMENTS[4].raw_bounds(), (1, u32::MAX as i64));
        assert_eq!(SEGMENTS[1].raw_bounds(), (-6283185, 6283185));
        assert_eq!(HB_TABLE_CRC.raw_bounds(), (0, u32::MAX as i64));
    }
}
