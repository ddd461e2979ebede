use calib_core::*;
fn main() {
    let samples: Vec<Sample<7>> = Scenario::new(ScenarioConfig::paper(), 1)
        .take(6000)
        .map(|s| s.sample)
        .collect();
    let mut c = 0.0;
    for _ in 0..30 {
        c += identify_ls::<7, 28>(&DhTable::paper_nominal(), &samples, &LsOptions::paper())
            .unwrap()
            .cost;
    }
    println!("{c}");
}
