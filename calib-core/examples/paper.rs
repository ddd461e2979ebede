//! The paper's Section 4 scenario, end to end: nominal → LS → paper EM → our EM, in-sample and
//! on a held-out session of the same arm.
//!
//! `cargo run -p calib-core --release --example paper -- --seed 1 --seconds 60`
//! (optional: `--pos-noise <m> --rot-noise <rad>` white pose noise, `--em-iterations <n>`).

use std::time::Instant;

use calib_core::{
    cramer_rao, em_drift_vec, expected_table_error, identify_ls, objective_y, objective_y_corrected, paper_em, table_error,
    DhTable, DriftEmOptions, LsOptions, PaperEmForm, PaperEmOptions, ParamErrors, ParamKind, Sample, Scenario, ScenarioConfig,
    TableError, SUIT_PARAMS,
};

/// Fresh drift-free poses the table error is averaged over (another motion of the same arm).
const FRESH_POSES: usize = 2000;

fn arg(name: &str, default: f64) -> f64 {
    let args: Vec<String> = std::env::args().collect();
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1))
        .map(|v| v.parse().unwrap_or_else(|_| panic!("{name} needs a number, got {v}")))
        .unwrap_or(default)
}

fn pct(new: f64, base: f64) -> String {
    format!("{:+.2}%", 100.0 * (new - base) / base)
}

fn errs(label: &str, t: &DhTable<7>) {
    let e = ParamErrors::between(t, &DhTable::paper_actual());
    println!(
        "  {label:<12} max|Δa| {:.2e} m  max|Δd| {:.2e} m  max|Δα| {:.2e} rad  max|Δθ| {:.2e} rad",
        e.a, e.d, e.alpha, e.theta
    );
}

/// `mm / mrad` of a table error.
fn te(e: &TableError) -> String {
    format!("{:.3} / {:.3}", 1e3 * e.position_m, 1e3 * e.rotation_rad)
}

/// A table error against the bound, `×` per component.
fn vs_bound(e: &TableError, bound: &TableError) -> String {
    format!(
        "{:.2}× / {:.2}×",
        e.position_m / bound.position_m,
        e.rotation_rad / bound.rotation_rad
    )
}

