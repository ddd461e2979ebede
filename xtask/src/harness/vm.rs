//! The VM path: Debian's kernel under `qemu-system-x86_64 -accel tcg`, for kernels without CAN.
//!
//! The guest is a kernel (resolved at run time through the `linux-image-amd64` package, never a
//! hard-coded version) and a small initramfs made here: a static busybox, the virtio, 9p and
//! can/can-raw/can-dev/vcan modules in dependency order (read from `modules.dep`), and an `/init`
//! that mounts the host root read-only over 9p, a tmpfs on its `/tmp`, `/run` and `/dev/shm`, and a
//! writable scratch folder (shared over 9p) at the same path as on the host. It creates vcan0 and
//! vcan1, runs the command chrooted into the host root with the caller's environment and working
//! directory, writes its stdout, stderr and exit status into the scratch folder, and powers off.
//! The host streams stdout and stderr as they grow, so output arrives live and byte for byte, and
//! kills QEMU at the time limit. QEMU dies with us (PR_SET_PDEATHSIG), so nothing is left running.
//! KVM is not used: it hangs on these machines.

use std::fs;
use std::io::{Read, Seek, SeekFrom, Write};
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};

use super::request::{note, Request, TIMED_OUT};
use crate::host;
use crate::process::{exit_code, shell_quote};

/// Modules the guest needs; their dependencies are added from `modules.dep`.
const MODULES: &[&str] = &[
    "virtio_pci",
    "9pnet_virtio",
    "9p",
    "can",
    "can_raw",
    "can_dev",
    "vcan",
    "overlay",
];

/// Bumped when the initramfs layout or `/init` changes, so cached images are rebuilt.
const INITRAMFS_VERSION: u32 = 6;

