//! `cargo xtask bench`: the comparisons BENCHMARKS.md's goals name, measured in one run and
//! written to `BENCHMARKS.md`.
//!
//! Parts (all by default, or pick with `--only calib,firmware,daemon,ingest`):
//!
//! * `calib` ([`calib`]): calib-core's LS against `scipy.optimize.least_squares` and Ceres Solver
//!   on the same exported datasets (`calib-core/examples/export_dataset.rs`,
//!   `benches/scipy_ls.py`, run from a venv under `<target>/bench-venv` that this command creates
//!   and fills from `benches/requirements.txt`; `benches/ceres/ceres_ls.cc`, built by [`ceres`]
//!   against libceres-dev), all pinned to CPU 0 with `taskset -c 0`, the goals judged on paired
//!   rounds; LS + our EM at K = 1,000 and 6,000; the per-sample kernel costs that bound the LS
//!   time, and the normal-equation update against this core's measured peak.
//! * `firmware` ([`firmware`], [`stack`]): `benches/firmware` (its own workspace) built for `thumbv7em-none-eabihf`:
//!   section sizes (`size -A`), code size per crate (`nm -S`), the peak stack measured by stack
//!   painting while the LS runs under `qemu-system-arm -machine mps2-an386` (a Cortex-M4F), and
//!   a static bound from the per-function frames of a nightly `-Z emit-stack-sizes` build
//!   walked over the call graph read from the disassembly.
//! * `daemon` ([`daemon`]): the daemon natively: the power-up latency of demo sessions on the
//!   in-process bus, and the CPU of `exocald offline` on a 6,000-sample CSV with its report.
//! * `ingest` ([`ingest`]): the daemon against `candump -l` on vcan inside the harness.
//!
//! Every figure is a median of repeated runs and every comparison a ratio; the report gives
//! each figure's command, the machine (nproc, CPU model, kernel, load average) and the date.
//! Nothing here is a pass/fail test: goals are reported as met or not, with what bounds them.
//! Exit status: 0 when every part ran (whatever the goals say), 1 when a part failed (its
//! section then says why), 2 on bad arguments.
//!
//! [`common`] holds what the parts share, [`report`] writes the file; no part imports another
//! (firmware uses the stack analyser, calib the Ceres build).

mod calib;
mod ceres;
mod common;
mod daemon;
mod firmware;
mod ingest;
mod report;
mod stack;

use std::path::PathBuf;
use std::process::{Command, Stdio};

use anyhow::{Context, Result};

use crate::paths;
use common::{Ctx, Section};

/// A part of the benchmark.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Part {
    /// calib-core against scipy and Ceres, LS + EM, the kernels.
    Calib,
    /// calib-core's LS path on thumbv7em-none-eabihf: sizes, measured and bounded stack.
    Firmware,
    /// The daemon natively: power-up latency on the in-process bus, offline CPU.
    Daemon,
    /// The daemon's ingest against candump on vcan, its RSS, power-up latency.
    Ingest,
}

/// Benchmarks against scipy, Ceres and candump, firmware memory; writes BENCHMARKS.md.
///
/// Measure calib-core against scipy and Ceres, its firmware memory use, and the daemon's ingest against
/// candump; write BENCHMARKS.md (long: not part of `test`).
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Fewer repeats, K up to 6,000.
    #[arg(long)]
    pub quick: bool,
    /// The parts to run, comma-separated (default: all).
    #[arg(long, value_enum, value_delimiter = ',', value_name = "PARTS")]
    pub only: Vec<Part>,
    /// Where to write the report (default: BENCHMARKS.md in the workspace).
    #[arg(long, value_name = "FILE")]
    pub out: Option<PathBuf>,
}

impl Args {
    /// The command line as given, for the report's first line.
    fn shown(&self) -> Vec<String> {
        let mut v = Vec::new();
        if self.quick {
            v.push("--quick".to_string());
        }
        if !self.only.is_empty() {
            let names: Vec<&str> = self.only.iter().map(|p| p.name()).collect();
            v.extend(["--only".to_string(), names.join(",")]);
        }
        if let Some(out) = &self.out {
            v.extend(["--out".to_string(), out.display().to_string()]);
        }
        v
    }
}

impl Part {
    /// Every part, in the order BENCHMARKS.md shows them.
    const ALL: [Part; 4] = [Part::Calib, Part::Firmware, Part::Daemon, Part::Ingest];

    fn name(self) -> &'static str {
        match self {
            Part::Calib => "calib",
            Part::Firmware => "firmware",
            Part::Daemon => "daemon",
            Part::Ingest => "ingest",
        }
    }

    fn title(self) -> &'static str {
        match self {
            Part::Calib => calib::TITLE,
            Part::Firmware => firmware::TITLE,
            Part::Daemon => daemon::TITLE,
            Part::Ingest => ingest::TITLE,
        }
    }
}

pub fn run(args: Args) -> Result<u8> {
    let root = paths::workspace_root();
    let parts = if args.only.is_empty() {
        Part::ALL.to_vec()
    } else {
        args.only.clone()
    };
    let quick = args.quick;
    let out = args
        .out
        .clone()
        .unwrap_or_else(|| root.join("BENCHMARKS.md"));
    let target = paths::target_dir();
    let pin = if Command::new("taskset")
        .arg("-V")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success())
    {
        vec!["taskset".to_string(), "-c".into(), "0".into()]
    } else {
        Vec::new()
    };
    let ctx = Ctx {
        cargo: paths::cargo(),
        root,
        target,
        quick,
        pin,
    };
    let machine_before = report::machine(&ctx);
    let mut sections = Vec::new();
    let mut failed = false;
    for part in &parts {
        eprintln!("==> bench: {}", part.name());
        let result = match part {
            Part::Calib => calib::measure(&ctx),
            Part::Firmware => firmware::measure(&ctx),
            Part::Daemon => daemon::measure(&ctx),
            Part::Ingest => ingest::measure(&ctx),
        };
        match result {
            Ok(s) => sections.push(s),
            Err(e) => {
                failed = true;
                eprintln!("bench {}: {e:#}", part.name());
                sections.push(Section {
                    title: part.title(),
                    body: format!(
                        "**This part failed to run:** `{}`\n",
                        format!("{e:#}").replace('`', "'")
                    ),
                    goals: Vec::new(),
                });
            }
        }
    }
    let load_after = report::read_trimmed("/proc/loadavg");
    for s in &mut sections {
        s.body = s
            .body
            .replace(ctx.target.to_string_lossy().as_ref(), "target")
            .replace(&format!("{}/", ctx.root.to_string_lossy()), "");
    }
    let ran: Vec<report::Rendered<'_>> = parts
        .iter()
        .zip(&sections)
        .map(|(p, s)| report::Rendered {
            part: p.name(),
            section: s,
        })
        .collect();
    let order: Vec<(&str, &str)> = Part::ALL.iter().map(|p| (p.name(), p.title())).collect();
    let previous = std::fs::read_to_string(&out).ok();
    let md = report::render(
        &ctx,
        &machine_before,
        &load_after,
        &ran,
        &order,
        &args.shown(),
        previous.as_deref(),
    );
    std::fs::write(&out, md).with_context(|| format!("writing {}", out.display()))?;
    eprintln!("==> wrote {}", out.display());
    Ok(u8::from(failed))
}
