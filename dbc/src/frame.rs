//! The wire: one classic CAN frame, and a frame with its receive time.
//!
//! Contract: [`Frame`] is the one frame type of the workspace (the transports send and receive
//! it, the codec decodes it, the log records it, readers of recorded sessions return it);
//! [`Received`] is a frame with its receive time since the transport clock's epoch, what the
//! data path takes in. No I/O, no clock: `no_std`.

use core::time::Duration;

use embedded_can::Id;

/// A classic CAN frame (0..=8 data bytes), standard or extended identifier, data or remote.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct Frame {
    id: Id,
    len: u8,
    data: [u8; 8],
    remote: bool,
}

impl embedded_can::Frame for Frame {
    fn new(id: impl Into<Id>, data: &[u8]) -> Option<Self> {
        if data.len() > 8 {
            return None;
        }
        let mut buf = [0u8; 8];
        buf[..data.len()].copy_from_slice(data);
        Some(Frame {
            id: id.into(),
            len: data.len() as u8,
            data: buf,
            remote: false,
        })
    }

    fn new_remote(id: impl Into<Id>, dlc: usize) -> Option<Self> {
        (dlc <= 8).then(|| Frame {
            id: id.into(),
            len: dlc as u8,
            data: [0; 8],
            remote: true,
        })
    }

    fn is_extended(&self) -> bool {
        matches!(self.id, Id::Extended(_))
    }

    fn is_remote_frame(&self) -> bool {
        self.remote
    }

    fn id(&self) -> Id {
        self.id
    }

    fn dlc(&self) -> usize {
        usize::from(self.len)
    }

    fn data(&self) -> &[u8] {
        if self.remote {
            &[]
        } else {
            &self.data[..usize::from(self.len)]
        }
    }
}

impl Frame {
    /// Copies any `embedded_can` frame.
    pub fn from_frame<F: embedded_can::Frame>(f: &F) -> Frame {
        if f.is_remote_frame() {
            Frame {
                id: f.id(),
                len: f.dlc().min(8) as u8,
                data: [0; 8],
                remote: true,
            }
        } else {
            let data = f.data();
            let len = data.len().min(8);
            let mut buf = [0u8; 8];
            buf[..len].copy_from_slice(&data[..len]);
            Frame {
                id: f.id(),
                len: len as u8,
                data: buf,
                remote: false,
            }
        }
    }

    /// Flips data bit `bit` (bit 0 = LSB of byte 0); a bit beyond the data is left alone. For
    /// fault injection: a corrupted frame as a noisy wire would deliver it.
    pub fn flip_bit(&mut self, bit: u32) {
        if !self.remote && bit < u32::from(self.len) * 8 {
            self.data[(bit / 8) as usize] ^= 1 << (bit % 8);
        }
    }

    /// The raw identifier (11 or 29 bits).
    pub fn raw_id(&self) -> u32 {
        match self.id {
            Id::Standard(id) => u32::from(id.as_raw()),
            Id::Extended(id) => id.as_raw(),
        }
    }
}

/// A frame as received, with its receive timestamp.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct Received {
    /// The frame.
    pub frame: Frame,
    /// Receive time since the transport clock's epoch (the UNIX epoch for SocketCAN and for the
    /// in-process bus's default clock).
    pub timestamp: Duration,
}

/// Why a `candump -L` line does not parse.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CandumpError {
    /// Not `(time) interface ID#DATA`, optionally followed by a direction flag.
    Shape,
    /// A fourth field other than the direction flag `R` (received) or `T` (transmitted).
    Direction,
    /// The `(seconds.fraction)` timestamp (1 to 9 fraction digits).
    Timestamp,
    /// No `#` between identifier and data.
    NoHash,
    /// A CAN FD frame (`##`): classic CAN only.
    Fd,
    /// An identifier of neither 3 nor 8 hex digits, or out of its range.
    Identifier,
    /// `R` followed by something other than one DLC digit.
    Remote,
    /// Data that is not hex byte pairs.
    Data,
    /// More than 8 data bytes.
    TooLong,
}

impl core::fmt::Display for CandumpError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(match self {
            CandumpError::Shape => {
                "expected `(time) interface ID#DATA`, optionally followed by `R` or `T`"
            }
            CandumpError::Direction => {
                "after `ID#DATA` only a direction flag may follow: `R` (received) or `T` (transmitted)"
            }
            CandumpError::Timestamp => "bad timestamp: expected `(seconds.fraction)`",
            CandumpError::NoHash => "no `#` between identifier and data",
            CandumpError::Fd => "CAN FD frames (`##`) are not supported",
            CandumpError::Identifier => {
                "bad identifier: 3 hex digits (≤ 7FF) or 8 hex digits (≤ 1FFFFFFF)"
            }
            CandumpError::Remote => "bad remote frame: `R` or `R` and one DLC digit",
            CandumpError::Data => "bad data: hex byte pairs",
            CandumpError::TooLong => "more than 8 data bytes",
        })
    }
}

