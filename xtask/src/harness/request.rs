//! What a run under the vcan harness asks for and what the paths report: the request, the
//! mode, the time-out status, the harness's own messages.
//!
//! A leaf module: it imports no other xtask module, so both paths ([`super::native`],
//! [`super::vm`]) and the dispatch ([`super`]) can use it.

use std::io::Write;
use std::path::PathBuf;
use std::time::Duration;

/// Set by the harness inside its namespace or guest: `native` or `vm`.
pub const HARNESS_ENV: &str = "EXOCAL_VCAN_HARNESS";

/// Which path to take.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Mode {
    /// Native when this kernel can, the VM when it must.
    Auto,
    /// This kernel's vcan in a private network namespace.
    Native,
    /// Debian's kernel under qemu-system-x86_64 -accel tcg.
    Vm,
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

/// Exit status reported when the time limit killed the run (as coreutils `timeout` does).
pub const TIMED_OUT: u8 = 124;

/// A harness message on stderr, so it never mixes into the command's stdout.
pub fn note(msg: &str) {
    let _ = writeln!(std::io::stderr(), "[vcan-harness] {msg}");
}
