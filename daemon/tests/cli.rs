//! The `exocald` binary as a user (or systemd) runs it: exit statuses and messages.

use std::process::Command;

fn exocald(args: &[&str]) -> (i32, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_exocald"))
        .args(args)
        .output()
        .expect("run exocald");
    (
        out.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

fn temp(name: &str, text: &str) -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!("exocald-cli-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let p = dir.join(name);
    std::fs::create_dir_all(p.parent().unwrap()).unwrap();
    std::fs::write(&p, text).unwrap();
    p
}

/// daemon/README.md quotes the error of `retries` misspelt in the shipped file: its line number
/// is the shipped file's, so the README cannot drift from it.
#[test]
fn the_readmes_misspelt_key_example_names_the_right_line() {
    let readme = include_str!("../README.md");
    let quoted: usize = readme
        .split("\"exocald.toml:")
        .nth(1)
        .and_then(|r| r.split(':').next())
        .and_then(|n| n.parse().ok())
        .expect("the README quotes `exocald.toml:LINE: key ...`");
    let misspelt = exocald::config::DEFAULT_TOML.replace("retries = ", "retrys = ");
    let path = temp("misspelt.toml", &misspelt);
    let (code, _, err) = exocald(&["--config", path.to_str().unwrap(), "check-config"]);
    assert_eq!(code, 78, "{err}");
    assert!(
        err.contains(&format!("misspelt.toml:{quoted}: key `push.retrys`")),
        "README says line {quoted}: {err}"
    );
}

#[test]
fn a_bad_config_exits_78_naming_the_key_and_line() {
    let text = exocald::config::DEFAULT_TOML.replace("retries = 3", "retries = 3\nretrys = 4");
    let line = text.lines().position(|l| l.starts_with("retrys")).unwrap() + 1;
    let path = temp("bad.toml", &text);
    for cmd in ["check-config", "calibrate", "run"] {
        let (code, _, err) = exocald(&["--config", path.to_str().unwrap(), cmd]);
        assert_eq!(code, 78, "{cmd}: {err}");
        assert!(
            err.contains(&format!(":{line}: key `push.retrys`")),
            "{cmd}: {err}"
        );
    }
}

/// A value past its key's upper bound is refused before anything allocates for it (`grid_hz =
/// 1e12` would make `offline` ask for 480 TB and abort with 134).
#[test]
fn an_absurd_value_exits_78_before_any_work() {
    let text = exocald::config::DEFAULT_TOML.replace("grid_hz = 100.0", "grid_hz = 1e12");
    let line = text.lines().position(|l| l.starts_with("grid_hz")).unwrap() + 1;
    let path = temp("huge.toml", &text);
    let csv = temp("samples.csv", "t,q1,q2,q3,q4,q5,q6,q7,x,y,z,qw,qx,qy,qz\n");
    let config = path.to_str().unwrap();
    for args in [
        vec!["--config", config, "check-config"],
        vec![
            "--config",
            config,
            "offline",
            "--input",
            csv.to_str().unwrap(),
        ],
    ] {
        let (code, _, err) = exocald(&args);
        assert_eq!(code, 78, "{args:?}: {err}");
        assert!(
            err.contains(&format!(":{line}: key `session.grid_hz`"))
                && err.contains("above the limit 1000"),
            "{args:?}: {err}"
        );
    }
}

#[test]
fn a_missing_interface_is_a_clear_error() {
    let (code, _, err) = exocald(&["calibrate", "--interface", "vcan93"]);
    assert_eq!(code, 69, "{err}");
    assert!(
        err.contains("vcan93") && err.contains("ip link add"),
        "{err}"
    );
}

/// Authentication on (the default) and no `exocal-keys` credential: exit 78 before the bus is
/// touched, saying how to provision it; a credential missing a node's key names the node.
/// Off (`authenticate = false`): the journal says so, and the daemon goes on (here to the CAN
/// socket, which `lo` cannot give: 69).
#[test]
fn missing_keys_exit_78_and_authentication_off_is_said() {
    let shipped = temp("shipped.toml", exocald::config::DEFAULT_TOML);
    for cmd in ["calibrate", "run"] {
        let out = Command::new(env!("CARGO_BIN_EXE_exocald"))
            .args([
                "--config",
                shipped.to_str().unwrap(),
                cmd,
                "--interface",
                "lo",
            ])
            .env_remove("CREDENTIALS_DIRECTORY")
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(78), "{cmd}: {err}");
        assert!(
            err.contains("exocal-keys") && err.contains("authenticate = false"),
            "{err}"
        );
    }
    // `calibrate -i lo` with the credential in `creds`'s folder and the state directory
    // `state` (none: unset): its status and stderr.
    let calibrate_with = |creds: &std::path::Path, state: Option<&std::path::Path>| {
        let mut cmd = Command::new(env!("CARGO_BIN_EXE_exocald"));
        cmd.args([
            "--config",
            shipped.to_str().unwrap(),
            "calibrate",
            "-i",
            "lo",
        ])
        .env("CREDENTIALS_DIRECTORY", creds.parent().unwrap())
        .env_remove("STATE_DIRECTORY");
        if let Some(state) = state {
            cmd.env("STATE_DIRECTORY", state);
        }
        let out = cmd.output().unwrap();
        (
            out.status.code(),
            String::from_utf8_lossy(&out.stderr).into_owned(),
        )
    };
    // Random keys, as `openssl rand -hex 16` makes them (patterned ones are refused).
    const KEYS: [&str; 8] = [
        "d2fe1afeaf1a7f865abffce7e70bc40f",
        "f8cdd3372ffdf62dd6e41bb3ca8305df",
        "83b0061fafc8061321dd9c86f166f1a9",
        "803141d6acbe79035aa51970f73b2a20",
        "4e8f6a2f12becd4cc10408154b93d44f",
        "8c093a86240c2d004be100a8d84da4cb",
        "892048930dc0381aae120438d77217d5",
        "6ef94891acfe2c5f0906f9eb19e38475",
    ];
    let creds = temp("exocal-keys", &format!("Joint1 {}\n", KEYS[0]));
    let (code, err) = calibrate_with(&creds, None);
    assert_eq!(code, Some(78), "{err}");
    assert!(err.contains("no key for Joint2"), "{err}");
    assert!(!err.contains(&KEYS[0][..6]), "a key in the message: {err}");
    // Every joint's key but not the end effector's (it signs its stream): 78, naming it.
    let joints: String = (1..=7)
        .map(|n| format!("Joint{n} {}\n", KEYS[n - 1]))
        .collect();
    let no_ee = temp("no-ee/exocal-keys", &joints);
    let (code, err) = calibrate_with(&no_ee, None);
    assert_eq!(code, Some(78), "{err}");
    assert!(err.contains("no key for EndEffector"), "{err}");
    // Every key, but no state directory: 78, naming it; with one, on to the socket.
    let all = format!("{joints}EndEffector {}\n", KEYS[7]);
    let full = temp("full/exocal-keys", &all);
    let state = full.parent().unwrap().join("state");
    for with_state in [false, true] {
        let (code, err) = calibrate_with(&full, with_state.then_some(state.as_path()));
        if with_state {
            assert_eq!(code, Some(69), "{err}");
        } else {
            assert_eq!(code, Some(78), "{err}");
            assert!(err.contains("STATE_DIRECTORY"), "{err}");
        }
    }
    let off = exocald::config::DEFAULT_TOML.replace("authenticate = true", "authenticate = false");
    let off = temp("off.toml", &off);
    let (code, _, err) = exocald(&["--config", off.to_str().unwrap(), "calibrate", "-i", "lo"]);
    assert!(err.contains("authentication is off"), "{err}");
    assert_eq!(code, 69, "{err}");
    // `lo` is no CAN socket: the error says why (a kernel without CAN, or not a CAN link),
    // never only "Address family not supported by protocol (os error 97)".
    assert!(
        err.contains("modprobe can-raw") || err.contains("`lo` is not a CAN interface"),
        "{err}"
    );
}

/// `nodes --json` with no bus: exit 69, and stdout is one JSON object naming the interface
/// (not empty: a script reading it gets the error too).
#[test]
fn nodes_json_without_a_bus_prints_a_json_error() {
    let (code, out, err) = exocald(&["nodes", "--json", "-i", "vcan93"]);
    assert_eq!(code, 69, "{err}");
    let v: serde_json::Value = serde_json::from_str(&out).expect("JSON on stdout");
    assert_eq!(v["exit"], 69, "{out}");
    assert!(v["error"].as_str().unwrap().contains("vcan93"), "{out}");
    // Without --json, stdout stays empty (the error is on stderr).
    let (code, out, err) = exocald(&["nodes", "-i", "vcan93"]);
    assert_eq!((code, out.as_str()), (69, ""), "{err}");
}

/// `demo --speed -1` reaches the value parser (64, naming the value), not clap's
/// "unexpected argument".
/// An endless input named as MCAP is refused at once, not read for ever.
#[test]
fn dev_zero_as_mcap_is_refused_at_once() {
    let (code, _, err) = exocald(&["offline", "-i", "/dev/zero", "--format", "mcap"]);
    assert_eq!(code, 65, "{err}");
    assert!(err.contains("not an MCAP file"), "{err}");
}

#[test]
fn demo_joints_calibrates_the_configurations_first_joints_and_refuses_more() {
    let dir = std::env::temp_dir().join(format!("exocald-cli-joints-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let out = dir.to_str().unwrap();
    let (code, json, err) = exocald(&[
        "demo", "--joints", "3", "--speed", "1e6", "-o", out, "--json",
    ]);
    assert_eq!(code, 0, "{err}");
    let v: serde_json::Value = serde_json::from_str(&json).expect("one JSON object");
    assert_eq!(v["verdict"], "pushed");
    assert_eq!(v["table"].as_array().map(Vec::len), Some(3), "{json}");
    let pushed: Vec<&str> = (v["push"].as_array().unwrap().iter())
        .map(|n| n["node"].as_str().unwrap())
        .collect();
    assert_eq!(pushed, ["Joint1", "Joint2", "Joint3"]);
    // More joints than the configuration's arm, and a joint count out of 1–7.
    let four = temp("arm4.toml", &{
        let mut c = exocald::config::Config::default_config();
        c.calibration = c.calibration.first(4);
        c.to_toml()
    });
    let (code, _, err) = exocald(&[
        "--config",
        four.to_str().unwrap(),
        "demo",
        "--joints",
        "5",
        "-o",
        out,
    ]);
    assert_eq!(code, 64, "{err}");
    assert!(
        err.contains("--joints 5: the configuration's arm has 4 joints"),
        "{err}"
    );
    let (code, _, err) = exocald(&["demo", "--joints", "8", "-o", out]);
    assert_eq!(code, 64, "{err}");
    assert!(err.contains("8 is not in 1..=7"), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_negative_speed_is_a_usage_error_naming_it() {
    let (code, _, err) = exocald(&["demo", "--speed", "-1"]);
    assert_eq!(code, 64, "{err}");
    assert!(err.contains("-1 is not a speed"), "{err}");
}

#[test]
fn usage_errors_are_64_and_help_is_0() {
    assert_eq!(exocald(&["calibrat"]).0, 64);
    let (code, out, _) = exocald(&["--help"]);
    assert_eq!(code, 0);
    assert!(out.contains("exocald demo"), "{out}");
}

#[test]
fn the_default_config_prints_and_checks() {
    let (code, out, _) = exocald(&["check-config", "--print-default"]);
    assert_eq!(code, 0);
    assert_eq!(out, exocald::config::DEFAULT_TOML);
    let path = temp("good.toml", &out);
    let (code, out, err) = exocald(&["--config", path.to_str().unwrap(), "check-config"]);
    assert_eq!(code, 0, "{err}");
    assert!(out.contains("valid"), "{out}");
    // What it prints is the effective configuration in the file's units, and is itself a valid
    // file that reads back to the same configuration.
    assert!(out.contains("alpha_deg = [-90.0, 90.0,"), "{out}");
    assert_eq!(
        exocald::config::Config::parse(&out).unwrap(),
        exocald::config::Config::parse(exocald::config::DEFAULT_TOML).unwrap()
    );
}

/// Without the sensors' spec the summary says what the expected table error leaves
/// out, with a figure: what a rate bias of 0.01 °/s, too small for the session to show, would
/// add to the table error (calib-core's consider allowance); with `[sensors]` it does not.
#[test]
#[cfg(feature = "demo")]
fn the_summary_says_when_the_sensors_rate_bias_is_not_configured() {
    let dir = std::env::temp_dir().join(format!("exocald-cli-sensors-{}", std::process::id()));
    let with = format!(
        "{}\n[sensors]\nrate_bias_deg_s = 0.005\nrate_bias_walk_deg_s_per_sqrt_s = 0.0001\n",
        exocald::config::DEFAULT_TOML
    );
    let with = temp("sensors.toml", &with);
    for (config, said) in [(None, true), (Some(with), false)] {
        let mut args: Vec<String> = Vec::new();
        if let Some(c) = &config {
            args.extend(["--config".into(), c.display().to_string()]);
        }
        let out_dir = dir.join(if said { "without" } else { "with" });
        args.extend(["demo", "--speed", "1000000", "-o"].map(String::from));
        args.push(out_dir.display().to_string());
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        let (code, out, err) = exocald(&args);
        assert_eq!(code, 0, "{err}");
        let line = out
            .lines()
            .find(|l| l.starts_with("sensors' rate bias: not configured ([sensors])"));
        assert_eq!(line.is_some(), said, "{out}");
        if let Some(line) = line {
            // `… one of 0.01 °/s, … would add ±4.68 mm, ±13.81 mrad (1σ) …`: a figure, not zero.
            let mm: f64 = line
                .split("would add ±")
                .nth(1)
                .and_then(|r| r.split(" mm").next())
                .and_then(|v| v.parse().ok())
                .unwrap_or_else(|| panic!("no figure in {line:?}"));
            assert!(mm > 0.5 && mm < 50.0, "{line}");
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// Completions for each shell and the manual pages, made from the CLI
/// definition, name every subcommand.
#[test]
fn completions_and_manual_pages_come_from_the_cli_definition() {
    let subcommands = [
        "calibrate",
        "run",
        "demo",
        "check-config",
        "offline",
        "recover",
        "nodes",
        "completions",
        "man",
    ];
    for shell in ["bash", "zsh", "fish", "elvish", "powershell"] {
        let (code, out, err) = exocald(&["completions", shell]);
        assert_eq!(code, 0, "{shell}: {err}");
        for sub in subcommands {
            assert!(out.contains(sub), "{shell} completions lack {sub}");
        }
    }
    assert!(exocald(&["completions", "bash"])
        .1
        .contains("--export-candump"));
    assert_eq!(exocald(&["completions", "tcsh"]).0, 64);

    let (code, page, err) = exocald(&["man"]);
    assert_eq!(code, 0, "{err}");
    assert!(page.contains(".TH exocald 1"), "{page}");
    for sub in subcommands {
        let roff = sub.replace('-', "\\-");
        assert!(
            page.contains(&format!("exocald\\-{roff}(1)")),
            "{sub}: {page}"
        );
    }
    let dir = std::env::temp_dir().join(format!("exocald-cli-{}-man", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let (code, _, err) = exocald(&["man", "--dir", dir.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    for sub in subcommands {
        let p = dir.join(format!("exocald-{sub}.1"));
        let text = std::fs::read_to_string(&p).unwrap_or_else(|e| panic!("{p:?}: {e}"));
        assert!(text.contains(&format!(".TH exocald-{sub} 1")), "{p:?}");
    }
    assert!(dir.join("exocald.1").exists());
    let demo = std::fs::read_to_string(dir.join("exocald-demo.1")).unwrap();
    assert!(demo.contains("\\-\\-listen"), "{demo}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// `demo --listen`: loopback only, and a taken port says what to do.
#[cfg(feature = "demo")]
#[test]
fn demo_listen_takes_loopback_only_and_a_taken_port_gets_a_hint() {
    let (code, _, err) = exocald(&["demo", "--listen", "0.0.0.0:8765"]);
    assert_eq!(code, 64, "{err}");
    assert!(err.contains("allow_remote"), "{err}");
    let (code, _, err) = exocald(&["demo", "--listen", "localhost"]);
    assert_eq!(code, 64, "{err}");
    assert!(err.contains("not an address and port"), "{err}");
    let taken = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = taken.local_addr().unwrap().to_string();
    let out = std::env::temp_dir().join(format!("exocald-cli-{}-taken", std::process::id()));
    let (code, _, err) = exocald(&["demo", "--listen", &addr, "-o", out.to_str().unwrap()]);
    assert_eq!(code, 74, "{err}");
    assert!(
        err.contains(&format!("listening on {addr}")) && err.contains("exocald demo --listen"),
        "{err}"
    );
    let _ = std::fs::remove_dir_all(&out);
}

/// The summary's last line is the verdict with the expected error; `--quiet` prints that line
/// alone, `--json` one object a script reads; offline says the same of the
/// demo's log, and a refusal says why.
#[cfg(feature = "demo")]
#[test]
fn the_verdict_is_the_last_line_and_quiet_and_json_say_it() {
    let dir = std::env::temp_dir().join(format!("exocald-cli-{}-verdict", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let out = dir.to_str().unwrap();
    let (code, text, err) = exocald(&["demo", "--speed", "1e6", "-o", out]);
    assert_eq!(code, 0, "{err}");
    let last = text.lines().last().unwrap().to_string();
    assert!(
        last.starts_with(
            "verdict: validated and pushed, every node holds the new table; \
                          expected table error ±"
        ),
        "{last}"
    );
    assert!(
        text.contains("drift model, every joint: Gauss-Markov"),
        "{text}"
    );
    assert!(
        text.contains("held-out mean error, nominal → calibrated: position "),
        "{text}"
    );

    let (code, quiet, err) = exocald(&["demo", "--speed", "1e6", "-o", out, "--quiet"]);
    assert_eq!(code, 0, "{err}");
    assert_eq!(quiet.trim_end(), last, "the same seed, the same verdict");
    assert!(err.is_empty(), "--quiet: nothing on stderr: {err}");

    let (code, json, err) = exocald(&["demo", "--speed", "1e6", "-o", out, "--json"]);
    assert_eq!(code, 0, "{err}");
    let v: serde_json::Value = serde_json::from_str(&json).expect("one JSON object");
    assert_eq!(v["verdict"], "pushed");
    assert_eq!(v["exit"], 0);
    assert_eq!(v["line"].as_str(), Some(last.as_str()));
    let mm = v["expected_error"]["position_mm"].as_f64().unwrap();
    assert!(last.contains(&format!("±{mm:.2} mm")), "{last} vs {mm}");
    let table = v["table"].as_array().unwrap();
    assert_eq!(table.len(), 7);
    assert!(
        table[2]["a"].as_f64().unwrap() > 0.3,
        "metres: {}",
        table[2]
    );
    let push = v["push"].as_array().unwrap();
    assert!(push.iter().all(|n| n["holds"] == "New"), "{json}");
    // The report's header: the emulated suit's seed, the start, the configuration.
    let report = std::fs::read_to_string(v["report"].as_str().unwrap()).unwrap();
    for says in [
        "(emulated suit, seed 2024), started 20",
        " UTC, logged to",
        "configured: window 20–180 s",
    ] {
        assert!(report.contains(says), "no {says:?} in the report's header");
    }

    let log = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .find(|p| p.extension().is_some_and(|x| x == "mcap"))
        .unwrap();
    let log = log.to_str().unwrap();
    let (code, json, err) = exocald(&["offline", "-i", log, "--json"]);
    assert_eq!(code, 0, "{err}");
    let o: serde_json::Value = serde_json::from_str(&json).unwrap();
    assert_eq!(o["verdict"], "validated");
    assert_eq!(o["table"], v["table"], "offline replays to the live table");
    assert!(o["push"].is_null());
    assert!(
        !err.contains("replaying"),
        "--json: no progress on stderr: {err}"
    );

    let strict = exocald::config::DEFAULT_TOML.replace(
        "max_expected_position_error_mm = 3.0",
        "max_expected_position_error_mm = 0.1",
    );
    let config = temp("strict.toml", &strict);
    let config = config.to_str().unwrap();
    let (code, text, _) = exocald(&["--config", config, "offline", "-i", log]);
    assert_eq!(code, 65);
    let last = text.lines().last().unwrap();
    assert!(
        last.starts_with("verdict: refused, nothing pushed: "),
        "{last}"
    );
    let (code, json, _) = exocald(&["--config", config, "offline", "-i", log, "--json"]);
    assert_eq!(code, 65);
    let r: serde_json::Value = serde_json::from_str(&json).unwrap();
    assert_eq!(
        (r["verdict"].as_str(), r["exit"].as_i64()),
        (Some("refused"), Some(65))
    );
    assert!(!r["refusals"].as_array().unwrap().is_empty(), "{json}");
    let (code, json, _) = exocald(&["offline", "-i", "/nonexistent.mcap", "--json"]);
    let e: serde_json::Value = serde_json::from_str(&json).expect("JSON on a failure too");
    assert_eq!(e["exit"].as_i64(), Some(i64::from(code)));
    let _ = std::fs::remove_dir_all(&dir);
}
