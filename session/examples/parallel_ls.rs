//! The multi-core figure of `cargo xtask bench`: LS (and LS + our EM) on the paper's Section 4
//! scenario, seed 1, K = 6,000, with the linearisation on 1 and 2 threads
//! ([`exocal_session::parallel::Parallel`]). One JSON line per thread count: wall-clock medians (the
//! point of more cores), the CPU time of the whole process beside them.
//!
//! `cargo run --release -p exocal-session --example parallel_ls -- [--repeats N] [--k K]`

use std::num::NonZeroUsize;
use std::time::Instant;

use calib_core::{
    em_drift_vec, identify_ls_with, median, DhTable, DriftEmOptions, LsOptions, Sample, Scenario,
    ScenarioConfig, SUIT_PARAMS,
};
use exocal_session::parallel::Parallel;

fn arg(name: &str, default: usize) -> usize {
    let args: Vec<String> = std::env::args().collect();
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1))
        .map(|v| {
            v.parse()
                .unwrap_or_else(|_| panic!("{name} needs a count, got {v}"))
        })
        .unwrap_or(default)
}

/// CPU time of the whole process (all threads), s.
fn process_cpu() -> f64 {
    // /proc/self/stat fields 14 and 15: utime and stime in clock ticks (100 Hz on Linux).
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    let after = stat.rsplit(')').next().unwrap_or("");
    let f: Vec<f64> = after
        .split_whitespace()
        .skip(11)
        .take(2)
        .filter_map(|v| v.parse().ok())
        .collect();
    f.iter().sum::<f64>() / 100.0
}

fn main() {
    let repeats = arg("--repeats", 7).max(1);
    let k = arg("--k", 6000);
    let cfg = ScenarioConfig::paper();
    let samples: Vec<Sample<7>> = Scenario::new(cfg, 1).take(k).map(|s| s.sample).collect();
    let start = DhTable::paper_nominal();
    let opts = LsOptions::paper();
    for threads in [1, 2] {
        let lin = Parallel::new(&samples, NonZeroUsize::new(threads).expect("non-zero"));
        let (mut ls_wall, mut all_wall) = (Vec::new(), Vec::new());
        let cpu0 = process_cpu();
        let mut cost = f64::NAN;
        for _ in 0..repeats {
            let t0 = Instant::now();
            let ls = identify_ls_with::<7, SUIT_PARAMS>(&start, &samples, &opts, &lin).expect("LS");
            ls_wall.push(t0.elapsed().as_secs_f64());
            em_drift_vec::<7, SUIT_PARAMS>(&ls.table, &samples, &DriftEmOptions::new(cfg.drift.dt))
                .expect("EM");
            all_wall.push(t0.elapsed().as_secs_f64());
            cost = ls.cost;
        }
        let cpu = (process_cpu() - cpu0) / repeats as f64;
        println!(
            "{{\"bench\":\"calib-parallel\",\"k\":{k},\"threads\":{threads},\"ls_wall_median_s\":{:e},\"ls_em_wall_median_s\":{:e},\"cpu_per_run_s\":{cpu:e},\"cost\":{cost:e}}}",
            median(&mut ls_wall),
            median(&mut all_wall)
        );
    }
}
