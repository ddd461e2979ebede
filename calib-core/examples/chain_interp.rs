//! Measurement (not a product change): does the daemon's per-node sampling
//! phase + linear interpolation onto the 100 Hz grid explain why, through the whole chain, the
//! drift EM's real table error is ~1.5× its stated expected error?
//!
//! Paper scenario (τ = 1 s, σ = 1 paper convention, no pose noise), 60 s, per seed the sweep's
//! true table (`sweep::true_table`) and fresh poses. Variants, all fitted by LS from nominal +
//! our drift EM (`Simulation::fit`, dt = 0.01 s):
//! * `a`  : the 100 Hz `Scenario` as is (joints and pose at the same instants);
//! * `a0` : the fine simulation below with every phase 0 (a check: same process as `a`);
//! * `b`  : the session simulated at `FINE` s (same motion, same τ and *stationary* drift
//!   variance: exact discretisation at the fine step), pose = FK(truth, m(t_k)) at the grid
//!   instants t_k; each joint read at 100 Hz with its own random phase o_j ∈ [0, 10 ms), reading
//!   = m(t) − d(t), linearly interpolated onto t_k;
//! * `c`  : drift interpolated, motion exact (reported = m(t_k) − interp d);
//! * `d`  : motion interpolated, drift exact (reported = interp m − d(t_k)).
//!
//! Real table error: against the truth on the fresh poses and on the session's own poses (the
//! ones `expected_error` averages over). Stated: `DriftEmResult::expected_error`.
//! Also printed: the EM's fitted pose noise r (√, per component), fitted τ and stationary σ, and
//! an AR(1)+white decomposition of the *effective* drift δ_k = m(t_k) − reported_k per joint
//! (from its lag-0/1/2 autocovariances: φ = γ2/γ1, s² = γ1/φ, white w = γ0 − s²).
//!
//! What it shows: the excess comes from where the drift sits (the HIL suit reads
//! `angle = q − drift`, pose = FK(q): the reported angle carries the drift, so it is not
//! exogenous to it), not from the interpolation, which smooths the drift in the reading and
//! *lowers* the ratio (b and c below a0 and d). The excess vanishes at small σ, grows with σ
//! and with the session, and refitting with the Jacobians at θ + δ̂ (`--relin`) does not
//! remove it.
//!
//! With `--separate`, every variant's samples go through `calib_core::separate` first, as the
//! daemon's do, and every variant's ratio is about 1 (figures of `--seeds 20` with and
//! without it: BENCHMARKS.md, section "Accuracy: calib-core's sweeps", rerun by
//! `cargo xtask figures --slow`; quoted in calib-core/README.md, "The drift in the reading").
//!
//! `cargo run -p calib-core --release --example chain_interp -- [--seeds N] [--seconds S]
//! [--sigma S] [--tau T] [--only PREFIX] [--relin] [--separate]` (`--only a` runs a, a0, a1, a2).

use calib_core::drift::{Discretisation, GaussMarkov};
use calib_core::metrics::TableError;
use calib_core::sweep::{Cell, Field, Simulation};
use calib_core::{
    em_drift_vec, identify_ls, table_error, DhTable, DriftEmOptions, LsOptions, Rng, Sample, Scenario, ScenarioConfig,
    SeparationSlot, EXPECTED_ERROR_POSES, SUIT_PARAMS,
};

/// Fine simulation step (s).
const FINE: f64 = 0.001;
/// Grid step (s).
const GRID: f64 = 0.01;

fn arg(name: &str) -> Option<f64> {
    let a: Vec<String> = std::env::args().collect();
    a.iter()
        .position(|x| x == name)
        .and_then(|i| a.get(i + 1))
        .map(|v| v.parse().unwrap())
}

#[derive(Clone, Copy, PartialEq)]
enum Variant {
    A,
    A0,
    A1,
    A2,
    B,
    C,
    D,
}

impl Variant {
    fn name(self) -> &'static str {
        match self {
            Variant::A => "a  baseline 100 Hz Scenario",
            Variant::A0 => "a0 fine sim, phases 0",
            Variant::A1 => "a1 fine, phases 0, sim conv",
            Variant::A2 => "a2 100 Hz, chain convention",
            Variant::B => "b  interp motion + drift",
            Variant::C => "c  interp drift only",
            Variant::D => "d  interp motion only",
        }
    }
}

