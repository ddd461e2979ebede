//! Benchmarks of the kernels under one LS linearisation, per sample: the pose error, the
//! residual Jacobian `M(e)`, adding the 6 rows to the normal equations (what `identify_ls`
//! does per sample), absorbing them into the streaming QR (Givens, per row) or a panel of 8
//! samples into it (blocked Householder, the fallback for ill-conditioned problems), and the
//! analyses of the 28 × 28 problem (SVD of the QR triangle; Cholesky + SVD of the normal
//! equations). `cargo bench -p calib-core --bench kernels`. (`cargo xtask bench`
//! times the same kernels with the process CPU clock and explains the LS time with them.)

use calib_core::model::error_jacobian;
use calib_core::{pose_error, DhTable, GramAccumulator, QrAccumulator, QrPanel, Sample, Scenario, ScenarioConfig, SUIT_PARAMS};
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

type Rows3 = [[f64; SUIT_PARAMS]; 3];

/// Rows of `rows()` split as `identify_ls` keeps them: 3 position rows, 3 rotation rows (zero in
/// the 14 `a`, `d` columns).
fn split_rows() -> (Rows3, Rows3, [f64; 3], [f64; 3]) {
    let (rows, e) = rows();
    (
        [rows[0], rows[1], rows[2]],
        [rows[3], rows[4], rows[5]],
        [e[0], e[1], e[2]],
        [e[3], e[4], e[5]],
    )
}

/// One sample's 6 rows into the normal equations (per sample, per linearisation).
#[divan::bench]
fn gram_add_6_rows(bencher: Bencher) {
    let (pos, rot, ep, er) = split_rows();
    let mut acc = GramAccumulator::<SUIT_PARAMS>::new();
    bencher.bench_local(|| {
        acc.add_rows_3_3(black_box(&pos), &ep, black_box(&rot), &er, 14);
    });
}

/// A panel of 8 samples (48 rows) into the QR by one blocked Householder update (per panel;
/// divide by 8 for per sample).
#[divan::bench]
fn householder_panel_8_samples(bencher: Bencher) {
    let (pos, rot, ep, er) = split_rows();
    let mut acc = QrAccumulator::<SUIT_PARAMS>::new();
    let mut panel = QrPanel::<SUIT_PARAMS, 24>::new(14);
    bencher.bench_local(|| {
        for _ in 0..8 {
            for r in 0..3 {
                let (row, y) = panel.push_full();
                *row = pos[r];
                *y = ep[r];
                let (row, y) = panel.push_tail();
                *row = rot[r];
                *y = er[r];
            }
        }
        acc.absorb(black_box(&mut panel));
    });
}

#[divan::bench(sample_count = 20)]
fn gram_analysis(bencher: Bencher) {
    let mut acc = GramAccumulator::<SUIT_PARAMS>::new();
    for s in Scenario::new(ScenarioConfig::paper(), 1).take(500) {
        let (t, cols) = DhTable::paper_nominal().fk_jacobian(&s.sample.joints);
        let e = pose_error(&t, &s.sample.pose);
        let m = error_jacobian(&e);
        let rows: [[f64; SUIT_PARAMS]; 6] = core::array::from_fn(|r| core::array::from_fn(|p| (m * cols[p / 7][p % 7])[r]));
        acc.add_rows(&rows, &e.into(), 0);
    }
    bencher.bench(|| black_box(&acc).analyse(1e-9).map(|a| a.rank));
}
