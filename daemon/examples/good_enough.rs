//! Stop when good enough, measured: demo sessions of the paper's scenario on the in-process
//! bus, seeds 1..=N, each run as the fixed minute (`min_duration_s = 60`, the rule off), as
//! `[session] stop_at_expected_error = [MM, MRAD]` with `min_duration_s = 15`, and — with
//! `--compliance P` — stopping so with an emulated wearer who follows the progress line's
//! guidance (`exocal_hil::wearer`: each piece of advice considered at most every 10 s, followed
//! with probability P, 2 s later, by 10 s of sweeps of the advised joint's whole range).
//! `--reach R1,…,R7` gives the wearer's free motion that fraction of each joint's range (a
//! lazy wrist: `1,1,1,1,0.6,0.6,0.6`). Per run: the collection window, the expected table
//! error the daemon stated and the table error the pushed table really has: RMS over 2,000
//! fresh drift-free poses (the emulated suit's motion generator with a seed no session uses, a
//! pose every 0.1 s) of the position / rotation difference between FK with the pushed table and
//! with the emulated arm's true table; then per kind of run the median and 90th percentile of
//! the window and real ÷ stated (RMS over the sessions; real on the fresh poses).
//!
//! `cargo run --release -p exocald --example good_enough -- [--seeds N] [--mm MM] [--mrad MRAD]
//! [--compliance P] [--reach R1,…,R7]` (defaults 5, 2.0, 6.0, 0, all 1). Simulated time: the
//! figures repeat exactly.

use calib_core::table_error;
use exocal_hil::{Scenario, Suit, Wearer};
use exocald::cmd::demo::{demo_config, run, DemoOptions};
use exocald::config::Config;

fn arg(name: &str, default: f64) -> f64 {
    text(name).map_or(default, |v| {
        v.parse()
            .unwrap_or_else(|_| panic!("{name} needs a number, got {v}"))
    })
}

/// The value after `name`, as text.
fn text(name: &str) -> Option<String> {
    let args: Vec<String> = std::env::args().collect();
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1).cloned())
}

/// The `q`-quantile of `v` (nearest rank).
fn quantile(v: &[f64], q: f64) -> f64 {
    let mut v = v.to_vec();
    v.sort_by(f64::total_cmp);
    v[((q * v.len() as f64).ceil() as usize).clamp(1, v.len()) - 1]
}

/// One kind of run: its name, its stop limits and its wearer.
struct Kind {
    name: String,
    stop: Option<(f64, f64)>,
    wearer: Wearer,
    /// Per session: window (s), and real ÷ stated (position, rotation), or the refusal.
    runs: Vec<Result<(f64, f64, f64), String>>,
}

