//! One node's calibration table: its D-H row and drift model, in fixed point.
//!
//! Contract: lengths in whole micrometres, angles in whole microradians, τ in microseconds and
//! σ in µrad/s, each within the range of its `TableCmd` segment signal in the DBC. The CRC-32
//! (ISO-HDLC, the one of `zlib.crc32`) is taken over the six raw values as 32-bit little-endian
//! words in sequence order (a, α, d, θ-offset, τ, σ): 24 bytes.

use crate::spec::{table_cmd, table_reply, SignalSpec};
use crate::EncodeError;

const CRC32: crc::Crc<u32> = crc::Crc::<u32>::new(&crc::CRC_32_ISO_HDLC);

/// The six fields of a table, in transfer order (sequence number = discriminant).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Field {
    /// D-H link length a (µm).
    A = 0,
    /// D-H link twist α (µrad).
    Alpha = 1,
    /// D-H link offset d (µm).
    D = 2,
    /// D-H joint-angle offset (µrad).
    ThetaOffset = 3,
    /// Drift correlation time τ (µs).
    Tau = 4,
    /// Drift deviation σ (µrad/s).
    Sigma = 5,
}

impl Field {
    /// All fields in sequence order.
    pub const ALL: [Field; 6] = [
        Field::A,
        Field::Alpha,
        Field::D,
        Field::ThetaOffset,
        Field::Tau,
        Field::Sigma,
    ];

    /// Field with this sequence number (0..6).
    pub const fn from_seq(seq: u8) -> Option<Field> {
        if (seq as usize) < 6 {
            Some(Field::ALL[seq as usize])
        } else {
            None
        }
    }

    /// Sequence number (0..6).
    pub const fn seq(self) -> u8 {
        self as u8
    }

    /// The `TableCmd` signal that carries this field (`SegA`, …).
    pub const fn segment(self) -> &'static SignalSpec {
        match self {
            Field::A => &table_cmd::SEG_A,
            Field::Alpha => &table_cmd::SEG_ALPHA,
            Field::D => &table_cmd::SEG_D,
            Field::ThetaOffset => &table_cmd::SEG_THETA_OFFSET,
            Field::Tau => &table_cmd::SEG_TAU,
            Field::Sigma => &table_cmd::SEG_SIGMA,
        }
    }

    /// The `TableReply` signal that reads this field back (`RbA`, …).
    pub const fn readback(self) -> &'static SignalSpec {
        match self {
            Field::A => &table_reply::RB_A,
            Field::Alpha => &table_reply::RB_ALPHA,
            Field::D => &table_reply::RB_D,
            Field::ThetaOffset => &table_reply::RB_THETA_OFFSET,
            Field::Tau => &table_reply::RB_TAU,
            Field::Sigma => &table_reply::RB_SIGMA,
        }
    }

    /// Valid raw range of this field.
    pub fn raw_bounds(self) -> (i64, i64) {
        self.segment().raw_bounds()
    }

    /// SI value → raw, checked.
    pub fn raw_from_si(self, value: f64) -> Result<i64, EncodeError> {
        let spec = self.segment();
        let mut scratch = [0u8; 8];
        spec.encode(&mut scratch, value)?;
        Ok(spec.raw(&scratch))
    }

    /// Raw → SI value.
    fn si(self, raw: i64) -> f64 {
        let spec = self.segment();
        raw as f64 * spec.factor + spec.offset
    }
}

/// One node's table in raw (fixed-point) units. Construct with [`Table::from_raw`] or
/// [`Table::from_si`]; every instance is within range.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct Table {
    raw: [i64; 6],
}

impl Table {
    /// From raw values in sequence order, each checked against its range.
    pub fn from_raw(raw: [i64; 6]) -> Result<Table, EncodeError> {
        for (field, value) in Field::ALL.iter().zip(raw) {
            let (lo, hi) = field.raw_bounds();
            if value < lo || value > hi {
                return Err(EncodeError::OutOfRange {
                    signal: field.segment().name,
                });
            }
        }
        Ok(Table { raw })
    }

