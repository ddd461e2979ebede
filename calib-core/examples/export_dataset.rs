//! The calibration-vs-scipy benchmark, Rust side: simulates the paper's Section 4 scenario,
//! exports it as CSV for `benches/scipy_ls.py`, and times calib-core on the same data.
//!
//! ```text
//! cargo run -p calib-core --release --example export_dataset -- \
//!     --out DIR [--k 1000,6000,20000] [--seed 1] [--repeats 7] [--em-k 1000,6000] [--em-repeats 3]
//! cargo run -p calib-core --release --example export_dataset -- --firmware-twin
//! ```
//!
//! (`--firmware-twin` only prints the LS result of `benches/firmware`'s dataset, computed here.)
//!
//! For every K it writes `DIR/k{K}/samples.csv` (one row per sample: the reported joint angles
//! `q1..q7` (rad), then the measured tool pose in the base frame, rotation row-major `r00..r22`
//! and position `px py pz` (m)) and `DIR/k{K}/tables.csv` (per parameter, in calib-core's order
//! `kind · 7 + joint` with kinds a, d, alpha, theta: the starting point, which is the nominal
//! Table 1, and the truth, Table 4). Floats are written in Rust's shortest round-trip form, so
//! Python reads back the identical doubles.
//!
//! Then it times [`identify_ls`] (`--repeats` runs, one after another in this thread) and, for
//! K in `--em-k`, LS followed by our EM ([`em_drift_vec`]), and prints one JSON object per line
//! on stdout (`{"bench":"calib-core", ...}`): every run's CPU time (`runs_s`; the process CPU
//! clock, so that other processes on a shared core do not count), their median (`median_s`),
//! the median wall time (`wall_median_s`), and the
//! accuracy of the result (LS cost Σ‖e‖², the paper's y of eq. 10, and the largest parameter
//! error of each kind against Table 4), and for LS the passes over the samples it made
//! (`linearisations`, `cost_passes`, counted on one more, untimed run). A first line
//! (`"bench":"calib-core-kernels"`) gives the per-sample cost of one LS linearisation split into
//! its kernels. Nothing else goes to stdout.

use std::fs::{self, File};
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::time::Instant;

use std::cell::Cell;

use calib_core::{
    em_drift_vec, identify_ls, identify_ls_with, median, normal_equations, objective_y, pose_error, table_error, DhTable,
    DriftEmOptions, GramAccumulator, Linearise, LsOptions, LsResult, ParamErrors, ParamKind, Sample, Scenario, ScenarioConfig,
    Sequential, SUIT_PARAMS,
};

struct Args {
    out: PathBuf,
    ks: Vec<usize>,
    seed: u64,
    repeats: usize,
    em_ks: Vec<usize>,
    em_repeats: usize,
}

fn parse_args() -> Result<Args, String> {
    let argv: Vec<String> = std::env::args().skip(1).collect();
    let get = |name: &str| -> Option<&str> {
        argv.iter()
            .position(|a| a == name)
            .and_then(|i| argv.get(i + 1))
            .map(String::as_str)
    };
    let list = |name: &str, default: &str| -> Result<Vec<usize>, String> {
        let v = get(name).unwrap_or(default);
        if v.is_empty() {
            return Ok(Vec::new());
        }
        v.split(',')
            .map(|x| x.trim().parse().map_err(|_| format!("{name}: `{x}` is not a count")))
            .collect()
    };
    let number = |name: &str, default: u64| -> Result<u64, String> {
        get(name).map_or(Ok(default), |v| {
            v.parse().map_err(|_| format!("{name}: `{v}` is not a number"))
        })
    };
    Ok(Args {
        out: PathBuf::from(get("--out").ok_or("--out DIR is required")?),
        ks: list("--k", "1000,6000,20000")?,
        seed: number("--seed", 1)?,
        repeats: number("--repeats", 7)?.max(1) as usize,
        em_ks: list("--em-k", "1000,6000")?,
        em_repeats: number("--em-repeats", 3)?.max(1) as usize,
    })
}

