//! CPU per frame of the daemon's hot path, natively, on a recorded session: every received frame
//! of an exocald MCAP log replayed through ingest (decode, per-node streams) alone, then through
//! ingest and the session log (the records a live session writes per frame: `/can/rx`, and
//! `/joint_states` or `/ee_pose`), into a log file on disk with the daemon's flush interval.
//! Times are the process's CPU time (user + system, `/proc/self/stat`, 10 ms ticks over passes of
//! about a second) of the fastest of `REPEATS` passes, per frame: CPU time rather than wall time,
//! so that other processes on a shared machine count as little as they can.
//!
//! `cargo bench -p exocald --bench log_cost -- SESSION.mcap` (e.g. the log `exocald demo` writes).

use std::time::Duration;

use exocal_log::write::SessionLog;
use exocal_session::ingest::{Event, Ingest};
use exocald::log::records::frame_record;
use exocald::shell::tee::Recorder;

const REPEATS: usize = 5;

/// CPU time of this process so far (user + system).
fn cpu_now() -> Duration {
    let stat = std::fs::read_to_string("/proc/self/stat").expect("/proc/self/stat");
    let fields: Vec<&str> = stat[stat.rfind(')').expect("(comm)") + 2..]
        .split_whitespace()
        .collect();
    // utime and stime are fields 14 and 15 of the file, 12 and 13 after `(comm) `.
    let ticks: u64 = fields[11].parse::<u64>().unwrap() + fields[12].parse::<u64>().unwrap();
    Duration::from_millis(ticks * 10)
}

fn pass(frames: &[exocal_bus::Received], log: bool, dir: &std::path::Path) -> (Duration, u64) {
    let mut ingest = Ingest::new(&[1, 2, 3, 4, 5, 6, 7]);
    let t0 = frames.first().map_or(0, |f| f.timestamp.as_nanos() as u64);
    let mut session = if log {
        let log = SessionLog::create_in(dir, t0, 500_000_000).expect("log").1;
        Some(Recorder::new(log, &[]))
    } else {
        None
    };
    let started = cpu_now();
    for rx in frames {
        let t = rx.timestamp.as_nanos() as u64;
        let event = ingest.on_frame(rx);
        if let Some(s) = session.as_mut() {
            // As the session's loop records each frame (`shell::io`, `Io::take_frame`).
            s.can_frame(false, &frame_record(&rx.frame, rx.timestamp))
                .expect("write");
            if let Event::Sample {
                stream,
                node_timestamp_us,
                reading,
            } = event
            {
                s.sample(t, stream, node_timestamp_us, reading)
                    .expect("write");
            }
            s.tick(t - t0).expect("flush");
        }
    }
    let bytes = match session {
        Some(s) => {
            s.finish().expect("finish");
            let elapsed = cpu_now() - started;
            let mut size = 0;
            for e in std::fs::read_dir(dir).unwrap() {
                let p = e.unwrap().path();
                size += std::fs::metadata(&p).unwrap().len();
                std::fs::remove_file(p).unwrap();
            }
            return (elapsed, size);
        }
        None => 0,
    };
    (cpu_now() - started, bytes)
}

fn main() {
    let path = std::env::args()
        .skip(1)
        .find(|a| !a.starts_with('-'))
        .expect("usage: log_cost SESSION.mcap");
    let bytes = std::fs::read(&path).expect("read the log");
    let frames = exocal_log::read::read_mcap_session(bytes.as_slice(), exocal_log::read::admit_all)
        .expect("an exocald log")
        .frames;
    let dir = std::env::temp_dir().join(format!("exocal-log-cost-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let n = frames.len() as f64;
    let best = |log: bool| {
        (0..REPEATS)
            .map(|_| pass(&frames, log, &dir))
            .min_by_key(|r| r.0)
            .unwrap()
    };
    let (ingest, _) = best(false);
    let (both, size) = best(true);
    let _ = std::fs::remove_dir_all(&dir);
    let us = |d: Duration| d.as_secs_f64() * 1e6 / n;
    println!(
        "LOG_COST frames={} ingest_us_per_frame={:.3} ingest_and_log_us_per_frame={:.3} log_us_per_frame={:.3} log_bytes={size}",
        frames.len(),
        us(ingest),
        us(both),
        us(both) - us(ingest),
    );
}
