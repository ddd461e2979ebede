//! Writes a session of the paper's Section 4 scenario as the CSV samples `exocald offline`
//! reads (`t,q1,…,q7,x,y,z,qw,qx,qy,qz`): the input of `cargo xtask bench`'s offline figure.
//!
//! `cargo run --release -p exocald --example scenario_csv -- OUT.csv [--samples K] [--seed S]`
//! (defaults: K = 6,000 samples at the scenario's 100 Hz, seed 1).

use calib_core::ScenarioConfig;
use exocal_session::detail::TimedSample;
use exocal_session::formats::csv_text;

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let value = |name: &str, default: u64| -> u64 {
        args.iter()
            .position(|a| a == name)
            .and_then(|i| args.get(i + 1))
            .map_or(default, |v| {
                v.parse()
                    .unwrap_or_else(|_| panic!("{name} needs a count, got {v}"))
            })
    };
    let Some(out) = args.first().filter(|a| !a.starts_with("--")) else {
        eprintln!("usage: scenario_csv OUT.csv [--samples K] [--seed S]");
        std::process::exit(2);
    };
    let k = value("--samples", 6_000) as usize;
    let cfg = ScenarioConfig::paper();
    let samples: Vec<TimedSample> = TimedSample::simulated(cfg, value("--seed", 1), k);
    std::fs::write(out, csv_text(&samples, 7)).unwrap_or_else(|e| panic!("writing {out}: {e}"));
    eprintln!("{out}: {k} samples");
}