fn main() {
    let seed = arg("--seed", 1.0) as u64;
    let seconds = arg("--seconds", 60.0);
    let mut cfg = ScenarioConfig::paper();
    cfg.position_noise = arg("--pos-noise", 0.0);
    cfg.rotation_noise = arg("--rot-noise", 0.0);
    let k = (seconds / cfg.drift.dt).round() as usize;
    let cal: Vec<_> = Scenario::new(cfg, seed).take(k).collect();
    let held: Vec<_> = Scenario::new(cfg, seed.wrapping_add(0x5EED_0F4E_1D00)).take(k).collect();
    let fresh: Vec<[f64; 7]> = Scenario::new(cfg, seed ^ 0xF2E5_4000_0000)
        .step_by(3)
        .take(FRESH_POSES)
        .map(|s| s.sample.joints)
        .collect();
    let samples: Vec<Sample<7>> = cal.iter().map(|s| s.sample).collect();
    let held_samples: Vec<Sample<7>> = held.iter().map(|s| s.sample).collect();
    let nominal = DhTable::paper_nominal();
    let truth = DhTable::paper_actual();

    let t0 = Instant::now();
    let ls = identify_ls::<7, SUIT_PARAMS>(&nominal, &samples, &LsOptions::paper()).expect("LS");
    let t_ls = t0.elapsed();
    let t0 = Instant::now();
    let pem_s = paper_em(&nominal, &ls.table, &samples, &PaperEmOptions::default()).expect("paper EM scalar");
    let pem_v = paper_em(
        &nominal,
        &ls.table,
        &samples,
        &PaperEmOptions {
            form: PaperEmForm::Vector,
            ..Default::default()
        },
    )
    .expect("paper EM vector");
    let t_pem = t0.elapsed();
    let t0 = Instant::now();
    let (em, drift) = em_drift_vec::<7, SUIT_PARAMS>(
        &ls.table,
        &samples,
        &DriftEmOptions {
            max_iterations: arg("--em-iterations", 100.0) as usize,
            ..DriftEmOptions::new(cfg.drift.dt)
        },
    )
    .expect("our EM");
    let t_em = t0.elapsed();

    let y_nom = objective_y(&nominal, &samples);
    let y_nom_h = objective_y(&nominal, &held_samples);
    let y_ls = objective_y(&ls.table, &samples);
    let y_ls_h = objective_y(&ls.table, &held_samples);
    let y_ps = objective_y(&pem_s.table, &samples);
    let y_ps_h = objective_y(&pem_s.table, &held_samples);
    let y_pv = objective_y(&pem_v.table, &samples);
    let y_pv_h = objective_y(&pem_v.table, &held_samples);
    let y_em = objective_y_corrected(&em.table, &samples, |k| drift[k]);
    let y_em_static = objective_y(&em.table, &samples);
    let y_em_h = objective_y(&em.table, &held_samples);
    let y_true = objective_y(&truth, &samples);
    let y_true_h = objective_y(&truth, &held_samples);
    let (pn, rn) = (cfg.position_noise.powi(2), cfg.rotation_noise.powi(2));
    let q = cfg.drift.process_variance();
    let crb = cramer_rao::<7, SUIT_PARAMS>(
        &truth,
        &samples,
        [cfg.drift.phi(); 7],
        [q; 7],
        [pn, pn, pn, rn, rn, rn],
        1e-14,
    )
    .expect("Cramér-Rao bound");
    let bound = expected_table_error::<7, SUIT_PARAMS>(&truth, &fresh, |u| crb.variance_along(u));
    let te_of = |t: &DhTable<7>| table_error(t, &truth, &fresh);
    let (te_nom, te_ls, te_ps, te_pv, te_em) = (
        te_of(&nominal),
        te_of(&ls.table),
        te_of(&pem_s.table),
        te_of(&pem_v.table),
        te_of(&em.table),
    );

    println!(
        "Section 4 scenario: seed {seed}, {seconds} s, K = {k} samples per session, Δt = 0.01 s, τ = 1 s, σ = 1 (paper discretisation), pose noise {} m / {} rad",
        cfg.position_noise, cfg.rotation_noise
    );
    println!();
    println!("| method | y calibration | vs | y held-out | vs | table error mm / mrad | vs bound |");
    println!("|---|---|---|---|---|---|---|");
    println!(
        "| nominal (Table 1) | {y_nom:.4} | | {y_nom_h:.4} | | {} | {} |",
        te(&te_nom),
        vs_bound(&te_nom, &bound)
    );
    println!(
        "| LS (28 params) | {y_ls:.4} | {} vs nominal | {y_ls_h:.4} | {} vs nominal | {} | {} |",
        pct(y_ls, y_nom),
        pct(y_ls_h, y_nom_h),
        te(&te_ls),
        vs_bound(&te_ls, &bound)
    );
    println!(
        "| paper EM, scalar (eq. 11 z = row 1) | {y_ps:.4} | {} vs LS | {y_ps_h:.4} | {} vs LS | {} | {} |",
        pct(y_ps, y_ls),
        pct(y_ps_h, y_ls_h),
        te(&te_ps),
        vs_bound(&te_ps, &bound)
    );
    println!(
        "| paper EM, 6-vector | {y_pv:.4} | {} vs LS | {y_pv_h:.4} | {} vs LS | {} | {} |",
        pct(y_pv, y_ls),
        pct(y_pv_h, y_ls_h),
        te(&te_pv),
        vs_bound(&te_pv, &bound)
    );
    println!(
        "| our EM (table + smoothed drift) | {y_em:.4} | {} vs LS | {y_em_h:.4} | {} vs LS | {} | {} |",
        pct(y_em, y_ls),
        pct(y_em_h, y_ls_h),
        te(&te_em),
        vs_bound(&te_em, &bound)
    );
    println!(
        "| our EM table only (no drift) | {y_em_static:.4} | {} vs LS | | | | |",
        pct(y_em_static, y_ls)
    );
    println!(
        "| truth (Table 4, drift unknown) | {y_true:.4} | {} vs LS | {y_true_h:.4} | {} vs LS | 0 / 0 | |",
        pct(y_true, y_ls),
        pct(y_true_h, y_ls_h)
    );
    println!();
    println!(
        "Table error: RMS over {FRESH_POSES} fresh drift-free poses of FK(table) against FK(Table 4). Bound: the Cramér-Rao bound at the truth (drift integrated out), {} mm / mrad; our EM's own expected error (the bound at its estimates) {} mm / mrad.",
        te(&bound),
        te(&em.expected_error)
    );
    println!();
    println!("Parameter errors against Table 4:");
    errs("LS", &ls.table);
    errs("paper EM s", &pem_s.table);
    errs("paper EM v", &pem_v.table);
    errs("our EM", &em.table);
    println!();
    println!(
        "LS: {} iterations, rank {}/28, condition {:.1}, O1 {:.3e} O2 {:.3e} O3 {:.3e} O4 {:.3e}, rms {:.3e}",
        ls.iterations,
        ls.rank,
        ls.condition,
        ls.observability.o1,
        ls.observability.o2,
        ls.observability.o3,
        ls.observability.o4,
        ls.rms
    );
    print!("LS 1-σ (white-noise CRB) of θ offsets (mrad):");
    for j in 0..7 {
        print!(" {:.3}", 1e3 * ls.std_errors[ParamKind::Theta.index(j, 7)]);
    }
    println!();
    print!("LS actual θ-offset errors (mrad):               ");
    for j in 0..7 {
        print!(" {:.3}", 1e3 * (ls.table.rows[j].theta_offset - truth.rows[j].theta_offset));
    }
    println!();
    println!(
        "paper EM scalar: {} iterations, π = {:?}\n  μ = {:?}",
        pem_s.log_likelihood.len(),
        pem_s.pi.map(|p| (p * 1e4).round() / 1e4),
        pem_s.mu.map(|p| (p * 1e4).round() / 1e4)
    );
    println!(
        "paper EM vector: {} iterations, π = {:?}",
        pem_v.log_likelihood.len(),
        pem_v.pi.map(|p| (p * 1e4).round() / 1e4)
    );
    println!(
        "our EM: {} maps on every {}th sample, {} exact informations (converged: {}), log-likelihood of all samples {:.1}, noise std {:?}",
        em.iterations,
        em.stride,
        em.information_passes,
        em.converged,
        em.final_log_likelihood,
        em.measurement_variance.map(|v| format!("{:.1e}", v.sqrt()))
    );
    let h = &em.log_likelihood;
    let hist: Vec<String> = h.iter().map(|v| format!("{v:.1}")).collect();
    println!(
        "our EM log-likelihood of the iterated samples at each accepted iterate: {}",
        hist.join(", ")
    );
    println!();
    println!(
        "| joint | τ (s) | stationary σ (mrad) | paper σ | offset/drift separability σ√(2τ/T) (mrad) | θ-offset error (mrad) | θ-offset CRB 1σ (mrad) |"
    );
    println!("|---|---|---|---|---|---|---|");
    for j in 0..7 {
        let d = em.drift[j];
        println!(
            "| {} | {:.3} | {:.3} | {:.3} | {:.3} | {:+.3} | {:.3} |",
            j + 1,
            d.tau,
            1e3 * d.stationary_sigma,
            d.paper_sigma,
            1e3 * em.separability[j],
            1e3 * (em.table.rows[j].theta_offset - truth.rows[j].theta_offset),
            1e3 * em.std_errors[ParamKind::Theta as usize][j]
        );
    }
    let rms_drift: f64 = (cal.iter().map(|s| s.drift.iter().map(|d| d * d).sum::<f64>()).sum::<f64>() / (7 * k) as f64).sqrt();
    let rms_track: f64 = (cal
        .iter()
        .zip(&drift)
        .map(|(s, d)| (0..7).map(|j| (s.drift[j] - d[j]).powi(2)).sum::<f64>())
        .sum::<f64>()
        / (7 * k) as f64)
        .sqrt();
    println!();
    println!(
        "true drift RMS {:.3} mrad; smoothed-drift error RMS {:.3} mrad",
        1e3 * rms_drift,
        1e3 * rms_track
    );
    println!("time: LS {t_ls:.2?}, both paper EMs {t_pem:.2?}, our EM {t_em:.2?}");
}
