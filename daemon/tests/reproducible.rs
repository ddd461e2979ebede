//! `exocald demo` is reproducible: the emulated suit and the daemon run on simulated time on the
//! in-process bus, so two sessions with the same seed push the same table to every node, align
//! the same samples and log the same messages.

mod common;

use std::path::{Path, PathBuf};

use common::live_session;

/// What must not change between two runs with the same seed.
#[derive(Debug, PartialEq)]
struct Fingerprint {
    /// (node, CRC of the pushed table) per joint node.
    pushed_crcs: Vec<(String, u32)>,
    aligned_samples: usize,
    /// Messages in the session's MCAP log (its statistics record).
    mcap_messages: u64,
    /// Simulated time from the end of the collection window to the last verified table: the
    /// emulated bus's and nodes' share of the power-up latency.
    latency_session: std::time::Duration,
}

fn temp_dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("exocald-repro-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

fn fingerprint(dir: &Path, seed: u64) -> Fingerprint {
    let (_, summary) = live_session(dir, seed);
    let push = summary.push.as_ref().expect("the session pushed");
    let latency = summary.latency.expect("a pushed session has its latency");
    assert!(latency.simulated, "{latency:?}");
    assert!(
        latency.real > std::time::Duration::ZERO && latency.session > std::time::Duration::ZERO,
        "{latency:?}"
    );
    assert_eq!(latency.total(), latency.real + latency.session);
    let bytes = std::fs::read(&summary.log_path).unwrap();
    let stats = mcap::Summary::read(&bytes)
        .unwrap()
        .expect("a finished log")
        .stats
        .expect("statistics");
    Fingerprint {
        pushed_crcs: push
            .nodes
            .iter()
            .map(|n| (n.node.clone(), n.new_crc))
            .collect(),
        aligned_samples: summary.aligned_samples,
        mcap_messages: stats.message_count,
        latency_session: latency.session,
    }
}

#[test]
fn the_same_seed_gives_the_same_tables_samples_and_log() {
    let (a_dir, b_dir) = (temp_dir("a"), temp_dir("b"));
    let a = fingerprint(&a_dir, 1);
    let b = fingerprint(&b_dir, 1);
    assert_eq!(a.pushed_crcs.len(), 7, "{a:?}");
    assert_eq!(a, b);
    std::fs::remove_dir_all(&a_dir).unwrap();
    std::fs::remove_dir_all(&b_dir).unwrap();
}
