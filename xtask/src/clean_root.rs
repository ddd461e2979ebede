//! `cargo xtask clean-root`: proves that `cargo xtask setup` installs everything on a clean
//! Debian, not only on a machine that has been used before.
//!
//! It bootstraps a minimal root of this machine's Debian release (`mmdebstrap --variant=minbase`,
//! from this machine's own apt sources) and runs this very xtask binary's `setup` inside it
//! (chroot): the same package list, installed the same way (`--no-install-recommends`), then the
//! same self-check. The Rust toolchain (rustup's and cargo's homes) and the workspace (for
//! `tests/requirements.txt`) are bind-mounted read-only: a Rust toolchain is the one thing a
//! newcomer's machine is assumed to have. Needs root.
//!
//! Everything happens in a private mount namespace of this process, with the root on a tmpfs:
//! nothing is mounted on the host, nothing is left on disk, and dpkg's many fsyncs cost nothing.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Instant;

use anyhow::{bail, Context, Result};

use crate::process::{self, shell_quote};
use crate::{host, paths};

/// Prove setup's package list complete in a freshly bootstrapped Debian root.
///
/// Prove setup's package list complete: bootstrap a minimal Debian root of this release
/// (mmdebstrap, this machine's apt sources) and run `setup` inside it (as root).
#[derive(Debug, clap::Args)]
pub struct Args {}

/// What the check itself needs on the host (not part of setup's list: only this check uses it).
const PACKAGES: &[&str] = &["mmdebstrap", "mount", "util-linux"];

/// The tmpfs the root lives on (a full setup fills about 3.2 GB).
const TMPFS_SIZE: &str = "size=8g";

/// `cargo xtask clean-root`.
pub fn run(_: Args) -> Result<u8> {
    if !host::is_root() {
        bail!("clean-root bootstraps and chroots into a Debian root: run it as root");
    }
    host::install_packages(&host::missing(PACKAGES.iter().copied()))?;
    let scratch = paths::workspace_root().join("target/xtask");
    std::fs::create_dir_all(&scratch)?;
    let root = scratch.join("clean-root");
    std::fs::create_dir_all(&root).with_context(|| format!("create {}", root.display()))?;
    private_mount_namespace()?;
    run_on(&["mount", "-t", "tmpfs", "-o", TMPFS_SIZE, "tmpfs"], &root)?;

    let started = Instant::now();
    let release = codename()?;
    let sources = apt_sources()?;
    println!(
        "==> clean-root: mmdebstrap --variant=minbase {release} on a tmpfs ({} apt source file(s))",
        sources.len()
    );
    let status = Command::new("mmdebstrap")
        .args(["--variant=minbase", "--mode=root", "--quiet", &release])
        .arg(&root)
        .args(&sources)
        .stdin(Stdio::null())
        .status()
        .context("run mmdebstrap")?;
    if !status.success() {
        bail!("mmdebstrap {release} failed ({status})");
    }
    let bootstrapped = started.elapsed();
    let base_size = used(&root);

    let xtask = root.join("usr/local/bin/exocal-xtask");
    std::fs::copy("/proc/self/exe", &xtask).context("copy the running xtask into the root")?;
    carry_site_network(&root)?;

    // apt's and pip's progress go to a log; setup's own lines (stderr) show as they come.
    let log_path = scratch.join("clean-root.log");
    let log = std::fs::File::create(&log_path)
        .with_context(|| format!("create {}", log_path.display()))?;
    println!(
        "==> clean-root: `cargo xtask setup` inside it (install, then self-check; apt's output \
         in {})",
        log_path.display()
    );
    let ran = Instant::now();
    let status = Command::new("sh")
        .arg("-euc")
        .arg(chroot_script(&root)?)
        .stdin(Stdio::null())
        .stdout(log)
        .status()
        .context("run the chroot script")?;
    let setup = ran.elapsed();
    if !status.success() {
        bail!(
            "`cargo xtask setup` failed in a clean {release} root ({status}): setup's package \
             list is incomplete, or a check above names what is missing (apt's output: {})",
            log_path.display()
        );
    }
    println!(
        "clean-root: a clean {release} root (minbase, {base_size}) bootstrapped in {:.0} s; \
         setup installed everything and its self-check passed in {:.0} s ({} in all)",
        bootstrapped.as_secs_f64(),
        setup.as_secs_f64(),
        used(&root),
    );
    Ok(0)
}

