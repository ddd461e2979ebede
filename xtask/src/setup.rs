//! `cargo xtask setup [--check]`: install what the project needs on a fresh Debian machine, then
//! prove it usable.
//!
//! The contract: on a Debian 12 machine with nothing but a Rust toolchain (rustup), run as root,
//! `cargo xtask setup` installs every Debian package, rustup target and Python package that
//! `cargo xtask test` uses, and ends with a self-check ([`check`]) that compiles, links and runs
//! what the suites will, naming the package when something is missing. Packages are installed
//! with `--no-install-recommends`, so every one the project needs is named here, never reached
//! through a recommendation (Debian's cross gcc only *recommends* the target's C library).
//! `cargo xtask clean-root` proves the list complete in a freshly bootstrapped Debian root.
//!
//! Not root, or not Debian: nothing is installed and the error says what to install.

use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{bail, Context, Result};

use crate::{harness, host, paths, process, targets};

/// Install what `test` needs (root, Debian), then self-check.
///
/// Install everything `test` needs on a fresh Debian machine (as root): the Debian packages
/// (cross gcc and the target C libraries, qemu-user-static, Chromium, lintian, python3-venv,
/// systemd, g++ and libceres-dev, and where this kernel has no vcan QEMU, Debian's kernel,
/// busybox-static, cpio), the rustup targets and the Python venv; then the self-check: C and
/// Rust hello-worlds built for every cross target and run under qemu-user, headless Chromium, a
/// program built against Ceres, lintian, the venv's modules, the guest's kernel, modules and
/// busybox.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Run the self-check only (install nothing).
    #[arg(long)]
    pub check: bool,
}

/// Debian packages every machine that runs `cargo xtask test` needs, with what needs each. The
/// cross targets' packages are in [`crate::targets::TARGETS`], the QEMU guest's in
/// [`harness::VM_PACKAGES`] (needed only where this kernel has no vcan).
pub const PACKAGES: &[(&str, &str)] = &[
    (
        "gcc",
        "cc for the host build of C in -sys crates (zstd-sys)",
    ),
    ("libc6-dev", "the host's C headers and crt files"),
    (
        "chromium",
        "renders the calibration report (report/tests/browser.rs)",
    ),
    ("lintian", "checks every Debian package the project builds"),
    ("python3", "runs the cantools and mcap cross-checks"),
    (
        "nodejs",
        "runs @mcap/core's indexed reader, Foxglove's, on the session log (tests/js; npm comes with it, or as Debian's npm)",
    ),
    ("python3-venv", "the project's venv for those cross-checks"),
    (
        "systemd",
        "PID 1 of the power-up guest (the host root is its root), systemd-analyze",
    ),
    ("dbus", "the power-up guest's system bus"),
    ("iproute2", "`ip link` makes vcan0/vcan1 in the harness"),
    (
        "can-utils",
        "candump -l, what the ingest bench (`cargo xtask bench --only ingest`) compares with; log2asc and asc2log, which write the candump logs session/tests/candump_tools.rs reads",
    ),
    ("kmod", "modprobe vcan on a kernel that has CAN"),
    (
        "util-linux",
        "unshare, nsenter and taskset in the harness and the benches",
    ),
    (
        "g++",
        "builds the Ceres side of the calibration bench (benches/ceres) and its test",
    ),
    (
        "libceres-dev",
        "Ceres Solver, what the calibration bench compares calib-core's LS with (xtask's Ceres test)",
    ),
    (
        "libeigen3-dev",
        "the Eigen headers Ceres' headers include (-I/usr/include/eigen3)",
    ),
    ("libgoogle-glog-dev", "glog, which the Ceres program links (-lglog)"),
];

/// The no_std target calib-core is cross-built for.
pub const EMBEDDED_TARGET: &str = "thumbv7em-none-eabihf";

/// `cargo xtask setup [--check]`.
pub fn run(args: Args) -> Result<u8> {
    if args.check {
        report(check())?;
    } else {
        install_all()?;
    }
    Ok(0)
}

/// Every Debian package this machine needs: [`PACKAGES`], the cross targets' and, where this
/// kernel has no vcan, the QEMU guest's. Sorted, without repeats.
pub fn packages() -> Vec<&'static str> {
    let mut all: Vec<&str> = PACKAGES.iter().map(|(p, _)| *p).collect();
    for t in cross_targets() {
        all.extend(t.packages);
    }
    if !native_vcan() {
        all.extend(harness::VM_PACKAGES);
    }
    all.sort();
    all.dedup();
    all
}

fn cross_targets() -> impl Iterator<Item = targets::Target> {
    targets::controllers()
}

