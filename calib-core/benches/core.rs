//! Benchmarks: FK + identification Jacobian per sample, LS at K = 1,000 / 6,000 / 20,000, both
//! EMs at K = 1,000 / 6,000, one exact-information pass of our EM (Section 4 scenario, seed 1).
//! `cargo bench -p calib-core`.

use calib_core::{
    cramer_rao, em_drift_vec, identify_ls, paper_em, DhTable, DriftEmOptions, LsOptions, PaperEmOptions, Sample, Scenario,
    ScenarioConfig,
};
use divan::{black_box, Bencher};

fn main() {
    divan::main();
}

fn samples(k: usize) -> Vec<Sample<7>> {
    Scenario::new(ScenarioConfig::paper(), 1).take(k).map(|s| s.sample).collect()
}

#[divan::bench]
fn fk_and_jacobian(bencher: Bencher) {
    let table = DhTable::paper_actual();
    let q = samples(1)[0].joints;
    bencher.bench(|| black_box(&table).fk_jacobian(black_box(&q)));
}

#[divan::bench(args = [1_000, 6_000, 20_000], sample_count = 3, sample_size = 1)]
fn least_squares(bencher: Bencher, k: usize) {
    let s = samples(k);
    let opts = LsOptions::paper();
    bencher.bench(|| identify_ls::<7, 28>(&DhTable::paper_nominal(), black_box(&s), &opts).map(|r| r.cost));
}

#[divan::bench(args = [1_000, 6_000], sample_count = 3, sample_size = 1)]
fn paper_em_scalar(bencher: Bencher, k: usize) {
    let s = samples(k);
    let nominal = DhTable::paper_nominal();
    let ls = identify_ls::<7, 28>(&nominal, &s, &LsOptions::paper()).expect("LS");
    bencher.bench(|| paper_em(&nominal, &ls.table, black_box(&s), &PaperEmOptions::default()).map(|r| r.delta_theta));
}

#[divan::bench(args = [1_000, 6_000], sample_count = 3, sample_size = 1)]
fn our_em(bencher: Bencher, k: usize) {
    let s = samples(k);
    let ls = identify_ls::<7, 28>(&DhTable::paper_nominal(), &s, &LsOptions::paper()).expect("LS");
    let opts = DriftEmOptions::new(0.01);
    bencher.bench(|| em_drift_vec::<7, 28>(&ls.table, black_box(&s), &opts).map(|r| r.0.iterations));
}

/// One pass of our EM's two-stage filter over every sample (linearisation, filter, normal
/// equations): what `cramer_rao` does, and what the EM does once over all samples at the end.
#[divan::bench(args = [1_000, 6_000], sample_count = 5, sample_size = 1)]
fn em_information_pass(bencher: Bencher, k: usize) {
    let s = samples(k);
    let d = ScenarioConfig::paper().drift;
    bencher.bench(|| {
        cramer_rao::<7, 28>(
            &DhTable::paper_actual(),
            black_box(&s),
            [d.phi(); 7],
            [d.process_variance(); 7],
            [1e-9; 6],
            1e-14,
        )
        .map(|a| a.rank)
    });
}
