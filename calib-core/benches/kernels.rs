//! Benchmarks of the kernels under one LS linearisation, per sample: the pose error, the
//! residual Jacobian `M(e)`, absorbing 6 rows into the streaming QR, and the SVD analysis of
//! the 28 × 28 triangle. `cargo bench -p calib-core --bench kernels`. (`cargo xtask bench`
//! times the same kernels with the process CPU clock and explains the LS time with them.)

use calib_core::model::error_jacobian;
use calib_core::{pose_error, DhTable, QrAccumulator, Sample, Scenario, ScenarioConfig, SUIT_PARAMS};
use divan::{black_box, Bencher};

fn main() {
    divan::main();
}

fn sample() -> Sample<7> {
    Scenario::new(ScenarioConfig::paper(), 1)
        .nth(100)
        .map(|s| s.sample)
        .expect("endless")
}

/// The 6 residual rows and the error of one sample at the nominal table.
fn rows() -> ([[f64; SUIT_PARAMS]; 6], [f64; 6]) {
    let s = sample();
    let (t, cols) = DhTable::paper_nominal().fk_jacobian(&s.joints);
    let e = pose_error(&t, &s.pose);
    let m = error_jacobian(&e);
    let mut rows = [[0.0; SUIT_PARAMS]; 6];
    for p in 0..SUIT_PARAMS {
        let c = m * cols[p / 7][p % 7];
        for (r, row) in rows.iter_mut().enumerate() {
            row[p] = c[r];
        }
    }
    (rows, e.into())
}

#[divan::bench]
fn pose_error_of_fk(bencher: Bencher) {
    let s = sample();
    let table = DhTable::paper_nominal();
    bencher.bench(|| pose_error(&black_box(&table).fk(black_box(&s.joints)), &s.pose));
}

#[divan::bench]
fn residual_jacobian(bencher: Bencher) {
    let s = sample();
    let e = pose_error(&DhTable::paper_nominal().fk(&s.joints), &s.pose);
    bencher.bench(|| error_jacobian(black_box(&e)));
}

#[divan::bench]
fn qr_absorb_6_rows(bencher: Bencher) {
    let (rows, e) = rows();
    let mut acc = QrAccumulator::<SUIT_PARAMS>::new();
    bencher.bench_local(|| {
        for (row, y) in rows.iter().zip(e) {
            acc.add_row(black_box(row), y);
        }
    });
}

#[divan::bench(sample_count = 20)]
fn svd_analysis(bencher: Bencher) {
    let mut acc = QrAccumulator::<SUIT_PARAMS>::new();
    for s in Scenario::new(ScenarioConfig::paper(), 1).take(500) {
        let (t, cols) = DhTable::paper_nominal().fk_jacobian(&s.sample.joints);
        let e = pose_error(&t, &s.sample.pose);
        let m = error_jacobian(&e);
        for r in 0..6 {
            let row: [f64; SUIT_PARAMS] = core::array::from_fn(|p| (m * cols[p / 7][p % 7])[r]);
            acc.add_row(&row, e[r]);
        }
    }
    bencher.bench(|| black_box(&acc).analyse(1e-9));
}
