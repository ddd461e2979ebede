//! Installing what the project needs on a fresh Debian machine.
//!
//! Nothing here is needed on a box with native vcan except the rustup target. As root on Debian
//! the packages are installed with apt; otherwise the error says what to install.

use std::process::{Command, Stdio};

use anyhow::{bail, Context, Result};

/// Where Debian's busybox-static puts its binary.
pub const BUSYBOX: &str = "/bin/busybox";

/// The Debian packages the QEMU path needs.
pub const VM_PACKAGES: &[&str] = &[
    "qemu-system-x86",
    "linux-image-amd64",
    "busybox-static",
    "cpio",
];

/// The no_std target calib-core is cross-built for.
pub const EMBEDDED_TARGET: &str = "thumbv7em-none-eabihf";

/// Whether a Debian package is installed.
pub fn installed(package: &str) -> bool {
    Command::new("dpkg-query")
        .args(["-W", "-f=${Status}", package])
        .stderr(Stdio::null())
        .output()
        .map(|o| String::from_utf8_lossy(&o.stdout).contains("install ok installed"))
        .unwrap_or(false)
}

/// The VM packages that are not installed.
pub fn missing_vm_packages() -> Vec<&'static str> {
    VM_PACKAGES
        .iter()
        .copied()
        .filter(|p| !installed(p))
        .collect()
}

/// Installs Debian packages with apt when we are root; otherwise says what to install.
pub fn install_packages(packages: &[&str]) -> Result<()> {
    if packages.is_empty() {
        return Ok(());
    }
    // SAFETY: geteuid has no preconditions.
    if unsafe { libc::geteuid() } != 0 {
        bail!(
            "not root, so not installing: run `sudo apt-get install -y {}`",
            packages.join(" ")
        );
    }
    if crate::vm::which("apt-get").is_none() {
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

/// `cargo xtask setup`: everything, so that a fresh machine can build and test.
pub fn install_all() -> Result<()> {
    add_rust_target(EMBEDDED_TARGET)?;
    if crate::native::available().is_ok() {
        eprintln!("[setup] native vcan works here: no VM packages needed");
        return Ok(());
    }
    install_packages(&missing_vm_packages())
}
