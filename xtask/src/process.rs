//! Running programs: a command's stdout, or its success, or a clear error, exit statuses as the shell reports
//! them, quoting for `sh`.
//!
//! A leaf module: it imports no other xtask module.

use std::process::{Child, Command, Stdio};

use anyhow::{bail, Context, Result};

/// Runs `cmd` with no stdin; returns its stdout, or an error with `what`, the exit status and
/// the tail of its stderr.
pub fn output(cmd: &mut Command, what: &str) -> Result<String> {
    let out = cmd
        .stdin(Stdio::null())
        .output()
        .with_context(|| format!("{what}: cannot start {:?}", cmd.get_program()))?;
    if !out.status.success() {
        let stderr = String::from_utf8_lossy(&out.stderr);
        let tail: Vec<&str> = stderr.lines().rev().take(6).collect();
        let tail: Vec<&str> = tail.into_iter().rev().collect();
        bail!("{what}: {} ({})", out.status, tail.join(" | "));
    }
    Ok(String::from_utf8_lossy(&out.stdout).into_owned())
}

/// Runs `cmd` with no stdin, its output passed through: an error naming `what` when it cannot
/// start, `failed` when it exits non-zero.
pub fn run(cmd: &mut Command, what: &str, failed: &str) -> Result<()> {
    let status = cmd
        .stdin(Stdio::null())
        .status()
        .with_context(|| what.to_string())?;
    if !status.success() {
        bail!("{failed}");
    }
    Ok(())
}

/// Exit status of a finished child as the shell reports it (128 + signal if a signal ended it).
pub fn exit_code(status: std::process::ExitStatus) -> u8 {
    use std::os::unix::process::ExitStatusExt;
    match (status.code(), status.signal()) {
        (Some(code), _) => code as u8,
        (None, Some(sig)) => 128u8.wrapping_add(sig as u8),
        _ => 1,
    }
}

/// Quotes a string for POSIX `sh`.
pub fn shell_quote(s: &str) -> String {
    format!("'{}'", s.replace('\'', r"'\''"))
}

/// `n` processes that keep a CPU busy each (`sh` spinning in a loop), for as long as this value
/// lives: a stress load for the suites (`cargo xtask test --load N`). Dropping it kills them.
pub struct BusyLoad {
    children: Vec<Child>,
}

impl BusyLoad {
    /// Starts `n` busy processes (none for 0).
    pub fn start(n: usize) -> Result<BusyLoad> {
        let mut load = BusyLoad {
            children: Vec::with_capacity(n),
        };
        for _ in 0..n {
            let child = Command::new("sh")
                .args(["-c", "while :; do :; done"])
                .stdin(Stdio::null())
                .stdout(Stdio::null())
                .spawn()
                .context("start a busy process (sh)")?;
            load.children.push(child);
        }
        Ok(load)
    }

    /// How many processes it runs.
    pub fn len(&self) -> usize {
        self.children.len()
    }
}

impl Drop for BusyLoad {
    fn drop(&mut self) {
        for child in &mut self.children {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn busy_load_runs_and_ends_its_processes() {
        let load = BusyLoad::start(2).unwrap();
        assert_eq!(load.len(), 2);
        let pids: Vec<u32> = load.children.iter().map(|c| c.id()).collect();
        for pid in &pids {
            assert!(std::path::Path::new(&format!("/proc/{pid}")).exists());
        }
        drop(load);
        for pid in &pids {
            // Reaped by the drop: the pid is gone (or reused by an unrelated process that is
            // not a spinning sh of ours, which the stat line would show).
            let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).unwrap_or_default();
            assert!(!stat.contains("(sh) R"), "{pid} still spinning: {stat}");
        }
    }

    #[test]
    fn shell_quote_survives_single_quotes() {
        assert_eq!(shell_quote("it's"), r"'it'\''s'");
        assert_eq!(shell_quote(""), "''");
    }
}
