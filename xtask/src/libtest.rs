//! libtest plumbing: counting `test result:` lines, building test binaries without running
//! them, and running a command while its output is copied and counted.
//!
//! A leaf module: it imports no other xtask module.

use std::io::{BufRead, BufReader, Write};
use std::process::{Command, Stdio};

use anyhow::{bail, Context, Result};

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

/// Runs a command, copying its stdout to ours and counting its test results.
pub fn run_teed(cmd: &mut Command, counts: &mut Counts) -> Result<bool> {
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

/// The crate of the suites that run in the harness, and every feature that turns some on.
pub const SUITE_PACKAGE: &str = "exocal-tests";
/// See [`SUITE_PACKAGE`].
pub const SUITE_FEATURES: &[&str] = &["vcan", "powerup"];

/// Builds (on the host, with `cargo`) the test targets of [`SUITE_PACKAGE`] that `feature` turns
/// on (their `required-features`); returns their executables, sorted.
///
/// They are built with `--workspace` and every [`SUITE_FEATURES`] on: the workspace's feature
/// unification, the same as `cargo test --workspace`'s, so after it nothing but the suites
/// themselves is compiled (built alone with `-p`, the shared dependencies get other features —
/// calib-core without `default`, clap with fewer — and most of the workspace is compiled again,
/// once per feature set).
pub fn build_suites(cargo: &str, feature: &str) -> Result<Vec<String>> {
    let names = suite_targets(cargo, feature)?;
    let features: Vec<String> = SUITE_FEATURES
        .iter()
        .map(|f| format!("{SUITE_PACKAGE}/{f}"))
        .collect();
    let mut bins: Vec<String> = test_artifacts(cargo, &["--features", &features.join(",")])
        .with_context(|| format!("building the {feature} suites"))?
        .into_iter()
        .filter(|msg| {
            msg["target"]["name"]
                .as_str()
                .is_some_and(|n| names.iter().any(|s| s == n))
        })
        .filter_map(|msg| msg["executable"].as_str().map(str::to_string))
        .collect();
    bins.sort();
    Ok(bins)
}

/// `cargo test --workspace --no-run ARGS`: builds (or finds built) every test binary, and
/// returns cargo's artifact message for each (`target`, `manifest_path`, `executable`...).
pub fn test_artifacts(cargo: &str, args: &[&str]) -> Result<Vec<serde_json::Value>> {
    let out = Command::new(cargo)
        .args(["test", "--workspace", "--no-run"])
        .args(args)
        .arg("--message-format=json-render-diagnostics")
        .stdin(Stdio::null())
        .stderr(Stdio::inherit())
        .output()
        .context("cargo test --no-run")?;
    if !out.status.success() {
        bail!("cargo test --workspace --no-run {} failed", args.join(" "));
    }
    Ok(String::from_utf8_lossy(&out.stdout)
        .lines()
        .filter_map(|line| serde_json::from_str::<serde_json::Value>(line).ok())
        .filter(|msg| {
            msg["reason"] == "compiler-artifact"
                && msg["profile"]["test"] == true
                && msg["executable"].is_string()
        })
        .collect())
}

/// `cargo metadata --no-deps` of the workspace.
pub fn metadata(cargo: &str) -> Result<serde_json::Value> {
    let out = Command::new(cargo)
        .args(["metadata", "--no-deps", "--format-version", "1"])
        .stdin(Stdio::null())
        .stderr(Stdio::inherit())
        .output()
        .context("cargo metadata")?;
    if !out.status.success() {
        bail!("cargo metadata failed");
    }
    serde_json::from_slice(&out.stdout).context("cargo metadata's output")
}

/// The names of [`SUITE_PACKAGE`]'s test targets whose `required-features` include `feature`
/// (from `cargo metadata`).
fn suite_targets(cargo: &str, feature: &str) -> Result<Vec<String>> {
    Ok(targets_needing(&metadata(cargo)?, SUITE_PACKAGE, feature))
}

/// The test targets of `package` in `cargo metadata` output that need `feature`.
fn targets_needing(meta: &serde_json::Value, package: &str, feature: &str) -> Vec<String> {
    let Some(packages) = meta["packages"].as_array() else {
        return Vec::new();
    };
    packages
        .iter()
        .filter(|p| p["name"] == package)
        .flat_map(|p| p["targets"].as_array().into_iter().flatten())
        .filter(|t| {
            t["kind"]
                .as_array()
                .is_some_and(|k| k.iter().any(|k| k == "test"))
        })
        .filter(|t| {
            t["required-features"]
                .as_array()
                .is_some_and(|f| f.iter().any(|f| f == feature))
        })
        .filter_map(|t| t["name"].as_str().map(str::to_string))
        .collect()
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
    fn suite_targets_are_read_from_required_features() {
        let meta = serde_json::json!({"packages": [
            {"name": "exocal-tests", "targets": [
                {"name": "vcan_smoke", "kind": ["test"], "required-features": ["vcan"]},
                {"name": "powerup_systemd", "kind": ["test"], "required-features": ["powerup"]},
                {"name": "exocal_tests", "kind": ["lib"]}
            ]},
            {"name": "other", "targets": [
                {"name": "x", "kind": ["test"], "required-features": ["vcan"]}
            ]}
        ]});
        assert_eq!(
            targets_needing(&meta, "exocal-tests", "vcan"),
            ["vcan_smoke"]
        );
        assert_eq!(
            targets_needing(&meta, "exocal-tests", "powerup"),
            ["powerup_systemd"]
        );
    }

    #[test]
    fn counts_ignore_other_lines() {
        let mut c = Counts::default();
        c.scan("test foo ... ok\nexocal: 9 passed, 0 failed\n");
        assert_eq!(c, Counts::default());
    }
}
