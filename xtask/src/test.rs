//! `cargo xtask test`: the one command that runs every test.
//!
//! 1. `cargo test --workspace`: unit, integration and doc tests of every crate.
//! 2. The suites that need real vcan (`exocal-tests` built with `--features vcan`) are built on
//!    the host, then run one after another inside the vcan harness (`run-suites`), one test
//!    thread each, since they share the bus.
//! 3. The power-up test ([`crate::powerup`]): the Debian package installed in a guest that boots
//!    systemd as PID 1, checked from inside.
//! 4. The cross-builds for the controller ([`crate::cross::check`]): aarch64 and armv7 binaries
//!    run under qemu-user (`--help`, an offline calibration equal to the host's), their Debian
//!    packages through lintian.
//!
//! Counts are read from libtest's `test result:` lines, and the last line is the total.

use std::process::Command;
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};

use crate::libtest::{self, Counts};
use crate::process::BusyLoad;
use crate::{cross, figures, harness, paths, powerup, setup, targets};

/// Run every test: workspace tests, vcan suites, power-up, cross-builds, README figures.
///
/// Run every test: `cargo test --workspace` (unit, integration and doc tests), the suites that
/// need real vcan (crate exocal-tests, feature `vcan`) inside the vcan harness, the power-up test
/// under systemd (`powerup`), the cross-builds under qemu-user (`cross`), and the README figures
/// (`figures`).
#[derive(Debug, clap::Args)]
pub struct Args {
    #[command(flatten)]
    pub harness: harness::Opts,
    /// Keep N busy processes on the host while the vcan and power-up suites run (a stress
    /// test: the suites must pass on a loaded machine).
    #[arg(long, value_name = "N", default_value_t = 0)]
    pub load: usize,
    /// For development: the host suites as plain `cargo test --workspace` runs them (not the
    /// ignored ones), without setup, release builds, vcan, power-up, cross-builds or figures.
    /// Not what CI runs.
    #[arg(long)]
    pub quick: bool,
}

/// `cargo test --workspace --no-fail-fast [-- --include-ignored]`, counted into `host` (a failure
/// of cargo itself with no failed test counts as broken).
fn workspace_tests(cargo: &str, include_ignored: bool, host: &mut Counts) -> Result<()> {
    let mut cmd = Command::new(cargo);
    // `--no-fail-fast`: a failing crate does not hide the results of the others.
    cmd.args(["test", "--workspace", "--no-fail-fast", "--color", "never"]);
    if include_ignored {
        // The tests plain `cargo test` ignores: those that need the project's Python venv
        // (EXOCAL_PYTHON) and the slow cost checks.
        cmd.args(["--", "--include-ignored"]);
    }
    let ok = libtest::run_teed(&mut cmd, host)?;
    if !ok && host.failed == 0 {
        host.broken += 1;
    }
    Ok(())
}

/// `cargo xtask test --quick`: the host suites as plain `cargo test` runs them.
fn quick() -> Result<u8> {
    let started = Instant::now();
    let mut host = Counts::default();
    workspace_tests(&paths::cargo(), false, &mut host)?;
    println!(
        "host suites ({:.0} s): {} passed, {} failed, {} ignored (the full run includes them)",
        started.elapsed().as_secs_f64(),
        host.passed,
        host.failed,
        host.ignored
    );
    println!(
        "exocal: {} passed, {} failed, {} skipped",
        host.passed,
        host.failed + host.broken,
        host.ignored
    );
    Ok(if host.failed + host.broken == 0 { 0 } else { 1 })
}

