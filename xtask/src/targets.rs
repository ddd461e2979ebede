//! The machines exocal ships to: this build machine and the suit's controllers (aarch64,
//! armv7): their triples, Debian architectures and toolchain packages, the release build of the
//! shipped binaries, and the command that runs such a binary here (qemu-user for a controller).
//!
//! Cross-linking uses Debian's cross gcc (`.cargo/config.toml` names it), and the binaries are
//! run with `qemu-<arch>-static -L /usr/<gnu triple>` directly, so no binfmt is needed.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use anyhow::{bail, Context, Result};

use crate::{host, paths};

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

/// The targets a `--target` list names; when it names none, the controllers (`cross`) or this
/// machine (`deb`).
pub fn or_default(given: &[Target], default_cross: bool) -> Vec<Target> {
    if !given.is_empty() {
        given.to_vec()
    } else if default_cross {
        controllers().collect()
    } else {
        vec![TARGETS[0]]
    }
}

/// The suit's controller targets (every target but this build machine).
pub fn controllers() -> impl Iterator<Item = Target> {
    TARGETS.iter().copied().filter(|t| t.qemu.is_some())
}

/// Installs the cross toolchain for `targets` (rustup targets, Debian packages).
pub fn ensure_toolchain(targets: &[Target]) -> Result<()> {
    let mut packages: Vec<&str> = Vec::new();
    for t in targets {
        packages.extend(t.packages);
        host::add_rust_target(t.triple)?;
    }
    packages.sort();
    packages.dedup();
    host::install_packages(&host::missing(packages))
}

/// Release-builds the shipped binaries for `t`; returns their paths.
pub fn build(t: &Target) -> Result<Vec<PathBuf>> {
    build_all(std::slice::from_ref(t))?;
    Ok(binaries(t))
}

/// Release-builds the shipped binaries for every target of `targets` in one cargo invocation
/// (cargo then interleaves the targets' crates on the cores, where one build alone leaves a core
/// idle in its serial stretches), as they ship: without default features, so the daemon links
/// no emulator (`exocald demo` is the workspace build's, not the package's). Each target's
/// binaries are then copied to [`binaries`]'s place. For the build machine's own target the
/// build lands in `target/release` too, replacing the `exocald` there with the one without the
/// demo: [`build_demo`] builds it back where the demo is needed (cargo's
/// `cargo run --release -p exocald -- demo` does the same).
pub fn build_all(targets: &[Target]) -> Result<()> {
    let root = paths::workspace_root();
    let mut cmd = Command::new(paths::cargo());
    cmd.current_dir(&root)
        .args(["build", "--release", "--no-default-features"])
        .stdin(Stdio::null());
    for t in targets {
        // The build machine's own binaries are built in target/release, beside the tests' (the
        // same dependencies; only the daemon differs, without its demo, and replaces the one
        // there until `build_demo`).
        if t.qemu.is_some() {
            cmd.args(["--target", t.triple]);
        }
    }
    // Each binary is its own package's; `-p` each.
    cmd.arg("--bins");
    for b in BINARIES {
        cmd.args(["-p", b]);
    }
    let status = cmd.status().context("cargo build")?;
    if !status.success() {
        let triples: Vec<&str> = targets.iter().map(|t| t.triple).collect();
        bail!("release build for {} failed", triples.join(", "));
    }
    for t in targets {
        let built = match t.qemu {
            None => paths::target_dir().join("release"),
            Some(_) => paths::target_dir().join(t.triple).join("release"),
        };
        for (b, to) in BINARIES.iter().zip(binaries(t)) {
            std::fs::create_dir_all(to.parent().context("shipped directory")?)?;
            std::fs::copy(built.join(b), &to)
                .with_context(|| format!("copy {} to {}", built.join(b).display(), to.display()))?;
        }
    }
    Ok(())
}

/// Where [`build`] puts the shipped binaries for `t`: `target/shipped/<triple>/`.
pub fn binaries(t: &Target) -> Vec<PathBuf> {
    let dir = paths::target_dir().join("shipped").join(t.triple);
    BINARIES.iter().map(|b| dir.join(b)).collect()
}

/// Release-builds the workspace's own `exocald` (default features: with `exocald demo`, as the
/// README's `cargo run --release -p exocald -- demo` builds it) and returns its path. What the
/// figures, the benches and the cross check's recording run.
pub fn build_demo() -> Result<PathBuf> {
    let status = Command::new(paths::cargo())
        .current_dir(paths::workspace_root())
        .args(["build", "--release", "-p", "exocald", "--bin", "exocald"])
        .stdin(Stdio::null())
        .status()
        .context("cargo build")?;
    if !status.success() {
        bail!("release build of exocald (with the demo) failed");
    }
    Ok(paths::target_dir().join("release/exocald"))
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn targets_resolve_by_triple_or_debian_arch() {
        assert_eq!(target("arm64").unwrap().triple, "aarch64-unknown-linux-gnu");
        assert!(target("mips").is_err());
        assert_eq!(or_default(&[], true).len(), 2);
        assert_eq!(or_default(&[], false)[0].triple, TARGETS[0].triple);
    }
}