struct Row {
    real: (f64, f64),
    stated: (f64, f64),
    fresh: (f64, f64),
    relin: (f64, f64),
    own: (f64, f64),
    sqrt_r: [f64; 6],
    tau: f64,
    stat_sigma: f64,
    white: f64,
    ar_sigma: f64,
}

/// The effective drift's AR(1)+white decomposition, averaged (RMS) over joints: (s, √w).
fn decompose(delta: &[[f64; 7]]) -> (f64, f64) {
    let (mut s_acc, mut w_acc) = (0.0, 0.0);
    for j in 0..7 {
        let x: Vec<f64> = delta.iter().map(|d| d[j]).collect();
        let mean = x.iter().sum::<f64>() / x.len() as f64;
        let g = |lag: usize| x.iter().zip(&x[lag..]).map(|(a, b)| (a - mean) * (b - mean)).sum::<f64>() / (x.len() - lag) as f64;
        let (g0, g1, g2) = (g(0), g(1), g(2));
        let phi = g2 / g1;
        let s2 = g1 / phi;
        s_acc += s2;
        w_acc += g0 - s2;
    }
    ((s_acc / 7.0).sqrt(), (w_acc / 7.0).signum() * (w_acc.abs() / 7.0).sqrt())
}

fn main() {
    let seeds = arg("--seeds").unwrap_or(5.0) as u64;
    let seconds = arg("--seconds").unwrap_or(60.0);
    let only: Option<String> = {
        let a: Vec<String> = std::env::args().collect();
        a.iter().position(|x| x == "--only").and_then(|i| a.get(i + 1)).cloned()
    };
    let cell = Cell {
        tau: arg("--tau").unwrap_or(1.0),
        sigma: arg("--sigma").unwrap_or(1.0),
        noise: (0.0, 0.0),
        seconds,
        field: Field::PAPER,
    };
    let variants = [
        Variant::A,
        Variant::A0,
        Variant::A1,
        Variant::A2,
        Variant::B,
        Variant::C,
        Variant::D,
    ];
    let ratio = (GRID / FINE).round() as usize;
    let k = (seconds / GRID).round() as usize;
    let mut rows: Vec<Vec<Row>> = variants.iter().map(|_| Vec::new()).collect();
    let relin = std::env::args().any(|a| a == "--relin");
    let separate = std::env::args().any(|a| a == "--separate");
    let t0 = std::time::Instant::now();
    for seed in 1..=seeds {
        let sim = Simulation::new(&cell, seed);
        // Fine simulation: same motion (Motion::random is drawn first from the seed's rng), same
        // τ and stationary drift variance as the 100 Hz paper drift.
        let stat = sim.drift.stationary_variance().sqrt();
        let fine_drift = GaussMarkov {
            dt: FINE,
            tau: cell.tau,
            sigma: stat,
            discretisation: Discretisation::Exact,
        };
        let cfg = ScenarioConfig {
            actual: sim.truth,
            drift: fine_drift,
            ..ScenarioConfig::paper()
        };
        let n_fine = ratio * (k + 2);
        let fine: Vec<([f64; 7], [f64; 7])> = Scenario::new(cfg, seed)
            .take(n_fine)
            .map(|s| (s.sample.joints, s.drift))
            .collect();
        let mut prng = Rng::new(seed ^ 0x0FF5_E700);
        let offsets: [usize; 7] = core::array::from_fn(|_| ((prng.uniform() * ratio as f64) as usize).min(ratio - 1));
        for (vi, &v) in variants.iter().enumerate() {
            if only.as_deref().is_some_and(|o| !v.name().starts_with(o)) {
                continue;
            }
            let mut deltas: Vec<[f64; 7]> = Vec::with_capacity(k);
            let scen100 = || {
                Scenario::new(
                    ScenarioConfig {
                        actual: sim.truth,
                        drift: sim.drift,
                        ..ScenarioConfig::paper()
                    },
                    seed,
                )
                .take(k)
            };
            let mut samples: Vec<Sample<7>> = if v == Variant::A {
                sim.samples.clone()
            } else if v == Variant::A2 {
                // The 100 Hz Scenario's motion m and drift d, but the drift in the reading:
                // reported = m − d, pose = FK(m).
                scen100()
                    .map(|s| {
                        deltas.push(s.drift);
                        Sample {
                            joints: core::array::from_fn(|j| s.sample.joints[j] - s.drift[j]),
                            pose: sim.truth.fk(&s.sample.joints),
                        }
                    })
                    .collect()
            } else if v == Variant::A1 {
                // Fine simulation, phases 0, the Scenario's convention: reported = m,
                // pose = FK(m + d).
                (0..k)
                    .map(|kk| {
                        let (m, d) = fine[ratio * (kk + 1)];
                        deltas.push(d);
                        Sample {
                            joints: m,
                            pose: sim.truth.fk(&core::array::from_fn(|j| m[j] + d[j])),
                        }
                    })
                    .collect()
            } else {
                (0..k)
                    .map(|kk| {
                        // Grid instant t_k at fine index g = ratio·(k+1); joint j read at fine
                        // indices ratio·m + o_j; t_k lies between readings m = k and k + 1.
                        let g = ratio * (kk + 1);
                        let (m_true, d_true) = fine[g];
                        let reported: [f64; 7] = core::array::from_fn(|j| {
                            let o = if v == Variant::A0 { 0 } else { offsets[j] };
                            let w = o as f64 / ratio as f64; // weight of the earlier reading
                            let (m0, d0) = (fine[ratio * kk + o].0[j], fine[ratio * kk + o].1[j]);
                            let (m1, d1) = (fine[ratio * (kk + 1) + o].0[j], fine[ratio * (kk + 1) + o].1[j]);
                            let mi = w * m0 + (1.0 - w) * m1;
                            let di = w * d0 + (1.0 - w) * d1;
                            match v {
                                Variant::A0 | Variant::B => mi - di,
                                Variant::C => m_true[j] - di,
                                Variant::D => mi - d_true[j],
                                _ => unreachable!(),
                            }
                        });
                        deltas.push(core::array::from_fn(|j| m_true[j] - reported[j]));
                        Sample {
                            joints: reported,
                            pose: sim.truth.fk(&m_true),
                        }
                    })
                    .collect()
            };
            if v == Variant::A {
                // Effective drift of the Scenario: pose = FK(joints + drift).
                deltas = scen100().map(|s| s.drift).collect();
            }
            if separate {
                // The product's way (daemon pipeline): calib_core::separate before LS and EM.
                let mut slots = vec![SeparationSlot::default(); samples.len()];
                calib_core::separate(
                    &mut samples,
                    &DhTable::paper_nominal(),
                    GRID,
                    DriftEmOptions::<7>::new(GRID).initial_tau,
                    &mut slots,
                );
            }
            let (ar_sigma, white) = decompose(&deltas);
            let opts = DriftEmOptions::new(sim.drift.dt);
            let fit = identify_ls::<7, SUIT_PARAMS>(&DhTable::paper_nominal(), &samples, &LsOptions::new())
                .and_then(|ls| em_drift_vec::<7, SUIT_PARAMS>(&ls.table, &samples, &opts));
            let (em, smoothed) = match fit {
                Ok(f) => f,
                Err(e) => {
                    println!("seed {seed} {}: fit failed: {e:?}", v.name());
                    continue;
                }
            };
            // `--relin`: a crude relinearisation test: a second EM from the first one's table on
            // samples whose joints are moved by the smoothed drift (θ + δ̂), so the Jacobians are
            // taken at the estimated actual angle; the residual drift δ − δ̂ is again fitted as
            // AR(1). Its real table error is compared with the first pass's stated error.
            let relin = if relin {
                let moved: Vec<Sample<7>> = samples
                    .iter()
                    .zip(&smoothed)
                    .map(|(s, d)| Sample {
                        joints: core::array::from_fn(|j| s.joints[j] + d[j]),
                        pose: s.pose,
                    })
                    .collect();
                match em_drift_vec::<7, SUIT_PARAMS>(&em.table, &moved, &opts) {
                    Ok((em2, _)) => {
                        let e = sim.table_error(&em2.table);
                        (
                            e.position_m / em.expected_error.position_m,
                            e.rotation_rad / em.expected_error.rotation_rad,
                        )
                    }
                    Err(_) => (f64::NAN, f64::NAN),
                }
            } else {
                (f64::NAN, f64::NAN)
            };
            let stated = em.expected_error;
            let real_fresh = sim.table_error(&em.table);
            let stride = samples.len().div_ceil(EXPECTED_ERROR_POSES);
            let real_own = table_error(&em.table, &sim.truth, samples.iter().step_by(stride).map(|s| &s.joints));
            let r = |e: TableError| (e.position_m / stated.position_m, e.rotation_rad / stated.rotation_rad);
            let row = Row {
                real: (real_fresh.position_m, real_fresh.rotation_rad),
                stated: (stated.position_m, stated.rotation_rad),
                fresh: r(real_fresh),
                relin,
                own: r(real_own),
                sqrt_r: em.measurement_variance.map(f64::sqrt),
                tau: em.drift.iter().map(|d| d.tau).sum::<f64>() / 7.0,
                stat_sigma: (em.drift.iter().map(|d| d.stationary_sigma.powi(2)).sum::<f64>() / 7.0).sqrt(),
                white,
                ar_sigma,
            };
            println!(
                "seed {seed} {:<28} real/stated fresh {:.2} {:.2} own {:.2} {:.2} | stated {:.3} mm {:.3} mrad, real(fresh) {:.3} mm {:.3} mrad | √r {:.1e} {:.1e} {:.1e} m {:.1e} {:.1e} {:.1e} rad | τ̂ {:.2} σ̂ {:.2} mrad | δ: AR σ {:.2} mrad, white {:.3} mrad | {:.0} s",
                v.name(),
                row.fresh.0,
                row.fresh.1,
                row.own.0,
                row.own.1,
                stated.position_m * 1e3,
                stated.rotation_rad * 1e3,
                real_fresh.position_m * 1e3,
                real_fresh.rotation_rad * 1e3,
                row.sqrt_r[0],
                row.sqrt_r[1],
                row.sqrt_r[2],
                row.sqrt_r[3],
                row.sqrt_r[4],
                row.sqrt_r[5],
                row.tau,
                row.stat_sigma * 1e3,
                row.ar_sigma * 1e3,
                row.white * 1e3,
                t0.elapsed().as_secs_f64()
            );
            if seed == 1 && v == Variant::B {
                println!("   offsets (ms): {:?}", offsets.map(|o| o as f64 * FINE * 1e3));
            }
            rows[vi].push(row);
        }
    }
    println!(
        "\nSummary over {seeds} seeds, {seconds} s, τ = {} s, σ = {} (paper), no pose noise: real / stated, mean [min, max] of per-seed ratios; pooled = RMS real / RMS stated (fresh poses)",
        cell.tau, cell.sigma
    );
    println!(
        "{:<28} | {:^20} | {:^20} | {:^20} | {:^20} | pooled pos, rot | √r pos (m) | √r rot (rad) | δ white (mrad){}",
        "variant",
        "pos (fresh)",
        "rot (fresh)",
        "pos (own poses)",
        "rot (own poses)",
        if relin { " | relin pos | relin rot" } else { "" }
    );
    for (vi, v) in variants.iter().enumerate() {
        let rs = &rows[vi];
        if rs.is_empty() {
            continue;
        }
        let stat = |f: &dyn Fn(&Row) -> f64| {
            let x: Vec<f64> = rs.iter().map(f).collect();
            let mean = x.iter().sum::<f64>() / x.len() as f64;
            let (lo, hi) = x
                .iter()
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &y| (l.min(y), h.max(y)));
            format!("{mean:.2} [{lo:.2}, {hi:.2}]")
        };
        let mean = |f: &dyn Fn(&Row) -> f64| rs.iter().map(f).sum::<f64>() / rs.len() as f64;
        println!(
            "{:<28} | {:^20} | {:^20} | {:^20} | {:^20} | {:.2} {:.2} | {:.1e} | {:.1e} | {:.3}{}",
            v.name(),
            stat(&|r| r.fresh.0),
            stat(&|r| r.fresh.1),
            stat(&|r| r.own.0),
            stat(&|r| r.own.1),
            (mean(&|r| r.real.0.powi(2)) / mean(&|r| r.stated.0.powi(2))).sqrt(),
            (mean(&|r| r.real.1.powi(2)) / mean(&|r| r.stated.1.powi(2))).sqrt(),
            mean(&|r| (r.sqrt_r[0] + r.sqrt_r[1] + r.sqrt_r[2]) / 3.0),
            mean(&|r| (r.sqrt_r[3] + r.sqrt_r[4] + r.sqrt_r[5]) / 3.0),
            mean(&|r| r.white * 1e3),
            if relin {
                format!(" | {} | {}", stat(&|r| r.relin.0), stat(&|r| r.relin.1))
            } else {
                String::new()
            },
        );
    }
}
