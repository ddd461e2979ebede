//! `cargo xtask cross [--target TRIPLE]..`: release-build exocald and exocal-hil for the
//! controller targets, run `--help` of each and `exocald offline` on a session the host's demo
//! recorded under qemu-user (the table must equal the host's), build their Debian packages, run
//! lintian, and report binary and package sizes.

use std::fs;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use anyhow::{bail, Context, Result};

use crate::targets::{self, Target, BINARIES, TARGETS};
use crate::{deb, paths};

/// Cross-build for the controllers, run under qemu-user, package, lintian.
///
/// Release-build exocald and exocal-hil for aarch64 and armv7 (or the given targets), run
/// --help of each and `exocald offline` on a session the host's demo recorded under qemu-user
/// (the table must equal the host's), build their Debian packages, run lintian, and report
/// binary and package sizes.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// A target triple or Debian architecture (repeatable; default: every controller target).
    #[arg(long = "target", value_name = "TRIPLE", value_parser = targets::target)]
    pub targets: Vec<Target>,
}

/// Runs `cmd`, failing with its stderr unless it exits with one of `ok_codes`; returns stdout.
fn run_checked(cmd: &mut Command, what: &str, ok_codes: &[i32]) -> Result<(i32, String)> {
    let out = cmd
        .stdin(Stdio::null())
        .output()
        .with_context(|| format!("run {what}"))?;
    let code = out.status.code().unwrap_or(-1);
    if !ok_codes.contains(&code) {
        bail!(
            "{what} exited {}:\n{}",
            out.status,
            String::from_utf8_lossy(&out.stderr)
        );
    }
    Ok((code, String::from_utf8_lossy(&out.stdout).into_owned()))
}

/// A recorded session for the offline runs: the host's own `exocald demo` (half a minute of the
/// paper scenario's motion), and the host's offline result on it (exit status, TOML export).
struct Recording {
    /// The host's exocal-hil, for comparisons.
    host_hil: PathBuf,
    mcap: PathBuf,
    code: i32,
    toml: String,
}

/// `demo`: the host's exocald with the demo (the workspace build's); `host`: the host's
/// shipped binaries.
fn record(demo: &Path, host: &[PathBuf], work: &Path) -> Result<Recording> {
    let host_exocald = &host[0];
    let root = paths::workspace_root();
    let shipped = fs::read_to_string(root.join("daemon/exocald.toml"))?;
    let config: String = shipped
        .lines()
        .map(|l| {
            if l.starts_with("min_duration_s") {
                "min_duration_s = 30.0".to_string()
            } else if l.starts_with("stop_at_expected_error") {
                // A fixed window: the guest's emulated CPU would spend it on the estimates.
                format!("# {l}")
            } else {
                l.to_string()
            }
        })
        .collect::<Vec<_>>()
        .join("\n");
    let cfg = work.join("exocald.toml");
    fs::write(&cfg, config + "\n")?;
    let out = work.join("demo");
    let _ = fs::remove_dir_all(&out);
    let mut cmd = Command::new(demo);
    cmd.arg("--config")
        .arg(&cfg)
        .args(["demo", "--speed", "4", "--output"])
        .arg(&out);
    println!("==> recording a session: exocald demo (host)");
    run_checked(&mut cmd, "exocald demo", &[0])?;
    let mcap = fs::read_dir(&out)?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .find(|p| p.extension().is_some_and(|e| e == "mcap"))
        .context("the demo wrote no MCAP")?;
    let (code, toml) = offline(None, host_exocald, &cfg, &mcap, &work.join("host"))?;
    Ok(Recording {
        host_hil: host[1].clone(),
        mcap,
        code,
        toml,
    })
}

/// `exocald offline` on `mcap` (under qemu-user for a cross target); returns its exit status and
/// TOML export.
fn offline(
    t: Option<&Target>,
    exocald: &Path,
    cfg: &Path,
    mcap: &Path,
    out: &Path,
) -> Result<(i32, String)> {
    fs::create_dir_all(out)?;
    let toml = out.join("calibrated.toml");
    let _ = fs::remove_file(&toml);
    let mut cmd = match t {
        Some(t) => targets::runner(t, exocald),
        None => Command::new(exocald),
    };
    cmd.arg("--config")
        .arg(cfg)
        .args(["offline", "--input"])
        .arg(mcap)
        .arg("--report")
        .arg(out.join("report.html"))
        .arg("--export-toml")
        .arg(&toml);
    // 65: refused by validation, still a result to agree on.
    let (code, _) = run_checked(
        &mut cmd,
        &format!("exocald offline ({})", out.display()),
        &[0, 65],
    )?;
    Ok((code, fs::read_to_string(&toml).unwrap_or_default()))
}

/// Every number in the `[nominal]` section of a TOML export, in order.
fn nominal_numbers(toml: &str) -> Vec<f64> {
    let mut out = Vec::new();
    let mut inside = false;
    for line in toml.lines() {
        let line = line.split('#').next().unwrap_or("").trim();
        if line.starts_with('[')
            && !line.starts_with("[[")
            && line.ends_with(']')
            && !line.contains('=')
        {
            inside = line == "[nominal]";
            continue;
        }
        if inside {
            if let Some((_, v)) = line.split_once('=') {
                out.extend(
                    v.split(['[', ']', ','])
                        .filter_map(|x| x.trim().parse::<f64>().ok()),
                );
            }
        }
    }
    out
}

