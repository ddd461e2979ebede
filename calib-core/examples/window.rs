//! How long must a wearer move? Per cell and seed: the table error LS reaches
//! after 60 s of motion (the fixed minute's calibration, judged on fresh drift-free poses), the
//! motion time our calibration (LS then our EM, as the daemon runs it) needs to reach that same
//! table error, and where the daemon's stop-when-good-enough rule closes the window: LS + EM
//! every 5 s from `min_s`, the window closing once the *stated* error (what the daemon states
//! and validates: [`calib_core::DriftEmResult::stated_error`]) is within the limits at `guard`
//! consecutive evaluations, at `max_s` at the latest.
//!
//! `cargo run -p calib-core --release --example window -- [--seeds N] [--limits MM,MRAD]
//! [--cells a,b]` (defaults: 8 seeds, the shipped limits 2 mm / 6 mrad, every cell below).
//! Per cell: the motion time to LS-60 s's table error (median and 90th percentile over seeds;
//! "> T" when a session never reached it within the evaluated T), and per guard the stop time
//! (median, 90th percentile), real ÷ stated at the stop (RMS over sessions; ≤ 1.15 is honest)
//! and the stop's table error ÷ LS-60 s's (RMS over sessions). And what bounds the window: the
//! motion time at which the Cramér-Rao bound itself (the true table, drift and noise; no
//! unbiased calibration of those samples does better) reaches LS-60 s's table error, and the
//! bound after the 20 s goal for the median window ÷ LS-60 s's error (RMS over sessions).

use calib_core::metrics::TableError;
use calib_core::sweep::{field_grid, Cell, Simulation};

/// The evaluation step and the longest motion evaluated (s).
const EVERY_S: f64 = 5.0;
const HORIZON_S: f64 = 90.0;
/// The fixed window of the reference (s).
const FIXED_S: f64 = 60.0;
/// The goal for the median window (s).
const GOAL_S: f64 = 20.0;
/// The stop rule's first evaluation (s).
const MIN_S: f64 = 10.0;
/// The guards measured: consecutive evaluations within the limits.
const GUARDS: [usize; 3] = [1, 2, 3];

fn arg(name: &str) -> Option<String> {
    let args: Vec<String> = std::env::args().collect();
    args.iter().position(|a| a == name).and_then(|i| args.get(i + 1)).cloned()
}

/// One evaluation: the stated and the real table error of LS + EM on a prefix.
#[derive(Clone, Copy)]
struct Eval {
    seconds: f64,
    stated: Option<TableError>,
    real: Option<TableError>,
    bound: Option<TableError>,
}

fn quantile(v: &mut [f64], q: f64) -> f64 {
    v.sort_by(f64::total_cmp);
    let i = ((v.len() as f64 - 1.0) * q).round() as usize;
    v[i]
}

fn fmt_time(t: f64) -> String {
    if t.is_finite() {
        format!("{t:.0}")
    } else {
        format!("> {HORIZON_S:.0}")
    }
}

fn rms_ratio(pairs: &[(TableError, TableError)]) -> (f64, f64) {
    let s = |f: fn(&TableError) -> f64| {
        let a: f64 = pairs.iter().map(|(a, _)| f(a).powi(2)).sum();
        let b: f64 = pairs.iter().map(|(_, b)| f(b).powi(2)).sum();
        (a / b).sqrt()
    };
    (s(|e| e.position_m), s(|e| e.rotation_rad))
}

