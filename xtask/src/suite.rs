//! `cargo xtask test`: the one command that runs every test.
//!
//! 1. `cargo test --workspace`: unit, integration and doc tests of every crate.
//! 2. The suites that need real vcan (`exocal-tests` built with `--features vcan`) are built on
//!    the host, then run one after another inside the vcan harness (`run-suites`), one test
//!    thread each, since they share the bus.
//! 3. The power-up test ([`crate::powerup`]): the Debian package installed in a guest that boots
//!    systemd as PID 1, checked from inside.
//! 4. The cross-builds for the controller ([`crate::ship::check`]): aarch64 and armv7 binaries
//!    run under qemu-user (`--help`, an offline calibration equal to the host's), their Debian
//!    packages through lintian.
//!
//! Counts are read from libtest's `test result:` lines, and the last line is the total.

use std::io::{BufRead, BufReader, Write};
use std::process::{Command, Stdio};

use anyhow::{bail, Context, Result};

use crate::harness;
use crate::HarnessArgs;

/// Passed, failed and ignored tests, summed over `test result:` lines.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
pub struct Counts {
    pub passed: u64,
    pub failed: u64,
    pub ignored: u64,
    /// Suites whose process failed without a result line (crash, build or harness error).
    pub broken: u64,
}

impl Counts {
    /// Adds every libtest `test result:` line in `text`.
    pub fn scan(&mut self, text: &str) {
        for line in text.lines() {
            let Some(rest) = line.trim().strip_prefix("test result: ") else {
                continue;
            };
            for part in rest.split(';') {
                let mut words = part.split_whitespace().rev();
                let (Some(kind), Some(n)) = (words.next(), words.next()) else {
                    continue;
                };
                let Ok(n) = n.parse::<u64>() else { continue };
                match kind {
                    "passed" => self.passed += n,
                    "failed" => self.failed += n,
                    "ignored" => self.ignored += n,
                    _ => {}
                }
            }
        }
    }
}

pub fn test_all(opts: &HarnessArgs) -> Result<u8> {
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let mut host = Counts::default();

    // Everything the suites need (Chromium, lintian, the cross toolchain, the VM packages when
    // this kernel has no vcan): installed when missing, as root on Debian.
    crate::setup::install_all()?;
    // The Python cross-checks (cantools, mcap) need their venv before any suite runs; the
    // guest is offline, so it is made here, and every suite finds it through EXOCAL_PYTHON.
    let python = crate::setup::python_env()?;
    std::env::set_var("EXOCAL_PYTHON", &python);
    std::env::set_var(
        "EXOCAL_PYENV",
        python.parent().and_then(|b| b.parent()).unwrap_or(&python),
    );
    // The end-to-end suites run the real binaries, optimised as shipped (in the TCG guest a
    // debug emulator cannot keep its nodes' clocks in step with real time): build them, and
    // tell the suites where.
    let bins = crate::ship::build(&crate::ship::TARGETS[0])?;
    let bin_dir = bins[0].parent().context("binary directory")?;
    std::env::set_var("EXOCAL_BIN_DIR", bin_dir);

    println!(
        "==> [1/5] cargo test --workspace -- --include-ignored (unit, integration and doc tests)"
    );
    let ok_host = run_teed(
        // `--include-ignored`: tests ignored for plain `cargo test` because they need the
        // project's Python venv (EXOCAL_PYTHON, made above) run here.
        Command::new(&cargo).args([
            "test",
            "--workspace",
            "--color",
            "never",
            "--",
            "--include-ignored",
        ]),
        &mut host,
    )?;
    if !ok_host && host.failed == 0 {
        host.broken += 1;
    }

    println!("==> [2/5] vcan suites (exocal-tests --features vcan) in the vcan harness");
    let bins = build_suites(&cargo, "vcan")?;
    let mut vcan = Counts::default();
    if bins.is_empty() {
        bail!("no vcan suites were built: exocal-tests has no test targets with feature vcan");
    }
    // `cargo test` may have rebuilt xtask's own binary under us: run a copy of this one.
    let exe = crate::host::workspace_root().join("target/xtask/suite-runner");
    std::fs::create_dir_all(exe.parent().context("target/xtask")?)?;
    std::fs::copy("/proc/self/exe", &exe).context("copy the running xtask")?;
    let mut argv = vec![exe.display().to_string(), "run-suites".to_string()];
    argv.extend(bins);
    let mut req = opts.request(argv)?;
    req.capture_stdout = true;
    let outcome = harness::run(&req)?;
    vcan.scan(&String::from_utf8_lossy(&outcome.stdout));
    if outcome.code != 0 && vcan.failed == 0 {
        vcan.broken += 1;
    }

    println!("==> [3/5] the power-up test under systemd (cargo xtask powerup)");
    let power = match crate::powerup::run(opts) {
        Ok(p) => p,
        Err(e) => {
            eprintln!("power-up test could not run: {e:#}");
            crate::powerup::PowerUp::broken()
        }
    };

    println!(
        "==> [4/5] cross-builds under qemu-user, Debian packages, lintian (cargo xtask cross)"
    );
    let mut cross = Counts::default();
    let cross_lines =
        match crate::ship::parse_targets(&[], true).and_then(|t| crate::ship::check(&t)) {
            Ok(lines) => {
                cross.passed = lines.len() as u64;
                lines
            }
            Err(e) => {
                cross.failed = 1;
                vec![format!("FAILED: {e:#}")]
            }
        };

    println!("==> [5/5] every figure the READMEs quote, from its command (cargo xtask figures)");
    let mut figures = Counts::default();
    let figures_line = match crate::figures::run(&crate::host::workspace_root(), false) {
        Ok(stale) if stale.is_empty() => {
            figures.passed = 1;
            "every quoted block matches its command's output".to_string()
        }
        Ok(stale) => {
            figures.failed = stale.len() as u64;
            format!(
                "stale: {} (`cargo xtask figures --write` regenerates them)",
                stale.join(", ")
            )
        }
        Err(e) => {
            figures.failed = 1;
            format!("FAILED: {e:#}")
        }
    };

    let total = Counts {
        passed: host.passed + vcan.passed + power.counts.passed + cross.passed + figures.passed,
        failed: host.failed
            + vcan.failed
            + host.broken
            + vcan.broken
            + power.counts.failed
            + power.counts.broken
            + cross.failed
            + figures.failed,
        ignored: host.ignored + vcan.ignored + power.counts.ignored,
        broken: host.broken + vcan.broken + power.counts.broken,
    };
    println!();
    println!(
        "host suites: {} passed, {} failed, {} ignored{}",
        host.passed,
        host.failed,
        host.ignored,
        if host.broken > 0 {
            " (cargo test itself failed)"
        } else {
            ""
        }
    );
    println!(
        "vcan suites ({}, {:.1} s): {} passed, {} failed{}",
        outcome.path,
        outcome.elapsed.as_secs_f64(),
        vcan.passed,
        vcan.failed,
        if vcan.broken > 0 {
            format!(" (harness run exited {})", outcome.code)
        } else {
            String::new()
        }
    );
    println!("{}", power.summary());
    println!(
        "cross-builds: {} checks passed, {} failed\n  {}",
        cross.passed,
        cross.failed,
        cross_lines.join("\n  ")
    );
    println!("README figures: {figures_line}");
    println!(
        "exocal: {} passed, {} failed, {} skipped",
        total.passed, total.failed, total.ignored
    );
    Ok(if total.failed == 0 { 0 } else { 1 })
}

