//! `cargo xtask deb [--target TRIPLE|ARCH]..`: the Debian package (default: this machine's
//! arch) into `target/debian/`, through lintian.

use std::fs;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use anyhow::{bail, Context, Result};

use crate::targets::{self, Target};
use crate::{host, paths};

/// Build the Debian package(s) into target/debian/, run lintian.
///
/// Build the Debian package (default: this machine's arch) into target/debian/, run lintian.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// A target triple or Debian architecture (repeatable; default: this machine's).
    #[arg(long = "target", value_name = "TRIPLE|ARCH", value_parser = targets::target)]
    pub targets: Vec<Target>,
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
systemd credential `exocal-keys`, loaded from /etc/credstore/exocal-keys: without that file
systemd does not start the unit (status 243/CREDENTIALS, the journal names the file); with a
node's key missing from it exocald exits 78 (bad configuration) and is not restarted.

Provision the keys (as root):

    umask 077
    for name in Joint1 Joint2 Joint3 Joint4 Joint5 Joint6 Joint7 EndEffector Trigger; do
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
    LoadCredentialEncrypted=exocal-keys:/etc/credstore.encrypted/exocal-keys

With `authenticate = false` in the [push] section of /etc/exocal/exocald.toml, exocald
sends plain transfers, which every node since exocal-3 refuses (keyed or not): nothing can be
pushed that way, and exocald warns in the journal at every start that the nodes' answers
and the sensor streams are unauthenticated.
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
    let root = paths::workspace_root();
    let out = paths::target_dir().join("debian");
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
    // The manual pages and shell completions, as the packaged exocald makes them from its CLI
    // definition (under qemu-user for a cross target).
    let exocald = bins
        .iter()
        .find(|b| b.file_name().is_some_and(|n| n == "exocald"))
        .context("no exocald among the binaries")?;
    let generated = |args: &[&str]| -> Result<Vec<u8>> {
        let out = targets::runner(t, exocald)
            .args(args)
            .output()
            .with_context(|| format!("run exocald {}", args.join(" ")))?;
        if !out.status.success() {
            bail!(
                "exocald {} failed: {}",
                args.join(" "),
                String::from_utf8_lossy(&out.stderr)
            );
        }
        Ok(out.stdout)
    };
    let man_dir = out.join(format!("{name}.man"));
    let _ = fs::remove_dir_all(&man_dir);
    generated(&["man", "--dir", &man_dir.to_string_lossy()])?;
    let mut pages: Vec<_> = fs::read_dir(&man_dir)?.collect::<Result<_, _>>()?;
    pages.sort_by_key(|e| e.file_name());
    for page in pages {
        let file = page.file_name().to_string_lossy().into_owned();
        put(
            &format!("usr/share/man/man1/{file}.gz"),
            &gzip(&fs::read(page.path())?)?,
            0o644,
        )?;
    }
    let _ = fs::remove_dir_all(&man_dir);
    for (shell, path) in [
        ("bash", "usr/share/bash-completion/completions/exocald"),
        ("zsh", "usr/share/zsh/vendor-completions/_exocald"),
        ("fish", "usr/share/fish/vendor_completions.d/exocald.fish"),
    ] {
        put(path, &generated(&["completions", shell])?, 0o644)?;
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
    // The bench's vcan0, and the drop-in the live view needs (installed by hand: it opens IP).
    for example in ["80-vcan0.netdev", "80-vcan0.network", "exocald-live.conf"] {
        put(
            &format!("usr/share/exocal/examples/{example}"),
            &read(&format!("systemd/{example}"))?,
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
 exocald collects free arm motion (until the table is good enough, 20 s to 3
 min) from the suit's IMU nodes over SocketCAN, identifies the D-H table by
 least squares and EM, validates it, pushes it to every node with CRC
 readback and logs the session as MCAP.
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
        "exocal-hil, the bench emulator, has `exocal-hil --help` (clap's long help) only; \
         exocald has exocald(1) and a page per subcommand",
    ),
    (
        "initial-upload-closes-no-bugs",
        "the package is built for the suit's controllers, never uploaded to Debian: no ITP bug",
    ),
];

/// Runs lintian on `deb`; fails on any error or warning outside [`LINTIAN_ACCEPTED`].
pub fn lintian(deb: &Path) -> Result<()> {
    if host::which("lintian").is_none() {
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
pub fn run(args: Args) -> Result<u8> {
    let targets = targets::or_default(&args.targets, false);
    targets::ensure_toolchain(&targets)?;
    for t in &targets {
        let bins = targets::build(t)?;
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
}
