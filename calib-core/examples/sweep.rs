//! The accuracy sweep: LS, our EM and the Cramér-Rao bound in table error over
//! drift τ × σ × pose noise × session length (see `calib_core::sweep`).
//!
//! `cargo run -p calib-core --release --example sweep` (the whole grid, 5 seeds per cell;
//! optional `--seeds N`, `--seconds S` to run one session length only).

use std::time::Instant;

use calib_core::sweep::{grid, session, Summary};

fn arg(name: &str) -> Option<f64> {
    let args: Vec<String> = std::env::args().collect();
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1))
        .map(|v| v.parse().unwrap_or_else(|_| panic!("{name} needs a number, got {v}")))
}

fn main() {
    let seeds = arg("--seeds").unwrap_or(5.0) as u64;
    let only = arg("--seconds");
    println!("| T (s) | pose noise | σ | τ (s) | LS mm / mrad | EM mm / mrad | bound mm / mrad | EM/bound | EM/bound, one session | LS/bound |");
    println!("|---|---|---|---|---|---|---|---|---|---|");
    let start = Instant::now();
    let mut worst: (f64, String) = (0.0, String::new());
    for cell in grid().into_iter().filter(|c| only.is_none_or(|s| s == c.seconds)) {
        let sessions: Vec<_> = (1..=seeds)
            .filter_map(|seed| match session(&cell, seed) {
                Ok(s) => Some(s),
                Err(e) => {
                    eprintln!("{cell:?} seed {seed}: {e}");
                    None
                }
            })
            .collect();
        let s = Summary::of(&sessions);
        let (ep, er) = s.em_ratio();
        let (lp, lr) = s.ls_ratio();
        let ((pl, ph), (rl, rh)) = s.em_ratio_range;
        let noise = if cell.noise.0 > 0.0 { "1 mm, 2 mrad" } else { "none" };
        let row = format!(
            "| {} | {noise} | {} | {} | {:.2} / {:.2} | {:.2} / {:.2} | {:.2} / {:.2} | {ep:.2} / {er:.2} | {pl:.2}–{ph:.2} / {rl:.2}–{rh:.2} | {lp:.2} / {lr:.2} |",
            cell.seconds,
            cell.sigma,
            cell.tau,
            s.ls.position_m * 1e3,
            s.ls.rotation_rad * 1e3,
            s.em.position_m * 1e3,
            s.em.rotation_rad * 1e3,
            s.bound.position_m * 1e3,
            s.bound.rotation_rad * 1e3,
        );
        println!("{row}");
        if ep.max(er) > worst.0 {
            worst = (ep.max(er), row);
        }
    }
    eprintln!("worst cell (EM / bound {:.2}): {}", worst.0, worst.1);
    eprintln!("{:.0} s", start.elapsed().as_secs_f64());
}