fn main() {
    let seeds: u64 = arg("--seeds").map_or(8, |s| s.parse().expect("--seeds N"));
    let limits: Vec<f64> = arg("--limits")
        .unwrap_or_else(|| "2,6".into())
        .split(',')
        .map(|x| x.parse().expect("--limits MM,MRAD"))
        .collect();
    let (lim_mm, lim_mrad) = (limits[0], limits[1]);
    let only: Option<Vec<String>> = arg("--cells").map(|c| c.split(',').map(str::to_string).collect());
    let mut cells: Vec<(&str, Cell)> = field_grid()
        .into_iter()
        .filter(|(n, _)| {
            [
                "drift in the reading (60 s)",
                "paper-like",
                "slow drift τ 3 s",
                "bias ramp 0.005",
                "glitches 1%",
            ]
            .iter()
            .any(|k| n.contains(k))
        })
        .collect();
    if let Some(only) = &only {
        cells.retain(|(n, _)| only.iter().any(|o| n.contains(o.as_str())));
    }
    let mut bounds = Vec::new();
    println!("limits {lim_mm} mm / {lim_mrad} mrad (stated, 1σ), evaluations every {EVERY_S} s from {MIN_S} s, {seeds} seeds\n");
    println!("| cell | LS 60 s (mm / mrad, RMS) | motion to LS-60 s, median / p90 (s) | guard | stop, median / p90 (s) | real ÷ stated at stop | stop ÷ LS 60 s |");
    println!("|---|---|---|---|---|---|---|");
    for (name, cell) in cells {
        let cell = Cell {
            seconds: HORIZON_S,
            ..cell
        };
        let mut reach = Vec::new();
        let mut bounded = Vec::new();
        let mut at_goal = Vec::new();
        let mut ls60s = Vec::new();
        let mut runs: Vec<Vec<Eval>> = Vec::new();
        for seed in 1..=seeds {
            let sim = Simulation::new(&cell, seed);
            let Ok((ls, _)) = sim.fit(sim.prefix(FIXED_S)) else {
                eprintln!("{name} seed {seed}: LS 60 s failed");
                continue;
            };
            let ls60 = sim.table_error(&ls.table);
            let mut evals = Vec::new();
            let mut t = EVERY_S;
            while t <= HORIZON_S + 1e-9 {
                let fit = sim.fit(sim.prefix(t)).ok();
                evals.push(Eval {
                    seconds: t,
                    stated: fit
                        .as_ref()
                        .filter(|(_, em)| em.refusals.is_empty())
                        .map(|(_, em)| em.stated_error),
                    real: fit.as_ref().map(|(_, em)| sim.table_error(&em.table)),
                    bound: sim.bound(sim.prefix(t)).ok(),
                });
                t += EVERY_S;
            }
            let within = |e: &Option<TableError>| {
                e.is_some_and(|r| r.position_m <= ls60.position_m && r.rotation_rad <= ls60.rotation_rad)
            };
            let reached = evals.iter().find(|e| within(&e.real)).map_or(f64::INFINITY, |e| e.seconds);
            bounded.push(evals.iter().find(|e| within(&e.bound)).map_or(f64::INFINITY, |e| e.seconds));
            if let Some(b) = evals.iter().find(|e| (e.seconds - GOAL_S).abs() < 1e-9).and_then(|e| e.bound) {
                at_goal.push((b, ls60));
            }
            eprintln!(
                "{name} seed {seed}: LS60 {:.2} mm, reached at {reached}",
                ls60.position_m * 1e3
            );
            reach.push(reached);
            ls60s.push(ls60);
            runs.push(evals);
        }
        let n = ls60s.len() as f64;
        let ls_rms = (
            (ls60s.iter().map(|e| e.position_m.powi(2)).sum::<f64>() / n).sqrt() * 1e3,
            (ls60s.iter().map(|e| e.rotation_rad.powi(2)).sum::<f64>() / n).sqrt() * 1e3,
        );
        let (r50, r90) = (quantile(&mut reach.clone(), 0.5), quantile(&mut reach.clone(), 0.9));
        let (b50, b90) = (quantile(&mut bounded.clone(), 0.5), quantile(&mut bounded.clone(), 0.9));
        let goal = rms_ratio(&at_goal);
        bounds.push(format!(
            "| {name} | {} / {} | {} / {} | {:.2} / {:.2} |",
            fmt_time(r50),
            fmt_time(r90),
            fmt_time(b50),
            fmt_time(b90),
            goal.0,
            goal.1
        ));
        for guard in GUARDS {
            let mut stops = Vec::new();
            let mut honest = Vec::new();
            let mut vs_ls = Vec::new();
            for (evals, ls60) in runs.iter().zip(&ls60s) {
                let mut streak = 0;
                let mut stop = evals.last().copied().expect("evaluations");
                for e in evals.iter().filter(|e| e.seconds >= MIN_S - 1e-9) {
                    let within = e
                        .stated
                        .is_some_and(|s| s.position_m * 1e3 <= lim_mm && s.rotation_rad * 1e3 <= lim_mrad);
                    streak = if within { streak + 1 } else { 0 };
                    if streak >= guard {
                        stop = *e;
                        break;
                    }
                }
                stops.push(stop.seconds);
                if let (Some(real), Some(stated)) = (stop.real, stop.stated) {
                    honest.push((real, stated));
                    vs_ls.push((real, *ls60));
                }
            }
            let (h, v) = (rms_ratio(&honest), rms_ratio(&vs_ls));
            println!(
                "| {name} | {:.2} / {:.2} | {} / {} | {guard} | {} / {} | {:.2} / {:.2} | {:.2} / {:.2} |",
                ls_rms.0,
                ls_rms.1,
                fmt_time(r50),
                fmt_time(r90),
                fmt_time(quantile(&mut stops.clone(), 0.5)),
                fmt_time(quantile(&mut stops, 0.9)),
                h.0,
                h.1,
                v.0,
                v.1,
            );
        }
    }
    println!("\nWhat bounds the window: the motion our calibration needs to reach LS-60 s's table error, the motion the Cramér-Rao bound needs, and the bound after {GOAL_S:.0} s ÷ LS-60 s's error\n");
    println!("| cell | calibration reaches LS-60 s, median / p90 (s) | the bound reaches it, median / p90 (s) | bound at {GOAL_S:.0} s ÷ LS 60 s (mm / mrad, RMS) |");
    println!("|---|---|---|---|");
    for row in bounds {
        println!("{row}");
    }
}