fn write_dataset(dir: &Path, samples: &[Sample<7>]) -> std::io::Result<()> {
    fs::create_dir_all(dir)?;
    let mut f = BufWriter::new(File::create(dir.join("samples.csv"))?);
    writeln!(f, "q1,q2,q3,q4,q5,q6,q7,r00,r01,r02,r10,r11,r12,r20,r21,r22,px,py,pz")?;
    for s in samples {
        let mut fields: Vec<String> = s.joints.iter().map(|q| format!("{q:e}")).collect();
        for i in 0..3 {
            for j in 0..3 {
                fields.push(format!("{:e}", s.pose.r[(i, j)]));
            }
        }
        fields.extend(s.pose.p.iter().map(|x| format!("{x:e}")));
        writeln!(f, "{}", fields.join(","))?;
    }
    f.flush()?;
    let mut t = BufWriter::new(File::create(dir.join("tables.csv"))?);
    writeln!(t, "index,kind,joint,start,truth")?;
    let (start, truth) = (DhTable::paper_nominal(), DhTable::paper_actual());
    for p in 0..SUIT_PARAMS {
        let (kind, joint) = ParamKind::of_index(p, 7);
        writeln!(
            t,
            "{p},{},{},{:e},{:e}",
            kind.name(),
            joint + 1,
            start.param(p),
            truth.param(p)
        )?;
    }
    t.flush()
}

fn json_list(xs: &[f64]) -> String {
    let items: Vec<String> = xs.iter().map(|x| format!("{x:e}")).collect();
    format!("[{}]", items.join(","))
}

/// The accuracy fields shared by every line: LS cost, y and the parameter errors of `table`.
fn accuracy(table: &DhTable<7>, samples: &[Sample<7>]) -> String {
    let cost: f64 = samples
        .iter()
        .map(|s| pose_error(&table.fk(&s.joints), &s.pose).norm_squared())
        .sum();
    let e = ParamErrors::between(table, &DhTable::paper_actual());
    let rms = (0..SUIT_PARAMS)
        .map(|p| (table.param(p) - DhTable::paper_actual().param(p)).powi(2))
        .sum::<f64>()
        .sqrt();
    format!(
        "\"cost\":{cost:e},\"y\":{:e},\"err_a\":{:e},\"err_d\":{:e},\"err_alpha\":{:e},\"err_theta\":{:e},\"err_norm\":{rms:e}",
        objective_y(table, samples),
        e.a,
        e.d,
        e.alpha,
        e.theta
    )
}

/// CPU time of this process (s): on a shared machine, unlike wall time, it leaves out the time
/// other processes held the core.
fn cpu_time() -> f64 {
    let mut ts = libc::timespec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: clock_gettime writes one timespec into the valid, exclusively borrowed `ts`.
    #[allow(unsafe_code)]
    let rc = unsafe { libc::clock_gettime(libc::CLOCK_PROCESS_CPUTIME_ID, &mut ts) };
    if rc != 0 {
        return f64::NAN;
    }
    ts.tv_sec as f64 + ts.tv_nsec as f64 * 1e-9
}

/// CPU and wall time since `start`.
struct Stopwatch {
    cpu: f64,
    wall: Instant,
}

impl Stopwatch {
    fn start() -> Self {
        Stopwatch {
            cpu: cpu_time(),
            wall: Instant::now(),
        }
    }

    /// (CPU seconds, wall seconds).
    fn read(&self) -> (f64, f64) {
        (cpu_time() - self.cpu, self.wall.elapsed().as_secs_f64())
    }
}

/// The passes over the samples an LS makes: linearisations (FK, Jacobians and the
/// normal-equation update per sample) and cost-only evaluations.
struct Counting<'a> {
    inner: Sequential<'a, 7>,
    linearisations: Cell<usize>,
    costs: Cell<usize>,
}

impl Linearise<7, SUIT_PARAMS> for Counting<'_> {
    fn normal_equations(&self, table: &DhTable<7>, out: &mut GramAccumulator<SUIT_PARAMS>) -> f64 {
        self.linearisations.set(self.linearisations.get() + 1);
        self.inner.normal_equations(table, out)
    }

    fn cost(&self, table: &DhTable<7>) -> f64 {
        self.costs.set(self.costs.get() + 1);
        Linearise::<7, SUIT_PARAMS>::cost(&self.inner, table)
    }
}

/// (linearisations, cost-only passes) of the LS of `samples`, counted on an untimed run.
fn ls_passes(samples: &[Sample<7>]) -> Result<(usize, usize), String> {
    let counting = Counting {
        inner: Sequential(samples),
        linearisations: Cell::new(0),
        costs: Cell::new(0),
    };
    identify_ls_with::<7, SUIT_PARAMS>(&DhTable::paper_nominal(), samples, &LsOptions::paper(), &counting)
        .map_err(|e| format!("LS: {e}"))?;
    Ok((counting.linearisations.get(), counting.costs.get()))
}

