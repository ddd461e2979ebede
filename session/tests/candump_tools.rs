//! candump logs as the ecosystem writes them: a log of ours passed through can-utils
//! (`log2asc`, then `asc2log`) and through python-can (`CanutilsLogReader`, then
//! `CanutilsLogWriter`) comes back with a direction flag on every line (` R`), and from
//! `asc2log` on a new time base; the reader `exocald offline` uses ([`parse_candump`]) takes
//! every line, and the frames are ours: identifiers, data, remote frames, and times relative to
//! the first frame to the microsecond.
//!
//! Needs can-utils and the project's Python venv (`EXOCAL_PYTHON`), both installed by `cargo
//! xtask setup`: ignored under plain `cargo test`, run by `cargo xtask test`. Without them the
//! tests fail; they never skip.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

use embedded_can::{ExtendedId, Frame as _, Id, StandardId};
use exocal_dbc::{Frame, Received};
use exocal_session::formats::{candump_text, parse_candump};
use exocal_session::Settings;

fn scratch(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("exocal-candump-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// 600 frames in receive order, as a bus log holds them: standard and extended identifiers,
/// 0 to 8 data bytes, remote frames (of DLC 0: python-can writes a remote frame's DLC as
/// neither candump nor we do), irregular microsecond steps.
fn frames() -> Vec<Received> {
    let mut state = 0x2545_f491_u32;
    let mut next = move || {
        state ^= state << 13;
        state ^= state >> 17;
        state ^= state << 5;
        state
    };
    let mut t = Duration::new(1_700_000_000, 123_456_000);
    (0..600)
        .map(|i| {
            t += Duration::from_micros(u64::from(next() % 5_000) + 1);
            let id: Id = if i % 3 == 0 {
                ExtendedId::new(next() & 0x1FFF_FFFF).unwrap().into()
            } else {
                StandardId::new((next() & 0x7FF) as u16).unwrap().into()
            };
            let len = (next() % 9) as usize;
            let frame = if i % 17 == 0 {
                Frame::new_remote(id, 0).unwrap()
            } else {
                let bytes = next().to_le_bytes();
                let more = next().to_le_bytes();
                let data: Vec<u8> = bytes.iter().chain(&more).copied().take(len).collect();
                Frame::new(id, &data).unwrap()
            };
            Received {
                frame,
                timestamp: t,
            }
        })
        .collect()
}

/// What `path` holds, read as `exocald offline` reads a candump log.
fn read_back(path: &Path) -> Vec<Received> {
    let text = std::fs::read_to_string(path).unwrap();
    assert!(
        text.lines().all(|l| l.ends_with(" R")),
        "{} has lines without a direction flag:\n{}",
        path.display(),
        text.lines().take(3).collect::<Vec<_>>().join("\n")
    );
    parse_candump(&text, &Settings::suit_default().window)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// `got` holds `want`'s frames in order, with the same times relative to the first frame.
fn assert_same_frames(got: &[Received], want: &[Received], by: &str) {
    assert_eq!(got.len(), want.len(), "{by}: frame count");
    for (i, (g, w)) in got.iter().zip(want).enumerate() {
        assert_eq!(
            (g.frame.id(), g.frame.is_remote_frame(), g.frame.dlc()),
            (w.frame.id(), w.frame.is_remote_frame(), w.frame.dlc()),
            "{by}: frame {i}"
        );
        assert_eq!(g.frame.data(), w.frame.data(), "{by}: frame {i}'s data");
        assert_eq!(
            g.timestamp - got[0].timestamp,
            w.timestamp - want[0].timestamp,
            "{by}: frame {i}'s time after the first"
        );
    }
}

fn run(cmd: &mut Command, what: &str) {
    let out = cmd
        .output()
        .unwrap_or_else(|e| panic!("cannot run {what}: {e} (cargo xtask setup installs it)"));
    assert!(
        out.status.success(),
        "{what} failed: {}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}

#[test]
#[ignore = "needs can-utils (cargo xtask setup): `cargo xtask test` runs it"]
fn a_log_through_can_utils_log2asc_and_asc2log_reads_back_the_same() {
    let dir = scratch("can-utils");
    let ours = frames();
    let log = dir.join("ours.log");
    std::fs::write(&log, candump_text(&ours, "vcan0")).unwrap();
    let asc = dir.join("ours.asc");
    run(
        Command::new("log2asc")
            .arg("-I")
            .arg(&log)
            .arg("-O")
            .arg(&asc)
            .arg("vcan0"),
        "log2asc",
    );
    let back = dir.join("asc2log.log");
    run(
        Command::new("asc2log")
            .arg("-I")
            .arg(&asc)
            .arg("-O")
            .arg(&back),
        "asc2log",
    );
    assert_same_frames(&read_back(&back), &ours, "log2asc | asc2log");
}

#[test]
#[ignore = "needs the project venv (EXOCAL_PYTHON): `cargo xtask test` runs it"]
fn a_log_through_python_can_reads_back_the_same() {
    let python = std::env::var("EXOCAL_PYTHON").unwrap_or_else(|_| "python3".into());
    let dir = scratch("python-can");
    let ours = frames();
    let log = dir.join("ours.log");
    std::fs::write(&log, candump_text(&ours, "vcan0")).unwrap();
    let back = dir.join("python-can.log");
    let script = "import sys, can\n\
                  with can.CanutilsLogWriter(sys.argv[2]) as out:\n    \
                      for msg in can.CanutilsLogReader(sys.argv[1]):\n        \
                          out.on_message_received(msg)\n";
    run(
        Command::new(&python)
            .args(["-c", script])
            .arg(&log)
            .arg(&back),
        "python-can",
    );
    assert_same_frames(&read_back(&back), &ours, "python-can");
}
