//! Shipping to the suit's controller: cross-builds and Debian packages.
//!
//! ```text
//! cargo xtask cross [--target TRIPLE]..   build exocald + exocal-hil, run them under qemu-user
//! cargo xtask deb   [--target TRIPLE]..   build the Debian package(s) into target/debian/
//! ```
//!
//! Cross-linking uses Debian's cross gcc (`.cargo/config.toml` names it), and the binaries are
//! run with `qemu-<arch>-static -L /usr/<gnu triple>` directly, so no binfmt is needed.

use std::fs;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use anyhow::{bail, Context, Result};

/// A target the controller may be.
#[derive(Debug, Clone, Copy)]
pub struct Target {
    pub triple: &'static str,
    /// Debian's architecture name.
    pub deb_arch: &'static str,
    /// The Debian packages that cross-compile and link C and Rust for it: the cross gcc and the
    /// target's C library (only *recommended* by the gcc, so named here), qemu-user to run the
    /// result. Empty for the build machine itself.
    pub packages: &'static [&'static str],
    /// Debian's multiarch triple: the cross sysroot is `/usr/<gnu>`.
    pub gnu: &'static str,
    /// The qemu-user binary (`None`: runs natively).
    pub qemu: Option<&'static str>,
}

pub const TARGETS: &[Target] = &[
    Target {
        triple: "x86_64-unknown-linux-gnu",
        deb_arch: "amd64",
        packages: &[],
        gnu: "x86_64-linux-gnu",
        qemu: None,
    },
    Target {
        triple: "aarch64-unknown-linux-gnu",
        deb_arch: "arm64",
        packages: &[
            "gcc-aarch64-linux-gnu",
            "libc6-dev-arm64-cross",
            "qemu-user-static",
        ],
        gnu: "aarch64-linux-gnu",
        qemu: Some("qemu-aarch64-static"),
    },
    Target {
        triple: "armv7-unknown-linux-gnueabihf",
        deb_arch: "armhf",
        packages: &[
            "gcc-arm-linux-gnueabihf",
            "libc6-dev-armhf-cross",
            "qemu-user-static",
        ],
        gnu: "arm-linux-gnueabihf",
        qemu: Some("qemu-arm-static"),
    },
];

/// The binaries that ship.
pub const BINARIES: &[&str] = &["exocald", "exocal-hil"];

pub fn target(triple: &str) -> Result<Target> {
    TARGETS
        .iter()
        .copied()
        .find(|t| t.triple == triple || t.deb_arch == triple)
        .with_context(|| {
            let known: Vec<_> = TARGETS.iter().map(|t| t.triple).collect();
            format!("unknown target {triple:?}; known: {}", known.join(", "))
        })
}

/// Parses `--target X` options; the cross targets when none is given.
pub fn parse_targets(args: &[String], default_cross: bool) -> Result<Vec<Target>> {
    let mut out = Vec::new();
    let mut it = args.iter();
    while let Some(a) = it.next() {
        match a.as_str() {
            "--target" => out.push(target(it.next().context("--target needs a value")?)?),
            other => bail!("unexpected argument {other:?}"),
        }
    }
    if out.is_empty() {
        if default_cross {
            out.extend(TARGETS.iter().copied().filter(|t| t.qemu.is_some()));
        } else {
            out.push(TARGETS[0]);
        }
    }
    Ok(out)
}

/// Installs the cross toolchain for `targets` (rustup targets, Debian packages).
pub fn ensure_toolchain(targets: &[Target]) -> Result<()> {
    let mut packages: Vec<&str> = Vec::new();
    for t in targets {
        packages.extend(t.packages);
        crate::host::add_rust_target(t.triple)?;
    }
    packages.sort();
    packages.dedup();
    crate::host::install_packages(&crate::host::missing(packages))
}

