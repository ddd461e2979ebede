//! `exocal-hil`: plays a scenario of the emulated suit on a SocketCAN interface.

use anyhow::Context;
use clap::Parser;
use exocal_bus::{SimClock, SocketCan};
use exocal_dbc::auth::KeySet;
use exocal_dbc::NodeId;
use exocal_hil::{Ended, Hil, Linger, Scenario};
use std::path::{Path, PathBuf};
use tokio::signal::unix::{signal, SignalKind};

/// Emulates the exocal suit's IMU nodes (7 joints + end-effector reference) on a CAN interface.
///
/// Nodes send joint states, raw IMU data, end-effector poses and heartbeats as described in
/// exocal.dbc, and accept table transfers, persisting tables to one flash file per node.
///
/// The motion lasts the scenario's duration (--duration). Then the arm rests but the nodes stay
/// up: they keep sending heartbeats and answering table transfers (readback included) until
/// SIGTERM or SIGINT, or for --linger seconds. When the motion ends, a line "exocal-hil: motion
/// ended after N s; ..." goes to stderr. On SIGTERM/SIGINT (during the motion too) or at the end
/// of --linger, the run's report goes to stdout and the exit status is 0. Exit status 69: the CAN
/// interface is missing or cannot be opened (the message says how to create it); 1: any other
/// error (named).
///
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
    /// Override the scenario's duration of motion, simulated seconds.
    #[arg(long)]
    duration: Option<f64>,
    /// After the motion, answer for this many seconds of simulated time (like --duration: it
    /// lasts LINGER/speed of wall-clock time), then exit; 0 exits when the motion ends. Without
    /// it, the nodes answer until SIGTERM or SIGINT.
    #[arg(long, value_name = "SECONDS", value_parser = non_negative)]
    linger: Option<f64>,
    /// Override the scenario's seed.
    #[arg(long)]
    seed: Option<u64>,
    /// Directory of the node flash files (node<N>.flash) and key slots (node<N>.key).
    #[arg(long, default_value = "hil-flash")]
    flash_dir: PathBuf,
    /// Provision the nodes' key slots from this key file before they boot (one `NAME HEX`
    /// line per node, `Joint1`…`Joint7` and `EndEffector`, 32 hex digits; exocald reads the
    /// same file as its `exocal-keys` credential). Default: the systemd credential
    /// $CREDENTIALS_DIRECTORY/exocal-keys, when the unit has one. A node with a key installs
    /// only authenticated tables; one without installs nothing (fail closed).
    #[arg(long, value_name = "FILE")]
    keys: Option<PathBuf>,
    /// Print the scenario (after overrides) as TOML and exit.
    #[arg(long)]
    print_scenario: bool,
}

/// `--linger`: a finite number of seconds, zero or more.
fn non_negative(text: &str) -> Result<f64, String> {
    match text.parse::<f64>() {
        Ok(v) if v.is_finite() && v >= 0.0 => Ok(v),
        Ok(v) => Err(format!("must be finite and ≥ 0, got {v}")),
        Err(e) => Err(e.to_string()),
    }
}

/// The CAN interface is missing or cannot be opened: exit 69 (EX_UNAVAILABLE), as exocald.
#[derive(Debug)]
struct Unavailable(String);

impl std::fmt::Display for Unavailable {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for Unavailable {}

/// Runs, and on an error says what it is (no backtrace) and exits 69 or 1.
fn main() -> std::process::ExitCode {
    match run(Cli::parse()) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("exocal-hil: {e:#}");
            let unavailable = e.downcast_ref::<Unavailable>().is_some();
            std::process::ExitCode::from(if unavailable { 69 } else { 1 })
        }
    }
}

fn run(cli: Cli) -> anyhow::Result<()> {
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
    if let Some(why) = exocal_bus::interface::missing(&iface) {
        return Err(Unavailable(format!("CAN interface {iface}: {why}")).into());
    }
    eprintln!(
        "exocal-hil: {}",
        provision_keys(cli.keys.as_deref(), &cli.flash_dir)?
    );
    let clock = SimClock::new(cli.speed)
        .with_context(|| format!("--speed must be positive, got {}", cli.speed))?;
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    rt.block_on(async {
        let mut term = signal(SignalKind::terminate()).context("handling SIGTERM")?;
        let mut int = signal(SignalKind::interrupt()).context("handling SIGINT")?;
        let stop = async {
            tokio::select! {
                _ = term.recv() => {}
                _ = int.recv() => {}
            }
        };
        let mut stop = std::pin::pin!(stop);
        let mut bus = SocketCan::open(&iface).map_err(|e| {
            let has_can = exocal_bus::interface::kernel_has_can();
            Unavailable(exocal_bus::interface::open_failure(&iface, &e, has_can))
        })?;
        let mut hil = Hil::new(scenario, &cli.flash_dir)?;
        let clock = SimClock::new(clock.speed()).expect("checked above");
        eprintln!(
            "exocal-hil: playing {} on {} at {}x",
            hil.suit().scenario().name,
            iface,
            clock.speed()
        );
        let linger = cli.linger.map_or(Linger::UntilStopped, Linger::For);
        match hil.play(&mut bus, &clock, stop.as_mut()).await? {
            Ended::Stopped => eprintln!(
                "exocal-hil: stopped by a signal after {:.3} s of motion",
                hil.suit().now_s()
            ),
            Ended::Elapsed => {
                eprintln!(
                    "exocal-hil: motion ended after {:.3} s; {}",
                    hil.suit().now_s(),
                    readiness(linger)
                );
                if hil.linger(&mut bus, &clock, linger, stop.as_mut()).await? == Ended::Stopped {
                    eprintln!("exocal-hil: stopped by a signal");
                }
            }
        }
        print!("{}", hil.report(&bus));
        Ok(())
    })
}