/// Moves this process into a mount namespace of its own in which nothing propagates back to
/// the host: every mount made from here on (and by children) goes when the process exits.
#[allow(unsafe_code)]
fn private_mount_namespace() -> Result<()> {
    // SAFETY: unshare has no memory-safety preconditions; it changes only this process's mount
    // namespace.
    if unsafe { libc::unshare(libc::CLONE_NEWNS) } != 0 {
        bail!("unshare(CLONE_NEWNS): {}", std::io::Error::last_os_error());
    }
    run_on(&["mount", "--make-rprivate"], Path::new("/"))
}

/// Runs `argv` followed by `path`, failing with its stderr.
fn run_on(argv: &[&str], path: &Path) -> Result<()> {
    process::output(
        Command::new(argv[0]).args(&argv[1..]).arg(path),
        &format!("{} {}", argv.join(" "), path.display()),
    )
    .map(drop)
}

/// The script that mounts what the chroot needs and runs setup in it (in this process's private
/// mount namespace, so every mount goes with it).
fn chroot_script(root: &Path) -> Result<String> {
    let home = std::env::var_os("HOME")
        .map(PathBuf::from)
        .unwrap_or("/root".into());
    let env_dir = |var: &str, default: &str| {
        std::env::var_os(var)
            .map(PathBuf::from)
            .unwrap_or_else(|| home.join(default))
    };
    let rustup = env_dir("RUSTUP_HOME", ".rustup");
    let cargo = env_dir("CARGO_HOME", ".cargo");
    let workspace = paths::workspace_root();
    let q = |p: &Path| shell_quote(&p.to_string_lossy());
    let r = q(root);
    let mut script = format!(
        "mount -t proc proc {r}/proc\nmount --rbind /dev {r}/dev\nmount -t sysfs sys {r}/sys\n"
    );
    for dir in [&rustup, &cargo, &workspace] {
        let (src, dst) = (q(dir), q(&root.join(dir.strip_prefix("/").unwrap_or(dir))));
        script +=
            &format!("mkdir -p {dst}\nmount --bind {src} {dst}\nmount -o remount,bind,ro {dst}\n");
    }
    script += &format!(
        "exec chroot {r} /usr/bin/env -i HOME=/root PATH={}:/usr/local/sbin:/usr/local/bin:\
         /usr/sbin:/usr/bin:/sbin:/bin RUSTUP_HOME={} CARGO_HOME={} EXOCAL_PYENV=/opt/exocal-pyenv {} \
         /usr/local/bin/exocal-xtask setup\n",
        q(&cargo.join("bin")),
        q(&rustup),
        q(&cargo),
        site_environment(root).join(" "),
    );
    Ok(script)
}

/// The site's network configuration is the machine's, not a package's: the root gets this
/// machine's resolver, its local CA certificates (a TLS-inspecting proxy's CA among them: the
/// root's ca-certificates package folds them into its bundle when setup installs it, and the
/// bundle is copied in now for anything that runs before) and pip's configuration file.
fn carry_site_network(root: &Path) -> Result<()> {
    for file in [
        "etc/resolv.conf",
        "etc/pip.conf",
        "etc/ssl/certs/ca-certificates.crt",
    ] {
        let src = Path::new("/").join(file);
        if src.is_file() {
            let dst = root.join(file);
            std::fs::create_dir_all(dst.parent().context("parent")?)?;
            std::fs::copy(&src, &dst)
                .with_context(|| format!("copy {} into the root", src.display()))?;
        }
    }
    let local = Path::new("/usr/local/share/ca-certificates");
    if local.is_dir() {
        let dst = root.join("usr/local/share/ca-certificates");
        std::fs::create_dir_all(&dst)?;
        for entry in std::fs::read_dir(local)? {
            let entry = entry?;
            if entry.path().is_file() {
                std::fs::copy(entry.path(), dst.join(entry.file_name()))?;
            }
        }
    }
    Ok(())
}