/// Wall time per step, for the summary (where CI's time goes).
#[derive(Default)]
struct Steps(Vec<(&'static str, Duration)>);

impl Steps {
    /// Runs `f` as step `name`, timing it.
    fn time<R>(&mut self, name: &'static str, f: impl FnOnce() -> R) -> R {
        let started = Instant::now();
        let r = f();
        self.0.push((name, started.elapsed()));
        r
    }

    fn line(&self) -> String {
        let parts: Vec<String> = self
            .0
            .iter()
            .map(|(n, d)| format!("{n} {:.0} s", d.as_secs_f64()))
            .collect();
        let total: f64 = self.0.iter().map(|(_, d)| d.as_secs_f64()).sum();
        format!("step times: {} (total {total:.0} s)", parts.join(", "))
    }
}

pub fn run(args: Args) -> Result<u8> {
    if args.quick {
        return quick();
    }
    let opts = &args.harness;
    let cargo = paths::cargo();
    let mut host = Counts::default();
    let mut steps = Steps::default();

    // Everything the suites need (Chromium, lintian, the cross toolchain, the VM packages when
    // this kernel has no vcan): installed when missing, as root on Debian.
    steps.time("setup", setup::install_all)?;
    // The Python cross-checks (cantools, mcap) need their venv before any suite runs; the
    // guest is offline, so it is made here, and every suite finds it through EXOCAL_PYTHON.
    let python = setup::python_env()?;
    std::env::set_var("EXOCAL_PYTHON", &python);
    // The JavaScript oracle (@mcap/core's indexed reader) for the host suites.
    setup::js_env()?;
    std::env::set_var(
        "EXOCAL_PYENV",
        python.parent().and_then(|b| b.parent()).unwrap_or(&python),
    );
    // The end-to-end suites run the real binaries, optimised as shipped (in the TCG guest a
    // debug emulator cannot keep its nodes' clocks in step with real time): build them, and
    // tell the suites where.
    let bins = steps.time("release build", || targets::build(&targets::TARGETS[0]))?;
    // The figures and the README's demo run the workspace build (with the demo).
    steps.time("release build (demo)", targets::build_demo)?;
    let bin_dir = bins[0].parent().context("binary directory")?;
    std::env::set_var("EXOCAL_BIN_DIR", bin_dir);

    println!(
        "==> [1/5] cargo test --workspace -- --include-ignored (unit, integration and doc tests)"
    );
    steps.time("[1/5] workspace tests", || {
        workspace_tests(&cargo, true, &mut host)
    })?;

    println!("==> [2/5] vcan suites (exocal-tests --features vcan) in the vcan harness");
    let started = Instant::now();
    let bins = libtest::build_suites(&cargo, "vcan")?;
    let mut vcan = Counts::default();
    if bins.is_empty() {
        bail!("no vcan suites were built: exocal-tests has no test targets with feature vcan");
    }
    // `cargo test` may have rebuilt xtask's own binary under us: run a copy of this one.
    let exe = paths::workspace_root().join("target/xtask/suite-runner");
    std::fs::create_dir_all(exe.parent().context("target/xtask")?)?;
    std::fs::copy("/proc/self/exe", &exe).context("copy the running xtask")?;
    let mut argv = vec![exe.display().to_string(), "run-suites".to_string()];
    argv.extend(bins);
    let mut req = opts.request(argv)?;
    req.capture_stdout = true;
    let load = BusyLoad::start(args.load)?;
    if load.len() > 0 {
        println!(
            "    with {} busy process(es) on the host (--load)",
            load.len()
        );
    }
    let outcome = harness::run(&req)?;
    steps.0.push(("[2/5] vcan suites", started.elapsed()));
    vcan.scan(&String::from_utf8_lossy(&outcome.stdout));
    if outcome.code != 0 && vcan.failed == 0 {
        vcan.broken += 1;
    }

    println!("==> [3/5] the power-up test under systemd (cargo xtask powerup)");
    let power = steps.time("[3/5] power-up", || match powerup::power_up(opts) {
        Ok(p) => p,
        Err(e) => {
            eprintln!("power-up test could not run: {e:#}");
            powerup::PowerUp::broken()
        }
    });
    drop(load);

    println!(
        "==> [4/5] cross-builds under qemu-user, Debian packages, lintian (cargo xtask cross)"
    );
    let mut cross = Counts::default();
    let cross_lines = steps.time("[4/5] cross", || {
        match cross::check(&targets::or_default(&[], true)) {
            Ok(lines) => {
                cross.passed = lines.len() as u64;
                lines
            }
            Err(e) => {
                cross.failed = 1;
                vec![format!("FAILED: {e:#}")]
            }
        }
    });

    println!("==> [5/5] every figure the READMEs quote, from its command (cargo xtask figures)");
    let mut figures = Counts::default();
    let figures_started = Instant::now();
    let figures_line = match figures::regenerate(&paths::workspace_root(), false, false) {
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
    steps.0.push(("[5/5] figures", figures_started.elapsed()));
    println!("{}", steps.line());
    println!(
        "exocal: {} passed, {} failed, {} skipped",
        total.passed, total.failed, total.ignored
    );
    Ok(if total.failed == 0 { 0 } else { 1 })
}
