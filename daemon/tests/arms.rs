//! Arms of fewer joints than the paper's seven. A configuration whose `[nodes] joints` lists
//! n nodes (and `[nominal]` and `[bounds]` n rows) calibrates an emulated suit of n joint
//! nodes, pushes every one of them, logs and reports the arm of n joints; `exocald offline`
//! replays its log, writes its aligned samples as a CSV of n joint columns and calibrates that
//! CSV again, and a configuration of another arm refuses the CSV (exit 65, naming both counts)
//! and names the joint nodes of the log that are not on it.

use std::path::PathBuf;

use exocal_session::formats::csv_header;
use exocald::cmd::demo::{self, check_flash, DemoOptions, DemoResult};
use exocald::cmd::offline::{self, OfflineOptions};
use exocald::config::Config;
use exocald::exit::{code, DaemonError};

fn temp_dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("exocald-arms-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// The shipped configuration cut to its first `joints` joints, as the file a user writes
/// (written and read back through the configuration's parser), for a demo in `dir`.
fn arm_config(joints: usize, dir: &std::path::Path) -> Config {
    let mut c = Config::default_config();
    c.calibration = c.calibration.first(joints);
    let text = c.to_toml();
    let parsed = Config::parse(&text).unwrap_or_else(|e| panic!("{e}\n{text}"));
    assert_eq!(parsed, c, "{text}");
    let mut c = demo::demo_config(parsed, dir, 1.0);
    c.calibration.window.min_duration_s = 20.0;
    c
}

/// The demo of `joints` joints with `seed` in `dir`, as `exocald demo` runs it.
fn demo_of(joints: usize, seed: u64, dir: &std::path::Path) -> (Config, DemoResult) {
    let config = arm_config(joints, dir);
    let opts = DemoOptions {
        seed,
        speed: 1e6,
        output: dir.to_path_buf(),
        hold: false,
        quiet: true,
        wearer: Default::default(),
        drift: Default::default(),
    };
    let result = demo::run(&config, &opts)
        .map_err(|e| *e)
        .unwrap_or_else(|e| panic!("{joints} joints: {}\n{:#?}", e.error, e.summary));
    (config, result)
}

/// Every node of the arm holds its pushed table, and only those nodes were pushed; the
/// summary, the report and the log have one row per joint.
fn pushed_to_every_node(joints: usize, config: &Config, result: &DemoResult) {
    check_flash(result, joints).unwrap_or_else(|e| panic!("{joints} joints: {e}"));
    let s = &result.summary;
    let push = s.push.as_ref().expect("pushed");
    assert!(push.complete(), "{joints} joints: {push:?}");
    let names: Vec<&str> = push.nodes.iter().map(|n| n.node.as_str()).collect();
    let want: Vec<String> = (1..=joints).map(|j| format!("Joint{j}")).collect();
    assert_eq!(names, want);
    let outcome = s.outcome.as_ref().expect("an outcome");
    assert_eq!(outcome.node_rows.len(), joints);
    assert_eq!(outcome.ls.rank, 4 * joints, "every parameter identified");
    let json = exocald::shell::summary::json(Some(s), None);
    assert_eq!(
        json["table"].as_array().map(Vec::len),
        Some(joints),
        "{json}"
    );

    let html = std::fs::read_to_string(s.report_path.as_ref().expect("a report")).unwrap();
    assert!(
        html.contains(&format!("every node ({joints}) holds")),
        "push line"
    );
    assert!(
        html.contains(&format!("<td>a{joints}</td>")),
        "a{joints} row"
    );
    assert!(
        !html.contains(&format!("<td>a{}</td>", joints + 1)),
        "a padded row"
    );
    assert!(
        !html.contains(&format!("Joint{}", joints + 1)),
        "a node off the arm"
    );

    let log = std::fs::read(&s.log_path).unwrap();
    let session =
        exocal_log::read::read_mcap_session(log.as_slice(), exocal_log::read::admit_all).unwrap();
    assert!(session.frames.len() > 1000);
    let limits = &config.calibration.bounds.joint_range.limits;
    let urdf = exocald::log::records::urdf(&outcome.table(), limits, joints).unwrap();
    assert!(urdf.contains(&format!("<link name=\"link{joints}\"/>")));
    assert!(!urdf.contains(&format!("<link name=\"link{}\"/>", joints + 1)));
}

#[test]
fn the_demo_of_a_four_joint_arm_pushes_every_node() {
    let dir = temp_dir("four");
    let (config, result) = demo_of(4, 2024, &dir);
    pushed_to_every_node(4, &config, &result);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The six-joint demo, then its log offline: the CSV of its aligned samples has six joint
/// columns and calibrates to the live table (to rounding: the CSV keeps the samples, not the
/// frames); the shipped seven-joint configuration refuses it as input (exit 65).
#[test]
fn the_demo_of_a_six_joint_arm_pushes_every_node_and_its_csv_calibrates_offline() {
    let dir = temp_dir("six");
    let (config, result) = demo_of(6, 2024, &dir);
    pushed_to_every_node(6, &config, &result);
    let live = result.summary.outcome.clone().unwrap();

    let csv = dir.join("samples.csv");
    let from_log = OfflineOptions {
        input: result.summary.log_path.clone(),
        report: Some(dir.join("offline.html")),
        export_csv: Some(csv.clone()),
        ..OfflineOptions::default()
    };
    let replayed = offline::run(&config, exocald::config::DEFAULT_TOML, &from_log)
        .map_err(|e| e.error)
        .unwrap();
    assert_eq!(
        replayed.outcome.unwrap().node_rows,
        live.node_rows,
        "the log replays bit for bit"
    );
    let text = std::fs::read_to_string(&csv).unwrap();
    assert_eq!(text.lines().next(), Some(csv_header(6).as_str()));
    assert_eq!(text.lines().nth(1).unwrap().split(',').count(), 1 + 6 + 7);

    let from_csv = OfflineOptions {
        input: csv.clone(),
        report: Some(dir.join("csv.html")),
        ..OfflineOptions::default()
    };
    let again = offline::run(&config, exocald::config::DEFAULT_TOML, &from_csv)
        .map_err(|e| e.error)
        .unwrap();
    let again = again.outcome.unwrap();
    assert_eq!(again.node_rows.len(), 6);
    for (a, b) in again.node_rows.iter().zip(&live.node_rows) {
        for d in [
            a.a - b.a,
            a.d - b.d,
            a.alpha - b.alpha,
            a.theta_offset - b.theta_offset,
        ] {
            assert!(d.abs() < 1e-9, "{a:?} vs {b:?}");
        }
    }

    // The six-joint log under a configuration of four: joints 5 and 6 are named, not used.
    let four = arm_config(4, &dir);
    let log_only = OfflineOptions {
        input: result.summary.log_path.clone(),
        report: Some(dir.join("four.html")),
        ..OfflineOptions::default()
    };
    let summary = match offline::run(&four, exocald::config::DEFAULT_TOML, &log_only) {
        Ok(s) => s,
        Err(e) => e.summary.unwrap_or_else(|| panic!("{}", e.error)),
    };
    let line = exocald::shell::summary::off_arm_line(&summary.frames).expect("a warning");
    assert!(
        line.contains("Joint5 (") && line.contains("Joint6 ("),
        "{line}"
    );
    assert!(!line.contains("Joint4"), "{line}");
    assert!(exocald::shell::summary::off_arm_line(&result.summary.frames).is_none());

    let seven = Config::default_config();
    let refused =
        offline::run(&seven, exocald::config::DEFAULT_TOML, &from_csv).map_err(|e| e.error);
    match refused {
        Err(e @ DaemonError::Input(_)) => {
            assert_eq!(e.exit_code(), code::DATAERR);
            let what = e.to_string();
            assert!(
                what.contains("6 joint columns") && what.contains("7 joints"),
                "{what}"
            );
        }
        other => panic!("a 6-joint CSV under a 7-joint configuration: {other:?}"),
    }
    std::fs::remove_dir_all(&dir).unwrap();
}
