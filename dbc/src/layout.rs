//! The types the generated protocol tables are made of, and the table-driven half of the codec.
//!
//! Contract: every frame is classic CAN, DLC 8, every signal little-endian (Intel); `build.rs`
//! refuses a DBC that needs anything else. A [`SignalSpec`] reads and writes one signal's raw
//! and physical value. [`lookup`] maps an identifier to its message and node, and
//! [`MessageSpec::check`] accepts a payload only if every signal the frame carries (the plain
//! ones, the switch, and the cases the switch selects) holds a raw value within its DBC range or
//! its invalid marker, and, where the signal has a `VAL_` table, a value the table lists. After
//! the check, [`SignalSpec::raw`] and [`SignalSpec::value`] cannot read anything the DBC does
//! not allow; the typed mapping in [`crate::message`] relies on it.

use crate::spec::{Kind, ALL};
use crate::{DecodeError, EncodeError, NodeId};

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
    /// Raw value that means "invalid" (decoded as NaN): the `VAL_` entry named `Invalid`.
    pub invalid_raw: Option<i64>,
    /// The other `VAL_` entries: when there are any, the signal holds one of these raw values.
    pub values: &'static [(i64, &'static str)],
}

impl SignalSpec {
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

    /// The physical value in `data`; the invalid marker reads as NaN. No range check: call it
    /// on a frame [`MessageSpec::check`] accepted.
    pub fn value(&self, data: &[u8; 8]) -> f64 {
        let raw = self.raw(data);
        if self.invalid_raw == Some(raw) {
            f64::NAN
        } else {
            raw as f64 * self.factor + self.offset
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

    /// Checks the raw value in `data`: within range or the invalid marker, and listed in the
    /// `VAL_` table if the signal has one (else [`DecodeError::BadMux`] for the switch,
    /// [`DecodeError::BadEnum`] for any other signal).
    pub fn check(&self, id: u16, data: &[u8; 8]) -> Result<(), DecodeError> {
        let raw = self.raw(data);
        if self.invalid_raw == Some(raw) {
            return Ok(());
        }
        let (lo, hi) = self.raw_bounds();
        if raw < lo || raw > hi {
            return Err(DecodeError::OutOfRange {
                id,
                signal: self.name,
            });
        }
        if self.values.is_empty() || self.values.iter().any(|(v, _)| *v == raw) {
            Ok(())
        } else if self.mux == MuxRole::Switch {
            // `build.rs` admits switches of at most 8 bits.
            Err(DecodeError::BadMux {
                id,
                value: raw as u8,
            })
        } else {
            Err(DecodeError::BadEnum {
                id,
                signal: self.name,
            })
        }
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
fn round(x: f64) -> i64 {
    if x >= 0.0 {
        (x + 0.5) as i64
    } else {
        (x - 0.5) as i64
    }
}

/// One message family: the same layout sent by (or to) each node in `nodes`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MessageSpec {
    /// Which family.
    pub kind: Kind,
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
    pub const fn id(&self, node: u8) -> u16 {
        if self.nodes.is_empty() {
            self.base_id
        } else {
            self.base_id | node as u16
        }
    }

    /// The identifier of this message for `node`, if the family exists for it.
    pub fn id_for(&self, node: NodeId) -> Result<u16, EncodeError> {
        if self.nodes.contains(&node.raw()) {
            Ok(self.id(node.raw()))
        } else {
            Err(EncodeError::BadNode(node))
        }
    }

    /// Looks a signal up by name.
    pub fn signal(&self, name: &str) -> Option<&'static SignalSpec> {
        self.signals.iter().find(|s| s.name == name)
    }

    /// Checks every signal `data` carries for this message (see the module docs): the switch
    /// first, then the others in DBC order.
    pub fn check(&self, id: u16, data: &[u8; 8]) -> Result<(), DecodeError> {
        let switch = self.signals.iter().find(|s| s.mux == MuxRole::Switch);
        if let Some(s) = switch {
            s.check(id, data)?;
        }
        let selected = switch.map(|s| s.raw(data));
        for s in self.signals {
            let carried = match s.mux {
                MuxRole::Plain => true,
                MuxRole::Switch => false,
                MuxRole::Case(v) => selected == Some(i64::from(v)),
            };
            if carried {
                s.check(id, data)?;
            }
        }
        Ok(())
    }
}

/// The message family of an 11-bit identifier, and the node in its low bits (`None` for a
/// family without nodes); `None` when the DBC defines no message with this identifier.
pub fn lookup(id: u16) -> Option<(&'static MessageSpec, Option<NodeId>)> {
    ALL.iter().find_map(|&spec| {
        if spec.nodes.is_empty() {
            return (spec.base_id == id).then_some((spec, None));
        }
        let node = (id & 0xF) as u8;
        if id & !0xF == spec.base_id && spec.nodes.contains(&node) {
            Some((spec, Some(NodeId::new(node)?)))
        } else {
            None
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::spec::{heartbeat, joint_state, table_cmd, trigger, TABLE_CMD, TRIGGER};

    #[test]
    fn raw_bits_round_trip_signed_and_unsigned() {
        let (angle, rate, ts) = (
            joint_state::ANGLE,
            joint_state::RATE,
            joint_state::TIMESTAMP,
        );
        let mut d = [0u8; 8];
        angle.put_raw(&mut d, -3);
        assert_eq!(angle.raw(&d), -3);
        rate.put_raw(&mut d, 2047);
        assert_eq!(rate.raw(&d), 2047);
        assert_eq!(angle.raw(&d), -3, "neighbouring signal untouched");
        ts.put_raw(&mut d, u32::MAX as i64);
        assert_eq!(ts.raw(&d), u32::MAX as i64);
    }

    #[test]
    fn encode_rejects_out_of_range_and_infinity_and_maps_nan() {
        let angle = joint_state::ANGLE;
        let mut d = [0u8; 8];
        assert_eq!(
            angle.encode(&mut d, 5.3),
            Err(EncodeError::OutOfRange { signal: "Angle" })
        );
        assert_eq!(
            angle.encode(&mut d, f64::INFINITY),
            Err(EncodeError::NotFinite { signal: "Angle" })
        );
        angle.encode(&mut d, f64::NAN).unwrap();
        assert!(angle.value(&d).is_nan());
        assert_eq!(angle.check(0x101, &d), Ok(()));
        assert_eq!(
            table_cmd::SEG_TAU.encode(&mut d, f64::NAN),
            Err(EncodeError::NotFinite { signal: "SegTau" })
        );
        angle.encode(&mut d, -1.234566).unwrap();
        assert!((angle.value(&d) + 1.23457).abs() < 1e-12);
    }

    #[test]
    fn raw_bounds_follow_the_physical_range() {
        assert_eq!(joint_state::ANGLE.raw_bounds(), (-524287, 524287));
        assert_eq!(table_cmd::SEG_TAU.raw_bounds(), (1, u32::MAX as i64));
        assert_eq!(table_cmd::SEG_ALPHA.raw_bounds(), (-6283185, 6283185));
        assert_eq!(heartbeat::TABLE_CRC.raw_bounds(), (0, u32::MAX as i64));
    }

    #[test]
    fn lookup_finds_family_and_node_and_nothing_else() {
        let (spec, node) = lookup(0x603).unwrap();
        assert_eq!((spec.kind, node), (Kind::TableCmd, NodeId::new(3)));
        assert_eq!(TABLE_CMD.id_for(NodeId::new(3).unwrap()), Ok(0x603));
        assert_eq!(
            lookup(TRIGGER.base_id).map(|(s, n)| (s.kind, n)),
            Some((Kind::Trigger, None))
        );
        assert!(
            lookup(0x608).is_none(),
            "no TableCmd for the end-effector node"
        );
        assert!(lookup(0x600).is_none(), "node 0 is the controller");
        let every = (0..0x800).filter(|&id| lookup(id).is_some()).count();
        let declared: usize = ALL.iter().map(|s| s.nodes.len().max(1)).sum();
        assert_eq!(every, declared);
    }

    #[test]
    fn check_reports_the_switch_the_enumeration_and_the_range() {
        let mut d = [0u8; 8];
        table_cmd::CMD.put_raw(&mut d, 2);
        assert_eq!(
            TABLE_CMD.check(0x601, &d),
            Err(DecodeError::BadMux {
                id: 0x601,
                value: 2
            })
        );
        table_cmd::CMD.put_raw(&mut d, i64::from(table_cmd::cmd::ABORT));
        assert_eq!(TABLE_CMD.check(0x601, &d), Ok(()));
        table_cmd::CMD.put_raw(&mut d, i64::from(table_cmd::cmd::BEGIN));
        assert_eq!(
            TABLE_CMD.check(0x601, &d),
            Err(DecodeError::OutOfRange {
                id: 0x601,
                signal: "SegmentCount"
            }),
            "a case the switch selects is checked"
        );
        table_cmd::CMD.put_raw(&mut d, i64::from(table_cmd::cmd::COMMIT_AUTH));
        assert_eq!(
            TABLE_CMD.check(0x601, &d),
            Ok(()),
            "cases not selected are not"
        );
        let mut t = [0u8; 8];
        assert_eq!(
            TRIGGER.check(0x020, &t),
            Err(DecodeError::OutOfRange {
                id: 0x020,
                signal: "Command"
            })
        );
        trigger::COMMAND.put_raw(&mut t, i64::from(trigger::command::ABORT));
        assert_eq!(TRIGGER.check(0x020, &t), Ok(()));
    }
}
