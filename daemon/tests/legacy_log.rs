//! Logs already in the field stay readable: `fixtures/json-session-v0.mcap` is a session log as
//! the daemon wrote it before the log was binary (JSON messages with JSON Schemas): `exocald
//! demo --seed 7` with `fixtures/json-session-v0.toml` (a 2 s collection window, so the file is
//! small; that run's summary is `fixtures/json-session-v0.txt`; recorded by commit ea84f72, the
//! last with the JSON writer). `exocald offline` reads from it the frames and samples the live
//! run collected, and replays them to the table today's demo computes live from the same seed
//! (its protobuf log), bit for bit, refused for the same reasons: the JSON reader hands the
//! pipeline exactly what the live session had, whatever the calibration of the day is.

use std::path::{Path, PathBuf};

use exocald::cmd::offline::{self, OfflineOptions};
use exocald::config::Config;
use exocald::exit::DaemonError;
use exocald::shell::summary::SessionError;

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
}

/// The live run's `/calibration` message (JSON, as the old writer wrote it), and its text.
fn live_calibration(log: &Path) -> (serde_json::Value, String) {
    let bytes = std::fs::read(log).unwrap();
    let m = mcap::MessageStream::new(&bytes)
        .unwrap()
        .map(Result::unwrap)
        .find(|m| m.channel.topic == "/calibration")
        .expect("the live run's calibration");
    assert_eq!(
        m.channel.message_encoding, "json",
        "a log of the old writer"
    );
    let text = String::from_utf8(m.data.to_vec()).unwrap();
    (serde_json::from_str(&text).unwrap(), text)
}

/// The calibrated rows' `key` values as written, parsed by the standard library (correctly
/// rounded: serde_json's default float parsing may be a unit in the last place off).
fn row_values(text: &str, key: &str) -> Vec<f64> {
    let rows = &text[text.find("\"node_rows\":[").expect("node_rows")..];
    let rows = &rows[..rows.find(']').unwrap()];
    let pattern = format!("\"{key}\":");
    rows.match_indices(&pattern)
        .map(|(at, _)| {
            let value = &rows[at + pattern.len()..];
            let end = value.find([',', '}']).unwrap();
            value[..end].parse().unwrap()
        })
        .collect()
}

/// Today's live session of the fixture's seed and configuration (`exocald demo --seed 7`): its
/// outcome.
fn todays_live_rows(config: &Config, dir: &Path) -> exocal_session::pipeline::Outcome {
    let opts = exocald::cmd::demo::DemoOptions {
        seed: 7,
        speed: 1e6,
        output: dir.join("today"),
        hold: false,
        quiet: false,
        wearer: Default::default(),
        drift: Default::default(),
    };
    let config = exocald::cmd::demo::demo_config(config.clone(), &opts.output, 1.0);
    let summary = match exocald::cmd::demo::run(&config, &opts) {
        Ok(r) => r.summary,
        Err(e) => e.summary.expect("a summary"),
    };
    summary.outcome.expect("an outcome")
}

#[test]
fn a_json_log_of_the_old_writer_replays_offline_to_the_live_table() {
    let log = fixture("json-session-v0.mcap");
    let text = std::fs::read_to_string(fixture("json-session-v0.toml")).unwrap();
    let config = Config::parse(&text).unwrap();
    let (live, live_text) = live_calibration(&log);

    let dir = std::env::temp_dir().join(format!("exocald-legacy-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let opts = OfflineOptions {
        input: log,
        report: Some(dir.join("offline.html")),
        ..OfflineOptions::default()
    };
    // The live run was refused (2 s of motion): so is the replay, for the reasons today's live
    // run gives.
    let (summary, error) = match offline::run(&config, &text, &opts).map_err(|e| *e) {
        Err(SessionError {
            error: error @ DaemonError::Validation(_),
            summary: Some(s),
        }) => (s, error),
        other => panic!("expected a refusal, got {other:?}"),
    };
    let outcome = summary.outcome.expect("an outcome");
    let today = todays_live_rows(&config, &dir);
    let reasons = today.verdict.reasons.clone();
    assert!(!reasons.is_empty());
    assert_eq!(outcome.verdict.reasons, reasons);
    assert!(matches!(error, DaemonError::Validation(r) if r == reasons));
    let old_reasons: Vec<String> =
        serde_json::from_value(live["outcome"]["verdict"]["reasons"].clone()).unwrap();
    assert!(!old_reasons.is_empty(), "the recorded run was refused too");

    // The same frames and samples as the live collection window.
    assert_eq!(summary.frames.received, live["frames"]["received"]);
    assert_eq!(summary.aligned_samples as u64, live["aligned_samples"]);
    // The recorded table has the right shape (the old writer wrote f64 in shortest round-trip
    // form); the replay gives today's live table, bit for bit.
    type Field = fn(&exocal_session::pipeline::NodeRow) -> f64;
    let fields: [(&str, Field); 6] = [
        ("a", |r| r.a),
        ("alpha", |r| r.alpha),
        ("d", |r| r.d),
        ("theta_offset", |r| r.theta_offset),
        ("tau", |r| r.tau),
        ("sigma", |r| r.sigma),
    ];
    for (name, field) in fields {
        let recorded = row_values(&live_text, name);
        assert_eq!(recorded.len(), outcome.node_rows.len(), "{name}");
        assert!(
            recorded.iter().all(|v| v.is_finite()),
            "{name}: {recorded:?}"
        );
        for (i, (row, want)) in outcome.node_rows.iter().zip(&today.node_rows).enumerate() {
            let (got, want) = (field(row), field(want));
            assert_eq!(
                got.to_bits(),
                want.to_bits(),
                "joint {} {name}: offline {got}, live {want}",
                i + 1
            );
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}
