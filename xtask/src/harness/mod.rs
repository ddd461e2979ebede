//! The vcan harness: run a command with real `vcan0` and `vcan1` up.
//!
//! Two paths, one contract. The *native* path uses this kernel's vcan inside a private network
//! namespace (`unshare --net --map-root-user`), so the host's interfaces are never touched and no
//! root is needed once the `vcan` module is loaded. The *VM* path boots Debian's packaged kernel
//! under `qemu-system-x86_64 -accel tcg` with the host root shared read-only over 9p, for kernels
//! without CAN. Either way the command's exit status and output come back unchanged, a time limit
//! kills a hung run, nothing is left running, and no stdin is read.

mod native;
mod request;
mod vm;

use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};

pub use native::available as native_available;
pub use request::{note, Mode, Request, HARNESS_ENV};
pub use vm::{check_parts as vm_check_parts, PACKAGES as VM_PACKAGES};

/// The harness options `vcan`, `test` and `powerup` share.
#[derive(Debug, Clone, clap::Args)]
pub struct Opts {
    /// `native` uses this kernel's vcan in a private network namespace (unshare); `vm` boots
    /// Debian's kernel under qemu-system-x86_64 -accel tcg with the host root shared read-only;
    /// `auto` picks native when it can and the VM when it must.
    #[arg(long, value_enum, default_value = "auto")]
    pub mode: Mode,
    /// Time limit of the whole run, in whole seconds: it only catches hangs.
    #[arg(long, value_name = "SECS", default_value_t = 1200)]
    pub timeout: u64,
    /// The guest's memory (VM path).
    #[arg(long = "mem", value_name = "MIB", default_value_t = 3072)]
    pub mem_mib: u32,
    /// Show the guest's console and where its files are.
    #[arg(long, short)]
    pub verbose: bool,
}

impl Opts {
    /// A request to run `argv` from the current directory with these options (no systemd, the
    /// command's stdout passed through).
    pub fn request(&self, argv: Vec<String>) -> Result<Request> {
        Ok(Request {
            argv,
            cwd: std::env::current_dir().context("current directory")?,
            timeout: Duration::from_secs(self.timeout),
            mode: self.mode,
            mem_mib: self.mem_mib,
            verbose: self.verbose,
            capture_stdout: false,
            systemd: false,
            setup: None,
        })
    }
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

/// Runs the request on the path its mode allows, failing loudly when neither is possible.
pub fn run(req: &Request) -> Result<Outcome> {
    let start = Instant::now();
    if req.systemd && req.mode == Mode::Native {
        bail!("--systemd needs the VM path: systemd must be PID 1");
    }
    let mode = if req.systemd { Mode::Vm } else { req.mode };
    let path = match mode {
        Mode::Native => {
            if let Err(why) = native::available() {
                bail!("native vcan is not available: {why}");
            }
            "native"
        }
        Mode::Vm => "vm",
        Mode::Auto => match native::available() {
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
        "native" => native::run(req)?,
        _ => vm::run(req)?,
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn opts_default_as_documented() {
        use clap::Parser;
        #[derive(clap::Parser)]
        struct Cli {
            #[command(flatten)]
            opts: Opts,
        }
        let o = Cli::try_parse_from(["x"]).unwrap().opts;
        assert_eq!(
            (o.mode, o.timeout, o.mem_mib, o.verbose),
            (Mode::Auto, 1200, 3072, false)
        );
        let o = Cli::try_parse_from(["x", "--mode", "vm", "--timeout", "60", "-v"])
            .unwrap()
            .opts;
        assert_eq!((o.mode, o.timeout, o.verbose), (Mode::Vm, 60, true));
        assert!(Cli::try_parse_from(["x", "--mode", "kvm"]).is_err());
        assert!(Cli::try_parse_from(["x", "--timeout", "1.5"]).is_err());
    }
}
