//! `cargo xtask`: exocal's long commands.
//!
//! ```text
//! cargo xtask test                 everything: unit + doc tests, vcan suites, power-up, cross-builds,
//!                                  README figures
//! cargo xtask vcan -- CMD [ARG..]  run CMD with real vcan0 and vcan1 up (native netns or QEMU guest)
//! cargo xtask setup [--check]      install what `test` needs (root, Debian), then self-check
//! cargo xtask clean-root           run `setup` in a freshly bootstrapped Debian root
//! cargo xtask figures [--write]    check (or regenerate) every figure the READMEs quote
//! ```
//!
//! Exit status: `vcan` returns the command's own status (128 + signal if it was killed); `test`
//! returns 0 only when every suite passed; 2 means the harness itself could not run.

mod bench;
mod cleanroot;
mod figures;
mod harness;
mod host;
mod native;
mod powerup;
mod setup;
mod ship;
mod suite;
mod vm;

use std::process::ExitCode;
use std::time::Duration;

use anyhow::{bail, Context, Result};

/// Set by the harness inside its namespace or guest: `native` or `vm`.
pub const HARNESS_ENV: &str = "EXOCAL_VCAN_HARNESS";

const USAGE: &str = "\
usage:
  cargo xtask test [--mode auto|native|vm] [--timeout SECS]
      Run every test: `cargo test --workspace` (unit, integration and doc tests), the suites
      that need real vcan (crate exocal-tests, feature `vcan`) inside the vcan harness, the
      power-up test under systemd (`powerup`), the cross-builds under qemu-user (`cross`), and
      the README figures (`figures`).
  cargo xtask vcan [--mode auto|native|vm] [--timeout SECS] [--mem MIB] [--verbose]
                   [--systemd [--setup SCRIPT]] -- CMD [ARG..]
      Run CMD with real vcan0 and vcan1 up. `native` uses this kernel's vcan in a private network
      namespace (unshare); `vm` boots Debian's kernel under qemu-system-x86_64 -accel tcg with the
      host root shared read-only. `auto` (default) picks native when it can and the VM when it must.
      The exit status and output of CMD come back unchanged.
      --systemd boots systemd as PID 1 in the guest (host root read-only under a tmpfs overlay),
      runs SCRIPT as root in that root before boot (install units, enable services; vcan0/vcan1
      are then the script's to create, e.g. with a .netdev), and runs CMD from a unit once
      multi-user.target is up; the boot's journal is kept for the caller (--verbose shows where).
  cargo xtask setup [--check]
      Install everything `test` needs on a fresh Debian machine (as root): the Debian packages
      (cross gcc and the target C libraries, qemu-user-static, Chromium, lintian, python3-venv,
      systemd, and where this kernel has no vcan QEMU, Debian's kernel, busybox-static, cpio),
      the rustup targets and the Python venv; then the self-check: C and Rust hello-worlds
      built for every cross target and run under qemu-user, headless Chromium, lintian, the
      venv's modules, the guest's kernel, modules and busybox. --check runs the self-check only.
  cargo xtask clean-root
      Prove setup's package list complete: bootstrap a minimal Debian root of this release
      (mmdebstrap, this machine's apt sources) and run `setup` inside it (as root).
  cargo xtask figures [--write]
      Regenerate every figure the READMEs quote (the demo's summary for its seeds, the paper
      example's tables, the config-error example, the unit's security deductions) from the
      command that prints it, and fail naming each block that differs (`--write`: rewrite them
      in place). Part of `test`.
  cargo xtask cross [--target TRIPLE]..
      Release-build exocald and exocal-hil for aarch64 and armv7 (or the given targets), run
      --help of each and `exocald offline` on a session the host's demo recorded under
      qemu-user (the table must equal the host's), build their Debian packages, run lintian,
      and report binary and package sizes.
  cargo xtask powerup [--timeout SECS] [--verbose]
      The power-up test: build this machine's Debian package, boot systemd as PID 1 in the
      guest with the package installed (dpkg -i), vcan0 from systemd-networkd and exocal-hil as a
      service, and check exocald.service's boot-time calibration from inside (READY, watchdog,
      no capabilities, read-only system, every node holds the pushed table, MCAP in the
      StateDirectory, systemctl stop mid-session). Part of `test`.
  cargo xtask deb [--target TRIPLE|ARCH]..
      Build the Debian package (default: this machine's arch) into target/debian/, run lintian.
  cargo xtask bench [--quick] [--only calib,firmware,ingest] [--out FILE]
      Measure calib-core against scipy, its firmware memory use, and the daemon's ingest against
      candump; write BENCHMARKS.md (long: not part of `test`).
  cargo xtask run-suites BIN [BIN..]
      (internal) Run test binaries one after another inside the harness, one thread each.";

fn main() -> ExitCode {
    match run(std::env::args().skip(1).collect()) {
        Ok(code) => ExitCode::from(code),
        Err(err) => {
            eprintln!("xtask: error: {err:#}");
            ExitCode::from(2)
        }
    }
}

fn run(args: Vec<String>) -> Result<u8> {
    let Some((cmd, rest)) = args.split_first() else {
        println!("{USAGE}");
        return Ok(2);
    };
    match cmd.as_str() {
        "vcan" => {
            let (opts, argv) = HarnessArgs::parse(rest)?;
            if argv.is_empty() {
                bail!("vcan: no command given\n{USAGE}");
            }
            let outcome = harness::run(&opts.request(argv)?)?;
            Ok(outcome.code)
        }
        "test" => {
            let (opts, extra) = HarnessArgs::parse(rest)?;
            if !extra.is_empty() {
                bail!("test: unexpected arguments {extra:?}");
            }
            suite::test_all(&opts)
        }
        "powerup" => {
            let (opts, extra) = HarnessArgs::parse(rest)?;
            if !extra.is_empty() {
                bail!("powerup: unexpected arguments {extra:?}");
            }
            powerup::main(&opts)
        }
        "run-suites" => suite::run_suites(rest),
        "bench" => bench::bench(rest),
        "cross" => ship::cross(rest),
        "deb" => ship::deb(rest),
        "setup" => setup::main(rest),
        "clean-root" => cleanroot::main(rest),
        "figures" => figures::main(rest),
        "help" | "--help" | "-h" => {
            println!("{USAGE}");
            Ok(0)
        }
        other => bail!("unknown command {other:?}\n{USAGE}"),
    }
}

/// Options shared by `vcan` and `test`.
#[derive(Debug, Clone)]
pub struct HarnessArgs {
    pub mode: harness::Mode,
    pub timeout: Duration,
    pub mem_mib: u32,
    pub verbose: bool,
    pub systemd: bool,
    pub setup: Option<std::path::PathBuf>,
}

impl HarnessArgs {
    /// Parses options up to `--`; returns them and the command after `--`.
    fn parse(args: &[String]) -> Result<(Self, Vec<String>)> {
        let mut opts = HarnessArgs {
            mode: harness::Mode::Auto,
            timeout: Duration::from_secs(1200),
            mem_mib: 3072,
            verbose: false,
            systemd: false,
            setup: None,
        };
        let mut it = args.iter();
        while let Some(arg) = it.next() {
            let mut value = |name: &str| {
                it.next()
                    .cloned()
                    .with_context(|| format!("{name} needs a value"))
            };
            match arg.as_str() {
                "--" => return Ok((opts, it.cloned().collect())),
                "--mode" => opts.mode = value("--mode")?.parse()?,
                "--timeout" => {
                    let secs: u64 = value("--timeout")?
                        .parse()
                        .context("--timeout takes whole seconds")?;
                    opts.timeout = Duration::from_secs(secs);
                }
                "--mem" => opts.mem_mib = value("--mem")?.parse().context("--mem takes MiB")?,
                "--verbose" | "-v" => opts.verbose = true,
                "--systemd" => opts.systemd = true,
                "--setup" => opts.setup = Some(value("--setup")?.into()),
                other if other.starts_with('-') => bail!("unknown option {other:?}\n{USAGE}"),
                _ => {
                    // A command without `--` is accepted too.
                    let mut argv = vec![arg.clone()];
                    argv.extend(it.cloned());
                    return Ok((opts, argv));
                }
            }
        }
        Ok((opts, Vec::new()))
    }

    fn request(&self, argv: Vec<String>) -> Result<harness::Request> {
        Ok(harness::Request {
            argv,
            cwd: std::env::current_dir().context("current directory")?,
            timeout: self.timeout,
            mode: self.mode,
            mem_mib: self.mem_mib,
            verbose: self.verbose,
            capture_stdout: false,
            systemd: self.systemd,
            setup: self.setup.clone(),
        })
    }
}
