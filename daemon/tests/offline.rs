//! `exocald offline` against a live session: one in-process session (the emulated suit and the
//! daemon on the in-process bus, as `exocald demo` runs them) is recalibrated offline from its
//! MCAP log, from that log exported as candump, and from its aligned samples as CSV; the report
//! the live run wrote, the exports, and bad inputs are checked on the way.

mod common;

use std::path::{Path, PathBuf};

use exocal_log::read::read_mcap_session;
use exocal_report::html::FIGURES;
use exocal_session::formats::{csv_text, CSV_HEADER};
use exocal_session::pipeline::Outcome;
use exocald::cmd::offline::{self, Format, OfflineOptions};
use exocald::config::Config;
use exocald::exit::{code, DaemonError};
use exocald::shell::summary::{SessionError, SessionSummary};

use common::live_session;

fn temp_dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("exocald-offline-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// Largest difference between two outcomes' D-H rows (m and rad), and largest relative
/// difference of their drift τ and σ.
fn table_and_drift_difference(a: &Outcome, b: &Outcome) -> (f64, f64) {
    let mut geometry = 0.0f64;
    let mut drift = 0.0f64;
    for (x, y) in a.node_rows.iter().zip(&b.node_rows) {
        for d in [
            x.a - y.a,
            x.alpha - y.alpha,
            x.d - y.d,
            x.theta_offset - y.theta_offset,
        ] {
            geometry = geometry.max(d.abs());
        }
        for (p, q) in [(x.tau, y.tau), (x.sigma, y.sigma)] {
            drift = drift.max((p - q).abs() / q.abs().max(1e-12));
        }
    }
    (geometry, drift)
}

/// The summary and outcome of an offline run, whether validation accepted it or not.
fn offline_outcome(
    config: &Config,
    opts: &OfflineOptions,
) -> Result<(SessionSummary, Outcome), DaemonError> {
    let summary = match offline::run(config, exocald::config::DEFAULT_TOML, opts).map_err(|e| *e) {
        Ok(s) => s,
        Err(SessionError {
            error: DaemonError::Validation(_),
            summary: Some(s),
        }) => s,
        Err(e) => return Err(e.error),
    };
    let outcome = summary.outcome.clone().expect("an outcome");
    Ok((summary, outcome))
}

#[test]
fn offline_recalibration_agrees_with_the_live_session() {
    let dir = temp_dir("agree");
    let (config, live) = live_session(&dir, 7);
    let live_outcome = live.outcome.clone().expect("the live session calibrated");
    let accepted = live_outcome.verdict.accepted();

    // (d) The live session wrote its report next to its log, with every figure drawn.
    let report = live.report_path.clone().expect("a report path");
    assert_eq!(report, live.log_path.with_extension("html"));
    let html = std::fs::read_to_string(&report).unwrap();
    for id in FIGURES {
        let at = html
            .find(&format!("id=\"{id}\""))
            .unwrap_or_else(|| panic!("figure {id} missing from {}", report.display()));
        let end = html[at..].find("</figure>").unwrap() + at;
        assert!(html[at..end].contains("<svg"), "{id} has no SVG");
    }
    assert!(
        !html.contains("class=\"missing\""),
        "a figure was not drawn"
    );
    assert!(html.contains("Joint7") && html.contains("EndEffector"));
    // After the push the report has its outcome per node, as the summary has it.
    if accepted {
        let push = live.push.as_ref().expect("a validated table is pushed");
        let all_new = push.complete();
        assert_eq!(
            html.contains("Validated and pushed: every node (7) holds"),
            all_new
        );
        assert!(html.contains("<h2 id=\"push\">Push</h2>"));
        for n in &push.nodes {
            assert!(html.contains(&format!("<td><code>{:#010x}</code></td>", n.new_crc)));
        }
    }

    // (a) The MCAP log, replayed offline up to its collection end: the same table, bit for bit.
    let session = read_mcap_session(
        std::fs::read(&live.log_path).unwrap().as_slice(),
        exocal_log::read::admit_all,
    )
    .unwrap();
    let used = session
        .collection_frames
        .expect("the collection-done marker") as usize;
    assert!(
        used < session.frames.len(),
        "frames arrived after collection"
    );
    let candump = dir.join("session.log");
    let csv = dir.join("samples.csv");
    let (toml_out, urdf_out) = (dir.join("calibrated.toml"), dir.join("calibrated.urdf"));
    let from_mcap = OfflineOptions {
        input: live.log_path.clone(),
        format: None,
        report: Some(dir.join("offline.html")),
        export_toml: Some(toml_out.clone()),
        export_urdf: Some(urdf_out.clone()),
        export_candump: Some(candump.clone()),
        export_csv: Some(csv.clone()),
        quiet: false,
    };
    // The live session's table, bit for bit, and its improvement.
    let same_table_as_live = |outcome: &Outcome| {
        assert_eq!(
            outcome.node_rows, live_outcome.node_rows,
            "not bit-identical"
        );
        assert_eq!(
            outcome.verdict.improvement,
            live_outcome.verdict.improvement
        );
    };
    let (summary, outcome) = offline_outcome(&config, &from_mcap).unwrap();
    // `used` counts the frames received (as logged); ingest took those the stream gate passed
    // (the digests verified by the collection's end), the same offline as live.
    assert!(summary.frames.received <= used as u64);
    // The live summary counts the same frames: those of its collection window.
    assert_eq!(summary.frames, live.frames);
    assert_eq!(summary.aligned_samples, live.aligned_samples);
    assert_eq!(summary.clocks, live.clocks);
    same_table_as_live(&outcome);
    assert_eq!(outcome.verdict.reasons, live_outcome.verdict.reasons);
    assert!(std::fs::metadata(dir.join("offline.html")).unwrap().len() > 10_000);

    // (b) Its frames as candump replay to the same table, bit for bit: `candump -L` keeps µs,
    // and ingest reads receive times at µs resolution.
    // Behind the stream gate: the frames it passed by the collection's end.
    // In receive order, as `candump -l` writes (the gate releases a node's frames a span at a
    // time, so the export has to put them back in order).
    let text = std::fs::read_to_string(&candump).unwrap();
    let times: Vec<f64> = text
        .lines()
        .map(|l| l[1..l.find(')').unwrap()].parse().unwrap())
        .collect();
    assert_eq!(times.len() as u64, summary.frames.received);
    let back = times.windows(2).filter(|w| w[1] < w[0]).count();
    assert_eq!(back, 0, "{back} timestamps step back in the export");
    let from_candump = OfflineOptions {
        input: candump.clone(),
        report: Some(dir.join("candump.html")),
        ..OfflineOptions::default()
    };
    let (summary_c, outcome_c) = offline_outcome(&config, &from_candump).unwrap();
    assert_eq!(summary_c.frames, summary.frames);
    assert_eq!(summary_c.aligned_samples, live.aligned_samples);
    same_table_as_live(&outcome_c);

    // (c) The aligned samples as CSV (`--export-csv` of the MCAP run: every aligned sample, in
    // the CSV format) bypass alignment and give the same table to rounding.
    let (recording, _, gate) = offline::read_input_gated(
        &live.log_path,
        std::fs::File::open(&live.log_path).unwrap(),
        Format::Mcap,
        &config.calibration,
    )
    .unwrap();
    let samples: Vec<_> = exocal_session::pipeline::timed(
        &offline::recalibrate(&recording, gate, &config)
            .unwrap()
            .job
            .collected()
            .samples,
    );
    assert_eq!(
        std::fs::read_to_string(&csv).unwrap(),
        csv_text(&samples, 7)
    );
    let from_csv = OfflineOptions {
        input: csv,
        report: Some(dir.join("csv.html")),
        ..OfflineOptions::default()
    };
    let (summary_s, outcome_s) = offline_outcome(&config, &from_csv).unwrap();
    assert_eq!(summary_s.aligned_samples, live.aligned_samples);
    // The CSV's orientation is a quaternion, the aligned sample's went through a rotation
    // matrix: poses differ by rounding (1e-16), which moves the D-H table by ~1e-10 and the
    // EM's converged τ and σ by ~1e-6 of themselves (its stopping tolerance).
    let (d_geometry, d_drift) = table_and_drift_difference(&outcome_s, &live_outcome);
    eprintln!("CSV samples vs live: D-H {d_geometry:.3e} (m, rad), τ/σ {d_drift:.3e} (relative)");
    assert!(d_geometry < 1e-8, "{d_geometry}");
    assert!(d_drift < 1e-4, "{d_drift}");

    // (e) The exports load: the URDF parses with a URDF crate, the TOML in the daemon.
    if accepted {
        let robot = urdf_rs::read_from_string(&std::fs::read_to_string(&urdf_out).unwrap())
            .unwrap_or_else(|e| panic!("URDF does not parse: {e}"));
        assert_eq!(robot.joints.len(), 8);
        assert_eq!(robot.links.len(), 9);
        let loaded = Config::load(&toml_out).unwrap();
        for (row, want) in loaded
            .calibration
            .nominal
            .rows
            .iter()
            .zip(&outcome.node_rows)
        {
            assert!((row.a - want.a).abs() < 1e-12, "{row:?} vs {want:?}");
            assert!((row.alpha - want.alpha).abs() < 1e-9);
        }
    } else {
        assert!(
            !urdf_out.exists() && !toml_out.exists(),
            "refused but exported"
        );
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

fn run_bad(dir: &Path, name: &str, bytes: &[u8], format: Option<Format>) -> DaemonError {
    let path = dir.join(name);
    std::fs::write(&path, bytes).unwrap();
    let opts = OfflineOptions {
        input: path,
        format,
        report: Some(dir.join("never.html")),
        ..OfflineOptions::default()
    };
    let err = offline::run(&Config::default_config(), "", &opts)
        .expect_err("bad input is an error")
        .error;
    assert!(!dir.join("never.html").exists(), "a report for bad input");
    err
}

#[test]
fn bad_inputs_are_errors_naming_the_file_line_and_problem() {
    let dir = temp_dir("bad");
    let header = CSV_HEADER;
    let cases: [(&str, Vec<u8>, Option<Format>, &str); 9] = [
        (
            "s.csv",
            format!("{header}\n0.0,0.1,0.2,0.3,0.4,0.5,0.6,0.7,0,0,0,2,0,0,0\n").into_bytes(),
            None,
            "s.csv: CSV samples, line 2: quaternion norm 2.000000",
        ),
        (
            "h.csv",
            b"t,q1,q2\n".to_vec(),
            None,
            "h.csv: CSV samples, line 1: header must be",
        ),
        (
            "c.log",
            b"(1.000000) can0 101#00\n(1.000100) can0 800#00\n".to_vec(),
            None,
            "c.log: candump log, line 2: bad identifier: 3 hex digits (≤ 7FF) or 8 hex digits \
             (≤ 1FFFFFFF), in \"(1.000100) can0 800#00\"",
        ),
        (
            "m.mcap",
            b"\x89MCAP0\r\nnot really".to_vec(),
            None,
            "m.mcap: MCAP log:",
        ),
        (
            "binary.bin",
            vec![0xff, 0xfe, 0x00, 0x01],
            Some(Format::Csv),
            "binary.bin: CSV samples, line 1: not UTF-8 text (byte 1 of the line)",
        ),
        (
            "what.txt",
            b"hello\n".to_vec(),
            None,
            "what.txt: cannot tell the format (text, its first line \"hello\"",
        ),
        // The content decides, the extension only where the content is none of the formats.
        (
            "mcap.log",
            b"\x89MCAP0\r\nnot really".to_vec(),
            None,
            "mcap.log: MCAP log:",
        ),
        (
            "candump.csv",
            b"(1.000000) can0 101#00\n(1.000100) can0 800#00\n".to_vec(),
            None,
            "candump.csv: candump log, line 2: bad identifier",
        ),
        (
            "what.bin",
            vec![0xff, 0xfe, 0x00, 0x01],
            None,
            "what.bin: cannot tell the format (binary, starting ff fe 00 01",
        ),
    ];
    for (name, bytes, format, want) in cases {
        let err = run_bad(&dir, name, &bytes, format);
        assert_eq!(err.exit_code(), code::DATAERR, "{name}: {err}");
        assert!(err.to_string().contains(want), "{name}: {err}");
    }
    // A missing file is an I/O error naming it.
    let opts = OfflineOptions {
        input: dir.join("missing.mcap"),
        ..OfflineOptions::default()
    };
    let err = offline::run(&Config::default_config(), "", &opts)
        .expect_err("a missing file is an error")
        .error;
    assert_eq!(err.exit_code(), code::IOERR);
    assert!(err.to_string().contains("missing.mcap"), "{err}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `seconds` of the paper scenario (seed 5) as CSV samples at its 100 Hz.
fn scenario_csv(path: &Path, seconds: f64) {
    let cfg = calib_core::ScenarioConfig::paper();
    let n = (seconds / cfg.drift.dt).round() as usize + 1;
    let samples: Vec<_> = exocal_report::TimedSample::simulated(cfg, 5, n);
    std::fs::write(path, csv_text(&samples, 7)).unwrap();
}

#[test]
fn a_recording_the_live_daemon_would_not_calibrate_is_not_calibrated_and_the_report_says_why() {
    let dir = temp_dir("short");
    let header = CSV_HEADER;
    let few = dir.join("few.csv");
    std::fs::write(
        &few,
        format!(
            "{header}\n0.00,0,0,0,0,0,0,0,0.4,0,0,1,0,0,0\n0.01,0,0,0,0,0,0,0,0.4,0,0,1,0,0,0\n"
        ),
    )
    .unwrap();
    let short = dir.join("short.csv");
    scenario_csv(&short, 30.0);
    let run = |input: &Path, config: &Config| {
        let report = input.with_extension("html");
        let opts = OfflineOptions {
            input: input.to_path_buf(),
            report: Some(report.clone()),
            ..OfflineOptions::default()
        };
        (offline::run(config, "", &opts).map_err(|e| *e), report)
    };
    // The fixed minute: a live daemon so configured collects for 60 s at least.
    let mut default = Config::default_config();
    default.calibration.window.min_duration_s = 60.0;
    default.calibration.window.stop_at_expected_error = None;
    for (input, want) in [
        (&few, "joint 1 covered 0% of its range, 50% required"),
        (
            &short,
            "the recording is 30.0 s long; session.min_duration_s is 60 s",
        ),
    ] {
        let (result, report) = run(input, &default);
        let err = result.expect_err("not calibrated");
        assert_eq!(err.error.exit_code(), code::NOINPUT, "{}", err.error);
        assert!(err.error.to_string().contains(want), "{}", err.error);
        let summary = err.summary.expect("a summary");
        assert!(summary.outcome.is_none());
        assert_eq!(summary.report_path.as_deref(), Some(report.as_path()));
        let html = std::fs::read_to_string(&report).expect("the report of a refused recording");
        assert!(
            html.contains("Not calibrated") && html.contains(want),
            "{want}"
        );
    }
    // The same 30 s under a configuration whose window is 30 s: calibrated (whatever the
    // validation then says).
    let mut shorter = default.clone();
    shorter.calibration.window.min_duration_s = 30.0;
    let (result, _) = run(&short, &shorter);
    match result {
        Ok(s) => assert!(s.outcome.is_some()),
        Err(SessionError {
            error: DaemonError::Validation(_),
            summary: Some(s),
        }) => assert!(s.outcome.is_some()),
        Err(e) => panic!("{}", e.error),
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn the_binary_exits_65_on_a_bad_csv_and_64_on_a_csv_candump_export() {
    let dir = temp_dir("cli");
    let csv = dir.join("bad.csv");
    std::fs::write(&csv, "t,q1\n").unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_exocald"))
        .args(["offline", "--input"])
        .arg(&csv)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(65), "{err}");
    assert!(err.contains("bad.csv: CSV samples, line 1"), "{err}");

    let header = CSV_HEADER;
    std::fs::write(&csv, format!("{header}\n0,0,0,0,0,0,0,0,0,0,0,1,0,0,0\n")).unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_exocald"))
        .args(["offline", "--input"])
        .arg(&csv)
        .arg("--export-candump")
        .arg(dir.join("x.log"))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(64), "{err}");
    assert!(err.contains("--export-candump"), "{err}");
    std::fs::remove_dir_all(&dir).unwrap();
}
