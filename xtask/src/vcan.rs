//! `cargo xtask vcan [OPTIONS] -- CMD [ARG..]`: run CMD with real vcan0 and vcan1 up (see
//! [`crate::harness`]); its exit status and output come back unchanged.

use std::path::PathBuf;

use anyhow::Result;

use crate::harness;

/// Run CMD with real vcan0 and vcan1 up (native netns or QEMU guest).
///
/// Run CMD with real vcan0 and vcan1 up. `native` uses this kernel's vcan in a private network
/// namespace (unshare); `vm` boots Debian's kernel under qemu-system-x86_64 -accel tcg with the
/// host root shared read-only. The exit status and output of CMD come back unchanged (128 +
/// signal if it was killed, 124 on time-out).
#[derive(Debug, clap::Args)]
pub struct Args {
    #[command(flatten)]
    pub harness: harness::Opts,
    /// Boot systemd as PID 1 in the guest (host root read-only under a tmpfs overlay) and run
    /// CMD from a unit once multi-user.target is up; the boot's journal is kept for the caller.
    #[arg(long)]
    pub systemd: bool,
    /// With --systemd: a script run as root in the guest's root before boot (install units,
    /// enable services; vcan0/vcan1 are then the script's to create, e.g. with a .netdev).
    #[arg(long, value_name = "SCRIPT", requires = "systemd")]
    pub setup: Option<PathBuf>,
    /// The command and its arguments (after `--`, or from the first word that is no option).
    #[arg(required = true, trailing_var_arg = true, allow_hyphen_values = true)]
    pub command: Vec<String>,
}

pub fn run(args: Args) -> Result<u8> {
    let mut req = args.harness.request(args.command)?;
    req.systemd = args.systemd;
    req.setup = args.setup;
    Ok(harness::run(&req)?.code)
}