/// The systemd credential holding the node keys.
const CREDENTIAL: &str = "exocal-keys";

/// Provisions the key slots from `file`, else from the `exocal-keys` credential if there is
/// one; says what the nodes hold (never the keys).
fn provision_keys(file: Option<&Path>, flash_dir: &Path) -> anyhow::Result<String> {
    let credential = std::env::var_os("CREDENTIALS_DIRECTORY")
        .map(|d| PathBuf::from(d).join(CREDENTIAL))
        .filter(|p| p.exists());
    let Some(path) = file.map(Path::to_path_buf).or(credential) else {
        let keyed = NodeId::JOINTS
            .into_iter()
            .filter(|&n| matches!(exocal_hil::flash::read_key(flash_dir, n), Ok(Some(_))))
            .count();
        return Ok(format!(
            "no key file given: {keyed} of 7 joint nodes hold a key from earlier provisioning; \
             the others install no table until they are provisioned"
        ));
    };
    // Wiped when dropped, as the keys are.
    let text = zeroize::Zeroizing::new(
        std::fs::read_to_string(&path)
            .with_context(|| format!("reading the key file {}", path.display()))?,
    );
    let keys = KeySet::parse(&text).with_context(|| format!("key file {}", path.display()))?;
    let done = exocal_hil::flash::provision(flash_dir, &keys)
        .with_context(|| format!("writing key slots in {}", flash_dir.display()))?;
    let mut line = format!(
        "provisioned the key slots of {} node(s) from {}",
        done.keyed.len(),
        path.display()
    );
    for (node, why) in &done.locked {
        line.push_str(&format!(
            "; node {} stays locked (installs nothing) until given a new key: {why}",
            node.raw()
        ));
    }
    Ok(line)
}

/// What the nodes do once the motion has ended, for the readiness line.
fn readiness(linger: Linger) -> String {
    match linger {
        Linger::UntilStopped => "nodes answering until SIGTERM".into(),
        Linger::For(s) if s > 0.0 => {
            format!("nodes answering for {s} s more (simulated), or until SIGTERM")
        }
        Linger::For(_) => "exiting (--linger 0)".into(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::CommandFactory;

    #[test]
    fn the_cli_is_consistent_and_linger_takes_finite_non_negative_seconds() {
        Cli::command().debug_assert();
        assert_eq!(non_negative("0"), Ok(0.0));
        assert_eq!(non_negative("2.5"), Ok(2.5));
        for bad in ["-1", "inf", "NaN", "soon"] {
            assert!(non_negative(bad).is_err(), "{bad}");
        }
        let cli = Cli::try_parse_from(["exocal-hil", "--iface", "vcan0", "--linger", "0"]).unwrap();
        assert_eq!(cli.linger, Some(0.0));
        assert!(Cli::try_parse_from(["exocal-hil", "--iface", "vcan0", "--linger=-3"]).is_err());
    }

    #[test]
    fn keys_are_provisioned_from_a_file_and_errors_never_show_a_key() {
        let dir = std::env::temp_dir().join(format!("exocal-hil-keys-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let file = dir.join("keys");
        std::fs::write(&file, "Joint2 6dce7822fccd695373724892c45655b8\n").unwrap();
        let said = provision_keys(Some(&file), &dir.join("flash")).unwrap();
        assert!(said.contains("1 node(s)"), "{said}");
        assert!(
            exocal_hil::flash::read_key(&dir.join("flash"), NodeId::JOINTS[1])
                .unwrap()
                .is_some()
        );
        std::fs::write(&file, "Joint2 6dce7822fccd695373724892c45655bz\n").unwrap();
        let e = format!(
            "{:#}",
            provision_keys(Some(&file), &dir.join("flash")).unwrap_err()
        );
        assert!(e.contains("line 1") && !e.contains("0001"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn the_readiness_line_says_how_long_the_nodes_answer() {
        assert_eq!(
            readiness(Linger::UntilStopped),
            "nodes answering until SIGTERM"
        );
        assert_eq!(
            readiness(Linger::For(30.0)),
            "nodes answering for 30 s more (simulated), or until SIGTERM"
        );
        assert_eq!(readiness(Linger::For(0.0)), "exiting (--linger 0)");
    }
}
