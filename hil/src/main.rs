//! `exocal-hil`: plays a scenario of the emulated suit on a SocketCAN interface.

use anyhow::Context;
use clap::Parser;
use exocal_bus::{SimClock, SocketCan};
use exocal_hil::{Hil, Scenario};
use std::path::PathBuf;

/// Emulates the exocal suit's IMU nodes (7 joints + end-effector reference) on a CAN interface.
///
/// Nodes send joint states, raw IMU data, end-effector poses and heartbeats as described in
/// exocal.dbc, and accept table transfers, persisting tables to one flash file per node.
/// Example: exocal-hil --iface vcan0 --speed 10
#[derive(Parser, Debug)]
#[command(version, about)]
struct Cli {
    /// CAN interface (e.g. vcan0, can0); not needed with --print-scenario.
    #[arg(long, required_unless_present = "print_scenario")]
    iface: Option<String>,
    /// Scenario TOML file (default: the paper's Section 4, scenarios/paper.toml).
    #[arg(long)]
    scenario: Option<PathBuf>,
    /// Simulated time per wall-clock time.
    #[arg(long, default_value_t = 1.0)]
    speed: f64,
    /// Override the scenario's duration, simulated seconds.
    #[arg(long)]
    duration: Option<f64>,
    /// Override the scenario's seed.
    #[arg(long)]
    seed: Option<u64>,
    /// Directory of the node flash files (node<N>.flash).
    #[arg(long, default_value = "hil-flash")]
    flash_dir: PathBuf,
    /// Print the scenario (after overrides) as TOML and exit.
    #[arg(long)]
    print_scenario: bool,
}

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    let mut scenario = match &cli.scenario {
        Some(p) => Scenario::load(p)?,
        None => Scenario::paper(),
    };
    if let Some(d) = cli.duration {
        scenario.duration_s = d;
    }
    if let Some(s) = cli.seed {
        scenario.seed = s;
    }
    scenario.validate()?;
    if cli.print_scenario {
        print!("{}", toml::to_string(&scenario)?);
        return Ok(());
    }
    let iface = cli.iface.context("--iface is required")?;
    let clock = SimClock::new(cli.speed)
        .with_context(|| format!("--speed must be positive, got {}", cli.speed))?;
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    rt.block_on(async {
        let mut bus = SocketCan::open(&iface)?;
        let mut hil = Hil::new(scenario, &cli.flash_dir)?;
        let clock = SimClock::new(clock.speed()).expect("checked above");
        eprintln!(
            "exocal-hil: playing {} on {} at {}x",
            hil.suit().scenario().name,
            iface,
            clock.speed()
        );
        let report = hil.run(&mut bus, &clock).await?;
        print!("{report}");
        Ok(())
    })
}