    /// From SI units: a, d in m; α, θ-offset in rad; τ in s; σ in rad/s. Rounded to the grid.
    pub fn from_si(
        a: f64,
        alpha: f64,
        d: f64,
        theta_offset: f64,
        tau: f64,
        sigma: f64,
    ) -> Result<Table, EncodeError> {
        let si = [a, alpha, d, theta_offset, tau, sigma];
        let mut raw = [0i64; 6];
        for (i, field) in Field::ALL.iter().enumerate() {
            raw[i] = field.raw_from_si(si[i])?;
        }
        Ok(Table { raw })
    }

    /// Raw value of one field.
    pub fn raw(&self, field: Field) -> i64 {
        self.raw[field as usize]
    }

    /// All raw values in sequence order.
    pub fn raw_values(&self) -> [i64; 6] {
        self.raw
    }

    /// SI value of one field (m, rad, s, rad/s).
    pub fn si(&self, field: Field) -> f64 {
        field.si(self.raw[field as usize])
    }

    /// `[a, α, d, θ-offset, τ, σ]` in SI units.
    pub fn to_si(&self) -> [f64; 6] {
        Field::ALL.map(|f| self.si(f))
    }

    /// The 24 bytes the CRC covers (and the emulated flash stores).
    pub fn to_bytes(&self) -> [u8; 24] {
        let mut out = [0u8; 24];
        for (chunk, r) in out.chunks_exact_mut(4).zip(self.raw) {
            chunk.copy_from_slice(&(r as u32).to_le_bytes());
        }
        out
    }

    /// Inverse of [`Table::to_bytes`], range-checked.
    pub fn from_bytes(bytes: &[u8; 24]) -> Result<Table, EncodeError> {
        let mut raw = [0i64; 6];
        for (i, chunk) in bytes.chunks_exact(4).enumerate() {
            let word = u32::from_le_bytes([chunk[0], chunk[1], chunk[2], chunk[3]]);
            raw[i] = if Field::ALL[i].segment().signed {
                i64::from(word as i32)
            } else {
                i64::from(word)
            };
        }
        Table::from_raw(raw)
    }

    /// CRC-32 of the table.
    pub fn crc(&self) -> u32 {
        crc32(&self.to_bytes())
    }
}

/// CRC-32/ISO-HDLC of `bytes` (the one of `zlib.crc32`).
pub fn crc32(bytes: &[u8]) -> u32 {
    CRC32.checksum(bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn crc_matches_zlib_check_value() {
        assert_eq!(crc32(b"123456789"), 0xCBF4_3926);
    }

    #[test]
    fn si_round_trip_is_within_half_a_micro_unit() {
        let t = Table::from_si(0.431, -1.2345678, 0.0, 1.2345678, 1.0, 1.0).unwrap();
        let si = t.to_si();
        for (got, want) in si.iter().zip([0.431, -1.2345678, 0.0, 1.2345678, 1.0, 1.0]) {
            assert!((got - want).abs() <= 0.5e-6, "{got} vs {want}");
        }
        assert_eq!(Table::from_bytes(&t.to_bytes()), Ok(t));
    }

    #[test]
    fn out_of_range_fields_are_refused_by_name() {
        assert_eq!(
            Table::from_si(1.5, 0.0, 0.0, 0.0, 1.0, 1.0),
            Err(EncodeError::OutOfRange { signal: "SegA" })
        );
        assert_eq!(
            Table::from_si(0.0, 0.0, 0.0, 0.0, 0.0, 1.0),
            Err(EncodeError::OutOfRange { signal: "SegTau" })
        );
        assert_eq!(
            Table::from_raw([0, 0, 0, 0, 1, -1]),
            Err(EncodeError::OutOfRange { signal: "SegSigma" })
        );
    }
}