impl Received {
    /// Parses one `candump -L` line, `(1700000000.123456) can0 123#DEADBEEF` (interface
    /// ignored; remote frames `ID#R` or `ID#R<dlc>`; exact nanosecond times). The line may end
    /// in a direction flag, ` R` or ` T`, as can-utils' `asc2log` and python-can's
    /// `CanutilsLogWriter` write them; it is ignored (a recorded frame is a frame on the bus,
    /// whichever way it went).
    pub fn from_candump(line: &str) -> Result<Received, CandumpError> {
        let mut parts = line.split_whitespace();
        let (Some(time), Some(_iface), Some(frame), direction, None) = (
            parts.next(),
            parts.next(),
            parts.next(),
            parts.next(),
            parts.next(),
        ) else {
            return Err(CandumpError::Shape);
        };
        if !matches!(direction, None | Some("R" | "T")) {
            return Err(CandumpError::Direction);
        }
        let timestamp = time
            .strip_prefix('(')
            .and_then(|t| t.strip_suffix(')'))
            .and_then(parse_time)
            .ok_or(CandumpError::Timestamp)?;
        let (id, data) = frame.split_once('#').ok_or(CandumpError::NoHash)?;
        if data.starts_with('#') {
            return Err(CandumpError::Fd);
        }
        let value = u32::from_str_radix(id, 16).map_err(|_| CandumpError::Identifier)?;
        let id: Id = match id.len() {
            3 => embedded_can::StandardId::new(u16::try_from(value).unwrap_or(u16::MAX))
                .map(Id::from),
            8 => embedded_can::ExtendedId::new(value).map(Id::from),
            _ => None,
        }
        .ok_or(CandumpError::Identifier)?;
        let frame = if let Some(rest) = data.strip_prefix('R') {
            let dlc = match rest.as_bytes() {
                [] => 0,
                [d] if d.is_ascii_digit() && *d <= b'8' => usize::from(d - b'0'),
                _ => return Err(CandumpError::Remote),
            };
            <Frame as embedded_can::Frame>::new_remote(id, dlc)
        } else {
            if data.len() % 2 != 0 || !data.bytes().all(|b| b.is_ascii_hexdigit()) {
                return Err(CandumpError::Data);
            }
            if data.len() > 16 {
                return Err(CandumpError::TooLong);
            }
            let mut bytes = [0u8; 8];
            for (i, b) in bytes.iter_mut().take(data.len() / 2).enumerate() {
                *b = u8::from_str_radix(&data[2 * i..2 * i + 2], 16)
                    .map_err(|_| CandumpError::Data)?;
            }
            <Frame as embedded_can::Frame>::new(id, &bytes[..data.len() / 2])
        }
        .ok_or(CandumpError::Data)?;
        Ok(Received { frame, timestamp })
    }

    /// This frame as a `candump -L` line on `iface` (no newline; microsecond times, as
    /// candump writes them): `format!("{}", rx.candump("can0"))`.
    pub fn candump<'a>(&'a self, iface: &'a str) -> CandumpLine<'a> {
        CandumpLine { rx: self, iface }
    }
}

/// A received frame as a `candump -L` line ([`Received::candump`]).
#[derive(Debug, Clone, Copy)]
pub struct CandumpLine<'a> {
    rx: &'a Received,
    iface: &'a str,
}

impl core::fmt::Display for CandumpLine<'_> {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        use embedded_can::Frame as _;
        let t = self.rx.timestamp;
        write!(
            f,
            "({}.{:06}) {} ",
            t.as_secs(),
            t.subsec_micros(),
            self.iface
        )?;
        let frame = &self.rx.frame;
        if frame.is_extended() {
            write!(f, "{:08X}#", frame.raw_id())?;
        } else {
            write!(f, "{:03X}#", frame.raw_id())?;
        }
        if frame.is_remote_frame() {
            f.write_str("R")
        } else {
            frame.data().iter().try_for_each(|b| write!(f, "{b:02X}"))
        }
    }
}

/// `"1700000000.123456"` → exact duration (1 to 9 fraction digits).
fn parse_time(s: &str) -> Option<Duration> {
    let (secs, frac) = s.split_once('.')?;
    let digits = |s: &str| !s.is_empty() && s.bytes().all(|b| b.is_ascii_digit());
    if !digits(secs) || !digits(frac) || frac.len() > 9 {
        return None;
    }
    let nanos: u32 = frac.parse::<u32>().ok()? * 10u32.pow(9 - frac.len() as u32);
    Some(Duration::new(secs.parse().ok()?, nanos))
}

