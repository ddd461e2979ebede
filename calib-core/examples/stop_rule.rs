//! Stop when good enough across the sweep's regimes: how long the daemon's rule
//! (LS + our EM every 5 s from 15 s, close the window when the EM's expected table error is
//! within [2 mm, 6 mrad], at 120 s at the latest) collects, and the table error it then reaches,
//! against a fixed minute of the same session (see `calib_core::sweep::good_enough`).
//!
//! `cargo run -p calib-core --release --example stop_rule` (τ ∈ {0.1, 0.3, 1, 3, 10} s ×
//! σ ∈ {0.25, 1, 4} × pose noise {none, 1 mm / 2 mrad}, 5 seeds per cell; optional `--seeds N`,
//! `--sigma S`, `--tau T`, `--noise 0|1` to run part of it, `--limits MM,MRAD`). The whole grid
//! takes about 4.5 min on one core: a session that never meets the limits
//! costs 22 fits, 2–9 s; most of the time goes to σ = 4, where most never do.
//!
//! Expected and real table errors are RMS over the cell's sessions (the expected error is a
//! 1σ figure: their ratio is 1 when it is calibrated); "met" counts sessions whose expected
//! error was within the limits when the window closed.

use std::time::Instant;

use calib_core::metrics::TableError;
use calib_core::sweep::{good_enough, Cell, Field, GoodEnough, StopRule};

/// The fixed window the rule is compared with (s).
const FIXED_S: f64 = 60.0;

fn arg(name: &str) -> Option<String> {
    let args: Vec<String> = std::env::args().collect();
    args.iter().position(|a| a == name).and_then(|i| args.get(i + 1)).cloned()
}

fn num(name: &str) -> Option<f64> {
    arg(name).map(|v| v.parse().unwrap_or_else(|_| panic!("{name} needs a number, got {v}")))
}

/// RMS over sessions of one figure (NaN where a fit failed).
fn rms(runs: &[GoodEnough], f: impl Fn(&GoodEnough) -> Option<TableError>) -> TableError {
    let n = runs.len() as f64;
    let e: Vec<TableError> = runs
        .iter()
        .map(|r| {
            f(r).unwrap_or(TableError {
                position_m: f64::NAN,
                rotation_rad: f64::NAN,
            })
        })
        .collect();
    TableError {
        position_m: (e.iter().map(|e| e.position_m.powi(2)).sum::<f64>() / n).sqrt(),
        rotation_rad: (e.iter().map(|e| e.rotation_rad.powi(2)).sum::<f64>() / n).sqrt(),
    }
}

fn mm(e: TableError) -> String {
    format!("{:.2} / {:.2}", e.position_m * 1e3, e.rotation_rad * 1e3)
}

fn ratio(a: TableError, b: TableError) -> String {
    format!("{:.2} / {:.2}", a.position_m / b.position_m, a.rotation_rad / b.rotation_rad)
}

fn main() {
    let seeds = num("--seeds").unwrap_or(5.0) as u64;
    let rule = match arg("--limits") {
        Some(l) => {
            let v: Vec<f64> = l.split(',').map(|x| x.parse().expect("--limits MM,MRAD")).collect();
            StopRule::new(v[0], v[1])
        }
        None => StopRule::new(2.0, 6.0),
    };
    let (only_sigma, only_tau, only_noise) = (num("--sigma"), num("--tau"), num("--noise"));
    println!(
        "| pose noise | σ | τ (s) | stop (s), mean (range) | met | expected at stop (mm / mrad) | real at stop (mm / mrad) | real (mm / mrad), fixed {FIXED_S} s | real / expected at stop | real / expected, fixed {FIXED_S} s |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|");
    let start = Instant::now();
    for noise in [(0.0, 0.0), (1e-3, 2e-3)] {
        for sigma in [0.25, 1.0, 4.0] {
            for tau in [0.1, 0.3, 1.0, 3.0, 10.0] {
                if only_sigma.is_some_and(|s| s != sigma)
                    || only_tau.is_some_and(|t| t != tau)
                    || only_noise.is_some_and(|n| (n > 0.0) != (noise.0 > 0.0))
                {
                    continue;
                }
                let cell = Cell {
                    tau,
                    sigma,
                    noise,
                    seconds: rule.max_s,
                    field: Field::PAPER,
                };
                let t0 = Instant::now();
                let runs: Vec<GoodEnough> = (1..=seeds).map(|seed| good_enough(&cell, seed, &rule, FIXED_S)).collect();
                let stops: Vec<f64> = runs.iter().map(|r| r.stop().seconds).collect();
                let mean = stops.iter().sum::<f64>() / stops.len() as f64;
                let (lo, hi) = stops
                    .iter()
                    .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &s| (l.min(s), h.max(s)));
                let met = runs.iter().filter(|r| r.met(&rule)).count();
                let expected = rms(&runs, |r| r.stop().expected);
                let real = rms(&runs, |r| r.stop().real);
                let fixed_expected = rms(&runs, |r| r.fixed.expected);
                let fixed_real = rms(&runs, |r| r.fixed.real);
                let noise = if noise.0 > 0.0 { "1 mm, 2 mrad" } else { "none" };
                println!(
                    "| {noise} | {sigma} | {tau} | {mean:.0} ({lo:.0}–{hi:.0}) | {met}/{} | {} | {} | {} | {} | {} |",
                    runs.len(),
                    mm(expected),
                    mm(real),
                    mm(fixed_real),
                    ratio(real, expected),
                    ratio(fixed_real, fixed_expected),
                );
                eprintln!("{cell:?}: {:.1} s, stops {stops:?}", t0.elapsed().as_secs_f64());
            }
        }
    }
    eprintln!("{:.0} s", start.elapsed().as_secs_f64());
}
