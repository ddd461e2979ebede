//! A report on the paper's simulated Section 4 session, without any CAN: LS then EM as the
//! daemon's pipeline runs them, rendered by exocal-report.
//! `cargo run -p exocald --release --example paper_report -- [out.html] [seconds] [seed]`.

use calib_core::{DhTable, DriftEmOptions, LsOptions, ScenarioConfig};
use exocal_report::{html, Quality, ReportInput, TimedSample};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let out = args.first().map_or("paper_report.html", String::as_str);
    let seconds: f64 = args.get(1).map_or(Ok(30.0), |s| s.parse())?;
    let seed: u64 = args.get(2).map_or(Ok(1), |s| s.parse())?;

    let cfg = ScenarioConfig::paper();
    let k = (seconds / cfg.drift.dt).round() as usize;
    let all: Vec<TimedSample> = TimedSample::simulated(cfg, seed, k);
    let (fit, held) = all.split_at(all.len() * 4 / 5);
    let nominal = DhTable::paper_nominal();
    let fit_samples: Vec<_> = fit.iter().map(|s| s.sample).collect();
    let started = std::time::Instant::now();
    let calibration = exocal_session::pipeline::ls_then_em::<7, 28>(
        &nominal,
        &fit_samples,
        &LsOptions::new(),
        &DriftEmOptions::new(cfg.drift.dt),
        true,
    )?;
    eprintln!("calibrated in {:.1?}", started.elapsed());
    let input = ReportInput {
        title: format!("Paper scenario, {seconds} s, seed {seed}"),
        source: "calib-core's simulated Section 4 session (Table 4 arm, Gauss-Markov drift)".into(),
        nominal,
        calibration,
        judged: None,
        fit: fit.to_vec(),
        held_out: held.to_vec(),
        quality: Quality {
            duration_s: seconds,
            grid_hz: 1.0 / cfg.drift.dt,
            joint_ranges: calib_core::JointRanges::<7>::paper().limits.to_vec(),
            excitation_required: Some(0.5),
            ..Quality::default()
        },
        verdict: None,
        at_rest: None,
        push: None,
    };
    let started = std::time::Instant::now();
    std::fs::write(out, html::render(&input))?;
    eprintln!("wrote {out} (rendered in {:.1?})", started.elapsed());
    Ok(())
}
