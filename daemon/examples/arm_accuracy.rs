//! Real ÷ stated through the whole daemon for arms of fewer joints: the demo (the emulated suit
//! and the daemon on the in-process bus) of the shipped configuration cut to its first n joints,
//! for seeds 1..=S, the pushed table against the emulated suit's true one (the paper's Table 4
//! arm, its first n rows) over 256 poses spread over the arm's ranges.
//!
//! `cargo run --release -p exocald --example arm_accuracy -- [SEEDS] [N...]` (default 8 seeds,
//! arms of 4, 6 and 7 joints). Prints one line per session and, per arm, the RMS of real ÷
//! stated (position / rotation) over the sessions pushed and how many were refused.

use calib_core::{table_error, DhTable, JointRanges};
use exocald::cmd::demo::{self, DemoOptions};
use exocald::config::Config;

fn session<const N: usize>(seed: u64, dir: &std::path::Path) -> Option<(f64, f64)> {
    let mut config = Config::default_config();
    config.calibration = config.calibration.first(N);
    let mut config = demo::demo_config(config, dir, 1.0);
    config.calibration.window.min_duration_s = 20.0;
    let opts = DemoOptions {
        seed,
        speed: 1e6,
        output: dir.to_path_buf(),
        hold: false,
        quiet: true,
        wearer: Default::default(),
        drift: Default::default(),
    };
    let summary = match demo::run(&config, &opts).map_err(|e| *e) {
        Ok(r) => r.summary,
        Err(e) => {
            println!("{N} joints, seed {seed}: {}", e.error);
            return None;
        }
    };
    let outcome = summary.outcome?;
    let stated = outcome.verdict.expected?;
    let truth: DhTable<N> = exocal_hil::Scenario::paper().arm.table().first();
    let ranges: JointRanges<N> = JointRanges::<7>::paper().first();
    let poses: Vec<[f64; N]> = (0..256).map(|i| ranges.spread(i)).collect();
    let real = table_error(&outcome.table().first::<N>(), &truth, poses.iter());
    let ratio = (
        real.position_m * 1e3 / stated.position_mm,
        real.rotation_rad * 1e3 / stated.rotation_mrad,
    );
    println!(
        "{N} joints, seed {seed}: real {:.2} mm / {:.2} mrad, stated ±{:.2} mm / ±{:.2} mrad, \
         real ÷ stated {:.2} / {:.2}",
        real.position_m * 1e3,
        real.rotation_rad * 1e3,
        stated.position_mm,
        stated.rotation_mrad,
        ratio.0,
        ratio.1
    );
    Some(ratio)
}

fn arm<const N: usize>(seeds: u64) {
    let dir = std::env::temp_dir().join(format!("exocal-arm-accuracy-{}", std::process::id()));
    let ratios: Vec<(f64, f64)> = (1..=seeds)
        .filter_map(|seed| {
            let _ = std::fs::remove_dir_all(&dir);
            session::<N>(seed, &dir)
        })
        .collect();
    let _ = std::fs::remove_dir_all(&dir);
    let rms = |f: fn(&(f64, f64)) -> f64| {
        (ratios.iter().map(|r| f(r) * f(r)).sum::<f64>() / ratios.len().max(1) as f64).sqrt()
    };
    println!(
        "{N} joints: RMS real ÷ stated {:.2} / {:.2} over {} sessions pushed, {} not",
        rms(|r| r.0),
        rms(|r| r.1),
        ratios.len(),
        seeds as usize - ratios.len()
    );
}

fn main() {
    let mut args = std::env::args().skip(1);
    let seeds: u64 = args.next().and_then(|s| s.parse().ok()).unwrap_or(8);
    let arms: Vec<usize> = args.filter_map(|s| s.parse().ok()).collect();
    for n in if arms.is_empty() { vec![4, 6, 7] } else { arms } {
        exocal_session::with_joints!(n, |N| arm::<N>(seeds));
    }
}
