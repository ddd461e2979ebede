//! Calibration: calib-core's LS against `scipy.optimize.least_squares` on the same exported
//! datasets (`calib-core/examples/export_dataset.rs`, `benches/scipy_ls.py`, from the bench venv),
//! both pinned to CPU 0; LS + our EM at K = 1,000 and 6,000; the per-sample kernel costs that
//! bound the LS time.

use std::fmt::Write as _;
use std::path::PathBuf;
use std::process::Command;

use anyhow::{Context, Result};
use serde_json::Value;

use super::common::{
    capture, f, json_lines, ms, pinned, run, s, show, venv_python, Ctx, Goal, Section,
};
use crate::paths;

/// This part's section title in the report.
pub const TITLE: &str = "Calibration: calib-core against scipy";

pub fn measure(ctx: &Ctx) -> Result<Section> {
    let (ks, repeats, em_repeats, py_repeats) = if ctx.quick {
        ("1000,6000", "3", "1", "1")
    } else {
        ("1000,6000,20000", "7", "3", "5")
    };
    let mut build = Command::new(paths::cargo());
    build.current_dir(&ctx.root).args([
        "build",
        "--release",
        "-p",
        "calib-core",
        "--example",
        "export_dataset",
    ]);
    let build_cmd = show(&build);
    run(&mut build)?;
    let data = ctx.target.join("bench/calib");
    let mut rust = pinned(ctx, ctx.target.join("release/examples/export_dataset"));
    rust.current_dir(&ctx.root).arg("--out").arg(&data).args([
        "--k",
        ks,
        "--repeats",
        repeats,
        "--em-k",
        "1000,6000",
        "--em-repeats",
        em_repeats,
    ]);
    let rust_cmd = show(&rust);
    let rust_out = json_lines(&capture(&mut rust)?);
    // The multi-core figure: the daemon's parallel linearisation, not pinned (it needs cores).
    let mut build_par = Command::new(paths::cargo());
    build_par.current_dir(&ctx.root).args([
        "build",
        "--release",
        "-p",
        "exocal-session",
        "--example",
        "parallel_ls",
    ]);
    let build_par_cmd = show(&build_par);
    run(&mut build_par)?;
    let mut par = Command::new(ctx.target.join("release/examples/parallel_ls"));
    par.current_dir(&ctx.root).args(["--repeats", repeats]);
    let par_cmd = show(&par);
    let par_out = json_lines(&capture(&mut par)?);
    let (python, venv_cmds) = venv_python(ctx)?;
    let dirs: Vec<PathBuf> = ks.split(',').map(|k| data.join(format!("k{k}"))).collect();
    let mut py = pinned(ctx, &python);
    py.current_dir(&ctx.root)
        .env("OPENBLAS_NUM_THREADS", "1")
        .env("OMP_NUM_THREADS", "1")
        .env("MKL_NUM_THREADS", "1")
        .arg("benches/scipy_ls.py")
        .args(&dirs)
        .args(["--repeats", py_repeats]);
    let py_cmd = show(&py);
    let py_out = json_lines(&capture(&mut py)?);
    // Paired rounds: this machine's speed drifts by tens of percent within minutes (shared
    // cores), more than the 20× goal's margin, and the run above times all of calib-core before
    // all of scipy. Each round times calib-core's LS and then scipy's analytic variants (the
    // fastest ones) on the same data, back to back; the goal is judged on the median over
    // rounds of each round's ratio.
    let rounds = if ctx.quick { 1 } else { 5 };
    let round_data = ctx.target.join("bench/calib-rounds");
    let mut rust_round = pinned(ctx, ctx.target.join("release/examples/export_dataset"));
    rust_round
        .current_dir(&ctx.root)
        .arg("--out")
        .arg(&round_data)
        .args(["--k", ks, "--repeats", repeats, "--em-k", ""]);
    let round_dirs: Vec<PathBuf> = ks
        .split(',')
        .map(|k| round_data.join(format!("k{k}")))
        .collect();
    let mut py_round = pinned(ctx, &python);
    py_round
        .current_dir(&ctx.root)
        .env("OPENBLAS_NUM_THREADS", "1")
        .env("OMP_NUM_THREADS", "1")
        .env("MKL_NUM_THREADS", "1")
        .arg("benches/scipy_ls.py")
        .args(&round_dirs)
        .args([
            "--repeats",
            py_repeats,
            "--variants",
            "trf-analytic,lm-analytic",
        ]);
    let round_cmds = format!(
        "for round in 1 2 3 4 5; do\n    {}\n    {}\ndone",
        show(&rust_round),
        show(&py_round)
    );
    let mut paired: Vec<Vec<f64>> = Vec::new();
    for _ in 0..rounds {
        let ours = json_lines(&capture(&mut rust_round)?);
        let theirs = json_lines(&capture(&mut py_round)?);
        paired.push(paired_ratios(ks, &ours, &theirs));
    }

    let by = |lines: &[Value], bench: &str| -> Vec<Value> {
        lines
            .iter()
            .filter(|v| s(v, "bench") == bench)
            .cloned()
            .collect()
    };
    let ls = by(&rust_out, "calib-core");
    let kernels = by(&rust_out, "calib-core-kernels")
        .into_iter()
        .next()
        .context("no kernel timings")?;
    let scipy = by(&py_out, "scipy");
    let checks = by(&py_out, "scipy-check");
    let mut body = String::new();
    let mut goals = Vec::new();
    let versions = checks
        .first()
        .map(|c| {
            format!(
                "Python {}, numpy {}, scipy {}",
                s(c, "python"),
                s(c, "numpy"),
                s(c, "scipy")
            )
        })
        .unwrap_or_default();
    let _ = writeln!(
        body,
        "The Section 4 scenario of the paper (seed 1, Table 4 arm, Gauss-Markov drift τ = 1 s, σ = 1 \
         on every joint, 100 Hz, no pose noise): the first K samples of one session, exported as \
         CSV and solved from Table 1 by both sides for all 28 D-H parameters, minimising the same \
         Σ‖e‖² of calib-core's tool-frame pose error. scipy side ({versions}): vectorised numpy \
         kinematics over all samples, `x_scale='jac'`, `ftol=1e-15, xtol=1e-12, gtol=1e-15` \
         against calib-core's step tolerance 1e-12 and cost-gain tolerance 1e-15, four variants \
         (`trf`/`lm` × analytic Jacobian / scipy's `2-point`); the fastest variant that reaches \
         the same cost is the one compared. Both sides single-threaded on CPU 0 \
         (`taskset -c 0`, BLAS threads 1). Times are medians of repeated solves (data loading \
         excluded; calib-core {repeats} runs, scipy {py_repeats} runs per variant) of the \
         process CPU clock, so that other processes on the shared core do not count; wall-clock \
         medians are given beside them.\n"
    );
    // Model agreement: both sides evaluate the starting cost on the same data.
    let _ = writeln!(body, "**Same model on both sides** (cost Σ‖e‖² at Table 1; analytic Jacobian vs central differences in numpy):\n");
    let _ = writeln!(body, "| K | calib-core | numpy | relative difference | numpy jac − FD (max abs) |\n|---|---|---|---|---|");
    for c in &checks {
        let k = f(c, "k");
        if let Some(r) = ls.iter().find(|v| s(v, "solver") == "ls" && f(v, "k") == k) {
            let (a, b) = (f(r, "cost_start"), f(c, "cost_start"));
            let _ = writeln!(
                body,
                "| {k} | {a:.15e} | {b:.15e} | {:.1e} | {:.1e} |",
                ((a - b) / a).abs(),
                f(c, "jac_max_abs_diff")
            );
        }
    }
    let _ = writeln!(body);
    let _ = writeln!(
        body,
        "| K | calib-core LS, CPU ms (wall) | fastest scipy, CPU ms (wall) | scipy ÷ calib-core | cost calib-core | cost scipy | y calib-core | y scipy | ‖x − truth‖ calib-core | ‖x − truth‖ scipy |\n|---|---|---|---|---|---|---|---|---|---|"
    );
    let mut worst_ratio = f64::INFINITY;
    let mut accuracy_ok = true;
    for r in ls.iter().filter(|v| s(v, "solver") == "ls") {
        let k = f(r, "k");
        let cost = f(r, "cost");
        // The fastest scipy variant that reached calib-core's cost (to 1e-9 relative).
        let best = scipy
            .iter()
            .filter(|v| f(v, "k") == k && f(v, "cost") <= cost * (1.0 + 1e-9))
            .min_by(|a, b| f(a, "median_s").total_cmp(&f(b, "median_s")))
            .or_else(|| {
                scipy
                    .iter()
                    .filter(|v| f(v, "k") == k)
                    .min_by(|a, b| f(a, "median_s").total_cmp(&f(b, "median_s")))
            });
        let Some(b) = best else { continue };
        let ratio = f(b, "median_s") / f(r, "median_s");
        worst_ratio = worst_ratio.min(ratio);
        accuracy_ok &= cost <= f(b, "cost") * (1.0 + 1e-9);
        let _ = writeln!(
            body,
            "| {k} | {} ({}) | {} ({}), {} | {ratio:.2}× | {:.10e} | {:.10e} | {:.6} | {:.6} | {:.3e} | {:.3e} |",
            ms(f(r, "median_s")),
            ms(f(r, "wall_median_s")),
            ms(f(b, "median_s")),
            ms(f(b, "wall_median_s")),
            s(b, "variant"),
            cost,
            f(b, "cost"),
            f(r, "y"),
            f(b, "y"),
            f(r, "err_norm"),
            f(b, "err_norm")
        );
    }
    let _ = writeln!(body, "\nEvery scipy variant (median CPU ms; function and Jacobian evaluations; ratio to calib-core's LS):\n");
    let _ = writeln!(body, "| K | variant | median (ms) | nfev | njev | scipy ÷ calib-core | cost | stop |\n|---|---|---|---|---|---|---|---|");
    for v in &scipy {
        let k = f(v, "k");
        let ours = ls
            .iter()
            .find(|r| s(r, "solver") == "ls" && f(r, "k") == k)
            .map(|r| f(r, "median_s"))
            .unwrap_or(f64::NAN);
        let _ = writeln!(
            body,
            "| {k} | {} | {} | {} | {} | {:.2}× | {:.10e} | {} |",
            s(v, "variant"),
            ms(f(v, "median_s")),
            v.get("nfev").map(Value::to_string).unwrap_or_default(),
            v.get("njev")
                .filter(|n| !n.is_null())
                .map_or("—".to_string(), Value::to_string),
            f(v, "median_s") / ours,
            f(v, "cost"),
            s(v, "message").replace('|', "/")
        );
    }
    let _ = writeln!(body, "\nParameter errors against Table 4 (largest per kind; the drift, not the solver, limits them: both sides reach the same least-squares optimum):\n");
    let _ = writeln!(body, "| K | solver | max\\|Δa\\| (m) | max\\|Δd\\| (m) | max\\|Δα\\| (rad) | max\\|Δθ\\| (rad) |\n|---|---|---|---|---|---|");
    for r in &ls {
        let _ = writeln!(
            body,
            "| {} | calib-core {} | {:.3e} | {:.3e} | {:.3e} | {:.3e} |",
            f(r, "k"),
            if s(r, "solver") == "ls" {
                "LS"
            } else {
                "LS + our EM"
            },
            f(r, "err_a"),
            f(r, "err_d"),
            f(r, "err_alpha"),
            f(r, "err_theta")
        );
    }
    for v in scipy.iter().filter(|v| s(v, "variant") == "lm-analytic") {
        let _ = writeln!(
            body,
            "| {} | scipy lm-analytic | {:.3e} | {:.3e} | {:.3e} | {:.3e} |",
            f(v, "k"),
            f(v, "err_a"),
            f(v, "err_d"),
            f(v, "err_alpha"),
            f(v, "err_theta")
        );
    }
    // LS + EM.
    let _ = writeln!(body, "\nLS followed by our EM (Kalman filter + RTS smoother over the drift), calib-core only (scipy has no counterpart):\n");
    let _ = writeln!(body, "| K | LS + EM, CPU ms (wall) | of which EM (CPU ms) | EM maps (on every n-th sample) | exact informations | converged | y (static table) | table error mm / mrad |\n|---|---|---|---|---|---|---|---|");
    let mut em6000 = None;
    for r in ls.iter().filter(|v| s(v, "solver") == "ls+em") {
        if f(r, "k") == 6000.0 {
            em6000 = Some(f(r, "median_s"));
        }
        let _ = writeln!(
            body,
            "| {} | {} ({}) | {} | {} (n = {}) | {} | {} | {:.4} | {:.3} / {:.3} |",
            f(r, "k"),
            ms(f(r, "median_s")),
            ms(f(r, "wall_median_s")),
            ms(f(r, "em_median_s")),
            r.get("em_iterations")
                .map(Value::to_string)
                .unwrap_or_default(),
            r.get("em_stride").map(Value::to_string).unwrap_or_default(),
            r.get("em_informations")
                .map(Value::to_string)
                .unwrap_or_default(),
            r.get("em_converged")
                .map(Value::to_string)
                .unwrap_or_default(),
            f(r, "y"),
            f(r, "table_error_mm"),
            f(r, "table_error_mrad")
        );
    }
    let _ = writeln!(
        body,
        "\nOur EM iterates on every n-th sample (the drift of a decimated session is the same \
         Gauss-Markov process), accelerated by SQUAREM, with the geometry step preconditioned by \
         an exact information recomputed only when the drift parameters have moved; one pass \
         over all samples then gives the final table and its Cramér-Rao bound \
         (`calib-core/src/drift_em.rs`). Table error: RMS over 2,000 fresh drift-free poses of \
         FK(table) against FK(Table 4).\n"
    );
    // Several cores: the daemon's parallel linearisation (wall clock; not pinned).
    let par_rows = by(&par_out, "calib-parallel");
    let _ = writeln!(body, "**Several cores** (`daemon/src/parallel.rs`: the LS linearisation in one block of samples per thread, merged in order; the EM is sequential in time), K = 6,000, wall-clock medians of {repeats} runs, not pinned, on this machine ({} cores available):\n", std::thread::available_parallelism().map_or(1, |n| n.get()));
    let _ = writeln!(body, "| threads | LS, wall ms | LS + our EM, wall ms | CPU ms per LS + EM (all threads) | cost |\n|---|---|---|---|---|");
    for r in &par_rows {
        let _ = writeln!(
            body,
            "| {} | {} | {} | {} | {:.10e} |",
            f(r, "threads"),
            ms(f(r, "ls_wall_median_s")),
            ms(f(r, "ls_em_wall_median_s")),
            ms(f(r, "cpu_per_run_s")),
            f(r, "cost")
        );
    }
    let par_of = |t: f64| par_rows.iter().find(|r| f(r, "threads") == t);
    let speedup = match (par_of(1.0), par_of(2.0)) {
        (Some(a), Some(b)) => Some((
            f(a, "ls_wall_median_s") / f(b, "ls_wall_median_s"),
            f(a, "ls_em_wall_median_s") / f(b, "ls_em_wall_median_s"),
        )),
        _ => None,
    };
    // What the LS time is made of: the model evaluation per sample (kernels measured by the
    // export), on the number of linearisations each solve took.
    let jac_cost = f(&kernels, "fk_jacobian_s") + f(&kernels, "residual_jacobian_s");
    let _ = writeln!(
        body,
        "\n**What the LS time is made of.** Per sample and linearisation (median of 7 × 20,000 \
         calls): FK + identification Jacobian {:.2} µs, residual Jacobian M(e)·J {:.2} µs. \
         calib-core's LS accumulates the column-scaled normal equations per linearisation (a \
         rank-6 update per sample; a blocked Householder QR over 8-sample panels instead when the \
         scaled problem is ill-conditioned), evaluates likely-rejected trial steps on the cost \
         alone, and takes the last Gauss-Newton step (predicted gain below 3e-10 of the cost) on \
         the cost alone. Per-kernel figures (normal-equation \
         update, QR panel, SVD analysis): `cargo bench -p calib-core --bench kernels`.\n",
        f(&kernels, "fk_jacobian_s") * 1e6,
        f(&kernels, "residual_jacobian_s") * 1e6,
    );
    let _ = writeln!(
        body,
        "| K | iterations | model evaluation alone: (iterations + 1) × K × (FK + Jacobians) (CPU ms) | measured (CPU ms) |\n|---|---|---|---|"
    );
    for r in ls.iter().filter(|v| s(v, "solver") == "ls") {
        let it = f(r, "iterations");
        let _ = writeln!(
            body,
            "| {} | {it} | {} | {} |",
            f(r, "k"),
            ms((it + 1.0) * f(r, "k") * jac_cost),
            ms(f(r, "median_s"))
        );
    }
    // The floor of any per-sample f64 implementation: as many Jacobians as scipy needs, at the
    // cost of FK + Jacobians alone (a free QR), against a twentieth of scipy's time.
    let _ = writeln!(
        body,
        "**Is 20× reachable?** A twentieth of the fastest scipy time against a floor for any \
         solver that evaluates this model per sample in f64: as many Jacobian evaluations as \
         scipy's fastest variant needed, each costing calib-core's FK + Jacobians alone (the \
         linear algebra and everything else for free):\n"
    );
    let _ = writeln!(body, "| K | fastest scipy ÷ 20 (CPU ms) | floor: njev × K × (FK + Jacobians) (CPU ms) |\n|---|---|---|");
    let mut floor_blocks = true;
    for r in ls.iter().filter(|v| s(v, "solver") == "ls") {
        let k = f(r, "k");
        let Some(b) = scipy
            .iter()
            .filter(|v| f(v, "k") == k)
            .min_by(|a, b| f(a, "median_s").total_cmp(&f(b, "median_s")))
        else {
            continue;
        };
        let njev = b
            .get("njev")
            .and_then(Value::as_f64)
            .unwrap_or(f(b, "nfev"));
        let floor = njev * k * jac_cost;
        floor_blocks &= floor > f(b, "median_s") / 20.0;
        let _ = writeln!(
            body,
            "| {k} | {} | {} |",
            ms(f(b, "median_s") / 20.0),
            ms(floor)
        );
    }
    let _ = writeln!(
        body,
        "\n{}\n",
        if floor_blocks {
            "At every K the floor is above a twentieth of scipy's time: numpy's vectorised \
             kinematics already run near C speed, so the 20× goal is out of reach for this \
             problem with a per-sample f64 model evaluation, whatever the solver does."
        } else {
            "The floor is below a twentieth of scipy's time for some K: the gap there is \
             calib-core's linear algebra (the normal-equation update) and iteration count, not \
             the model evaluation alone."
        }
    );
    let _ = writeln!(
        body,
        "Reproduce:\n\n```sh\n{build_cmd}\n{rust_cmd}\n{}\n{py_cmd}\n{build_par_cmd}\n{par_cmd}\n```\n",
        venv_cmds.join("\n")
    );
    // The paired rounds: per K, the median and range of the rounds' ratios.
    let k_list: Vec<&str> = ks.split(',').collect();
    let _ = writeln!(
        body,
        "**Paired rounds** (what the goal is judged on): this machine's speed drifts by tens of percent within minutes (its cores are shared), and the run above times all of calib-core's solves before all of scipy's. {rounds} more rounds each time calib-core's LS ({repeats} solves per K) and then scipy's two analytic variants ({py_repeats} solves each per K) back to back on the same data; a round's ratio is scipy's faster analytic median ÷ calib-core's median (the `2-point` variants are 4× slower still and left out here):\n"
    );
    let _ = writeln!(
        body,
        "| K | ratio per round | median | range |\n|---|---|---|---|"
    );
    let mut worst_paired = f64::INFINITY;
    for (i, k) in k_list.iter().enumerate() {
        let mut rs: Vec<f64> = paired.iter().filter_map(|r| r.get(i).copied()).collect();
        let per_round = rs
            .iter()
            .map(|r| format!("{r:.2}×"))
            .collect::<Vec<_>>()
            .join(", ");
        rs.sort_by(f64::total_cmp);
        let median = rs.get(rs.len() / 2).copied().unwrap_or(f64::NAN);
        worst_paired = worst_paired.min(median);
        let _ = writeln!(
            body,
            "| {k} | {per_round} | {median:.2}× | {:.2}× – {:.2}× |",
            rs.first().copied().unwrap_or(f64::NAN),
            rs.last().copied().unwrap_or(f64::NAN)
        );
    }
    let _ = writeln!(
        body,
        "\nReproduce the rounds:\n\n```sh\n{round_cmds}\n```\n"
    );
    goals.push(Goal {
        what: "calib-core LS ≥ 20× faster than scipy's fastest least_squares variant at equal accuracy (K = 1,000 / 6,000 / 20,000)".into(),
        met: worst_paired >= 20.0 && accuracy_ok,
        detail: format!(
            "slowest K's median over {rounds} paired rounds {worst_paired:.2}× (scipy ÷ calib-core; the single run of the tables: slowest {worst_ratio:.2}×); accuracy {}. Bounded by the per-sample work of each linearisation: FK + Jacobians and the normal-equation update{}",
            if accuracy_ok { "equal (same optimum)" } else { "worse" },
            if floor_blocks {
                "; scipy's Jacobian count × calib-core's FK + Jacobians alone already exceeds a twentieth of scipy's time"
            } else {
                ""
            }
        ),
    });
    goals.push(Goal {
        what: "LS + our EM ≤ 100 ms at K = 6,000 on one core".into(),
        met: em6000.is_some_and(|t| t <= 0.1),
        detail: em6000.map_or("not measured".into(), |t| {
            format!(
                "{} ms median (CPU). Most of it is our EM: its filter/smoother maps on every 4th sample, a few exact informations, and one two-stage pass plus one filter/smoother pass over all 6,000 samples (counts in the table above); the rest is the LS",
                ms(t)
            )
        }),
    });
    goals.push(Goal {
        what: "the daemon linearises on several cores (multi-core figure)".into(),
        met: speedup.is_some_and(|(ls, _)| ls >= 1.3),
        detail: speedup.map_or("not measured".into(), |(ls, all)| {
            format!(
                "2 threads against 1 at K = 6,000 (wall clock, not pinned): LS {ls:.2}× faster, LS + our EM {all:.2}×. Bounded by the machine's second core being free (see the load average: other processes share both cores) and by the EM, a Kalman filter and smoother sequential in time: only the LS parallelises"
            )
        }),
    });
    Ok(Section {
        title: TITLE,
        body,
        goals,
    })
}

/// Per K of `ks` (in order), scipy's fastest analytic median ÷ calib-core's LS median of one
/// paired round (NaN where either side is missing).
fn paired_ratios(ks: &str, ours: &[Value], theirs: &[Value]) -> Vec<f64> {
    ks.split(',')
        .map(|k| {
            let k: f64 = k.parse().unwrap_or(f64::NAN);
            let ls = ours
                .iter()
                .find(|v| s(v, "bench") == "calib-core" && s(v, "solver") == "ls" && f(v, "k") == k)
                .map_or(f64::NAN, |v| f(v, "median_s"));
            let scipy = theirs
                .iter()
                .filter(|v| s(v, "bench") == "scipy" && f(v, "k") == k)
                .map(|v| f(v, "median_s"))
                .fold(f64::INFINITY, f64::min);
            scipy / ls
        })
        .collect()
}