fn run_ls(samples: &[Sample<7>]) -> Result<LsResult<7, SUIT_PARAMS>, String> {
    identify_ls::<7, SUIT_PARAMS>(&DhTable::paper_nominal(), samples, &LsOptions::paper()).map_err(|e| format!("LS: {e}"))
}

fn bench(args: &Args) -> Result<(), String> {
    let cfg = ScenarioConfig::paper();
    let kmax = args.ks.iter().chain(&args.em_ks).copied().max().unwrap_or(0);
    // One session; every K is its first K samples (K = 6,000 is the paper's 60 s at 100 Hz).
    let all: Vec<Sample<7>> = Scenario::new(cfg, args.seed).take(kmax.max(1)).map(|s| s.sample).collect();
    kernels(&all);
    for &k in &args.ks {
        let samples = &all[..k];
        let dir = args.out.join(format!("k{k}"));
        write_dataset(&dir, samples).map_err(|e| format!("writing {}: {e}", dir.display()))?;
        let (mut times, mut walls) = (Vec::new(), Vec::new());
        let mut last = None;
        for _ in 0..args.repeats {
            let t0 = Stopwatch::start();
            let r = run_ls(samples)?;
            let (cpu, wall) = t0.read();
            times.push(cpu);
            walls.push(wall);
            last = Some(r);
        }
        let r = last.ok_or("no run")?;
        let (linearisations, cost_passes) = ls_passes(samples)?;
        println!(
            "{{\"bench\":\"calib-core\",\"solver\":\"ls\",\"k\":{k},\"seed\":{},\"dir\":\"{}\",\"median_s\":{:e},\"runs_s\":{},\"wall_median_s\":{:e},\"iterations\":{},\"linearisations\":{linearisations},\"cost_passes\":{cost_passes},\"condition\":{:e},\"cost_start\":{:e},\"y_start\":{:e},{}}}",
            args.seed,
            dir.display(),
            median(&mut times.clone()),
            json_list(&times),
            median(&mut walls.clone()),
            r.iterations,
            r.condition,
            samples
                .iter()
                .map(|s| pose_error(&DhTable::paper_nominal().fk(&s.joints), &s.pose).norm_squared())
                .sum::<f64>(),
            objective_y(&DhTable::paper_nominal(), samples),
            accuracy(&r.table, samples)
        );
    }
    for &k in &args.em_ks {
        let samples = &all[..k];
        let (mut times, mut em_times, mut walls) = (Vec::new(), Vec::new(), Vec::new());
        let mut last = None;
        for _ in 0..args.em_repeats {
            let t0 = Stopwatch::start();
            let ls = run_ls(samples)?;
            let t1 = Stopwatch::start();
            let (em, _drift) = em_drift_vec::<7, SUIT_PARAMS>(&ls.table, samples, &DriftEmOptions::new(cfg.drift.dt))
                .map_err(|e| format!("EM: {e}"))?;
            em_times.push(t1.read().0);
            let (cpu, wall) = t0.read();
            times.push(cpu);
            walls.push(wall);
            last = Some(em);
        }
        let em = last.ok_or("no run")?;
        // Table error over 2,000 fresh drift-free poses (as the paper example computes it).
        let fresh: Vec<[f64; 7]> = Scenario::new(cfg, args.seed ^ 0xF2E5_4000_0000)
            .step_by(3)
            .take(2000)
            .map(|s| s.sample.joints)
            .collect();
        let te = table_error(&em.table, &cfg.actual, &fresh);
        println!(
            "{{\"bench\":\"calib-core\",\"solver\":\"ls+em\",\"k\":{k},\"seed\":{},\"median_s\":{:e},\"runs_s\":{},\"wall_median_s\":{:e},\"em_median_s\":{:e},\"em_iterations\":{},\"em_stride\":{},\"em_informations\":{},\"em_converged\":{},\"table_error_mm\":{:e},\"table_error_mrad\":{:e},{}}}",
            args.seed,
            median(&mut times.clone()),
            json_list(&times),
            median(&mut walls.clone()),
            median(&mut em_times.clone()),
            em.iterations,
            em.stride,
            em.information_passes,
            em.converged,
            1e3 * te.position_m,
            1e3 * te.rotation_rad,
            accuracy(&em.table, samples)
        );
    }
    Ok(())
}