/// Release-builds the shipped binaries for `t`; returns their paths.
pub fn build(t: &Target) -> Result<Vec<PathBuf>> {
    let root = crate::host::workspace_root();
    let mut cmd = Command::new(crate::host::cargo());
    cmd.current_dir(&root)
        .args(["build", "--release"])
        .stdin(Stdio::null());
    // The build machine's own binaries live in target/release, shared with the tests.
    let native = t.qemu.is_none();
    if !native {
        cmd.args(["--target", t.triple]);
    }
    // Each binary is its own package's; `-p` each, as `cargo xtask test` builds them: the same
    // feature set, so no rebuild.
    cmd.arg("--bins");
    for b in BINARIES {
        cmd.args(["-p", b]);
    }
    let status = cmd.status().context("cargo build")?;
    if !status.success() {
        bail!("release build for {} failed", t.triple);
    }
    let dir = if native {
        target_dir(&root).join("release")
    } else {
        target_dir(&root).join(t.triple).join("release")
    };
    Ok(BINARIES.iter().map(|b| dir.join(b)).collect())
}

fn target_dir(root: &Path) -> PathBuf {
    std::env::var_os("CARGO_TARGET_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| root.join("target"))
}

/// The command that runs a binary built for `t` on this machine.
pub fn runner(t: &Target, bin: &Path) -> Command {
    match t.qemu {
        None => Command::new(bin),
        Some(qemu) => {
            let mut cmd = Command::new(qemu);
            cmd.arg("-L").arg(format!("/usr/{}", t.gnu)).arg(bin);
            cmd
        }
    }
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

fn record(host: &[PathBuf], work: &Path) -> Result<Recording> {
    let host_exocald = &host[0];
    let root = crate::host::workspace_root();
    let shipped = fs::read_to_string(root.join("daemon/exocald.toml"))?;
    let config: String = shipped
        .lines()
        .map(|l| {
            if l.starts_with("min_duration_s") {
                "min_duration_s = 30.0".to_string()
            } else {
                l.to_string()
            }
        })
        .collect::<Vec<_>>()
        .join("\n");
    let cfg = work.join("exocald.toml");
    fs::write(&cfg, config + "\n")?;
    let demo = work.join("demo");
    let _ = fs::remove_dir_all(&demo);
    let mut cmd = Command::new(host_exocald);
    cmd.arg("--config")
        .arg(&cfg)
        .args(["demo", "--speed", "4", "--output"])
        .arg(&demo);
    println!("==> recording a session: exocald demo (host)");
    run_checked(&mut cmd, "exocald demo", &[0])?;
    let mcap = fs::read_dir(&demo)?
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
        Some(t) => runner(t, exocald),
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
    println!("==> {}: release build", t.triple);
    let bins = build(t)?;
    let mut lines = Vec::new();
    for bin in &bins {
        let name = bin
            .file_name()
            .unwrap_or_default()
            .to_string_lossy()
            .into_owned();
        let (_, help) = run_checked(
            runner(t, bin).arg("--help"),
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
    if scenario(&mut runner(t, &bins[1]))? != scenario(&mut Command::new(&rec.host_hil))? {
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
    let deb = package(t, &bins)?;
    let stripped: u64 = BINARIES
        .iter()
        .map(|b| {
            let dir = deb.with_extension("");
            fs::metadata(dir.join("usr/bin").join(b))
                .map(|m| m.len())
                .unwrap_or(0)
        })
        .sum();
    lintian(&deb)?;
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
    ensure_toolchain(targets)?;
    let root = crate::host::workspace_root();
    let work = target_dir(&root).join("xtask/cross");
    fs::create_dir_all(&work)?;
    let host = build(&TARGETS[0])?;
    let rec = record(&host, &work)?;
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
pub fn cross(args: &[String]) -> Result<u8> {
    let lines = check(&parse_targets(args, true)?)?;
    println!("\ncross-builds:\n{}", lines.join("\n"));
    Ok(0)
}

/// The package's version: the workspace version, Debian revision 1.
fn package_version() -> String {
    format!("{}-1", env!("CARGO_PKG_VERSION"))
}

/// The highest `GLIBC_2.N` symbol version a binary needs, for `Depends: libc6 (>= 2.N)`.
fn glibc_floor(bin: &[u8]) -> String {
    let needle = b"GLIBC_2.";
    let mut best = (2u32, 17u32);
    let mut i = 0;
    while let Some(pos) = bin[i..].windows(needle.len()).position(|w| w == needle) {
        let start = i + pos + needle.len();
        let digits: String = bin[start..]
            .iter()
            .take_while(|b| b.is_ascii_digit() || **b == b'.')
            .map(|b| *b as char)
            .collect();
        let minor = digits
            .split('.')
            .next()
            .and_then(|m| m.parse().ok())
            .unwrap_or(0);
        best = best.max((2, minor));
        i = start;
    }
    format!("{}.{}", best.0, best.1)
}

const POSTINST: &str = "#!/bin/sh
set -e
if [ \"$1\" = configure ] || [ \"$1\" = abort-upgrade ]; then
    # Start at every boot; not now (the installer's bus may be anything).
    deb-systemd-helper unmask exocald.service >/dev/null || true
    deb-systemd-helper enable exocald.service >/dev/null || true
    if [ -d /run/systemd/system ]; then
        systemctl --system daemon-reload >/dev/null || true
    fi
fi
";

const PRERM: &str = "#!/bin/sh
set -e
if [ -d /run/systemd/system ] && [ \"$1\" = remove ]; then
    deb-systemd-invoke stop exocald.service >/dev/null || true
fi
";

const POSTRM: &str = "#!/bin/sh
set -e
if [ -d /run/systemd/system ]; then
    systemctl --system daemon-reload >/dev/null || true
fi
if [ \"$1\" = remove ]; then
    deb-systemd-helper mask exocald.service >/dev/null || true
fi
if [ \"$1\" = purge ]; then
    deb-systemd-helper purge exocald.service >/dev/null || true
    deb-systemd-helper unmask exocald.service >/dev/null || true
fi
";

/// What an administrator must do after installing: provision the node keys.
const README_DEBIAN: &str = "exocal for Debian
=================

exocald.service calibrates at every boot and pushes the table to the suit's nodes over
authenticated transfers (AES-128-CMAC, one key per node). It needs the node keys, as the
systemd credential `exocal-keys`; without them it exits 78 (bad configuration) and is not
restarted.

Provision the keys (as root):

    umask 077
    for name in Joint1 Joint2 Joint3 Joint4 Joint5 Joint6 Joint7 Trigger; do
        echo \"$name $(od -An -N16 -tx1 /dev/urandom | tr -d ' \\n')\"
    done > exocal-keys
    install -d -m 0700 /etc/credstore
    install -m 0600 exocal-keys /etc/credstore/exocal-keys

then program the same keys into the nodes (the emulated suit: exocal-hil.service reads the
same credential), keep a copy offline, delete the working copy, and reboot or
`systemctl restart exocald`. To keep the file encrypted at rest instead:

    systemd-creds encrypt --name=exocal-keys exocal-keys /etc/credstore.encrypted/exocal-keys

with a drop-in /etc/systemd/system/exocald.service.d/keys.conf:

    [Service]
    LoadCredential=
    LoadCredentialEncrypted=exocal-keys

A bench whose nodes hold no keys may set `authenticate = false` in the [push] section of
/etc/exocal/exocald.toml instead: then anyone on the CAN bus can change a node's table, and
exocald says so in the journal at every start.
";

const COPYRIGHT: &str = "Format: https://www.debian.org/doc/packaging-manuals/copyright-format/1.0/
Upstream-Name: exocal
Source: https://example.invalid/exocal

Files: *
Copyright: 2026 exocal developers
License: MIT or Apache-2.0
 Licensed under either of the Apache License, Version 2.0 or the MIT license, at your option.
 .
 On Debian systems, the full text of the Apache License, Version 2.0 can be found in
 /usr/share/common-licenses/Apache-2.0.
";

/// Builds the Debian package for `t` from already-built binaries; returns its path.
pub fn package(t: &Target, bins: &[PathBuf]) -> Result<PathBuf> {
    let root = crate::host::workspace_root();
    let out = target_dir(&root).join("debian");
    let name = format!("exocal_{}_{}", package_version(), t.deb_arch);
    let stage = out.join(&name);
    let _ = fs::remove_dir_all(&stage);
    let put = |rel: &str, data: &[u8], mode: u32| -> Result<()> {
        use std::os::unix::fs::PermissionsExt;
        let path = stage.join(rel);
        fs::create_dir_all(path.parent().expect("has a parent"))?;
        fs::write(&path, data)?;
        fs::set_permissions(&path, fs::Permissions::from_mode(mode))?;
        Ok(())
    };
    let read = |rel: &str| fs::read(root.join(rel)).with_context(|| format!("read {rel}"));

    let mut glibc = String::from("2.17");
    for bin in bins {
        let file = bin.file_name().context("binary name")?.to_string_lossy();
        let stripped = stage.join("usr/bin").join(&*file);
        fs::create_dir_all(stripped.parent().expect("usr/bin"))?;
        let strip = if t.qemu.is_some() {
            format!("{}-strip", t.gnu)
        } else {
            "strip".into()
        };
        let status = Command::new(&strip)
            .arg("--strip-unneeded")
            .arg("-o")
            .arg(&stripped)
            .arg(bin)
            .status()
            .with_context(|| format!("run {strip} (binutils for {})", t.gnu))?;
        if !status.success() {
            bail!("{strip} failed on {}", bin.display());
        }
        let floor = glibc_floor(&fs::read(&stripped)?);
        if version_key(&floor) > version_key(&glibc) {
            glibc = floor;
        }
    }
    put(
        "lib/systemd/system/exocald.service",
        &read("systemd/exocald.service")?,
        0o644,
    )?;
    // The emulated suit's unit ships for benches; nothing enables it.
    put(
        "lib/systemd/system/exocal-hil.service",
        &read("systemd/exocal-hil.service")?,
        0o644,
    )?;
    put(
        "usr/lib/systemd/network/80-can0.network",
        &read("systemd/80-can0.network")?,
        0o644,
    )?;
    for bench in ["80-vcan0.netdev", "80-vcan0.network"] {
        put(
            &format!("usr/share/exocal/examples/{bench}"),
            &read(&format!("systemd/{bench}"))?,
            0o644,
        )?;
    }
    put(
        "etc/exocal/exocald.toml",
        &read("daemon/exocald.toml")?,
        0o644,
    )?;
    put(
        "usr/share/exocal/exocal.dbc",
        &read("dbc/exocal.dbc")?,
        0o644,
    )?;
    if root.join("hil/scenarios").is_dir() {
        for entry in fs::read_dir(root.join("hil/scenarios"))? {
            let entry = entry?;
            let file = entry.file_name().to_string_lossy().into_owned();
            if file.ends_with(".toml") {
                put(
                    &format!("usr/share/exocal/scenarios/{file}"),
                    &fs::read(entry.path())?,
                    0o644,
                )?;
            }
        }
    }
    put(
        "usr/share/doc/exocal/copyright",
        COPYRIGHT.as_bytes(),
        0o644,
    )?;
    put(
        "usr/share/doc/exocal/README.Debian",
        README_DEBIAN.as_bytes(),
        0o644,
    )?;
    let changelog = format!(
        "exocal ({}) unstable; urgency=medium\n\n  * Release {}.\n\n -- exocal developers <dev@exocal.invalid>  Sat, 21 Nov 2026 12:00:00 +0000\n",
        package_version(),
        env!("CARGO_PKG_VERSION")
    );
    put(
        "usr/share/doc/exocal/changelog.Debian.gz",
        &gzip(changelog.as_bytes())?,
        0o644,
    )?;

    let installed_kib = dir_size(&stage)?.div_ceil(1024);
    let control = format!(
        "Package: exocal
Version: {version}
Architecture: {arch}
Maintainer: exocal developers <dev@exocal.invalid>
Installed-Size: {installed_kib}
Depends: libc6 (>= {glibc}), libgcc-s1, init-system-helpers (>= 1.52)
Section: misc
Priority: optional
Homepage: https://example.invalid/exocal
Description: kinematic calibration for the exocal exoskeleton
 exocald collects a minute of free arm motion from the suit's IMU nodes over
 SocketCAN, identifies the D-H table by least squares and EM, validates it,
 pushes it to every node with CRC readback and logs the session as MCAP.
 exocal-hil emulates the nodes for benches without hardware.
",
        version = package_version(),
        arch = t.deb_arch,
    );
    put("DEBIAN/control", control.as_bytes(), 0o644)?;
    put("DEBIAN/conffiles", b"/etc/exocal/exocald.toml\n", 0o644)?;
    put("DEBIAN/postinst", POSTINST.as_bytes(), 0o755)?;
    put("DEBIAN/prerm", PRERM.as_bytes(), 0o755)?;
    put("DEBIAN/postrm", POSTRM.as_bytes(), 0o755)?;
    let deb = out.join(format!("{name}.deb"));
    let status = Command::new("dpkg-deb")
        .args(["--root-owner-group", "-Zxz", "--build"])
        .arg(&stage)
        .arg(&deb)
        .stdout(Stdio::null())
        .status()
        .context("dpkg-deb")?;
    if !status.success() {
        bail!("dpkg-deb failed for {}", deb.display());
    }
    Ok(deb)
}

fn version_key(v: &str) -> Vec<u32> {
    v.split('.').filter_map(|p| p.parse().ok()).collect()
}

fn gzip(data: &[u8]) -> Result<Vec<u8>> {
    use std::io::Write;
    let mut child = Command::new("gzip")
        .args(["-9n"])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .spawn()
        .context("gzip")?;
    child.stdin.take().context("stdin")?.write_all(data)?;
    let out = child.wait_with_output()?;
    Ok(out.stdout)
}

fn dir_size(dir: &Path) -> Result<u64> {
    let mut total = 0;
    for entry in fs::read_dir(dir)? {
        let entry = entry?;
        let meta = entry.metadata()?;
        total += if meta.is_dir() {
            dir_size(&entry.path())?
        } else {
            meta.len()
        };
    }
    Ok(total)
}

/// lintian tags we accept, and why. Everything else lintian reports fails `cargo xtask deb`.
pub const LINTIAN_ACCEPTED: &[(&str, &str)] = &[
    (
        "no-manual-page",
        "`exocald --help` and `exocal-hil --help` (clap's long help) are the manual",
    ),
    (
        "initial-upload-closes-no-bugs",
        "the package is built for the suit's controllers, never uploaded to Debian: no ITP bug",
    ),
];

/// Runs lintian on `deb`; fails on any error or warning outside [`LINTIAN_ACCEPTED`].
pub fn lintian(deb: &Path) -> Result<()> {
    if crate::host::which("lintian").is_none() {
        bail!("lintian is not installed (cargo xtask setup installs it)");
    }
    let accepted: Vec<&str> = LINTIAN_ACCEPTED.iter().map(|(tag, _)| *tag).collect();
    let out = Command::new("lintian")
        .args(["--tag-display-limit", "0", "--fail-on", "error,warning"])
        .arg("--suppress-tags")
        .arg(accepted.join(","))
        .arg(deb)
        .stderr(Stdio::null())
        .output()
        .context("run lintian")?;
    let text = String::from_utf8_lossy(&out.stdout);
    if !out.status.success() {
        bail!("lintian on {}:\n{text}", deb.display());
    }
    println!(
        "lintian {}: clean{}",
        deb.file_name().unwrap_or_default().to_string_lossy(),
        if text.trim().is_empty() {
            String::new()
        } else {
            format!(" of errors and warnings; notes:\n{text}")
        }
    );
    for (tag, why) in LINTIAN_ACCEPTED {
        println!("  accepted {tag}: {why}");
    }
    Ok(())
}

/// `cargo xtask deb`: build the package(s) and run lintian on them.
pub fn deb(args: &[String]) -> Result<u8> {
    let targets = parse_targets(args, false)?;
    ensure_toolchain(&targets)?;
    for t in &targets {
        let bins = build(t)?;
        let deb = package(t, &bins)?;
        println!(
            "built {} ({} KiB)",
            deb.display(),
            fs::metadata(&deb)?.len() / 1024
        );
        lintian(&deb)?;
    }
    Ok(0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn glibc_floor_takes_the_highest_version() {
        assert_eq!(
            glibc_floor(b"xxGLIBC_2.2.5\0GLIBC_2.34\0GLIBC_2.17\0"),
            "2.34"
        );
        assert_eq!(glibc_floor(b"nothing"), "2.17");
    }

    #[test]
    fn targets_resolve_by_triple_or_debian_arch() {
        assert_eq!(target("arm64").unwrap().triple, "aarch64-unknown-linux-gnu");
        assert!(target("mips").is_err());
        let cross = parse_targets(&[], true).unwrap();
        assert_eq!(cross.len(), 2);
    }
}
