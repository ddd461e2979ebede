//! Firmware memory: `benches/firmware` (its own workspace) built for `thumbv7em-none-eabihf`:
//! section sizes (`size -A`), code size per crate (`nm -S`), the peak stack measured by stack
//! painting while the LS runs under `qemu-system-arm -machine mps2-an386` (a Cortex-M4F), and the
//! static bound of [`super::stack`].

use std::collections::{BTreeMap, HashMap};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use anyhow::{Context, Result};

use super::common::{capture, json_lines, run, s, show, tool, Ctx, Goal, Section};
use super::stack;
use crate::paths;

pub const THUMB: &str = "thumbv7em-none-eabihf";

pub fn firmware_build(ctx: &Ctx, nightly: bool) -> Result<(PathBuf, String)> {
    let dir = ctx.root.join("benches/firmware");
    let target_dir = ctx.target.join(if nightly {
        "bench-firmware-nightly"
    } else {
        "bench-firmware"
    });
    let mut c = Command::new("cargo");
    if nightly {
        c.arg("+nightly");
    }
    c.current_dir(&dir)
        .env_remove("CARGO_ENCODED_RUSTFLAGS")
        .env_remove("RUSTUP_TOOLCHAIN")
        .env("CARGO_TARGET_DIR", &target_dir)
        .args(["build", "--release"]);
    if nightly {
        c.env("RUSTFLAGS", "-C link-arg=-Tlink.x -Z emit-stack-sizes");
    } else {
        c.env_remove("RUSTFLAGS");
    }
    let shown = format!(
        "(cd benches/firmware && {})",
        show(&c).replace(&ctx.target.to_string_lossy().to_string(), "target")
    );
    run(&mut c)?;
    Ok((target_dir.join(THUMB).join("release/calib-firmware"), shown))
}

/// `name → size` of the ELF sections from `size -A`.
pub fn sections(size_tool: &str, elf: &Path) -> Result<BTreeMap<String, u64>> {
    let out = capture(Command::new(size_tool).arg("-A").arg(elf))?;
    Ok(out
        .lines()
        .filter_map(|l| {
            let mut w = l.split_whitespace();
            let (name, size) = (w.next()?, w.next()?.parse().ok()?);
            name.starts_with('.').then(|| (name.to_string(), size))
        })
        .collect())
}

/// Bytes per crate.
pub type CodeSizes = BTreeMap<&'static str, u64>;

/// Code bytes per crate, from `nm -C -S` (text symbols), and the data symbols.
pub fn code_by_crate(nm: &str, elf: &Path) -> Result<(CodeSizes, Vec<(String, u64)>)> {
    let out = capture(Command::new(nm).args(["-C", "-S", "--size-sort"]).arg(elf))?;
    let mut per = BTreeMap::new();
    let mut bss = Vec::new();
    for l in out.lines() {
        let mut w = l.splitn(4, ' ');
        let (Some(_addr), Some(size), Some(kind), Some(name)) =
            (w.next(), w.next(), w.next(), w.next())
        else {
            continue;
        };
        let Ok(size) = u64::from_str_radix(size, 16) else {
            continue;
        };
        match kind {
            "t" | "T" | "r" | "R" => {
                let bucket = classify(name);
                *per.entry(bucket).or_insert(0) += size;
            }
            "b" | "B" | "d" | "D" => bss.push((name.to_string(), size)),
            _ => {}
        }
    }
    Ok((per, bss))
}

pub fn classify(name: &str) -> &'static str {
    let n = name.trim_start_matches('<');
    if n.contains("calib_core") {
        "calib-core"
    } else if n.starts_with("nalgebra") {
        "nalgebra"
    } else if n.starts_with("libm") {
        "libm"
    } else if n.starts_with("__aeabi") || n.starts_with("compiler_builtins") || n.starts_with("__")
    {
        "compiler-builtins (soft f64, memcpy)"
    } else if n.starts_with("core::")
        || n.starts_with("<core::")
        || n.starts_with("<u")
        || n.starts_with("<usize")
    {
        "core (fmt, panics, sort)"
    } else {
        "firmware, cortex-m-rt, semihosting, vector table"
    }
}

/// What the firmware printed under QEMU.
pub struct FirmwareRun {
    stack_used: u64,
    stack_painted: u64,
    iterations: String,
    rank: String,
    cost_bits: String,
}

