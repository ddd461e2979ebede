//! The vcan harness: run a command with real `vcan0` and `vcan1` up.
//!
//! Two paths, one contract. The *native* path uses this kernel's vcan inside a private network
//! namespace (`unshare --net --map-root-user`), so the host's interfaces are never touched and no
//! root is needed once the `vcan` module is loaded. The *VM* path boots Debian's packaged kernel
//! under `qemu-system-x86_64 -accel tcg` with the host root shared read-only over 9p, for kernels
//! without CAN. Either way the command's exit status and output come back unchanged, a time limit
//! kills a hung run, nothing is left running, and no stdin is read.

use std::io::Write;
use std::path::PathBuf;
use std::str::FromStr;
use std::time::{Duration, Instant};

use anyhow::{bail, Result};

/// Which path to take.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Mode {
    /// Native when this kernel can, the VM when it must.
    Auto,
    Native,
    Vm,
}

impl FromStr for Mode {
    type Err = anyhow::Error;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "auto" => Ok(Mode::Auto),
            "native" => Ok(Mode::Native),
            "vm" => Ok(Mode::Vm),
            other => bail!("--mode must be auto, native or vm, not {other:?}"),
        }
    }
}

/// One command to run under the harness.
#[derive(Debug, Clone)]
pub struct Request {
    pub argv: Vec<String>,
    pub cwd: PathBuf,
    pub timeout: Duration,
    pub mode: Mode,
    pub mem_mib: u32,
    pub verbose: bool,
    /// Keep a copy of the command's stdout (it is still forwarded as it comes).
    pub capture_stdout: bool,
    /// Boot systemd as PID 1 (VM only) and run the command from a unit once the system is up.
    pub systemd: bool,
    /// With `systemd`: a script run as root in the guest's root before systemd starts (install
    /// units, create the vcan `.netdev`, enable services).
    pub setup: Option<PathBuf>,
}

/// What came back.
#[derive(Debug)]
pub struct Outcome {
    /// The command's exit status; 128 + signal if a signal ended it; 124 on time-out.
    pub code: u8,
    /// Where it ran: "native" or "vm".
    pub path: &'static str,
    /// The command's stdout when `capture_stdout` was set.
    pub stdout: Vec<u8>,
    pub elapsed: Duration,
}

/// Exit status reported when the time limit killed the run (as coreutils `timeout` does).
pub const TIMED_OUT: u8 = 124;

/// Runs the request on the path its mode allows, failing loudly when neither is possible.
pub fn run(req: &Request) -> Result<Outcome> {
    let start = Instant::now();
    if req.systemd && req.mode == Mode::Native {
        bail!("--systemd needs the VM path: systemd must be PID 1");
    }
    let mode = if req.systemd { Mode::Vm } else { req.mode };
    let path = match mode {
        Mode::Native => {
            if let Err(why) = crate::native::available() {
                bail!("native vcan is not available: {why}");
            }
            "native"
        }
        Mode::Vm => "vm",
        Mode::Auto => match crate::native::available() {
            Ok(()) => "native",
            Err(why) => {
                note(&format!("no native vcan ({why}); using the QEMU guest"));
                "vm"
            }
        },
    };
    note(&format!(
        "running {:?} with vcan0, vcan1 ({path})",
        req.argv
    ));
    let (code, stdout) = match path {
        "native" => crate::native::run(req)?,
        _ => crate::vm::run(req)?,
    };
    let elapsed = start.elapsed();
    note(&format!(
        "{path} run finished in {:.1} s with exit status {code}",
        elapsed.as_secs_f64()
    ));
    Ok(Outcome {
        code,
        path,
        stdout,
        elapsed,
    })
}

/// A harness message on stderr, so it never mixes into the command's stdout.
pub fn note(msg: &str) {
    let _ = writeln!(std::io::stderr(), "[vcan-harness] {msg}");
}

/// Quotes a string for POSIX `sh`.
pub fn shell_quote(s: &str) -> String {
    format!("'{}'", s.replace('\'', r"'\''"))
}

/// Exit status of a finished child as the shell reports it.
pub fn exit_code(status: std::process::ExitStatus) -> u8 {
    use std::os::unix::process::ExitStatusExt;
    match (status.code(), status.signal()) {
        (Some(code), _) => code as u8,
        (None, Some(sig)) => 128u8.wrapping_add(sig as u8),
        _ => 1,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shell_quote_survives_single_quotes() {
        assert_eq!(shell_quote("it's"), r"'it'\''s'");
        assert_eq!(shell_quote(""), "''");
    }

    #[test]
    fn mode_parses_and_rejects() {
        assert_eq!("vm".parse::<Mode>().unwrap(), Mode::Vm);
        assert!("kvm".parse::<Mode>().is_err());
    }
}
