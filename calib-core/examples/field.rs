//! The field cells of the accuracy sweep (issue 30): real ÷ stated, our table against LS and
//! against the bound, on a real suit's sensors (see `calib_core::sweep::field_grid`).
//!
//! `cargo run -p calib-core --release --example field [-- --seeds N] [--only SUBSTRING]
//! [--without rate-bias,robust,restricted|all[,+relinearise]] [--spec]` (`+relinearise` turns the
//! re-linearisation at the smoothed drift on) (`--spec`: the EM is told
//! the sensors' rate bias, `DriftEmOptions::rate_bias_spec`, as the cell simulates it)

use std::time::Instant;

use calib_core::sweep::{field_grid, pooled, session_with, Session};
use calib_core::DriftEmOptions;
use calib_core::TableError;

fn arg(name: &str) -> Option<String> {
    let a: Vec<String> = std::env::args().collect();
    a.iter().position(|x| x == name).and_then(|i| a.get(i + 1)).cloned()
}

/// The EM's options without the parts named in `without` (comma-separated: `rate-bias`,
/// `robust`, `relinearise`, `restricted`, or `all` for the paper's model alone).
fn variant(o: DriftEmOptions<7>, without: &str) -> DriftEmOptions<7> {
    let mut o = o;
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

fn main() {
    let seeds: u64 = arg("--seeds").map_or(8, |v| v.parse().expect("--seeds N"));
    let only = arg("--only");
    let without = arg("--without").unwrap_or_default();
    let spec = std::env::args().any(|a| a == "--spec");
    // `--prior RAMP_DEG_S,WALK`: the same spec told in every cell, whatever it simulates (a
    // default the daemon could ship for sensors whose spec nobody configured).
    let prior = arg("--prior").map(|v| {
        let (r, w) = v.split_once(',').expect("--prior RAMP_DEG_S,WALK_RAD_S_SQRT_S");
        calib_core::RateBias {
            ramp: r.parse::<f64>().expect("ramp °/s").to_radians(),
            walk: w.parse().expect("walk rad/s/√s"),
        }
    });
    println!("| cell | real ÷ stated (pos / rot) | our table vs LS | vs the bound | real (mm / mrad) | stated | refused |");
    println!("|---|---|---|---|---|---|---|");
    let t0 = Instant::now();
    for (name, cell) in field_grid() {
        if only.as_deref().is_some_and(|o| !name.contains(o)) {
            continue;
        }
        let mut sessions = Vec::new();
        let mut failed = 0;
        for seed in 1..=seeds {
            match session_with(&cell, seed, |o| {
                let o = variant(o, &without);
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
        // A refused session states nothing: real ÷ stated is over the accepted ones.
        let refused = sessions.iter().filter(|s| s.refused).count();
        let accepted: Vec<Session> = sessions.iter().filter(|s| !s.refused).copied().collect();
        let rs = pooled(&accepted, |s| s.em, |s| s.stated);
        let vl = pooled(&sessions, |s| s.em, |s| s.ls);
        let vb = pooled(&sessions, |s| s.em, |s| s.bound);
        let real = pooled(
            &sessions,
            |s| s.em,
            |_| TableError {
                position_m: 1e-3,
                rotation_rad: 1e-3,
            },
        );
        let st = pooled(
            &sessions,
            |s| s.stated,
            |_| TableError {
                position_m: 1e-3,
                rotation_rad: 1e-3,
            },
        );
        println!(
            "| {name} | {:.2} / {:.2} | {:.2} / {:.2} | {:.2} / {:.2} | {:.2} / {:.2} | {:.2} / {:.2} | {refused}+{failed}/{seeds} |",
            rs.0, rs.1, vl.0, vl.1, vb.0, vb.1, real.0, real.1, st.0, st.1
        );
    }
    eprintln!("{:.0} s", t0.elapsed().as_secs_f64());
}
