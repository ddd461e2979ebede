//! The daemon natively: the power-up latency of a whole session on
//! the in-process bus (`exocald demo`), and the CPU of `exocald offline` on a 6,000-sample CSV
//! with its HTML report. Both pinned to CPU 0, the release binary.
//!
//! The latency is the daemon's own figure (its summary line "end of collection to every table
//! verified", `exocald::shell::summary::Latency`): this machine's real time computing (alignment, LS,
//! EM, validation, refit, report, push) plus the simulated time the emulated bus and nodes
//! took. The offline CPU is the child's user + system time (`getrusage(RUSAGE_CHILDREN)` around
//! each run).

use std::fmt::Write as _;
use std::process::Command;
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};

use super::common::{capture, cargo_release, pinned, run, show, Ctx, Goal, Section};

/// This part's section title in the report.
pub const TITLE: &str = "The daemon natively: power-up latency and offline CPU";

/// The latency goal (s) and the offline CPU goal (s).
const LATENCY_GOAL_S: f64 = 1.0;
const OFFLINE_GOAL_S: f64 = 0.5;
/// Samples in the offline CSV (60 s of the paper's scenario at 100 Hz).
const OFFLINE_SAMPLES: &str = "6000";

/// One demo session's latency line: (total, computing, emulated bus and nodes), s.
fn latency_line(stdout: &str) -> Option<(f64, f64, f64)> {
    let line = stdout
        .lines()
        .find_map(|l| l.strip_prefix("end of collection to every table verified: "))?;
    let nums: Vec<f64> = line
        .split(|c: char| !(c.is_ascii_digit() || c == '.'))
        .filter_map(|w| w.parse().ok())
        .collect();
    match nums[..] {
        [total, real, session] => Some((total, real, session)),
        _ => None,
    }
}

