//! `cargo xtask run-suites BIN..` (internal, run inside the harness by `test`): each test
//! binary in turn, one test thread each, since they share the bus.

use std::io::Write;
use std::process::{Command, Stdio};

use anyhow::{Context, Result};

use crate::harness::HARNESS_ENV;

/// (internal) Run test binaries one after another inside the harness, one thread each.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The test executables.
    #[arg(required = true)]
    pub bins: Vec<String>,
}

pub fn run(args: Args) -> Result<u8> {
    let place = std::env::var(HARNESS_ENV).unwrap_or_else(|_| "no harness".into());
    let mut failed = Vec::new();
    for bin in &args.bins {
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