/// Median CPU time (s) of one call of `f`, over `reps` batches of `n` calls.
fn time_per_call(reps: usize, n: usize, mut f: impl FnMut()) -> f64 {
    let mut times: Vec<f64> = (0..reps)
        .map(|_| {
            let t0 = Stopwatch::start();
            for _ in 0..n {
                f();
            }
            t0.read().0 / n as f64
        })
        .collect();
    median(&mut times)
}

/// Least CPU time (s) of one call of `f`, over `reps` batches of `n` calls.
fn fastest_per_call(reps: usize, n: usize, mut f: impl FnMut()) -> f64 {
    (0..reps)
        .map(|_| {
            let t0 = Stopwatch::start();
            for _ in 0..n {
                f();
            }
            t0.read().0 / n as f64
        })
        .fold(f64::INFINITY, f64::min)
}

/// Per-sample cost of one LS linearisation, split into its kernels: FK + identification
/// Jacobian, the residual Jacobian `M(e)·J`, and absorbing the 6 rows into the streaming QR;
/// plus one SVD analysis of the 28 × 28 triangle. Then what `identify_ls` does per pass: a
/// whole linearisation per sample, the normal-equation update alone, a cost-only pass, and the
/// analyses of the normal equations, cold and warm.
fn kernels(all: &[Sample<7>]) {
    use calib_core::model::error_jacobian;
    use calib_core::QrAccumulator;
    use std::hint::black_box;
    let table = DhTable::paper_nominal();
    let n = all.len().clamp(1, 2000);
    let s = &all[..n];
    let mut i = 0;
    let mut next = || {
        i = (i + 1) % n;
        &s[i]
    };
    let fk_jac = time_per_call(7, 20_000, || {
        black_box(black_box(&table).fk_jacobian(&next().joints));
    });
    let (t, cols) = table.fk_jacobian(&s[0].joints);
    let e = pose_error(&t, &s[0].pose);
    let residual_jac = time_per_call(7, 20_000, || {
        let m = error_jacobian(black_box(&e));
        let mut rows = [[0.0; SUIT_PARAMS]; 6];
        for p in 0..SUIT_PARAMS {
            let c = m * cols[p / 7][p % 7];
            for r in 0..6 {
                rows[r][p] = c[r];
            }
        }
        black_box(rows);
    });
    let rows: [[f64; SUIT_PARAMS]; 6] = core::array::from_fn(|r| core::array::from_fn(|p| cols[p / 7][p % 7][r]));
    let mut acc = QrAccumulator::<SUIT_PARAMS>::new();
    let qr_rows = time_per_call(7, 20_000, || {
        for (r, row) in rows.iter().enumerate() {
            acc.add_row(black_box(row), e[r]);
        }
    });
    // What-if: the same Givens update with `sqrt(a² + b²)` instead of `libm::hypot` (safe here:
    // the entries are O(1) to O(√K)), to show how much of the QR time is the hypot call.
    let mut r = [[0.0; SUIT_PARAMS]; SUIT_PARAMS];
    let mut z = [0.0; SUIT_PARAMS];
    let qr_rows_sqrt = time_per_call(7, 20_000, || {
        for (k, row) in rows.iter().enumerate() {
            givens_sqrt(&mut r, &mut z, black_box(row), e[k]);
        }
    });
    let analyse = time_per_call(7, 20, || {
        black_box(black_box(&acc).analyse(1e-9));
    });
    // What an LS pass is made of (per sample), on the first n samples at Table 1: a whole
    // linearisation (FK, Jacobians, the 6 residual rows, the normal-equation update), the
    // normal-equation update alone (`identify_ls` splits the rows as 3 position rows and 3
    // rotation rows, zero in the 14 a and d columns), and a cost-only pass; and one analysis of
    // the normal equations (Cholesky, SVD), cold and warm. Each the fastest of its batches (the
    // least disturbed by other processes on a shared core), to be set against the fastest LS run
    // and a peak measured the same way.
    let mut gram = GramAccumulator::<SUIT_PARAMS>::new();
    let linearisation = fastest_per_call(15, 5, || {
        gram.clear();
        black_box(normal_equations(black_box(&table), s, &mut gram));
    }) / n as f64;
    let cost_pass = fastest_per_call(15, 5, || {
        black_box(calib_core::ls::cost(black_box(&table), s));
    }) / n as f64;
    let (pos, rot) = ([rows[0], rows[1], rows[2]], [rows[3], rows[4], rows[5]]);
    let mut acc6 = GramAccumulator::<SUIT_PARAMS>::new();
    let mut gram_update = || acc6.add_rows_3_3(black_box(&pos), &[e[0], e[1], e[2]], black_box(&rot), &[e[3], e[4], e[5]], 14);
    // The fastest of 25 batches: set against a peak measured the same way (`benches/peak.c`),
    // the run least disturbed by other processes on a shared core.
    let gram_rows = fastest_per_call(25, 20_000, &mut gram_update);
    let gram_analyse = fastest_per_call(15, 10, || {
        black_box(black_box(&gram).analyse(1e-9));
    });
    // The LS starts every analysis after the first from the previous iterate's singular
    // vectors: here, the normal equations at the optimum from the analysis at Table 1.
    let start = gram.analyse(1e-9);
    let mut at_optimum = GramAccumulator::<SUIT_PARAMS>::new();
    if let Ok(ls) = run_ls(s) {
        normal_equations(&ls.table, s, &mut at_optimum);
    }
    let gram_analyse_warm = fastest_per_call(15, 10, || {
        black_box(black_box(&at_optimum).analyse_from(1e-9, start.as_ref()));
    });
    println!(
        "{{\"bench\":\"calib-core-kernels\",\"fk_jacobian_s\":{fk_jac:e},\"residual_jacobian_s\":{residual_jac:e},\"qr_6_rows_s\":{qr_rows:e},\"qr_6_rows_sqrt_s\":{qr_rows_sqrt:e},\"analyse_s\":{analyse:e},\"linearisation_per_sample_s\":{linearisation:e},\"cost_per_sample_s\":{cost_pass:e},\"gram_6_rows_s\":{gram_rows:e},\"gram_analyse_s\":{gram_analyse:e},\"gram_analyse_warm_s\":{gram_analyse_warm:e}}}"
    );
}

