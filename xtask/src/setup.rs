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

/// Debian packages the test suites need on every machine: Chromium renders the calibration
/// report in a test; lintian checks the Debian packages.
pub const TEST_PACKAGES: &[&str] = &["chromium", "lintian"];

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

/// The workspace root (xtask sits in it).
pub fn workspace_root() -> std::path::PathBuf {
    let here = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    here.parent().unwrap_or(here).to_path_buf()
}

/// The project's Python venv (`target/exocal-pyenv`, from `tests/requirements.txt`), made or
/// updated when the requirements changed; returns its interpreter.
pub fn python_env() -> Result<std::path::PathBuf> {
    let root = workspace_root();
    let venv = std::env::var_os("EXOCAL_PYENV")
        .map(std::path::PathBuf::from)
        .unwrap_or_else(|| root.join("target/exocal-pyenv"));
    let python = venv.join("bin/python");
    let wanted = std::fs::read_to_string(root.join("tests/requirements.txt"))
        .context("read tests/requirements.txt")?;
    let stamp = venv.join("exocal-requirements.txt");
    if python.exists() && std::fs::read_to_string(&stamp).ok().as_deref() == Some(&wanted) {
        return Ok(python);
    }
    if !python.exists() {
        if crate::vm::which("python3").is_none() {
            bail!("python3 is needed for the cantools and mcap cross-checks: install python3");
        }
        let ok = Command::new("python3")
            .args(["-m", "venv"])
            .arg(&venv)
            .stdin(Stdio::null())
            .status()
            .context("python3 -m venv")?
            .success();
        if !ok {
            bail!("python3 -m venv failed: install python3-venv");
        }
    }
    eprintln!(
        "[setup] pip install -r tests/requirements.txt into {}",
        venv.display()
    );
    let ok = Command::new(&python)
        .args([
            "-m",
            "pip",
            "install",
            "--quiet",
            "--disable-pip-version-check",
            "-r",
        ])
        .arg(root.join("tests/requirements.txt"))
        .stdin(Stdio::null())
        .status()
        .context("pip install")?
        .success();
    if !ok {
        bail!("pip install -r tests/requirements.txt failed (is PyPI reachable?)");
    }
    std::fs::write(&stamp, wanted)?;
    Ok(python)
}

/// `cargo xtask setup`: everything, so that a fresh machine can build and test.
pub fn install_all() -> Result<()> {
    add_rust_target(EMBEDDED_TARGET)?;
    // The controller's targets: rustup targets, Debian's cross gcc and qemu-user-static.
    crate::ship::ensure_toolchain(&crate::ship::parse_targets(&[], true)?)?;
    python_env()?;
    let missing: Vec<&str> = TEST_PACKAGES
        .iter()
        .copied()
        .filter(|p| !installed(p))
        .collect();
    install_packages(&missing)?;
    if crate::native::available().is_ok() {
        eprintln!("[setup] native vcan works here: no VM packages needed");
        return Ok(());
    }
    install_packages(&missing_vm_packages())
}