/// Runs the firmware under `qemu-system-arm` (mps2-an386, a Cortex-M4F) and reads its line.
pub fn qemu_run(ctx: &Ctx, elf: &Path) -> Result<(FirmwareRun, String)> {
    let qemu = tool(&["qemu-system-arm"])
        .context("qemu-system-arm (apt-get install qemu-system-arm) runs the firmware")?;
    let mut q = Command::new(&qemu);
    q.args([
        "-machine",
        "mps2-an386",
        "-cpu",
        "cortex-m4",
        "-nographic",
        "-semihosting-config",
        "enable=on,target=native",
        "-kernel",
    ])
    .arg(elf)
    .stdin(Stdio::null());
    let shown = show(&q).replace(ctx.target.to_string_lossy().as_ref(), "target");
    let out = capture(&mut q)?;
    let line = out
        .lines()
        .find(|l| l.starts_with("FIRMWARE ok"))
        .with_context(|| format!("no result line from the firmware: {out}"))?;
    let field = |k: &str| -> Result<String> {
        line.split_whitespace()
            .find_map(|w| w.strip_prefix(k)?.strip_prefix('='))
            .map(str::to_string)
            .with_context(|| format!("no {k} in {line:?}"))
    };
    let run = FirmwareRun {
        stack_used: field("stack_used")?.parse().context("stack_used")?,
        stack_painted: field("stack_painted")?.parse().context("stack_painted")?,
        iterations: field("iterations")?,
        rank: field("rank")?,
        cost_bits: field("cost_bits")?,
    };
    Ok((run, shown))
}

/// This part's section title in the report.
pub const TITLE: &str = "Memory: calib-core's LS path on thumbv7em-none-eabihf";