/// The environment variables that carry the site's network configuration (proxies, CA bundles,
/// pip's settings) into the root, as `NAME=value` words for `env`. A variable naming a path that the root lacks (a host-only wheel cache, say) is left out.
fn site_environment(root: &Path) -> Vec<String> {
    const CA: &[&str] = &[
        "SSL_CERT_FILE",
        "SSL_CERT_DIR",
        "REQUESTS_CA_BUNDLE",
        "CURL_CA_BUNDLE",
    ];
    std::env::vars()
        .filter(|(k, _)| {
            CA.contains(&k.as_str())
                || k.starts_with("PIP_")
                || k.to_ascii_lowercase().ends_with("_proxy")
        })
        .filter(|(_, v)| !v.starts_with('/') || root.join(&v[1..]).exists())
        .map(|(k, v)| shell_quote(&format!("{k}={v}")))
        .collect()
}

/// This machine's Debian codename (`VERSION_CODENAME` in /etc/os-release).
fn codename() -> Result<String> {
    let text = std::fs::read_to_string("/etc/os-release").context("read /etc/os-release")?;
    text.lines()
        .find_map(|l| l.strip_prefix("VERSION_CODENAME="))
        .map(|v| v.trim_matches('"').to_string())
        .filter(|v| !v.is_empty())
        .context("/etc/os-release names no VERSION_CODENAME (is this Debian?)")
}

/// This machine's enabled apt source files: the new root installs from the same archives.
fn apt_sources() -> Result<Vec<PathBuf>> {
    let mut files = Vec::new();
    let list = Path::new("/etc/apt/sources.list");
    if std::fs::read_to_string(list)
        .map(|t| t.lines().any(|l| l.trim_start().starts_with("deb")))
        .unwrap_or(false)
    {
        files.push(list.to_path_buf());
    }
    let mut parts: Vec<PathBuf> = std::fs::read_dir("/etc/apt/sources.list.d")
        .map(|d| d.filter_map(|e| e.ok().map(|e| e.path())).collect())
        .unwrap_or_default();
    parts.sort();
    files.extend(
        parts
            .into_iter()
            .filter(|p| p.extension().is_some_and(|e| e == "list" || e == "sources")),
    );
    if files.is_empty() {
        bail!("this machine has no apt sources (/etc/apt/sources.list, sources.list.d)");
    }
    Ok(files)
}

/// How much of the root's tmpfs is used, as `df -h` says it.
fn used(root: &Path) -> String {
    Command::new("df")
        .args(["-h", "--output=used"])
        .arg(root)
        .output()
        .ok()
        .and_then(|o| String::from_utf8(o.stdout).ok())
        .and_then(|s| s.lines().nth(1).map(|l| l.trim().to_string()))
        .unwrap_or_else(|| "?".into())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_chroot_script_mounts_read_only_and_runs_setup_last() {
        let script = chroot_script(Path::new("/tmp/a root")).unwrap();
        let lines: Vec<&str> = script.lines().collect();
        assert_eq!(lines[0], "mount -t proc proc '/tmp/a root'/proc");
        let binds = lines
            .iter()
            .filter(|l| l.starts_with("mount --bind"))
            .count();
        let ro = lines
            .iter()
            .filter(|l| l.starts_with("mount -o remount,bind,ro"))
            .count();
        assert_eq!((binds, ro), (3, 3), "{script}");
        let last = lines.last().unwrap();
        assert!(
            last.starts_with("exec chroot '/tmp/a root' /usr/bin/env -i "),
            "{last}"
        );
        assert!(
            last.ends_with("/usr/local/bin/exocal-xtask setup"),
            "{last}"
        );
    }
}