fn native_vcan() -> bool {
    harness::native_available().is_ok()
}

/// Installs everything (rustup targets, Debian packages, the Python venv), then runs [`check`].
pub fn install_all() -> Result<()> {
    host::add_rust_target(EMBEDDED_TARGET)?;
    for t in cross_targets() {
        host::add_rust_target(t.triple)?;
    }
    host::install_packages(&host::missing(packages()))?;
    python_env()?;
    js_env()?;
    report(check())
}

/// Prints the self-check's lines; fails naming every failed check.
fn report(lines: Vec<Result<String>>) -> Result<()> {
    let mut failed = 0;
    for line in lines {
        match line {
            Ok(ok) => eprintln!("[setup] ok: {ok}"),
            Err(e) => {
                eprintln!("[setup] FAILED: {e:#}");
                failed += 1;
            }
        }
    }
    if failed > 0 {
        bail!(
            "setup self-check: {} check(s) failed, each named above with what to install",
            failed
        );
    }
    Ok(())
}

/// The self-check: uses every tool the way the suites will, and names the Debian package to
/// install when one fails. Installs nothing.
pub fn check() -> Vec<Result<String>> {
    let scratch = std::env::temp_dir().join(format!("exocal-setup-check-{}", std::process::id()));
    let mut lines = vec![check_packages()];
    match std::fs::create_dir_all(&scratch) {
        Ok(()) => {
            for t in cross_targets() {
                lines.push(check_cross_c(&t, &scratch));
                lines.push(check_cross_rust(&t, &scratch));
            }
            lines.push(check_chromium(&scratch));
            lines.push(check_ceres(&scratch));
        }
        Err(e) => lines.push(Err(anyhow::anyhow!("create {}: {e}", scratch.display()))),
    }
    lines.push(check_embedded_target());
    lines.push(check_program(&["lintian", "--version"], "lintian"));
    lines.push(check_program(&["systemd-analyze", "--version"], "systemd"));
    lines.push(check_python());
    lines.push(check_program(&["node", "--version"], "node"));
    if native_vcan() {
        lines.push(Ok(
            "native vcan works here: the QEMU guest is not needed".into()
        ));
    } else {
        lines.push(harness::vm_check_parts().context("the QEMU guest (this kernel has no vcan)"));
    }
    let _ = std::fs::remove_dir_all(&scratch);
    lines
}

fn check_packages() -> Result<String> {
    let all = packages();
    let missing = host::missing(all.iter().copied());
    if !missing.is_empty() {
        bail!(
            "Debian packages not installed: {} (cargo xtask setup installs them as root)",
            missing.join(" ")
        );
    }
    Ok(format!("{} Debian packages installed", all.len()))
}

/// A package hint for a failed check of `t`: the target's packages that are missing, or all.
fn hint(t: &targets::Target) -> String {
    let missing = host::missing(t.packages.iter().copied());
    let named = if missing.is_empty() {
        t.packages.to_vec()
    } else {
        missing
    };
    format!("needs the Debian packages {}", named.join(" "))
}

/// Runs `bin` for `t` under qemu-user and expects `want` on its stdout.
fn run_under_qemu(t: &targets::Target, bin: &Path, want: &str) -> Result<()> {
    let out = process::output(
        &mut targets::runner(t, bin),
        &format!("run {} under qemu-user", bin.display()),
    )?;
    if out.trim() != want {
        bail!("{} printed {out:?}, expected {want:?}", bin.display());
    }
    Ok(())
}

/// A C hello-world that includes libc headers, cross-compiled and linked with the target's gcc
/// (as the cc crate does for zstd-sys), run under qemu-user.
fn check_cross_c(t: &targets::Target, dir: &Path) -> Result<String> {
    let src = dir.join("hello.c");
    std::fs::write(
        &src,
        "#include <stdint.h>\n#include <stdio.h>\nint main(void) { uint8_t x = 42; \
         printf(\"hello %u\\n\", x); return 0; }\n",
    )?;
    let bin = dir.join(format!("hello-c-{}", t.deb_arch));
    let gcc = format!("{}-gcc", t.gnu);
    process::output(
        Command::new(&gcc).arg(&src).arg("-o").arg(&bin),
        &format!("{gcc} hello.c"),
    )
    .and_then(|_| run_under_qemu(t, &bin, "hello 42"))
    .with_context(|| format!("C for {} ({})", t.triple, hint(t)))?;
    Ok(format!("C hello-world for {} builds and runs", t.triple))
}

