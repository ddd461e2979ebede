//! The native path: this kernel's vcan, in a private network namespace.
//!
//! `unshare --net --map-root-user` gives the command a network namespace of its own, where it is
//! root over the namespace (and nothing else): vcan0 and vcan1 are created there and vanish with
//! it, so the host's interfaces are never touched. Only loading the `vcan` module needs real root;
//! when we are root we load it, otherwise we say so.

use std::io::{Read, Write};
use std::os::unix::process::CommandExt;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{Context, Result};

use super::request::{note, Request, TIMED_OUT};
use crate::host;
use crate::process::exit_code;

/// Creates the interfaces, then execs the command given as "$@".
const SETUP: &str = "set -e
ip link set lo up
for i in vcan0 vcan1; do ip link add dev \"$i\" type vcan; ip link set \"$i\" up; done
export EXOCAL_VCAN_HARNESS=native
exec \"$@\"";

/// Whether the native path can work here; the reason when it cannot.
pub fn available() -> Result<(), String> {
    // SAFETY: plain socket(2) call; the descriptor is closed right away.
    #[allow(unsafe_code)]
    let fd = unsafe { libc::socket(libc::AF_CAN, libc::SOCK_RAW, libc::CAN_RAW) };
    if fd < 0 {
        let err = std::io::Error::last_os_error();
        return Err(format!(
            "socket(AF_CAN) failed: {err} (kernel built without CONFIG_CAN, or the can module is missing)"
        ));
    }
    // SAFETY: `fd` is a descriptor we own.
    #[allow(unsafe_code)]
    unsafe {
        libc::close(fd)
    };

    if !std::path::Path::new("/sys/module/vcan").exists() && host::is_root() {
        let _ = Command::new("modprobe")
            .arg("vcan")
            .stdin(Stdio::null())
            .stderr(Stdio::null())
            .status();
    }
    let probe = Command::new("unshare")
        .args(["--net", "--map-root-user", "--", "sh", "-c"])
        .arg("ip link add dev vcan0 type vcan && ip link add dev vcan1 type vcan")
        .stdin(Stdio::null())
        .output();
    match probe {
        Err(err) => Err(format!("cannot run unshare (util-linux): {err}")),
        Ok(out) if !out.status.success() => Err(format!(
            "cannot create vcan in a private network namespace: {} (is the vcan module loaded? \
             `sudo modprobe vcan`; are unprivileged user namespaces enabled?)",
            String::from_utf8_lossy(&out.stderr).trim()
        )),
        Ok(_) => Ok(()),
    }
}

/// Runs the request in a fresh network namespace with vcan0 and vcan1 up.
pub fn run(req: &Request) -> Result<(u8, Vec<u8>)> {
    let mut cmd = Command::new("unshare");
    cmd.args(["--net", "--map-root-user", "--", "sh", "-c", SETUP, "sh"])
        .args(&req.argv)
        .current_dir(&req.cwd)
        .stdin(Stdio::null())
        .stdout(if req.capture_stdout {
            Stdio::piped()
        } else {
            Stdio::inherit()
        })
        .process_group(0);
    // SAFETY: prctl is async-signal-safe; it only asks the kernel to kill the child if we die,
    // so that a killed harness leaves nothing running.
    #[allow(unsafe_code)]
    unsafe {
        cmd.pre_exec(|| {
            libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL);
            Ok(())
        });
    }
    let mut child = cmd.spawn().context("spawn unshare")?;
    let pgid = child.id() as i32;
    let tee = child.stdout.take().map(|mut out| {
        std::thread::spawn(move || {
            let mut all = Vec::new();
            let mut buf = [0u8; 8192];
            while let Ok(n) = out.read(&mut buf) {
                if n == 0 {
                    break;
                }
                all.extend_from_slice(&buf[..n]);
                let mut stdout = std::io::stdout().lock();
                let _ = stdout.write_all(&buf[..n]);
                let _ = stdout.flush();
            }
            all
        })
    });
    let deadline = Instant::now() + req.timeout;
    let code = loop {
        if let Some(status) = child.try_wait()? {
            break exit_code(status);
        }
        if Instant::now() >= deadline {
            note(&format!(
                "time limit of {} s reached: killing the command",
                req.timeout.as_secs()
            ));
            // SAFETY: signals the process group we created for the child.
            #[allow(unsafe_code)]
            unsafe {
                libc::kill(-pgid, libc::SIGKILL)
            };
            let _ = child.wait();
            break TIMED_OUT;
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    // Whatever the command left behind in its group goes with it.
    // SAFETY: as above; the group may already be gone (ESRCH is fine).
    #[allow(unsafe_code)]
    unsafe {
        libc::kill(-pgid, libc::SIGKILL)
    };
    let stdout = tee
        .map(|t| t.join().unwrap_or_default())
        .unwrap_or_default();
    Ok((code, stdout))
}
