fn cpu() -> f64 {
    let mut ts = libc::timespec { tv_sec: 0, tv_nsec: 0 };
    #[allow(unsafe_code)]
    unsafe {
        libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut ts)
    };
    ts.tv_sec as f64 * 1e3 + ts.tv_nsec as f64 * 1e-6
}
struct Instant(f64);
impl Instant {
    fn now() -> Self {
        Instant(cpu())
    }
    fn elapsed(&self) -> std::time::Duration {
        std::time::Duration::from_secs_f64((cpu() - self.0) * 1e-3)
    }
}
use calib_core::*;

const BASE: [(f64, f64); 5] = [
    (1.0677, 3.7910),
    (1.1032, 4.0339),
    (1.2774, 6.9241),
    (1.2183, 4.4434),
    (1.3975, 4.6632),
];
fn main() {
    let args: Vec<String> = std::env::args().collect();
    let seeds: u64 = args.get(1).map(|s| s.parse().unwrap()).unwrap_or(5);
    let secs: f64 = args.get(2).map(|s| s.parse().unwrap()).unwrap_or(60.0);
    let cfg = ScenarioConfig::paper();
    let k = (secs / cfg.drift.dt).round() as usize;
    let maxit: usize = args.get(3).map(|s| s.parse().unwrap()).unwrap_or(100);
    let mut em_opts = DriftEmOptions::new(cfg.drift.dt);
    em_opts.max_iterations = maxit;
    if args.len() > 4 {
        em_opts.param_tolerance = 1e-12;
        em_opts.tolerance = 1e-15;
        em_opts.se_tolerance = 1e-15;
    }
    if let Ok(v) = std::env::var("STRIDE") {
        em_opts.max_stride = v.parse().unwrap();
    }
    if let Ok(v) = std::env::var("PTOL") {
        em_opts.param_tolerance = v.parse().unwrap();
    }
    if let Ok(v) = std::env::var("TOL") {
        em_opts.tolerance = v.parse().unwrap();
    }
    if let Ok(v) = std::env::var("NOISE0") {
        em_opts.initial_noise_std = v.parse().unwrap();
    }
    if let Ok(v) = std::env::var("SETOL") {
        em_opts.se_tolerance = v.parse().unwrap();
    }
    for seed in 1..=seeds {
        let samples: Vec<Sample<7>> = Scenario::new(cfg, seed).take(k).map(|s| s.sample).collect();
        let fresh: Vec<[f64; 7]> = Scenario::new(cfg, seed ^ 0xF2E5_4000_0000)
            .step_by(3)
            .take(2000)
            .map(|s| s.sample.joints)
            .collect();
        let truth = DhTable::paper_actual();
        let t0 = Instant::now();
        let ls = identify_ls::<7, 28>(&DhTable::paper_nominal(), &samples, &LsOptions::paper()).unwrap();
        let t_ls = t0.elapsed();
        let t0 = Instant::now();
        let (em, _) = em_drift_vec::<7, 28>(&ls.table, &samples, &em_opts).unwrap();
        let t_em = t0.elapsed();
        let q = cfg.drift.process_variance();
        let crb = cramer_rao::<7, 28>(&truth, &samples, [cfg.drift.phi(); 7], [q; 7], [0.0; 6], 1e-14).unwrap();
        let b = expected_table_error::<7, 28>(&truth, &fresh, |u| crb.variance_along(u));
        let el = table_error(&ls.table, &truth, &fresh);
        let ee = table_error(&em.table, &truth, &fresh);
        println!("seed {seed}: LS {:.4} mm {:.4} mrad | EM {:.4} mm {:.4} mrad {:+.2}% {:+.2}% | bound {:.4} mm {:.4} mrad | reported {:.4} {:.4} | EM it {} info {} stride {} conv {} | LS {:.1} ms EM {:.1} ms",
            ee.position_m*0.0 + el.position_m*1e3, el.rotation_rad*1e3, ee.position_m*1e3, ee.rotation_rad*1e3, 100.0*(ee.position_m*1e3/BASE[seed as usize-1].0-1.0), 100.0*(ee.rotation_rad*1e3/BASE[seed as usize -1].1-1.0), b.position_m*1e3, b.rotation_rad*1e3,
            em.expected_error.position_m*1e3, em.expected_error.rotation_rad*1e3, em.iterations, em.information_passes, em.stride, em.converged, t_ls.as_secs_f64()*1e3, t_em.as_secs_f64()*1e3);
    }
}
