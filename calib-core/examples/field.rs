//! The field cells of the accuracy sweep: real ÷ stated, our table against LS and
//! against the bound, on a real suit's sensors (see `calib_core::sweep::field_grid`).
//!
//! `cargo run -p calib-core --release --example field [-- --seeds N] [--only SUBSTRING[,…]]
//! [--without rate-bias,robust,restricted|all[,+relinearise]] [--spec] [--prior RAMP_DEG_S,WALK]
//! [--consider RAMP_DEG_S,WALK|simulated]` (`+relinearise` turns the
//! re-linearisation at the smoothed drift on) (`--spec`: the EM is told
//! the sensors' rate bias, `DriftEmOptions::rate_bias_spec`, as the cell simulates it; `--prior`:
//! that spec in every cell; `--consider`: the stated error with the allowance for that rate
//! bias, `DriftEmOptions::consider`; `--consider simulated`: at the rate bias each cell
//! simulates)

use std::time::Instant;

use calib_core::sweep::{field_grid, pooled, session_with, Session};
use calib_core::DriftEmOptions;
use calib_core::{TableChoice, TableError};

fn arg(name: &str) -> Option<String> {
    let a: Vec<String> = std::env::args().collect();
    a.iter().position(|x| x == name).and_then(|i| a.get(i + 1)).cloned()
}

/// The EM's options without the parts named in `without` (comma-separated: `rate-bias`,
/// `robust`, `relinearise`, `restricted`, or `all` for the paper's model alone).
fn variant(o: DriftEmOptions<7>, without: &str) -> DriftEmOptions<7> {
    let mut o = o;
    if let Ok(v) = std::env::var("TAU0") {
        o.initial_tau = v.parse().unwrap();
    }
    if let Ok(v) = std::env::var("STD0") {
        o.initial_drift_std = v.parse().unwrap();
    }
    for w in without.split(',') {
        match w {
            "rate-bias" => o.rate_bias = false,
            "robust" => o.robust = false,
            "relinearise" => o.relinearisations = 0,
            "restricted" => o.restricted = false,
            "all" => o = DriftEmOptions::plain(o.dt),
            // Not a removal: the re-linearisation is off by default; this turns it on.
            "+relinearise" => o.relinearisations = 2,
            "" => {}
            other => panic!("--without {other}?"),
        }
    }
    o
}

/// `RAMP_DEG_S,WALK_RAD_S_SQRT_S` as a [`calib_core::RateBias`].
fn rate_bias(v: &str) -> calib_core::RateBias {
    let (r, w) = v.split_once(',').expect("RAMP_DEG_S,WALK_RAD_S_SQRT_S");
    calib_core::RateBias {
        ramp: r.parse::<f64>().expect("ramp °/s").to_radians(),
        walk: w.parse().expect("walk rad/s/√s"),
    }
}

fn main() {
    let seeds: u64 = arg("--seeds").map_or(8, |v| v.parse().expect("--seeds N"));
    let only = arg("--only");
    let without = arg("--without").unwrap_or_default();
    let spec = std::env::args().any(|a| a == "--spec");
    // `--prior RAMP_DEG_S,WALK`: the same spec told in every cell, whatever it simulates (a
    // default the daemon could ship for sensors whose spec nobody configured).
    let prior = arg("--prior").map(|v| rate_bias(&v));
    // `--consider RAMP_DEG_S,WALK`: the EM weighs such a rate bias where its model leaves it out
    // (`DriftEmOptions::consider`), in every cell; real ÷ stated is then of the stated error with
    // that allowance (`DriftEmResult::stated_with_allowance`).
    let consider = arg("--consider");
    println!("| cell | real ÷ stated (pos / rot) | ours ÷ LS | ÷ the bound | real (mm / mrad) | stated | LS kept | refused | > 3× stated |");
    println!("|---|---|---|---|---|---|---|---|---|");
    let t0 = Instant::now();
    for (name, cell) in field_grid() {
        if only.as_deref().is_some_and(|o| !o.split(',').any(|o| name.contains(o))) {
            continue;
        }
        let mut sessions = Vec::new();
        let mut failed = 0;
        for seed in 1..=seeds {
            match session_with(&cell, seed, |o| {
                let consider = match consider.as_deref() {
                    None => calib_core::RateBias::NONE,
                    Some("simulated") => cell.field.bias,
                    Some(v) => rate_bias(v),
                };
                let o = DriftEmOptions {
                    consider,
                    ..variant(o, &without)
                };
                match (spec, prior) {
                    (true, _) => DriftEmOptions {
                        rate_bias_spec: cell.field.bias,
                        ..o
                    },
                    (false, Some(p)) => DriftEmOptions { rate_bias_spec: p, ..o },
                    (false, None) => o,
                }
            }) {
                Ok(s) => sessions.push(s),
                Err(e) => {
                    eprintln!("{name} seed {seed}: {e}");
                    failed += 1;
                }
            }
        }
        // What the daemon would push (the arbiter's table, or nothing where refused): a
        // refused session states nothing, so the ratios are over the pushed ones.
        let pushed: Vec<Session> = sessions.iter().filter(|s| s.pushed.is_some()).copied().collect();
        let real = |s: &Session| s.pushed.expect("pushed").0;
        let stated = |s: &Session| s.pushed.expect("pushed").1;
        let mm = TableError {
            position_m: 1e-3,
            rotation_rad: 1e-3,
        };
        let pair = |v: (f64, f64)| format!("{:.2} / {:.2}", v.0, v.1);
        let ratios = |a: &dyn Fn(&Session) -> TableError, b: &dyn Fn(&Session) -> TableError| {
            if pushed.is_empty() {
                "–".to_string()
            } else {
                pair(pooled(&pushed, a, b))
            }
        };
        let refused = sessions.len() - pushed.len();
        let ls_kept = sessions.iter().filter(|s| s.choice == TableChoice::Ls).count();
        let beyond = sessions.iter().filter(|s| s.pushed_beyond(3.0)).count();
        println!(
            "| {name} | {} | {} | {} | {} | {} | {ls_kept} | {refused}+{failed}/{seeds} | {beyond} |",
            ratios(&real, &stated),
            ratios(&real, &|s| s.ls),
            ratios(&real, &|s| s.bound),
            ratios(&real, &|_| mm),
            ratios(&stated, &|_| mm),
        );
    }
    eprintln!("{:.0} s", t0.elapsed().as_secs_f64());
}