pub fn measure(ctx: &Ctx) -> Result<Section> {
    let size_tool = tool(&["arm-none-eabi-size", "llvm-size"])?;
    let nm = tool(&["arm-none-eabi-nm", "llvm-nm"])?;
    let (elf, build_cmd) = firmware_build(ctx, false)?;
    let secs = sections(&size_tool, &elf)?;
    let (code, data_syms) = code_by_crate(&nm, &elf)?;
    let mut body = String::new();
    let mut goals = Vec::new();
    let get = |n: &str| secs.get(n).copied().unwrap_or(0);
    let flash = get(".vector_table") + get(".text") + get(".rodata") + get(".data");
    let ram_static = get(".data") + get(".bss") + get(".uninit");
    let dataset: u64 = data_syms
        .iter()
        .filter(|(n, _)| n.contains("SAMPLES"))
        .map(|(_, s)| s)
        .sum();
    let _ = writeln!(
        body,
        "`benches/firmware`: a `#![no_std]`, `#![no_main]` binary (cortex-m-rt, panic-halt, \
         semihosting for the one result line) that simulates 200 samples of the Section 4 scenario \
         (one every 0.1 s, with drift) into a static buffer and runs \
         `identify_ls::<7, 28>(&DhTable::paper_nominal(), samples, &LsOptions::paper())`. \
         Release profile: `opt-level = \"s\"`, fat LTO, one codegen unit, `panic = \"abort\"`. \
         f64 is emulated in software on the Cortex-M4F (single-precision FPU only).\n"
    );
    let _ = writeln!(body, "| section | bytes |\n|---|---|");
    for (name, size) in secs
        .iter()
        .filter(|(n, _)| !n.starts_with(".debug") && *n != ".comment" && *n != ".ARM.attributes")
    {
        let _ = writeln!(body, "| `{name}` | {size} |");
    }
    let _ = writeln!(
        body,
        "\nFlash {flash} bytes in all; static RAM {ram_static} bytes, of which {dataset} bytes are the \
         caller's 200-sample dataset (152 bytes per sample) and the rest the firmware's own: \
         **calib-core itself has no static data** (no `static`, no allocation).\n"
    );
    let _ = writeln!(
        body,
        "Code and read-only data per crate (`{nm} -C -S`):\n\n| crate | bytes |\n|---|---|"
    );
    let mut code: Vec<_> = code.into_iter().collect();
    code.sort_by_key(|c| std::cmp::Reverse(c.1));
    for (name, size) in &code {
        let _ = writeln!(body, "| {name} | {size} |");
    }
    // The run under QEMU: stack painting.
    let (run, qemu_cmd) = qemu_run(ctx, &elf)?;
    let measured = run.stack_used;
    let cost = u64::from_str_radix(run.cost_bits.trim_start_matches("0x"), 16)
        .map(f64::from_bits)
        .unwrap_or(f64::NAN);
    let mut twin = Command::new(paths::cargo());
    twin.current_dir(&ctx.root).args([
        "run",
        "-q",
        "--release",
        "-p",
        "calib-core",
        "--example",
        "export_dataset",
        "--",
        "--firmware-twin",
    ]);
    let twin_cmd = show(&twin);
    let host = json_lines(&capture(&mut twin)?);
    let host_bits = host
        .iter()
        .find(|v| s(v, "bench") == "calib-core-firmware-twin")
        .map(|v| s(v, "cost_bits").to_string())
        .unwrap_or_default();
    let _ = writeln!(
        body,
        "\n**Peak stack, measured**: {measured} bytes from reset to the end of the LS call (stack \
         painted down to {} bytes below its origin, so the measurement did not saturate), \
         under `qemu-system-arm -machine mps2-an386` (Cortex-M4F). The LS ran {} iterations, rank \
         {}, cost {cost:.10e} (bits `{}`); the same LS on the host (x86-64, hardware f64) gives \
         bits `{host_bits}`: {}.\n",
        run.stack_painted,
        run.iterations,
        run.rank,
        run.cost_bits,
        if host_bits == run.cost_bits {
            "bit-identical"
        } else {
            "**different**"
        }
    );
    // Static bound from a nightly build with .stack_sizes.
    let mut bound_cmds = Vec::new();
    match firmware_build(ctx, true) {
        Ok((nelf, ncmd)) => {
            bound_cmds.push(ncmd);
            let readobj = tool(&["llvm-readobj"])?;
            let objdump = tool(&["arm-none-eabi-objdump", "llvm-objdump"])?;
            bound_cmds.push(format!(
                "{readobj} --stack-sizes <elf>; {objdump} -d --no-show-raw-insn <elf>"
            ));
            let frames = stack::stack_sizes(&readobj, &nelf)?;
            let graph = stack::call_graph(&objdump, &nelf)?;
            let names: Vec<String> = graph.keys().cloned().collect();
            let pretty: HashMap<String, String> =
                names.iter().cloned().zip(stack::demangle(&names)).collect();
            let is_reporting = |n: &str| {
                let p = pretty.get(n).map(String::as_str).unwrap_or(n);
                p.contains("panic")
                    || p.contains("semihosting")
                    || p.contains("core::fmt")
                    || p.contains("::fmt")
                    || p.contains("rust_begin_unwind")
            };
            let b = stack::stack_bound(&graph, &frames, "Reset", &is_reporting);
            let (nrun, _) = qemu_run(ctx, &nelf)?;
            let _ = writeln!(
                body,
                "**Peak stack, static bound**: {} bytes for the nightly build (whose measured peak, \
                 by the same painting under QEMU, is {} bytes): the deepest path of the call graph \
                 read from the disassembly, from `Reset`, with each function's frame from `-Z emit-stack-sizes` \
                 (nightly) or, for precompiled compiler-builtins without that section, from its \
                 prologue (`push`/`vpush`/`sub sp`). Paths into panics and the result print \
                 (core::fmt, semihosting) are left out: they do not return to the LS (panic-halt) or \
                 run after it. No interrupts are enabled. Recursion found: {}. Indirect calls on the \
                 walked paths: {}.\n",
                b.bytes,
                nrun.stack_used,
                if b.cycles.is_empty() { "none".to_string() } else { b.cycles.iter().map(|c| pretty.get(c).cloned().unwrap_or(c.clone())).collect::<Vec<_>>().join(", ") },
                if b.indirect.is_empty() { "none".to_string() } else { b.indirect.iter().map(|c| pretty.get(c).cloned().unwrap_or(c.clone())).collect::<Vec<_>>().join(", ") }
            );
            let _ = writeln!(
                body,
                "| deepest path (caller first) | frame (bytes) |\n|---|---|"
            );
            for (name, own, from_prologue) in &b.path {
                let _ = writeln!(
                    body,
                    "| `{}` | {own}{} |",
                    pretty.get(name).cloned().unwrap_or(name.clone()),
                    if *from_prologue { " (prologue)" } else { "" }
                );
            }
            // The largest frames on the LS path.
            let mut big: Vec<(String, u64)> = frames
                .iter()
                .filter(|(_, s)| **s >= 512)
                .map(|(n, s)| (pretty.get(n).cloned().unwrap_or_else(|| n.clone()), *s))
                .collect();
            big.sort_by_key(|c| std::cmp::Reverse(c.1));
            let _ = writeln!(body, "\nFrames of 512 bytes or more (`identify_ls` is inlined into `main`):\n\n| function | frame (bytes) |\n|---|---|");
            for (n, s) in big {
                let _ = writeln!(body, "| `{n}` | {s} |");
            }
            let _ = writeln!(body);
            goals.push(Goal {
                what: "calib-core's LS path: static and stack use on thumbv7em-none-eabihf stated".into(),
                met: true,
                detail: format!(
                    "no static data of its own; {flash} B flash for the whole firmware; peak stack {measured} B measured, {} B static bound",
                    b.bytes
                ),
            });
        }
        Err(e) => {
            let _ = writeln!(body, "**Static stack bound: not computed**: the nightly build with `-Z emit-stack-sizes` failed ({e:#}); the measured peak above stands alone.\n");
            goals.push(Goal {
                what: "calib-core's LS path: static and stack use on thumbv7em-none-eabihf stated"
                    .into(),
                met: true,
                detail: format!(
                    "peak stack {measured} B measured; no static bound (nightly build failed)"
                ),
            });
        }
    }
    let _ = writeln!(
        body,
        "Reproduce:\n\n```sh\n{build_cmd}\n{size_tool} -A target/bench-firmware/{THUMB}/release/calib-firmware\n{qemu_cmd}\n{twin_cmd}\n{}\n```\n",
        bound_cmds.join("\n")
    );
    Ok(Section {
        title: TITLE,
        body,
        goals,
    })
}