/// User + system CPU of the children this process has waited for.
fn children_cpu() -> Duration {
    let mut usage = std::mem::MaybeUninit::<libc::rusage>::zeroed();
    // SAFETY: getrusage writes a whole `rusage` into the pointer it is given; RUSAGE_CHILDREN
    // is a valid `who`. The all-zero value is a valid `rusage` if it fails.
    #[allow(unsafe_code)]
    let usage = unsafe {
        libc::getrusage(libc::RUSAGE_CHILDREN, usage.as_mut_ptr());
        usage.assume_init()
    };
    let tv = |t: libc::timeval| {
        Duration::from_secs(t.tv_sec.max(0) as u64) + Duration::from_micros(t.tv_usec.max(0) as u64)
    };
    tv(usage.ru_utime) + tv(usage.ru_stime)
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

pub fn measure(ctx: &Ctx) -> Result<Section> {
    let (seeds, repeats) = if ctx.quick { (3, 3) } else { (5, 7) };
    let more = ["--bin", "exocald", "--example", "scenario_csv"];
    let mut build = cargo_release(ctx, "build", "exocald", &more);
    let build_cmd = show(&build);
    run(&mut build)?;
    let exocald = ctx.target.join("release/exocald");
    let data = ctx.target.join("bench/daemon");
    std::fs::create_dir_all(&data).with_context(|| format!("creating {}", data.display()))?;

    // Power-up latency: demo sessions, one per seed.
    let mut latencies = Vec::new();
    let mut demo_cmd = String::new();
    for seed in 1..=seeds {
        let out = data.join(format!("demo-seed{seed}"));
        let _ = std::fs::remove_dir_all(&out);
        let mut demo = pinned(ctx, &exocald);
        demo.current_dir(&ctx.root)
            .args(["demo", "--seed", &seed.to_string(), "--output"])
            .arg(&out);
        demo_cmd = show(&demo);
        let stdout = capture(&mut demo)?;
        let l = latency_line(&stdout)
            .with_context(|| format!("no latency line in the demo's output:\n{stdout}"))?;
        latencies.push((seed, l));
    }
    let total = median(latencies.iter().map(|(_, l)| l.0).collect());
    let computing = median(latencies.iter().map(|(_, l)| l.1).collect());
    let bus = median(latencies.iter().map(|(_, l)| l.2).collect());
    let worst = latencies.iter().map(|(_, l)| l.0).fold(0.0, f64::max);

    // Offline: a 6,000-sample CSV, calibrated with its report.
    let csv = data.join("k6000.csv");
    let mut gen = Command::new(ctx.target.join("release/examples/scenario_csv"));
    gen.arg(&csv)
        .args(["--samples", OFFLINE_SAMPLES, "--seed", "1"]);
    let gen_cmd = show(&gen);
    run(&mut gen)?;
    let report = data.join("offline.html");
    let mut cpu = Vec::new();
    let mut wall = Vec::new();
    let mut offline_cmd = String::new();
    for _ in 0..repeats {
        let mut offline = pinned(ctx, &exocald);
        offline
            .current_dir(&ctx.root)
            .args(["offline", "--input"])
            .arg(&csv)
            .arg("--report")
            .arg(&report);
        offline_cmd = show(&offline);
        let (before, started) = (children_cpu(), Instant::now());
        capture(&mut offline)?;
        wall.push(started.elapsed().as_secs_f64());
        cpu.push((children_cpu() - before).as_secs_f64());
    }
    let report_bytes = std::fs::metadata(&report)
        .with_context(|| format!("the offline run wrote no {}", report.display()))?
        .len();
    let (cpu_med, wall_med) = (median(cpu.clone()), median(wall));
    if !(total.is_finite() && cpu_med.is_finite()) {
        bail!("no figures (latency {total}, offline CPU {cpu_med})");
    }

    let mut body = String::new();
    let _ = writeln!(
        body,
        "Natively on this machine, the release binary pinned to CPU 0 (`taskset -c 0`: one \
         core, as on a single-core controller; the LS's linearisation threads share it).\n"
    );
    let _ = writeln!(
        body,
        "**Power-up latency** (end of the collection window → every node's table verified by \
         CRC read-back), from the daemon's own summary line over {seeds} demo sessions (seeds \
         1–{seeds}, the paper's scenario, the shipped collection window, authenticated push): this machine's real \
         time computing — alignment, LS, our EM, validation, the refit on all samples, the HTML \
         report, the push — plus the simulated time the in-process bus and the emulated nodes \
         took (the session clock stands still while the daemon computes).\n"
    );
    let _ = writeln!(
        body,
        "| seed | latency (s) | computing (s) | emulated bus and nodes (s) |\n|---|---|---|---|"
    );
    for (seed, (t, r, s)) in &latencies {
        let _ = writeln!(body, "| {seed} | {t:.3} | {r:.3} | {s:.3} |");
    }
    let _ = writeln!(
        body,
        "| median | {total:.3} | {computing:.3} | {bus:.3} |\n\nCommand (per seed): \
         `{demo_cmd}`\n"
    );
    let _ = writeln!(
        body,
        "What the figure leaves out, bounded: the in-process bus has no bit rate and the \
         emulated nodes write their flash at once. On a 1 Mbit/s bus each node's authenticated \
         transfer is 29 frames, stop-and-wait (10 commands, 19 replies; ≤ 130 bits each: \
         ≈ 3.8 ms of wire time a node, ≈ 26 ms for seven), plus each node's response times; a \
         real node's flash erase and write is not modelled. A controller-class core \
         several times slower than this one multiplies the computing column.\n"
    );
    let _ = writeln!(
        body,
        "**`exocald offline` on a {OFFLINE_SAMPLES}-sample CSV** (60 s of the paper's scenario, \
         seed 1): parse, LS, our EM, validation, refit and the HTML report ({report_bytes} \
         bytes; its plots decimated as in every report, report/README.md). CPU is the child's user + system time \
         (`getrusage(RUSAGE_CHILDREN)`), median of {repeats} runs: **{cpu_med:.3} s CPU**, \
         {wall_med:.3} s wall. Runs: {}.\n\nCommands: `{build_cmd}`; `{gen_cmd}`; \
         `{offline_cmd}`\n",
        cpu.iter()
            .map(|c| format!("{c:.3}"))
            .collect::<Vec<_>>()
            .join(", ")
    );
    let goals = vec![
        Goal {
            what: "power-up latency (end of collection window → every node's table verified), \
                   natively on the in-process bus, ≤ 1 s"
                .into(),
            met: total <= LATENCY_GOAL_S,
            detail: format!(
                "{total:.3} s median over {seeds} demo sessions on one pinned core (worst \
                 {worst:.3} s): {computing:.3} s computing + {bus:.3} s of emulated bus and \
                 nodes. Bounded by the computing (LS + our EM, report); a real 1 Mbit/s bus adds \
                 ≈ 26 ms of frames, a real node's flash write is not modelled"
            ),
        },
        Goal {
            what: format!(
                "`exocald offline` on a {OFFLINE_SAMPLES}-sample CSV with its HTML report ≤ 0.5 s \
                 CPU"
            ),
            met: cpu_med <= OFFLINE_GOAL_S,
            detail: format!(
                "{cpu_med:.3} s CPU median ({wall_med:.3} s wall), the report included"
            ),
        },
    ];
    Ok(Section {
        title: TITLE,
        body,
        goals,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_latency_line_is_read_whole_or_not_at_all() {
        let out = "push Joint7: New table\nend of collection to every table verified: 0.333 s \
                   (0.323 s computing on this machine + 0.010 s of emulated bus and nodes)\n";
        assert_eq!(latency_line(out), Some((0.333, 0.323, 0.010)));
        let wall = "end of collection to every table verified: 0.500 s\n";
        assert_eq!(latency_line(wall), None);
        assert_eq!(latency_line("report: x.html\n"), None);
    }
}
