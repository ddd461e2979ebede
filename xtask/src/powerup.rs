//! `cargo xtask powerup`: the power-up test under a real systemd.
//!
//! 1. builds the Debian package for this machine from the release binaries (`ship::package`);
//! 2. boots the harness's guest with systemd as PID 1 on a tmpfs overlay of the host root, after
//!    `tests/powerup/bench-setup.sh` ran in that root: `dpkg -i` of the package, the bench's
//!    `vcan0` through systemd-networkd, `exocal-hil.service` enabled, a short watchdog;
//! 3. once multi-user.target is up, the harness's unit runs the `powerup_systemd` suite
//!    (exocal-tests, feature `powerup`) as root in the guest; it watches exocald's boot-time
//!    calibration and asserts on it. Its libtest output comes back; the boot's whole journal is
//!    kept in `target/xtask/last-boot-journal.txt`.

use std::path::Path;
use std::time::Duration;

use anyhow::{bail, Context, Result};

use crate::libtest::{self, Counts};
use crate::process::shell_quote;
use crate::{deb, harness, paths, targets};

/// The power-up test: the Debian package booted under systemd in the guest.
///
/// The power-up test: build this machine's Debian package, boot systemd as PID 1 in the guest
/// with the package installed (dpkg -i), vcan0 from systemd-networkd and exocal-hil as a service,
/// and check exocald.service's boot-time calibration from inside (READY, watchdog, no
/// capabilities, read-only system, every node holds the pushed table, MCAP in the
/// StateDirectory, systemctl stop mid-session).
#[derive(Debug, clap::Args)]
pub struct Args {
    #[command(flatten)]
    pub harness: harness::Opts,
}

/// The suite's result, and how long the boot took.
pub struct PowerUp {
    pub counts: Counts,
    pub code: u8,
    pub elapsed: Duration,
}

impl PowerUp {
    /// One line: time, passed, failed, and the guest's exit status if the run itself failed.
    pub fn summary(&self) -> String {
        format!(
            "power-up under systemd ({:.1} s): {} passed, {} failed{}",
            self.elapsed.as_secs_f64(),
            self.counts.passed,
            self.counts.failed,
            if self.counts.broken > 0 {
                format!(" (the guest run failed, exit {})", self.code)
            } else {
                String::new()
            }
        )
    }

    /// A run that could not happen (the build or the harness failed): one broken suite.
    pub fn broken() -> Self {
        PowerUp {
            counts: Counts {
                broken: 1,
                ..Counts::default()
            },
            code: 2,
            elapsed: Duration::ZERO,
        }
    }
}

/// Builds the package and the suite, boots, runs it. `opts` gives the time limit and verbosity.
pub fn power_up(opts: &harness::Opts) -> Result<PowerUp> {
    let cargo = paths::cargo();
    let root = paths::workspace_root();
    let host = targets::TARGETS[0];
    println!("==> power-up: building the {} package", host.deb_arch);
    let bins = targets::build(&host)?;
    let deb = deb::package(&host, &bins)?;
    deb::lintian(&deb)?;
    let suites = libtest::build_suites(&cargo, "powerup")?;
    let Some(suite) = suites.into_iter().find(|s| {
        Path::new(s)
            .file_name()
            .is_some_and(|n| n.to_string_lossy().starts_with("powerup_systemd"))
    }) else {
        bail!("the powerup_systemd suite was not built");
    };

    let setup = root.join("target/xtask/powerup-setup.sh");
    std::fs::create_dir_all(setup.parent().context("target/xtask")?)?;
    let bench = std::fs::read_to_string(root.join("tests/powerup/bench-setup.sh"))
        .context("read tests/powerup/bench-setup.sh")?;
    std::fs::write(
        &setup,
        format!(
            "#!/bin/sh\nEXOCAL_DEB={}\n{bench}",
            shell_quote(&deb.display().to_string())
        ),
    )?;

    let mut req = opts.request(vec![suite, "--test-threads=1".into(), "--nocapture".into()])?;
    req.systemd = true;
    req.setup = Some(setup);
    req.capture_stdout = true;
    println!("==> power-up: booting systemd with {}", deb.display());
    let outcome = harness::run(&req)?;
    let mut counts = Counts::default();
    counts.scan(&String::from_utf8_lossy(&outcome.stdout));
    if outcome.code != 0 && counts.failed == 0 {
        counts.broken += 1;
    }
    Ok(PowerUp {
        counts,
        code: outcome.code,
        elapsed: outcome.elapsed,
    })
}

/// `cargo xtask powerup`: exit 0 only if every power-up test passed.
pub fn run(args: Args) -> Result<u8> {
    let r = power_up(&args.harness)?;
    println!("{}", r.summary());
    Ok(if r.code == 0 && r.counts.failed == 0 {
        0
    } else {
        1
    })
}
