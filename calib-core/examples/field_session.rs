//! One session of a field cell in detail: what LS and our EM make of it, the drift
//! model each joint got and why, the discounted reference samples, the consistency statistics,
//! the refusals, against the simulated truth.
//!
//! `cargo run -p calib-core --release --example field_session -- CELL SEED [OPTIONS]`, CELL a
//! substring of a `sweep::field_grid` cell's name, OPTIONS comma-separated: `plain` (the paper's
//! model alone, `DriftEmOptions::plain`), `no-rate-bias`, `no-robust`, `no-restricted`,
//! `relinearise`, `spec` (the EM told the sensors' rate bias as the cell simulates it), `arm` (the
//! cell's drift in the arm instead of the reading), `from-truth` (the EM started at the true
//! table instead of LS), `no-separate` (the readings fitted as they come, not separated first).

use calib_core::sweep::{field_grid, Simulation};
use calib_core::{
    em_drift_vec, identify_ls, separate, DhTable, DriftEmOptions, DriftSite, LsOptions, Scenario, ScenarioConfig, SeparationSlot,
};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let (Some(only), Some(seed)) = (args.get(1), args.get(2).and_then(|s| s.parse::<u64>().ok())) else {
        eprintln!("usage: field_session CELL SEED [OPTIONS]");
        std::process::exit(64);
    };
    let options: Vec<&str> = args.get(3).map_or(Vec::new(), |s| s.split(',').collect());
    let has = |o: &str| options.contains(&o);
    for (name, mut cell) in field_grid() {
        if !name.contains(only.as_str()) {
            continue;
        }
        if has("arm") {
            cell.field.site = DriftSite::Arm;
        }
        let sim = Simulation::new(&cell, seed);
        let mut opts = if has("plain") {
            DriftEmOptions::plain(sim.drift.dt)
        } else {
            DriftEmOptions::new(sim.drift.dt)
        };
        opts.rate_bias &= !has("no-rate-bias");
        opts.robust &= !has("no-robust");
        opts.restricted &= !has("no-restricted");
        if has("relinearise") {
            opts.relinearisations = 2;
        }
        if has("spec") {
            opts.rate_bias_spec = cell.field.bias;
        }
        let mut samples = sim.samples.clone();
        let mut slots = vec![SeparationSlot::default(); samples.len()];
        if !has("no-separate") {
            let fits = separate(
                &mut samples,
                &DhTable::paper_nominal(),
                sim.drift.dt,
                opts.initial_tau,
                &mut slots,
            );
            println!(
                "  separated: readings moved by {:?} mrad RMS",
                fits.map(|f| (f.correction_rms * 1e4).round() / 10.0)
            );
        }
        let ls = identify_ls::<7, 28>(&DhTable::paper_nominal(), &samples, &LsOptions::new()).expect("LS");
        let start = if has("from-truth") { sim.truth } else { ls.table };
        let t0 = std::time::Instant::now();
        let (em, _) = em_drift_vec::<7, 28>(&start, &samples, &opts).expect("EM");
        let ms = t0.elapsed().as_secs_f64() * 1e3;
        let (real, lse) = (sim.table_error(&em.table), sim.table_error(&ls.table));
        let mm = |e: calib_core::TableError| format!("{:.2} mm / {:.2} mrad", e.position_m * 1e3, e.rotation_rad * 1e3);
        println!("{name}, seed {seed} {options:?}: K = {}, {ms:.0} ms", samples.len());
        println!(
            "  EM: {} maps, {} informations, converged {}, stride {}",
            em.iterations, em.information_passes, em.converged, em.stride
        );
        println!(
            "  real {} (LS {}); stated {}, its bound part {}",
            mm(real),
            mm(lse),
            mm(em.stated_error),
            mm(em.expected_error)
        );
        // The truth of the drift: the Gauss-Markov part's τ, σ and each joint's integrated rate bias.
        let no_gm = ScenarioConfig {
            actual: sim.truth,
            drift: calib_core::GaussMarkov { sigma: 0.0, ..sim.drift },
            bias: cell.field.bias,
            heading: cell.field.heading,
            ..ScenarioConfig::paper()
        };
        let end = Scenario::new(no_gm, seed).nth(samples.len() - 1).expect("a sample").drift;
        println!(
            "  truth: τ {} s, σ {:.2} mrad; rate bias's angle at the end {:?} mrad",
            cell.tau,
            sim.drift.stationary_variance().sqrt() * 1e3,
            end.map(|x| (x * 1e4).round() / 10.0)
        );
        for j in 0..7 {
            let c = em.consistency.joints[j];
            println!(
                "  joint {}: τ {:.2} s, σ {:.2} mrad; {}; innovations: long-run {:.2}, lag-1 {:+.2}, largest {:.1} at {}",
                j + 1,
                em.drift[j].tau,
                em.drift[j].stationary_sigma * 1e3,
                em.models[j],
                c.long_run,
                c.lag1,
                c.largest,
                c.at
            );
        }
        println!(
            "  pose noise (1σ) {:?}",
            em.measurement_variance.map(|v| format!("{:.1e}", v.sqrt()))
        );
        let d = &em.discounted;
        println!(
            "  discounted {} of {} (glitched in truth {}), Student-t ν {:.1}, first runs {:?}",
            d.count,
            d.samples,
            sim.glitched.iter().filter(|g| **g).count(),
            d.dof,
            &d.runs[..d.runs.len().min(6)]
        );
        let c = &em.consistency;
        println!(
            "  pose innovations: NIS {:?}, long-run {:?} ({} blocks)",
            c.pose_nis.map(|v| format!("{v:.2}")),
            c.pose_long_run.map(|v| format!("{v:.2}")),
            c.blocks
        );
        for r in &em.refusals {
            println!("  REFUSED: {r}");
        }
    }
}