const INIT: &str = r#"#!/bin/sh
# exocal vcan harness: guest init (busybox). Never exits: it powers the guest off.
PATH=/bin
export PATH
mount -t proc proc /proc
mount -t sysfs sysfs /sys
mount -t devtmpfs devtmpfs /dev
fail() { echo "exocal-init: $*"; poweroff -f; }
while read -r m; do insmod "/modules/$m" || fail "insmod $m failed"; done < /modules/order
scratch=$(sed -n 's/.*exocal\.scratch=\([^ ]*\).*/\1/p' /proc/cmdline)
[ -n "$scratch" ] || fail "no exocal.scratch= on the kernel command line"
mode=$(sed -n 's/.*exocal\.mode=\([^ ]*\).*/\1/p' /proc/cmdline)
if [ "$mode" = systemd ]; then
  # systemd as PID 1 on a tmpfs overlay of the read-only host root.
  mkdir -p /lower /rw /newroot
  mount -t 9p -o trans=virtio,version=9p2000.L,msize=524288,cache=loose,ro hostroot /lower || fail "mount host root"
  mount -t tmpfs -o mode=755 tmpfs /rw || fail "mount overlay tmpfs"
  mkdir -p /rw/upper /rw/work
  mount -t overlay overlay -o lowerdir=/lower,upperdir=/rw/upper,workdir=/rw/work /newroot || fail "mount overlay"
  # The host root may be a container's (Docker leaves /.dockerenv): systemd would take the guest
  # for that container and leave every mount private, so no LoadCredential= file would reach
  # a unit. This guest is a virtual machine, as a controller is a machine.
  rm -f /newroot/.dockerenv /newroot/run/.containerenv
  mount -t 9p -o trans=virtio,version=9p2000.L,msize=524288 scratch "/newroot$scratch" || fail "mount scratch"
  mount -t proc proc /newroot/proc
  mount -t sysfs sysfs /newroot/sys
  mount -t devtmpfs devtmpfs /newroot/dev
  # The host's own services and timers (databases, apt, man-db) are not the guest's business.
  rm -f /newroot/etc/systemd/system/multi-user.target.wants/* /newroot/etc/systemd/system/timers.target.wants/*
  # Boot-time cleaning of /tmp (tmpfiles.d tmp.conf) would delete a checkout living there.
  mkdir -p /newroot/etc/tmpfiles.d && : > /newroot/etc/tmpfiles.d/tmp.conf
  cp "/newroot$scratch/exocal-harness.service" /newroot/etc/systemd/system/ || fail "install harness unit"
  mkdir -p /newroot/etc/systemd/system/multi-user.target.wants
  ln -sf ../exocal-harness.service /newroot/etc/systemd/system/multi-user.target.wants/exocal-harness.service
  if [ -f "/newroot$scratch/setup.sh" ]; then
    chroot /newroot /bin/sh "$scratch/setup.sh" > "/newroot$scratch/setup.log" 2>&1 || fail "setup script failed: see setup.log"
  fi
  umount /newroot/proc /newroot/sys /newroot/dev
  echo "exocal-init: switching to systemd"
  exec switch_root /newroot /lib/systemd/systemd
fi
mkdir -p /host
mount -t 9p -o trans=virtio,version=9p2000.L,msize=524288,cache=loose,ro hostroot /host || fail "mount host root"
mount -t tmpfs -o mode=755 tmpfs /host/run || fail "mount /run"
mkdir -p /host/run/tmp && chmod 1777 /host/run/tmp
# A fresh /tmp, unless the work (a clone under /tmp, as CI may make) lives there: then the
# command writes to $TMPDIR=/run/tmp instead.
case "$scratch" in
  /tmp/*) ;;
  *) mount -t tmpfs -o mode=1777 tmpfs /host/tmp || fail "mount /tmp" ;;
esac
mount -t proc proc /host/proc
mount -t sysfs sysfs /host/sys
mount -t devtmpfs devtmpfs /host/dev
mkdir -p /host/dev/shm /host/dev/pts
mount -t tmpfs -o mode=1777 tmpfs /host/dev/shm
mount -t devpts devpts /host/dev/pts
mount -t 9p -o trans=virtio,version=9p2000.L,msize=524288 scratch "/host$scratch" || fail "mount scratch"
ip link set lo up
for i in vcan0 vcan1; do
  ip link add dev "$i" type vcan || fail "ip link add $i type vcan"
  ip link set "$i" up || fail "ip link set $i up"
done
echo "exocal-init: vcan0 and vcan1 up; running the command"
chroot /host /bin/sh "$scratch/run.sh" > "/host$scratch/stdout" 2> "/host$scratch/stderr" < /dev/null
echo $? > "/host$scratch/rc.tmp"
mv "/host$scratch/rc.tmp" "/host$scratch/rc"
sync
umount "/host$scratch"
poweroff -f
"#;

/// With `--systemd`: the unit that runs the command once the system is up, records its exit
/// status and the boot's journal in the scratch folder, and powers the guest off.
const HARNESS_UNIT: &str = "[Unit]
Description=exocal harness: run the command, report, power off
After=multi-user.target
SuccessAction=poweroff
FailureAction=poweroff

[Service]
Type=oneshot
StandardOutput=file:@SCRATCH@/stdout
StandardError=file:@SCRATCH@/stderr
ExecStart=/bin/sh @SCRATCH@/run.sh
ExecStopPost=/bin/sh -c 'journalctl -b --no-pager -o short-monotonic > @SCRATCH@/journal.txt 2>&1; echo \"$EXIT_STATUS\" > @SCRATCH@/rc.tmp; mv @SCRATCH@/rc.tmp @SCRATCH@/rc'
TimeoutStartSec=infinity
";

/// The guest's kernel and modules.
struct Kernel {
    version: String,
    image: PathBuf,
    modules: PathBuf,
}

/// Runs the request in a QEMU guest; returns the exit status and, if asked, the stdout.
pub fn run(req: &Request) -> Result<(u8, Vec<u8>)> {
    let qemu = ensure_tools()?;
    let kernel = find_kernel()?;
    let target = target_dir(&req.cwd)?;
    let initramfs = build_initramfs(&kernel, &target.join("xtask"))?;

    let scratch = target.join("xtask").join(format!(
        "vcan-run-{}-{}",
        std::process::id(),
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_nanos())
            .unwrap_or(0)
    ));
    fs::create_dir_all(&scratch).with_context(|| format!("create {}", scratch.display()))?;
    let scratch = scratch.canonicalize()?;
    let result = boot(req, &qemu, &kernel, &initramfs, &scratch);
    if result.is_ok() && !req.verbose {
        let _ = fs::remove_dir_all(&scratch);
    } else {
        note(&format!("guest files kept in {}", scratch.display()));
    }
    result
}

fn boot(
    req: &Request,
    qemu: &Path,
    kernel: &Kernel,
    initramfs: &Path,
    scratch: &Path,
) -> Result<(u8, Vec<u8>)> {
    write_run_script(req, scratch)?;
    let mut append = format!(
        "console=ttyS0 quiet loglevel=3 panic=-1 exocal.scratch={}",
        scratch.display()
    );
    if req.systemd {
        fs::write(
            scratch.join("exocal-harness.service"),
            HARNESS_UNIT.replace("@SCRATCH@", &scratch.display().to_string()),
        )?;
        if let Some(setup) = &req.setup {
            fs::copy(setup, scratch.join("setup.sh"))
                .with_context(|| format!("copy setup script {}", setup.display()))?;
        }
        append.push_str(" exocal.mode=systemd systemd.unit=multi-user.target");
    }
    for name in ["stdout", "stderr"] {
        fs::File::create(scratch.join(name))?;
    }
    let console = scratch.join("console.log");
    let mut cmd = Command::new(qemu);
    cmd.args(["-accel", "tcg,thread=multi", "-cpu", "max", "-smp", "2"])
        .args(["-m", &req.mem_mib.to_string()])
        .args([
            "-nodefaults",
            "-no-user-config",
            "-no-reboot",
            "-display",
            "none",
        ])
        .args(["-monitor", "none"])
        .arg("-serial")
        .arg(format!("file:{}", console.display()))
        .arg("-kernel")
        .arg(&kernel.image)
        .arg("-initrd")
        .arg(initramfs)
        .arg("-append")
        .arg(append)
        .arg("-virtfs")
        .arg("local,path=/,mount_tag=hostroot,security_model=none,readonly=on,multidevs=remap")
        .arg("-virtfs")
        .arg(format!(
            "local,path={},mount_tag=scratch,security_model=none",
            scratch.display()
        ))
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped());
    // SAFETY: prctl is async-signal-safe; QEMU is killed if the harness dies.
    #[allow(unsafe_code)]
    unsafe {
        cmd.pre_exec(|| {
            libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL);
            Ok(())
        });
    }
    let started = Instant::now();
    let mut child = cmd
        .spawn()
        .with_context(|| format!("start {}", qemu.display()))?;
    let mut qemu_err = child.stderr.take();
    let err_thread = std::thread::spawn(move || {
        let mut s = String::new();
        if let Some(e) = qemu_err.as_mut() {
            let _ = e.read_to_string(&mut s);
        }
        s
    });

    let mut out = Follower::new(scratch.join("stdout"), req.capture_stdout);
    let mut err = Follower::new(scratch.join("stderr"), false);
    let deadline = started + req.timeout;
    let mut timed_out = false;
    let status = loop {
        out.pump(&mut std::io::stdout())?;
        err.pump(&mut std::io::stderr())?;
        if let Some(status) = child.try_wait()? {
            break Some(status);
        }
        if Instant::now() >= deadline {
            note(&format!(
                "time limit of {} s reached: killing the guest",
                req.timeout.as_secs()
            ));
            let _ = child.kill();
            let _ = child.wait();
            timed_out = true;
            break None;
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    out.pump(&mut std::io::stdout())?;
    err.pump(&mut std::io::stderr())?;
    let qemu_stderr = err_thread.join().unwrap_or_default();
    if timed_out {
        show_console(&console);
        return Ok((TIMED_OUT, out.captured));
    }
    if req.systemd {
        let kept = scratch
            .parent()
            .unwrap_or(scratch)
            .join("last-boot-journal.txt");
        if fs::copy(scratch.join("journal.txt"), &kept).is_ok() {
            note(&format!("the boot's journal is in {}", kept.display()));
        }
    }
    let rc = fs::read_to_string(scratch.join("rc")).ok();
    match rc.as_deref().map(str::trim).map(str::parse::<u8>) {
        Some(Ok(code)) => {
            if req.verbose {
                show_console(&console);
            }
            Ok((code, out.captured))
        }
        _ => {
            show_console(&console);
            bail!(
                "the guest stopped without reporting an exit status (QEMU {}; stderr: {})",
                status.map(exit_code).unwrap_or(0),
                qemu_stderr.trim()
            )
        }
    }
}

/// Writes `run.sh`: the caller's environment, working directory and command, quoted for `sh`.
fn write_run_script(req: &Request, scratch: &Path) -> Result<()> {
    let mut script = String::from("# written by cargo xtask vcan\n");
    for (key, value) in std::env::vars() {
        let valid = !key.is_empty()
            && key.chars().all(|c| c == '_' || c.is_ascii_alphanumeric())
            && !key.starts_with(|c: char| c.is_ascii_digit());
        if valid && !matches!(key.as_str(), "PWD" | "OLDPWD" | "SHLVL" | "_") {
            script.push_str(&format!("export {key}={}\n", shell_quote(&value)));
        }
    }
    script.push_str("export EXOCAL_VCAN_HARNESS=vm PYTHONDONTWRITEBYTECODE=1\n");
    if !req.systemd {
        // The host root is read-only in the guest; /run is a tmpfs.
        script.push_str("export TMPDIR=/run/tmp\n");
    }
    script.push_str(&format!(
        "cd {} || exit 125\n",
        shell_quote(&req.cwd.display().to_string())
    ));
    let argv: Vec<String> = req.argv.iter().map(|a| shell_quote(a)).collect();
    script.push_str(&format!("exec {}\n", argv.join(" ")));
    fs::write(scratch.join("run.sh"), script)?;
    Ok(())
}

/// Follows a file that the guest appends to, forwarding new bytes.
struct Follower {
    path: PathBuf,
    pos: u64,
    capture: bool,
    captured: Vec<u8>,
}

impl Follower {
    fn new(path: PathBuf, capture: bool) -> Self {
        Follower {
            path,
            pos: 0,
            capture,
            captured: Vec::new(),
        }
    }

    fn pump(&mut self, sink: &mut impl Write) -> Result<()> {
        let Ok(mut file) = fs::File::open(&self.path) else {
            return Ok(());
        };
        file.seek(SeekFrom::Start(self.pos))?;
        let mut buf = Vec::new();
        file.read_to_end(&mut buf)?;
        if !buf.is_empty() {
            self.pos += buf.len() as u64;
            sink.write_all(&buf)?;
            sink.flush()?;
            if self.capture {
                self.captured.extend_from_slice(&buf);
            }
        }
        Ok(())
    }
}

fn show_console(console: &Path) {
    let text = fs::read_to_string(console).unwrap_or_default();
    let tail: Vec<&str> = text.lines().rev().take(60).collect();
    note("guest console (last lines):");
    for line in tail.into_iter().rev() {
        eprintln!("  | {line}");
    }
}

/// The Debian packages the guest is made of: QEMU, Debian's kernel (with its CAN, virtio and 9p
/// modules), a static busybox for the initramfs, cpio to pack it. qemu-system-x86's
/// recommendations (GUI, OVMF, block drivers) are not needed: the guest boots `-kernel` directly,
/// with no display and no disk.
pub const PACKAGES: &[&str] = &[
    "qemu-system-x86",
    "linux-image-amd64",
    "busybox-static",
    "cpio",
];

/// Where Debian's busybox-static puts its binary.
pub const BUSYBOX: &str = "/bin/busybox";

/// Finds QEMU and busybox, installing them (as root on Debian) when missing.
fn ensure_tools() -> Result<PathBuf> {
    let missing = host::missing(PACKAGES.iter().copied());
    if !missing.is_empty() {
        host::install_packages(&missing).with_context(|| {
            format!(
                "the QEMU path needs the Debian packages {}: install them \
                 (`sudo apt-get install {}`) or run on a kernel with vcan",
                missing.join(", "),
                missing.join(" ")
            )
        })?;
    }
    let qemu = host::which("qemu-system-x86_64").context("qemu-system-x86_64 not found on PATH")?;
    if !is_static_elf(Path::new(BUSYBOX))? {
        bail!("{BUSYBOX} is not statically linked: install busybox-static");
    }
    Ok(qemu)
}

/// Checks, without installing or booting anything, that every part of the guest is usable:
/// QEMU starts, busybox is static and runs, the kernel resolves and has every module the guest
/// loads. Returns a one-line summary.
pub fn check_parts() -> Result<String> {
    let qemu = host::which("qemu-system-x86_64")
        .context("qemu-system-x86_64 is not on PATH (package qemu-system-x86)")?;
    let version = crate::process::output(
        Command::new(&qemu).arg("--version"),
        "qemu-system-x86_64 --version (package qemu-system-x86)",
    )?;
    if !is_static_elf(Path::new(BUSYBOX)).unwrap_or(false) {
        bail!("{BUSYBOX} is missing or not statically linked (package busybox-static)");
    }
    crate::process::output(
        Command::new(BUSYBOX).arg("true"),
        "busybox true (package busybox-static)",
    )?;
    host::which("cpio").context("cpio is not on PATH (package cpio)")?;
    let kernel = find_kernel()?;
    let modules = module_order(&kernel.modules).with_context(|| {
        format!(
            "modules of kernel {} (package linux-image-amd64)",
            kernel.version
        )
    })?;
    Ok(format!(
        "{}; kernel {} with {} modules to load; static busybox",
        version.lines().next().unwrap_or("QEMU").trim(),
        kernel.version,
        modules.len()
    ))
}

/// Resolves the kernel through the `linux-image-amd64` metapackage.
fn find_kernel() -> Result<Kernel> {
    let out = Command::new("dpkg-query")
        .args(["-W", "-f=${Depends}", "linux-image-amd64"])
        .output()
        .context("dpkg-query (is this Debian?)")?;
    let depends = String::from_utf8_lossy(&out.stdout);
    let package = depends
        .split([',', '|'])
        .map(str::trim)
        .find_map(|dep| dep.split_whitespace().next())
        .filter(|p| p.starts_with("linux-image-"))
        .with_context(|| {
            format!(
                "linux-image-amd64 does not name a kernel package (dpkg-query said {:?}); \
                 install linux-image-amd64",
                depends.trim()
            )
        })?;
    let version = package.trim_start_matches("linux-image-").to_string();
    let image = PathBuf::from(format!("/boot/vmlinuz-{version}"));
    let modules = PathBuf::from(format!("/lib/modules/{version}"));
    for p in [&image, &modules] {
        if !p.exists() {
            bail!(
                "{} is missing although {package} is named by linux-image-amd64",
                p.display()
            );
        }
    }
    Ok(Kernel {
        version,
        image,
        modules,
    })
}

/// Builds (or reuses) the initramfs for this kernel.
fn build_initramfs(kernel: &Kernel, cache: &Path) -> Result<PathBuf> {
    let image = cache.join(format!(
        "initramfs-{}-v{INITRAMFS_VERSION}.cpio",
        kernel.version
    ));
    if image.exists() {
        return Ok(image);
    }
    // Built in a folder of our own and renamed into place, so that concurrent runs never see
    // a half-written image.
    let root = cache.join(format!(
        "initramfs-{}.{}.d",
        kernel.version,
        std::process::id()
    ));
    let _ = fs::remove_dir_all(&root);
    for dir in ["bin", "modules", "proc", "sys", "dev", "host", "tmp"] {
        fs::create_dir_all(root.join(dir))?;
    }
    fs::copy(BUSYBOX, root.join("bin/busybox"))?;
    for applet in [
        "sh",
        "mount",
        "umount",
        "insmod",
        "mkdir",
        "ip",
        "poweroff",
        "sed",
        "chroot",
        "echo",
        "mv",
        "sync",
        "cat",
        "sleep",
        "ls",
        "cp",
        "ln",
        "switch_root",
    ] {
        std::os::unix::fs::symlink("busybox", root.join("bin").join(applet))?;
    }
    let init = root.join("init");
    fs::write(&init, INIT)?;
    set_mode(&init, 0o755)?;

    let order = module_order(&kernel.modules)?;
    let mut list = String::new();
    for rel in &order {
        let src = kernel.modules.join(rel);
        let name = Path::new(rel)
            .file_name()
            .and_then(|n| n.to_str())
            .context("module name")?;
        let (plain, bytes) = decompress_module(&src, name)?;
        fs::write(root.join("modules").join(&plain), bytes)?;
        list.push_str(&plain);
        list.push('\n');
    }
    fs::write(root.join("modules/order"), list)?;

    let tmp = image.with_extension(format!("{}.tmp", std::process::id()));
    let out = fs::File::create(&tmp)?;
    let status = Command::new("sh")
        .arg("-c")
        .arg("find . -print | LC_ALL=C sort | cpio -o -H newc --quiet")
        .current_dir(&root)
        .stdout(out)
        .status()
        .context("run cpio (install the cpio package)")?;
    if !status.success() {
        bail!("cpio failed building {}", image.display());
    }
    fs::rename(&tmp, &image)?;
    let _ = fs::remove_dir_all(&root);
    note(&format!(
        "built initramfs for kernel {} ({} modules)",
        kernel.version,
        order.len()
    ));
    Ok(image)
}

/// The modules to load, dependencies first, as paths relative to the modules folder.
fn module_order(modules: &Path) -> Result<Vec<String>> {
    let dep = fs::read_to_string(modules.join("modules.dep"))
        .with_context(|| format!("read {}/modules.dep", modules.display()))?;
    let builtin = fs::read_to_string(modules.join("modules.builtin")).unwrap_or_default();
    resolve_modules(&dep, &builtin, MODULES)
}

/// Canonical module name of a path in `modules.dep`: file stem, `-` read as `_`.
fn module_name(path: &str) -> String {
    let file = path.rsplit('/').next().unwrap_or(path);
    let stem = file.split(".ko").next().unwrap_or(file);
    stem.replace('-', "_")
}

/// Dependency-ordered closure of `wanted`; built-in modules need no loading.
fn resolve_modules(dep: &str, builtin: &str, wanted: &[&str]) -> Result<Vec<String>> {
    use std::collections::HashMap;
    let mut table: HashMap<String, (String, Vec<String>)> = HashMap::new();
    for line in dep.lines() {
        let Some((path, deps)) = line.split_once(':') else {
            continue;
        };
        let deps = deps.split_whitespace().map(str::to_string).collect();
        table.insert(module_name(path), (path.to_string(), deps));
    }
    let builtin: Vec<String> = builtin.lines().map(module_name).collect();
    let mut order = Vec::new();
    fn visit(name: &str, table: &HashMap<String, (String, Vec<String>)>, order: &mut Vec<String>) {
        let Some((path, deps)) = table.get(name) else {
            return;
        };
        if order.contains(path) {
            return;
        }
        for d in deps {
            visit(&module_name(d), table, order);
        }
        order.push(path.clone());
    }
    for want in wanted {
        let name = want.replace('-', "_");
        if !table.contains_key(&name) && !builtin.contains(&name) {
            bail!("kernel module {want} is neither in modules.dep nor built in");
        }
        visit(&name, &table, &mut order);
    }
    Ok(order)
}

/// Reads a module, decompressing `.ko.xz` / `.ko.zst` / `.ko.gz` (busybox insmod takes plain `.ko`).
fn decompress_module(src: &Path, name: &str) -> Result<(String, Vec<u8>)> {
    let tool = if name.ends_with(".ko.xz") {
        Some("xz")
    } else if name.ends_with(".ko.zst") {
        Some("zstd")
    } else if name.ends_with(".ko.gz") {
        Some("gzip")
    } else {
        None
    };
    let plain = format!("{}.ko", name.split(".ko").next().unwrap_or(name));
    let bytes = match tool {
        None => fs::read(src)?,
        Some(tool) => {
            let out = Command::new(tool)
                .args(["-dc"])
                .arg(src)
                .output()
                .with_context(|| format!("{tool} is needed to unpack {}", src.display()))?;
            if !out.status.success() {
                bail!("{tool} -dc {} failed", src.display());
            }
            out.stdout
        }
    };
    Ok((plain, bytes))
}

/// Whether an ELF file has no program interpreter (is statically linked).
fn is_static_elf(path: &Path) -> Result<bool> {
    let data = fs::read(path).with_context(|| format!("read {}", path.display()))?;
    if data.len() < 64 || &data[..4] != b"\x7fELF" || data[4] != 2 {
        return Ok(false);
    }
    let u16_at = |o: usize| u16::from_le_bytes([data[o], data[o + 1]]) as usize;
    let u64_at = |o: usize| {
        let mut b = [0u8; 8];
        b.copy_from_slice(&data[o..o + 8]);
        u64::from_le_bytes(b) as usize
    };
    let (phoff, phentsize, phnum) = (u64_at(0x20), u16_at(0x36), u16_at(0x38));
    for i in 0..phnum {
        let o = phoff + i * phentsize;
        if o + 4 > data.len() {
            return Ok(false);
        }
        if u32::from_le_bytes([data[o], data[o + 1], data[o + 2], data[o + 3]]) == 3 {
            return Ok(false); // PT_INTERP
        }
    }
    Ok(true)
}

fn set_mode(path: &Path, mode: u32) -> Result<()> {
    use std::os::unix::fs::PermissionsExt;
    fs::set_permissions(path, fs::Permissions::from_mode(mode))?;
    Ok(())
}

/// The workspace's target directory, as cargo would pick it.
fn target_dir(cwd: &Path) -> Result<PathBuf> {
    if let Some(dir) = std::env::var_os("CARGO_TARGET_DIR") {
        return Ok(cwd.join(dir));
    }
    let root = Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .context("workspace root")?;
    Ok(root.join("target"))
}

#[cfg(test)]
mod tests {
    use super::*;

    const DEP: &str = "\
kernel/drivers/virtio/virtio.ko: kernel/drivers/virtio/virtio_ring.ko
kernel/drivers/virtio/virtio_ring.ko:
kernel/drivers/virtio/virtio_pci.ko: kernel/drivers/virtio/virtio.ko kernel/drivers/virtio/virtio_ring.ko
kernel/net/can/can-raw.ko.xz: kernel/net/can/can.ko.xz
kernel/net/can/can.ko.xz:
";

    #[test]
    fn modules_load_dependencies_first() {
        let order = resolve_modules(DEP, "", &["virtio_pci", "can_raw"]).unwrap();
        assert_eq!(
            order,
            [
                "kernel/drivers/virtio/virtio_ring.ko",
                "kernel/drivers/virtio/virtio.ko",
                "kernel/drivers/virtio/virtio_pci.ko",
                "kernel/net/can/can.ko.xz",
                "kernel/net/can/can-raw.ko.xz",
            ]
        );
    }

    #[test]
    fn builtin_modules_are_skipped_and_unknown_ones_named() {
        let order = resolve_modules(DEP, "kernel/fs/9p/9p.ko\n", &["9p"]).unwrap();
        assert!(order.is_empty());
        let err = resolve_modules(DEP, "", &["vcan"]).unwrap_err();
        assert!(err.to_string().contains("vcan"), "{err}");
    }

    #[test]
    fn run_script_quotes_arguments() {
        let dir = std::env::temp_dir().join(format!("xtask-test-{}", std::process::id()));
        fs::create_dir_all(&dir).unwrap();
        let req = Request {
            argv: vec!["echo".into(), "it's $HOME".into()],
            cwd: "/work dir".into(),
            timeout: Duration::from_secs(1),
            mode: super::super::request::Mode::Vm,
            mem_mib: 512,
            verbose: false,
            capture_stdout: false,
            systemd: false,
            setup: None,
        };
        write_run_script(&req, &dir).unwrap();
        let script = fs::read_to_string(dir.join("run.sh")).unwrap();
        assert!(script.contains("cd '/work dir' || exit 125"));
        assert!(
            script.ends_with("exec 'echo' 'it'\\''s $HOME'\n"),
            "{script}"
        );
        fs::remove_dir_all(dir).unwrap();
    }

    #[test]
    fn this_busybox_check_reads_elf_headers() {
        // /bin/sh on Debian is dynamically linked dash.
        if Path::new("/bin/dash").exists() {
            assert!(!is_static_elf(Path::new("/bin/dash")).unwrap());
        }
    }
}