fn main() {
    let seeds = arg("--seeds", 5.0) as u64;
    let limits = (arg("--mm", 2.0), arg("--mrad", 6.0));
    let compliance = arg("--compliance", 0.0);
    let mut reach = [1.0; 7];
    if let Some(r) = text("--reach") {
        let v: Vec<f64> = r
            .split(',')
            .map(|x| x.parse().expect("--reach needs 7 numbers, comma-separated"))
            .collect();
        reach = v.try_into().expect("--reach needs 7 numbers");
    }
    let wearer = Wearer {
        reach,
        ..Wearer::default()
    };
    let stop = format!("stop at ±{} mm, ±{} mrad", limits.0, limits.1);
    let mut kinds = vec![
        Kind {
            name: "fixed minute".into(),
            stop: None,
            wearer: wearer.clone(),
            runs: Vec::new(),
        },
        Kind {
            name: stop.clone(),
            stop: Some(limits),
            wearer: wearer.clone(),
            runs: Vec::new(),
        },
    ];
    if compliance > 0.0 {
        kinds.push(Kind {
            name: format!("{stop}, guidance followed ({compliance})"),
            stop: Some(limits),
            wearer: Wearer {
                compliance,
                ..wearer.clone()
            },
            runs: Vec::new(),
        });
    }
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
        for (k, kind) in kinds.iter_mut().enumerate() {
            let output = root.join(format!("seed{seed}-{k}"));
            let mut config = demo_config(Config::default_config(), &output, 1.0);
            config.calibration.window.min_duration_s = match kind.stop {
                Some(_) => 15.0,
                None => 60.0,
            };
            config.calibration.window.stop_at_expected_error = kind.stop;
            let opts = DemoOptions {
                seed,
                speed: 1_000.0,
                output,
                hold: false,
                quiet: false,
                wearer: kind.wearer.clone(),
                drift: Default::default(),
            };
            let result = match run(&config, &opts) {
                Ok(r) => r,
                Err(e) => {
                    println!("| {seed} | {} | refused: {} | | | |", kind.name, e.error);
                    kind.runs.push(Err(e.error.to_string()));
                    continue;
                }
            };
            let summary = &result.summary;
            let Some(outcome) = summary.outcome.as_ref() else {
                println!("| {seed} | {} | no calibration | | | |", kind.name);
                kind.runs.push(Err("no calibration".into()));
                continue;
            };
            let te = table_error(&outcome.table(), &truth, &fresh);
            // The session's own poses (the suit's true joints over its window, every 30 ms):
            // what the stated expected error is an RMS over.
            let window_s = summary.aligned_samples as f64 / config.calibration.window.grid_hz;
            // A guided wearer's poses depend on the advice: known to the session only.
            let own = (kind.wearer.compliance == 0.0).then(|| {
                let mut scenario = Scenario::paper();
                scenario.seed = seed;
                scenario.wearer = kind.wearer.clone();
                let suit = Suit::new(scenario, &truth_dir).expect("the paper scenario");
                let poses: Vec<[f64; 7]> = (0..(window_s / 0.03) as usize)
                    .map(|k| suit.true_joints(k as f64 * 0.03))
                    .collect();
                table_error(&outcome.table(), &truth, &poses)
            });
            let expected = outcome.verdict.expected;
            if let Some(e) = expected {
                kind.runs.push(Ok((
                    window_s,
                    te.position_m * 1e3 / e.position_mm,
                    te.rotation_rad * 1e3 / e.rotation_mrad,
                )));
            }
            let expected = expected.map_or_else(
                || "?".into(),
                |e| format!("{:.2} / {:.2}", e.position_mm, e.rotation_mrad),
            );
            let own = own.map_or_else(
                || "—".into(),
                |o| format!("{:.2} / {:.2}", o.position_m * 1e3, o.rotation_rad * 1e3),
            );
            println!(
                "| {seed} | {} | {window_s:.1} | {expected} | {:.2} / {:.2} | {own} |",
                kind.name,
                te.position_m * 1e3,
                te.rotation_rad * 1e3,
            );
        }
    }
    println!();
    println!(
        "| run | sessions calibrated | window, median / p90 (s) | real (fresh poses) ÷ stated, RMS (mm / mrad) |"
    );
    println!("|---|---|---|---|");
    for kind in &kinds {
        let ok: Vec<(f64, f64, f64)> = kind.runs.iter().filter_map(|r| r.clone().ok()).collect();
        let windows: Vec<f64> = ok.iter().map(|r| r.0).collect();
        let rms = |f: fn(&(f64, f64, f64)) -> f64| {
            (ok.iter().map(|r| f(r).powi(2)).sum::<f64>() / ok.len() as f64).sqrt()
        };
        if ok.is_empty() {
            println!("| {} | 0 of {} | | |", kind.name, kind.runs.len());
        } else {
            println!(
                "| {} | {} of {} | {:.1} / {:.1} | {:.2} / {:.2} |",
                kind.name,
                ok.len(),
                kind.runs.len(),
                quantile(&windows, 0.5),
                quantile(&windows, 0.9),
                rms(|r| r.1),
                rms(|r| r.2)
            );
        }
    }
    let _ = std::fs::remove_dir_all(&root);
}