/// `QrAccumulator::add_row` with `sqrt(a² + b²)` for `hypot` (the what-if of [`kernels`]).
fn givens_sqrt(r: &mut [[f64; SUIT_PARAMS]; SUIT_PARAMS], z: &mut [f64; SUIT_PARAMS], h: &[f64; SUIT_PARAMS], y: f64) {
    let (mut h, mut y) = (*h, y);
    for j in 0..SUIT_PARAMS {
        if h[j] == 0.0 {
            continue;
        }
        let a = r[j][j];
        let rr = (a * a + h[j] * h[j]).sqrt();
        let (c, s) = (a / rr, h[j] / rr);
        r[j][j] = rr;
        for k in j + 1..SUIT_PARAMS {
            let (rk, hk) = (r[j][k], h[k]);
            r[j][k] = c * rk + s * hk;
            h[k] = c * hk - s * rk;
        }
        let zj = z[j];
        z[j] = c * zj + s * y;
        y = c * y - s * zj;
    }
}

/// The dataset and LS of `benches/firmware` (200 samples, one every 0.1 s, seed 1), run here:
/// its cost bits let the report check the Cortex-M4F result (software f64) against the host.
fn firmware_twin() -> Result<(), String> {
    let samples: Vec<Sample<7>> = Scenario::new(ScenarioConfig::paper(), 1)
        .step_by(10)
        .take(200)
        .map(|s| s.sample)
        .collect();
    let r = run_ls(&samples)?;
    println!(
        "{{\"bench\":\"calib-core-firmware-twin\",\"k\":200,\"iterations\":{},\"rank\":{},\"cost_bits\":\"{:#x}\"}}",
        r.iterations,
        r.rank,
        r.cost.to_bits()
    );
    Ok(())
}

fn main() {
    if std::env::args().any(|a| a == "--firmware-twin") {
        if let Err(e) = firmware_twin() {
            eprintln!("export_dataset: {e}");
            std::process::exit(2);
        }
        return;
    }
    let result = parse_args().and_then(|a| bench(&a));
    if let Err(e) = result {
        eprintln!("export_dataset: {e}");
        std::process::exit(2);
    }
}