/// A Rust hello-world for the target, linked by its gcc (as `.cargo/config.toml` says), run
/// under qemu-user.
fn check_cross_rust(t: &targets::Target, dir: &Path) -> Result<String> {
    let src = dir.join("hello.rs");
    std::fs::write(&src, "fn main() { println!(\"hello {}\", 6 * 7); }\n")?;
    let bin = dir.join(format!("hello-rs-{}", t.deb_arch));
    process::output(
        Command::new(rustc())
            .args(["--edition", "2021", "--target", t.triple])
            .arg(format!("-Clinker={}-gcc", t.gnu))
            .arg(&src)
            .arg("-o")
            .arg(&bin),
        &format!("rustc --target {}", t.triple),
    )
    .and_then(|_| run_under_qemu(t, &bin, "hello 42"))
    .with_context(|| {
        format!(
            "Rust for {} (rustup target add {}; {})",
            t.triple,
            t.triple,
            hint(t)
        )
    })?;
    Ok(format!("Rust hello-world for {} builds and runs", t.triple))
}

fn rustc() -> String {
    std::env::var("RUSTC").unwrap_or_else(|_| "rustc".into())
}

/// The embedded target's standard library is there (`rustc --print sysroot` has it).
fn check_embedded_target() -> Result<String> {
    let sysroot = process::output(
        Command::new(rustc()).args(["--print", "sysroot"]),
        "rustc --print sysroot",
    )?;
    let lib = Path::new(sysroot.trim()).join(format!("lib/rustlib/{EMBEDDED_TARGET}/lib"));
    if !lib.is_dir() {
        bail!("no standard library for {EMBEDDED_TARGET}: rustup target add {EMBEDDED_TARGET}");
    }
    Ok(format!("rustup target {EMBEDDED_TARGET} installed"))
}

fn check_program(argv: &[&str], package: &str) -> Result<String> {
    let out = process::output(
        Command::new(argv[0]).args(&argv[1..]),
        &format!("{} (package {package})", argv.join(" ")),
    )?;
    Ok(format!(
        "{}: {}",
        argv[0],
        out.lines().next().unwrap_or("").trim()
    ))
}

/// Headless Chromium renders a page with an SVG, as the report test does.
fn check_chromium(dir: &Path) -> Result<String> {
    let page = dir.join("page.html");
    std::fs::write(
        &page,
        "<html><body><svg id=\"plot\" width=\"10\" height=\"10\"><polyline points=\"0,0 5,5\"/>\
         </svg><script>document.body.dataset.drawn = \
         document.getElementById('plot').getBBox().width;</script></body></html>",
    )?;
    let chromium = host::which("chromium").context("chromium is not on PATH (package chromium)")?;
    let dom = process::output(
        Command::new(chromium)
            .args([
                "--headless",
                "--no-sandbox",
                "--disable-gpu",
                "--disable-background-networking",
                "--no-first-run",
                "--disable-component-update",
                "--disable-sync",
            ])
            .arg(format!("--user-data-dir={}", dir.join("profile").display()))
            .arg("--dump-dom")
            .arg(format!("file://{}", page.display())),
        "headless chromium --dump-dom (package chromium)",
    )?;
    if !dom.contains("data-drawn=\"5\"") {
        bail!("headless chromium did not draw the test SVG (package chromium): {dom:?}");
    }
    Ok("headless chromium renders SVG".into())
}

/// A C++ program that includes Ceres' headers builds against libceres (as the calibration
/// bench's does, `xtask/src/bench/ceres.rs`) and runs.
fn check_ceres(dir: &Path) -> Result<String> {
    let src = dir.join("ceres.cc");
    std::fs::write(
        &src,
        "#include <ceres/ceres.h>\n#include <cstdio>\nint main() { ceres::Solver::Options o; \
         std::string why; std::printf(\"%s %d\\n\", CERES_VERSION_STRING, o.IsValid(&why) ? 1 : 0); }\n",
    )?;
    let bin = dir.join("ceres-check");
    process::output(
        Command::new("g++")
            .args(["-std=c++17", "-O1", "-I/usr/include/eigen3"])
            .arg(&src)
            .arg("-o")
            .arg(&bin)
            .args(["-lceres", "-lglog"]),
        "g++ with Ceres (packages g++ libceres-dev libeigen3-dev libgoogle-glog-dev)",
    )?;
    let out = process::output(
        &mut Command::new(&bin),
        "run a program linked with libceres",
    )?;
    let version = out.split_whitespace().next().unwrap_or("?").to_string();
    if !out.trim().ends_with(" 1") {
        bail!("the Ceres check program printed {out:?} (package libceres-dev)");
    }
    Ok(format!(
        "Ceres {version} builds and runs (g++, libceres-dev)"
    ))
}