#[cfg(test)]
mod tests {
    use super::*;
    use embedded_can::{ExtendedId, Frame as _, StandardId};

    #[test]
    fn frame_type_follows_embedded_can() {
        assert!(Frame::new(StandardId::new(1).unwrap(), &[0; 9]).is_none());
        let f = Frame::new(ExtendedId::new(0x1234_5678).unwrap(), &[1, 2, 3]).unwrap();
        assert!(f.is_extended());
        assert_eq!(
            (f.raw_id(), f.dlc(), f.data()),
            (0x1234_5678, 3, &[1u8, 2, 3][..])
        );
        let r = Frame::new_remote(StandardId::new(7).unwrap(), 4).unwrap();
        assert!(r.is_remote_frame() && r.data().is_empty() && r.dlc() == 4);
        assert_eq!(Frame::from_frame(&r), r);
    }

    #[test]
    fn a_flipped_bit_stays_within_the_data() {
        let mut f = Frame::new(StandardId::new(1).unwrap(), &[0, 0]).unwrap();
        f.flip_bit(9);
        assert_eq!(f.data(), &[0, 2]);
        f.flip_bit(16);
        assert_eq!(f.data(), &[0, 2]);
    }

    #[test]
    fn candump_lines_round_trip_exactly() {
        let rx = Received::from_candump("(1700000000.123456) vcan0 123#DEADBEEF").unwrap();
        assert_eq!(rx.timestamp, Duration::new(1_700_000_000, 123_456_000));
        assert_eq!(
            (rx.frame.raw_id(), rx.frame.data()),
            (0x123, &[0xDE, 0xAD, 0xBE, 0xEF][..])
        );
        extern crate std;
        use std::string::ToString;
        assert_eq!(
            rx.candump("vcan0").to_string(),
            "(1700000000.123456) vcan0 123#DEADBEEF"
        );
        let remote = Received::from_candump("(1.5) can1 001ABCDE#R").unwrap();
        assert!(remote.frame.is_extended() && remote.frame.is_remote_frame());
        assert_eq!(remote.timestamp, Duration::from_millis(1500));
        assert_eq!(
            remote.candump("can1").to_string(),
            "(1.500000) can1 001ABCDE#R"
        );
        let empty = Received::from_candump("(0.000001) can0 7FF#").unwrap();
        assert_eq!(empty.frame.data(), &[] as &[u8]);
    }

    /// can-utils' `asc2log` and python-can's `CanutilsLogWriter` end each line with the
    /// frame's direction; the frame is the one without it.
    #[test]
    fn a_direction_flag_is_read_and_ignored() {
        extern crate std;
        use std::format;
        let plain = Received::from_candump("(1700000000.123456) vcan0 123#DEADBEEF").unwrap();
        for flag in ["R", "T"] {
            let line = format!("(1700000000.123456) vcan0 123#DEADBEEF {flag}");
            assert_eq!(Received::from_candump(&line), Ok(plain), "{line}");
        }
        let remote = Received::from_candump("(1.5) can0 321#R R").unwrap();
        assert!(remote.frame.is_remote_frame() && remote.frame.raw_id() == 0x321);
    }

    #[test]
    fn a_bad_candump_line_says_what_is_wrong() {
        for (line, why) in [
            ("", CandumpError::Shape),
            ("(1.0) can0", CandumpError::Shape),
            ("(1.0) can0 123#00 extra", CandumpError::Direction),
            ("(1.0) can0 123#00 r", CandumpError::Direction),
            ("(1.0) can0 123#00 R extra", CandumpError::Shape),
            ("1.0 can0 123#00", CandumpError::Timestamp),
            ("(1.0000000001) can0 123#00", CandumpError::Timestamp),
            ("(-1.0) can0 123#00", CandumpError::Timestamp),
            ("(1.0) can0 12300", CandumpError::NoHash),
            ("(1.0) can0 123##100", CandumpError::Fd),
            ("(1.0) can0 800#00", CandumpError::Identifier),
            ("(1.0) can0 12#00", CandumpError::Identifier),
            ("(1.0) can0 20000000#00", CandumpError::Identifier),
            ("(1.0) can0 1G3#00", CandumpError::Identifier),
            ("(1.0) can0 123#R9", CandumpError::Remote),
            ("(1.0) can0 123#0", CandumpError::Data),
            ("(1.0) can0 123#ZZ", CandumpError::Data),
            ("(1.0) can0 123#001122334455667788", CandumpError::TooLong),
        ] {
            assert_eq!(Received::from_candump(line), Err(why), "{line:?}");
        }
    }
}