/// Checks one controller target: cross-build, `--help` of each binary and an offline
/// calibration of `rec` under qemu-user that must agree with the host's, the Debian package and
/// lintian. Returns report lines.
fn check_target(t: &Target, rec: &Recording, cfg: &Path, work: &Path) -> Result<Vec<String>> {
    let bins = targets::binaries(t);
    let mut lines = Vec::new();
    for bin in &bins {
        let name = bin
            .file_name()
            .unwrap_or_default()
            .to_string_lossy()
            .into_owned();
        let (_, help) = run_checked(
            targets::runner(t, bin).arg("--help"),
            &format!("{name} --help"),
            &[0],
        )?;
        if help.trim().is_empty() {
            bail!("{name} --help printed nothing under {:?}", t.qemu);
        }
        lines.push(format!(
            "{:30} {:11} {:>6.2} MiB (with line tables)  --help ok",
            t.triple,
            name,
            fs::metadata(bin)?.len() as f64 / f64::from(1 << 20)
        ));
    }
    // The emulated suit's scenario, parsed and written back: the same TOML as the host's.
    let scenario = |cmd: &mut Command| -> Result<String> {
        cmd.args(["--iface", "vcan0", "--print-scenario"]);
        Ok(run_checked(cmd, "exocal-hil --print-scenario", &[0])?.1)
    };
    if scenario(&mut targets::runner(t, &bins[1]))? != scenario(&mut Command::new(&rec.host_hil))? {
        bail!(
            "{}: exocal-hil --print-scenario differs from the host's",
            t.triple
        );
    }
    lines.push(format!(
        "{:30} exocal-hil --print-scenario = host's",
        t.triple
    ));
    println!(
        "==> {}: exocald offline under {}",
        t.triple,
        t.qemu.unwrap_or("the host")
    );
    let started = std::time::Instant::now();
    let (code, toml) = offline(Some(t), &bins[0], cfg, &rec.mcap, &work.join(t.deb_arch))?;
    let (ours, host) = (nominal_numbers(&toml), nominal_numbers(&rec.toml));
    if code != rec.code || ours.len() != host.len() {
        bail!(
            "{}: offline exited {code} with {} numbers, the host {} with {}",
            t.triple,
            ours.len(),
            rec.code,
            host.len()
        );
    }
    let worst = ours
        .iter()
        .zip(&host)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f64::max);
    if worst > 1e-6 {
        bail!(
            "{}: the calibrated table differs from the host's by {worst:e}",
            t.triple
        );
    }
    lines.push(format!(
        "{:30} exocald offline: exit {code}, table = host's to {worst:.1e} ({} values, {:.1} s)",
        t.triple,
        ours.len(),
        started.elapsed().as_secs_f64()
    ));
    let deb = deb::package(t, &bins)?;
    let stripped: u64 = BINARIES
        .iter()
        .map(|b| {
            let dir = deb.with_extension("");
            fs::metadata(dir.join("usr/bin").join(b))
                .map(|m| m.len())
                .unwrap_or(0)
        })
        .sum();
    deb::lintian(&deb)?;
    lines.push(format!(
        "{:30} {} {:.2} MiB (binaries stripped: {:.2} MiB), lintian clean",
        t.triple,
        deb.file_name().unwrap_or_default().to_string_lossy(),
        fs::metadata(&deb)?.len() as f64 / f64::from(1 << 20),
        stripped as f64 / f64::from(1 << 20)
    ));
    Ok(lines)
}

/// Cross-checks `targets` (see [`check_target`]); returns the report, or the first failure.
pub fn check(targets: &[Target]) -> Result<Vec<String>> {
    targets::ensure_toolchain(targets)?;
    let work = paths::target_dir().join("xtask/cross");
    fs::create_dir_all(&work)?;
    let host = targets::build(&TARGETS[0])?;
    let demo = targets::build_demo()?;
    let rec = record(&demo, &host, &work)?;
    let controllers: Vec<Target> = targets
        .iter()
        .copied()
        .filter(|t| t.qemu.is_some())
        .collect();
    println!("==> release build for every controller target at once");
    targets::build_all(&controllers)?;
    println!(
        "host offline on {}: exit {}, {} table values",
        rec.mcap.display(),
        rec.code,
        nominal_numbers(&rec.toml).len()
    );
    let cfg = work.join("exocald.toml");
    let mut lines = Vec::new();
    for t in targets.iter().filter(|t| t.qemu.is_some()) {
        lines.extend(check_target(t, &rec, &cfg, &work)?);
    }
    Ok(lines)
}

/// `cargo xtask cross`: build for the controller targets, run under qemu-user, package.
pub fn run(args: Args) -> Result<u8> {
    let lines = check(&targets::or_default(&args.targets, true))?;
    println!("\ncross-builds:\n{}", lines.join("\n"));
    Ok(0)
}