/// The venv has every module the cross-checks import.
fn check_python() -> Result<String> {
    let python = venv_python();
    process::output(
        Command::new(&python).args(["-c", "import cantools, mcap, zstandard, mcap_protobuf"]),
        &format!(
            "{} imports cantools, mcap, zstandard, mcap_protobuf (cargo xtask setup makes the venv)",
            python.display()
        ),
    )?;
    Ok(format!(
        "python venv {} has the cross-check modules",
        python.display()
    ))
}

/// The project's Python venv: `$EXOCAL_PYENV`, or `target/exocal-pyenv`.
fn venv_dir() -> PathBuf {
    std::env::var_os("EXOCAL_PYENV")
        .map(PathBuf::from)
        .unwrap_or_else(|| paths::workspace_root().join("target/exocal-pyenv"))
}

fn venv_python() -> PathBuf {
    venv_dir().join("bin/python")
}

/// The project's Python venv (from `tests/requirements.txt`), made or updated when the
/// requirements changed; returns its interpreter.
pub fn python_env() -> Result<PathBuf> {
    let venv = venv_dir();
    let python = venv_python();
    let requirements = paths::workspace_root().join("tests/requirements.txt");
    let wanted = std::fs::read_to_string(&requirements)
        .with_context(|| format!("read {}", requirements.display()))?;
    let stamp = venv.join("exocal-requirements.txt");
    if python.exists() && std::fs::read_to_string(&stamp).ok().as_deref() == Some(&wanted) {
        return Ok(python);
    }
    if !python.exists() {
        if host::which("python3").is_none() {
            bail!("python3 is needed for the cantools and mcap cross-checks: install python3");
        }
        process::run(
            Command::new("python3").args(["-m", "venv"]).arg(&venv),
            "python3 -m venv",
            "python3 -m venv failed: install python3-venv",
        )?;
    }
    eprintln!(
        "[setup] pip install -r tests/requirements.txt into {}",
        venv.display()
    );
    let pip = [
        "-m",
        "pip",
        "install",
        "--quiet",
        "--disable-pip-version-check",
        "-r",
    ];
    process::run(
        Command::new(&python).args(pip).arg(&requirements),
        "pip install",
        "pip install -r tests/requirements.txt failed (is PyPI reachable?)",
    )?;
    std::fs::write(&stamp, wanted)?;
    Ok(python)
}

/// The JavaScript oracles of `tests/js` (`@mcap/core`): `npm ci` there when its lockfile
/// changed since the last install (npm from Debian's package when nodejs came without it);
/// returns the directory.
pub fn js_env() -> Result<PathBuf> {
    let dir = paths::workspace_root().join("tests/js");
    let lock = std::fs::read_to_string(dir.join("package-lock.json"))
        .with_context(|| format!("read {}/package-lock.json", dir.display()))?;
    let stamp = dir.join("node_modules/.exocal-lock.json");
    if std::fs::read_to_string(&stamp).ok().as_deref() == Some(&lock) {
        return Ok(dir);
    }
    if host::which("npm").is_none() {
        host::install_packages(&host::missing(["npm"]))?;
    }
    eprintln!("[setup] npm ci in {}", dir.display());
    process::run(
        Command::new("npm")
            .args(["ci", "--no-audit", "--no-fund", "--prefix"])
            .arg(&dir),
        "npm ci",
        "npm ci in tests/js failed (is the npm registry reachable?)",
    )?;
    std::fs::write(&stamp, lock)?;
    Ok(dir)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Debian's cross gcc only recommends the target's C library, and setup installs without
    /// recommendations: every cross target must name its libc explicitly (issue: a fresh
    /// machine could not build zstd-sys for aarch64).
    #[test]
    fn every_cross_target_names_its_c_library_and_qemu() {
        let all = packages();
        for t in cross_targets() {
            let libc = t
                .packages
                .iter()
                .find(|p| p.starts_with("libc6-dev-") && p.ends_with("-cross"))
                .unwrap_or_else(|| panic!("{} names no libc6-dev-*-cross", t.triple));
            assert!(all.contains(libc), "{libc} is not in setup's list");
            assert!(t.packages.contains(&"qemu-user-static"), "{}", t.triple);
            let gcc = format!("gcc-{}", t.gnu.replace('_', "-"));
            assert!(
                t.packages.contains(&gcc.as_str()),
                "{} lacks {gcc}",
                t.triple
            );
        }
    }

    #[test]
    fn the_list_is_sorted_without_repeats_and_has_every_named_package() {
        let all = packages();
        let mut sorted = all.clone();
        sorted.sort();
        sorted.dedup();
        assert_eq!(all, sorted);
        for (p, why) in PACKAGES {
            assert!(all.contains(p) && !why.is_empty(), "{p}");
        }
    }
}
