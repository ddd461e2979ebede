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

/// Builds the test targets of exocal-tests that `feature` turns on (on the host) with `cargo`;
/// returns their executables, sorted.
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
