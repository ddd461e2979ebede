//! Measures how fast the emulated suit generates the paper scenario (no bus).
fn main() {
    let dir = std::env::temp_dir().join(format!("exocal-hil-throughput-{}", std::process::id()));
    let mut suit = exocal_hil::Suit::new(exocal_hil::Scenario::paper(), &dir).expect("suit");
    let t0 = std::time::Instant::now();
    let n = suit.advance(60.0).len();
    let wall = t0.elapsed().as_secs_f64();
    println!(
        "60 simulated s, {n} frames in {wall:.3} s wall: {:.0}x real time, {:.0} frames/s",
        60.0 / wall,
        n as f64 / wall
    );
    let _ = std::fs::remove_dir_all(&dir);
}
