//! Stop when good enough, measured (issue 18.5): demo sessions of the paper's scenario on the
//! in-process bus, seeds 1..=N, each run twice — the fixed minute (the default configuration)
//! and `[session] stop_at_expected_error = [MM, MRAD]` with `min_duration_s = 15` — printing
//! per run the collection window, the expected table error the daemon stated and the table
//! error the pushed table really has: RMS over 2,000 fresh drift-free poses (the emulated suit's
//! motion generator with a seed no session uses, a pose every 0.1 s) of the position / rotation difference between FK with the pushed
//! table and with the emulated arm's true table.
//!
//! `cargo run --release -p exocald --example good_enough -- [--seeds N] [--mm MM] [--mrad MRAD]`
//! (defaults 5, 2.0, 6.0). Simulated time: the figures repeat exactly.

use calib_core::table_error;
use exocal_hil::{Scenario, Suit};
use exocald::cmd::demo::{demo_config, run, DemoOptions};
use exocald::config::Config;

fn arg(name: &str, default: f64) -> f64 {
    let args: Vec<String> = std::env::args().collect();
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1))
        .map_or(default, |v| {
            v.parse()
                .unwrap_or_else(|_| panic!("{name} needs a number, got {v}"))
        })
}

fn main() {
    let seeds = arg("--seeds", 5.0) as u64;
    let limits = (arg("--mm", 2.0), arg("--mrad", 6.0));
    let root = std::env::temp_dir().join(format!("exocal-good-enough-{}", std::process::id()));
    // Fresh poses: the emulated suit's own motion generator with a seed no session uses.
    let mut other = Scenario::paper();
    other.seed = 0xF2E5_4000;
    let fresh_dir = root.join("fresh");
    std::fs::create_dir_all(&fresh_dir).expect("a scratch directory");
    let fresh_suit = Suit::new(other, &fresh_dir).expect("the paper scenario");
    let fresh: Vec<[f64; 7]> = (0..2_000)
        .map(|k| fresh_suit.true_joints(k as f64 * 0.1))
        .collect();
    println!(
        "| seed | window | collected (s) | expected (mm / mrad, 1σ) | table error, fresh poses \
         (mm / mrad) | on the session's poses |"
    );
    println!("|---|---|---|---|---|---|");
    for seed in 1..=seeds {
        let mut scenario = Scenario::paper();
        scenario.seed = seed;
        let truth_dir = root.join(format!("truth-{seed}"));
        std::fs::create_dir_all(&truth_dir).expect("a scratch directory");
        let suit = Suit::new(scenario, &truth_dir).expect("the paper scenario");
        let truth = *suit.true_table();
        for stop in [None, Some(limits)] {
            let output = root.join(format!("seed{seed}-{}", stop.is_some()));
            let mut config = demo_config(Config::default_config(), &output, 1.0);
            if stop.is_some() {
                config.calibration.window.min_duration_s = 15.0;
                config.calibration.window.stop_at_expected_error = stop;
            }
            let opts = DemoOptions {
                seed,
                speed: 1_000.0,
                output,
                hold: false,
            };
            let result = run(&config, &opts).unwrap_or_else(|e| panic!("seed {seed}: {}", e.error));
            let summary = &result.summary;
            let outcome = summary.outcome.as_ref().expect("a calibration");
            let te = table_error(&outcome.table(), &truth, &fresh);
            // The session's own poses (the suit's true joints over its window, every 30 ms):
            // what the stated expected error is an RMS over.
            let window_s = summary.aligned_samples as f64 / config.calibration.window.grid_hz;
            let own: Vec<[f64; 7]> = (0..(window_s / 0.03) as usize)
                .map(|k| suit.true_joints(k as f64 * 0.03))
                .collect();
            let te_own = table_error(&outcome.table(), &truth, &own);
            let window = match stop {
                None => "fixed minute".to_string(),
                Some((mm, mrad)) => format!("stop at ±{mm} mm, ±{mrad} mrad"),
            };
            let expected = outcome.verdict.expected.map_or_else(
                || "?".into(),
                |e| format!("{:.2} / {:.2}", e.position_mm, e.rotation_mrad),
            );
            println!(
                "| {seed} | {window} | {window_s:.1} | {expected} | {:.2} / {:.2} | {:.2} / {:.2} |",
                te.position_m * 1e3,
                te.rotation_rad * 1e3,
                te_own.position_m * 1e3,
                te_own.rotation_rad * 1e3
            );
        }
    }
    let _ = std::fs::remove_dir_all(&root);
}