/// Runs a command, copying its stdout to ours and counting its test results.
fn run_teed(cmd: &mut Command, counts: &mut Counts) -> Result<bool> {
    let mut child = cmd
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .spawn()
        .context("spawn cargo")?;
    let reader = BufReader::new(child.stdout.take().context("stdout")?);
    let mut out = std::io::stdout();
    for line in reader.lines() {
        let line = line?;
        writeln!(out, "{line}")?;
        counts.scan(&line);
    }
    Ok(child.wait()?.success())
}

/// Builds the suites of exocal-tests that `feature` turns on (on the host); returns their
/// executables.
pub fn build_suites(cargo: &str, feature: &str) -> Result<Vec<String>> {
    let out = Command::new(cargo)
        .args([
            "test",
            "-p",
            "exocal-tests",
            "--features",
            feature,
            "--tests",
            "--no-run",
            "--message-format=json-render-diagnostics",
        ])
        .stdin(Stdio::null())
        .stderr(Stdio::inherit())
        .output()
        .context("cargo test --no-run")?;
    if !out.status.success() {
        bail!("building the {feature} suites failed");
    }
    let mut bins = Vec::new();
    for line in String::from_utf8_lossy(&out.stdout).lines() {
        let Ok(msg) = serde_json::from_str::<serde_json::Value>(line) else {
            continue;
        };
        let is_test_target = msg["reason"] == "compiler-artifact"
            && msg["profile"]["test"] == true
            && msg["target"]["kind"]
                .as_array()
                .is_some_and(|k| k.iter().any(|k| k == "test"));
        if let (true, Some(exe)) = (is_test_target, msg["executable"].as_str()) {
            bins.push(exe.to_string());
        }
    }
    bins.sort();
    Ok(bins)
}

/// `run-suites`: runs each test binary in turn (inside the harness), one test thread each.
pub fn run_suites(bins: &[String]) -> Result<u8> {
    let place = std::env::var(crate::HARNESS_ENV).unwrap_or_else(|_| "no harness".into());
    let mut failed = Vec::new();
    for bin in bins {
        let name = std::path::Path::new(bin)
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_else(|| bin.clone());
        println!("==> suite {name} ({place})");
        let _ = std::io::stdout().flush();
        let status = Command::new(bin)
            .args(["--test-threads=1", "--nocapture"])
            .stdin(Stdio::null())
            .status()
            .with_context(|| format!("run {bin}"))?;
        if !status.success() {
            failed.push(name);
        }
    }
    if failed.is_empty() {
        Ok(0)
    } else {
        eprintln!("vcan suites failed: {}", failed.join(", "));
        Ok(1)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counts_read_libtest_result_lines() {
        let mut c = Counts::default();
        c.scan("running 3 tests\ntest result: ok. 3 passed; 0 failed; 1 ignored; 0 measured; 0 filtered out; finished in 0.01s\n");
        c.scan("test result: FAILED. 1 passed; 2 failed; 0 ignored; 0 measured; 0 filtered out");
        assert_eq!(
            c,
            Counts {
                passed: 4,
                failed: 2,
                ignored: 1,
                broken: 0
            }
        );
    }

    #[test]
    fn counts_ignore_other_lines() {
        let mut c = Counts::default();
        c.scan("test foo ... ok\nexocal: 9 passed, 0 failed\n");
        assert_eq!(c, Counts::default());
    }
}
