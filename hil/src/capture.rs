//! A bus recorder: what `candump -L` would log, for tests and offline decoding.
//!
//! Contract: [`record`] keeps every frame a transport receives, with its receive timestamp,
//! until `stop` resolves and the bus has then been quiet for `quiet`; [`candump_line`] formats
//! one frame as a `candump -L` log line (`(secs.micros) iface ID#DATA`, 3 hex digits for
//! standard and 8 for extended identifiers, `R` for remote frames).

use exocal_bus::embedded_can::Frame as _;
use exocal_bus::{BusError, Received, Transport};
use std::future::Future;
use std::time::Duration;

/// Records frames until `stop` has resolved and nothing arrived for `quiet`.
pub async fn record<T: Transport, F: Future>(
    bus: &mut T,
    stop: F,
    quiet: Duration,
) -> Result<Vec<Received>, BusError> {
    let mut out = Vec::with_capacity(1 << 16);
    tokio::pin!(stop);
    let mut stopped = false;
    loop {
        tokio::select! {
            biased;
            r = bus.recv() => out.push(r?),
            _ = &mut stop, if !stopped => stopped = true,
            _ = tokio::time::sleep(quiet), if stopped => return Ok(out),
        }
    }
}

/// One `candump -L` line (without the newline).
pub fn candump_line(r: &Received, iface: &str) -> String {
    let f = &r.frame;
    let id = if f.is_extended() {
        format!("{:08X}", f.raw_id())
    } else {
        format!("{:03X}", f.raw_id())
    };
    let data: String = if f.is_remote_frame() {
        "R".to_string()
    } else {
        f.data().iter().map(|b| format!("{b:02X}")).collect()
    };
    format!(
        "({}.{:06}) {iface} {id}#{data}",
        r.timestamp.as_secs(),
        r.timestamp.subsec_micros()
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use exocal_bus::embedded_can::{ExtendedId, StandardId};
    use exocal_bus::{Frame, InProcessBus};

    #[test]
    fn lines_look_like_candump() {
        let r = |frame| Received {
            frame,
            timestamp: Duration::new(1_436_509_052, 249_713_000),
        };
        let std = Frame::new(StandardId::new(0x101).unwrap(), &[0, 0x11, 0xAB]).unwrap();
        assert_eq!(
            candump_line(&r(std), "vcan0"),
            "(1436509052.249713) vcan0 101#0011AB"
        );
        let ext = Frame::new(ExtendedId::new(0x1234).unwrap(), &[]).unwrap();
        assert_eq!(
            candump_line(&r(ext), "can0"),
            "(1436509052.249713) can0 00001234#"
        );
    }

    #[tokio::test]
    async fn records_until_stopped_and_quiet() {
        let bus = InProcessBus::new();
        let tx = bus.attach();
        let mut rx = bus.attach();
        for i in 0..5u8 {
            tx.send_now(&Frame::new(StandardId::new(0x100).unwrap(), &[i]).unwrap());
        }
        let got = record(&mut rx, async {}, Duration::from_millis(20))
            .await
            .unwrap();
        assert_eq!(got.len(), 5);
        assert_eq!(got[4].frame.data(), &[4]);
    }
}
