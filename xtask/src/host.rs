//! What this machine has: Debian packages (apt), programs on `PATH`, rustup targets, root, and
//! installing the missing ones.
//!
//! A leaf module: it imports no other xtask module, so every command can use it.

use std::path::PathBuf;
use std::process::{Command, Stdio};

use anyhow::{bail, Context, Result};

/// Whether we run as root (apt, modprobe and chroot need it).
#[allow(unsafe_code)]
pub fn is_root() -> bool {
    // SAFETY: geteuid has no preconditions.
    unsafe { libc::geteuid() == 0 }
}

/// Whether a Debian package is installed.
pub fn installed(package: &str) -> bool {
    Command::new("dpkg-query")
        .args(["-W", "-f=${Status}", package])
        .stderr(Stdio::null())
        .output()
        .map(|o| String::from_utf8_lossy(&o.stdout).contains("install ok installed"))
        .unwrap_or(false)
}

/// The packages of `packages` that are not installed.
pub fn missing<'a>(packages: impl IntoIterator<Item = &'a str>) -> Vec<&'a str> {
    packages.into_iter().filter(|p| !installed(p)).collect()
}

/// Installs Debian packages with apt when we are root; otherwise says what to install.
///
/// Recommended packages are never installed (`--no-install-recommends`, as on a lean machine),
/// so every package the project needs must be named by the caller.
pub fn install_packages(packages: &[&str]) -> Result<()> {
    if packages.is_empty() {
        return Ok(());
    }
    if !is_root() {
        bail!(
            "not root, so not installing: run `sudo apt-get install -y --no-install-recommends {}`",
            packages.join(" ")
        );
    }
    if which("apt-get").is_none() {
        bail!(
            "no apt-get (not Debian): install the equivalents of {}",
            packages.join(", ")
        );
    }
    eprintln!("[setup] apt-get install {}", packages.join(" "));
    let update = Command::new("apt-get")
        .args(["update", "-qq"])
        .stdin(Stdio::null())
        .status()
        .context("apt-get update")?;
    if !update.success() {
        bail!("apt-get update failed");
    }
    let status = Command::new("apt-get")
        .args(["install", "-y", "-qq", "--no-install-recommends"])
        .args(packages)
        .env("DEBIAN_FRONTEND", "noninteractive")
        .stdin(Stdio::null())
        .status()
        .context("apt-get install")?;
    if !status.success() {
        bail!("apt-get install {} failed", packages.join(" "));
    }
    Ok(())
}

/// Adds a rustup target if it is missing.
pub fn add_rust_target(triple: &str) -> Result<()> {
    let list = Command::new("rustup")
        .args(["target", "list", "--installed"])
        .output()
        .context("rustup (cross-builds need rustup)")?;
    if String::from_utf8_lossy(&list.stdout)
        .lines()
        .any(|l| l.trim() == triple)
    {
        return Ok(());
    }
    let status = Command::new("rustup")
        .args(["target", "add", triple])
        .stdin(Stdio::null())
        .status()?;
    if !status.success() {
        bail!("rustup target add {triple} failed");
    }
    Ok(())
}

/// The full path of `program` on `PATH` (or in `/usr/sbin`, `/sbin`).
pub fn which(program: &str) -> Option<PathBuf> {
    let path = std::env::var_os("PATH")?;
    std::env::split_paths(&path)
        .chain(["/usr/sbin", "/sbin"].map(PathBuf::from))
        .map(|d| d.join(program))
        .find(|p| p.is_file())
}
