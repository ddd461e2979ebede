//! Smoke test of the harness: a real kernel CAN bus carries 10,000 frames intact and in order.
//!
//! Needs vcan0: run through `cargo xtask test` or `cargo xtask vcan -- <this binary>`.

use std::time::Duration;

use embedded_can::{Frame as _, StandardId};
use socketcan::tokio::CanSocket;
use socketcan::{CanFrame, SocketOptions};

const FRAMES: u32 = 10_000;

/// The payload of frame `n`: its sequence number and a checksum-like pattern, so that a
/// corrupted, duplicated or reordered frame is told apart.
fn frame(n: u32) -> CanFrame {
    let id = StandardId::new((n % 0x7ff) as u16 + 1).expect("11-bit id");
    let seq = n.to_le_bytes();
    let mix = n.wrapping_mul(2_654_435_761).to_le_bytes();
    let data = [
        seq[0], seq[1], seq[2], seq[3], mix[0], mix[1], mix[2], mix[3],
    ];
    CanFrame::new(id, &data[..(n % 9) as usize]).expect("classic frame")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn vcan0_carries_10000_frames_intact_and_in_order() {
    exocal_tests::require_vcan("vcan0");
    let rx = CanSocket::open("vcan0").expect("open vcan0 for reading");
    let tx = CanSocket::open("vcan0").expect("open vcan0 for writing");
    // Large receive queue, as the daemon uses: the reader must never be the bottleneck.
    let big = 8 << 20;
    if rx
        .set_socket_option_int(libc::SOL_SOCKET, libc::SO_RCVBUFFORCE, big)
        .is_err()
    {
        rx.set_socket_option_int(libc::SOL_SOCKET, libc::SO_RCVBUF, big)
            .expect("SO_RCVBUF");
    }

    let reader = tokio::spawn(async move {
        let mut got = Vec::with_capacity(FRAMES as usize);
        while got.len() < FRAMES as usize {
            match tokio::time::timeout(Duration::from_secs(20), rx.read_frame()).await {
                Ok(Ok(f)) => got.push(f),
                Ok(Err(e)) => panic!("read error after {} frames: {e}", got.len()),
                Err(_) => break,
            }
        }
        got
    });
    for n in 0..FRAMES {
        tx.write_frame(frame(n)).await.expect("write frame");
    }
    let got = reader.await.expect("reader task");
    assert_eq!(got.len(), FRAMES as usize, "frames lost on vcan0");
    for (n, f) in got.iter().enumerate() {
        let want = frame(n as u32);
        assert_eq!(f.id(), want.id(), "frame {n}: id");
        assert_eq!(f.data(), want.data(), "frame {n}: data");
    }
    println!(
        "vcan0: {FRAMES} frames sent, {} received intact and in order",
        got.len()
    );
}
