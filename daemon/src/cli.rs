//! Command line: what a newcomer types, and what systemd runs.
//!
//! `exocald calibrate` is the power-up service (one session, then exit); `exocald run` serves and
//! calibrates when triggered; `exocald demo` runs the emulated suit and the daemon in one process
//! (no CAN, no root); `exocald check-config` validates a configuration file and prints it;
//! `exocald offline` recalibrates from a recorded session; `exocald recover` rewrites a log cut
//! short as a complete file; `exocald nodes` asks every node which table it holds;
//! `exocald completions SHELL` and `exocald man` print what the shell and man(1) need, made
//! from this definition.

use std::path::PathBuf;

use clap::{Args, Parser, Subcommand};

/// Where the packaged configuration lives; used when `--config` is not given and it exists.
pub const SYSTEM_CONFIG: &str = "/etc/exocal/exocald.toml";

/// exocald: calibrates the exoskeleton's kinematic table from free arm motion.
///
/// At power-up (`exocald calibrate`, run by systemd) the daemon listens to the IMU nodes on CAN,
/// aligns their clocks, collects free arm motion until the table is expected within the limits
/// (every joint moved enough, at least `min_duration_s`, at most `max_duration_s`), identifies
/// the D-H table (least squares, then EM over the joint-angle drift), checks the result against
/// the anatomical bounds and on a held-out slice of the session, and only then pushes it to every
/// node. Every session is logged to an MCAP file you can open in Foxglove.
#[cfg_attr(feature = "demo", doc = "")]
#[cfg_attr(
    feature = "demo",
    doc = "New here? Try `exocald demo`: the whole story in one process, with an emulated suit."
)]
#[derive(Debug, Parser)]
#[command(name = "exocald", version, about, long_about, propagate_version = true)]
pub struct Cli {
    /// Configuration file (TOML). Default: /etc/exocal/exocald.toml if it exists, otherwise the
    /// built-in defaults (print them with `exocald check-config --print-default`).
    #[arg(long, short = 'c', global = true, value_name = "FILE")]
    pub config: Option<PathBuf>,

    #[command(subcommand)]
    /// What to do.
    pub command: Command,
}

/// The subcommands.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Collect one session, calibrate, validate, push to every node, then exit.
    ///
    /// This is what the systemd unit runs at power-up. Exit status: 0 pushed; 65 calibration
    /// refused by validation (nothing pushed), or a second sender on a node's identifiers; 66
    /// the session never had enough motion, or too much of the sensor streams failed
    /// authentication; 69 CAN interface missing or a node unreachable; 74 I/O error; 75
    /// interrupted (nothing pushed); 78 bad configuration.
    Calibrate(SessionArgs),
    /// Serve: keep listening, and run a session on each CAN Trigger frame or SIGUSR1.
    ///
    /// Idle, it feeds the watchdog and says so on stderr ("idle: waiting for a trigger"). A
    /// trigger that arrives during a session is ignored, and said so (stderr; a frame also in
    /// the session's log). Exit status: 0 stopped by SIGTERM/SIGINT while idle; 75 stopped
    /// during a session (nothing pushed); 69 CAN interface missing; 74 I/O error; 78 bad
    /// configuration. A session that fails is reported and the daemon waits again.
    Run(SessionArgs),
    /// Emulated suit and daemon in one process, on the in-process bus: no CAN, no root.
    ///
    /// Plays the paper's simulation scenario (Table 4 "actual" arm, drifting joint angles),
    /// calibrates, pushes to the emulated nodes and writes the session's MCAP log.
    /// Exit status: 0 pushed and every emulated node persisted the table; 64 a bad option value
    /// (e.g. --speed 0); 65 calibration refused by validation (nothing pushed); 66 the session
    /// never had enough motion; 69 a node did not take the table, or its flash disagrees; 74
    /// I/O error; 75 interrupted by SIGTERM/SIGINT (nothing pushed, the log finished); 78 bad
    /// configuration.
    #[cfg(feature = "demo")]
    Demo(DemoArgs),
    /// Check a configuration file: print what was understood, or the error.
    ///
    /// Exit status: 0 the file is valid (or the default was printed); 78 it cannot be read, or
    /// it is invalid (the key and the reason named).
    CheckConfig(CheckConfigArgs),
    /// Recalibrate from a recorded session (MCAP log, candump log or CSV samples), no bus.
    ///
    /// Frames are replayed through the daemon's own ingest, alignment and calibration (an MCAP
    /// log up to the end of its collection window), so the same data gives the live run's
    /// table. Writes the HTML report and the requested exports: TOML and URDF for a validated
    /// table, the candump log and CSV samples whatever the verdict.
    /// Exit status: 0 validated; 64 options that do not go together (--export-candump of CSV
    /// samples); 65 refused by validation, or the input does not parse; 66 the recording misses the session rules (duration, excitation, samples); 74 I/O
    /// error; 78 bad configuration.
    Offline(OfflineArgs),
    /// Rewrite a session log cut short (kill -9, power loss) as a complete, indexed MCAP.
    ///
    /// Keeps every message of every complete chunk (schemas, channels, ids, sequence numbers and
    /// times as written) and says how much that is and where the input was cut; the output has
    /// a summary, indexes and a footer, so Foxglove and any MCAP reader open it. `offline`
    /// reads a cut log directly; this makes a file for other tools.
    /// Exit status: 0 written; 64 OUT is IN; 65 IN is not an MCAP file; 74 I/O error.
    Recover(RecoverArgs),
    /// Ask every joint node which table it holds (CAN bus required).
    ///
    /// Reads each node's table over the bus (the table transfer's readback): node id, the CRC of
    /// the table held, its D-H row and drift τ/σ, and whether it is the table the last session
    /// pushed — the table the node confirmed at the end of the newest session log in the output
    /// directory that has a push (or in --log FILE). Names every node that does not answer.
    /// Exit status: 0 every node answered; 69 some node did not answer (each named), or the CAN
    /// interface is missing; 74 I/O error; 78 bad configuration.
    Nodes(NodesArgs),
    /// Print the shell completion script for SHELL on stdout.
    ///
    /// bash: `exocald completions bash > ~/.local/share/bash-completion/completions/exocald`;
    /// zsh: into a directory of your `fpath` as `_exocald`; fish:
    /// `~/.config/fish/completions/exocald.fish`. The Debian package installs all three.
    /// Exit status: 0 printed; 74 stdout could not be written.
    Completions(CompletionsArgs),
    /// Print the manual page (roff) on stdout, or write one per subcommand into --dir.
    ///
    /// `exocald man | man -l -` reads it now. The Debian package installs them (man exocald,
    /// man exocald-offline, …). Exit status: 0 written; 74 I/O error.
    Man(ManArgs),
}

/// Options of `completions`.
#[derive(Debug, Args)]
pub struct CompletionsArgs {
    /// The shell.
    #[arg(value_enum)]
    pub shell: clap_complete::Shell,
}

/// Options of `man`.
#[derive(Debug, Args)]
pub struct ManArgs {
    /// Write `exocald.1` and `exocald-SUBCOMMAND.1` into this directory instead.
    #[arg(long, value_name = "DIR")]
    pub dir: Option<PathBuf>,
}

/// Options of `nodes`.
#[derive(Debug, Args)]
pub struct NodesArgs {
    /// CAN interface, overriding `can.interface` (e.g. vcan0).
    #[arg(long, short = 'i', value_name = "IFACE")]
    pub interface: Option<String>,
    /// Folder of the session logs, overriding `output.directory`.
    #[arg(long, short = 'o', value_name = "DIR")]
    pub output: Option<PathBuf>,
    /// Compare with the tables pushed in this session log instead.
    #[arg(long, value_name = "FILE.mcap")]
    pub log: Option<PathBuf>,
    /// Print the listing as JSON (for scripts).
    #[arg(long)]
    pub json: bool,
}

/// Options of `recover`.
#[derive(Debug, Args)]
pub struct RecoverArgs {
    /// The session log cut short.
    #[arg(value_name = "IN")]
    pub input: PathBuf,
    /// Where to write the complete file (replaced if it exists; never IN itself).
    #[arg(value_name = "OUT")]
    pub output: PathBuf,
}

/// Options of `offline`.
#[derive(Debug, Args)]
pub struct OfflineArgs {
    /// The recorded session: an exocald MCAP log, a `candump -L` log, or CSV samples.
    #[arg(long, short = 'i', value_name = "FILE")]
    pub input: PathBuf,
    /// Input format; detected from the content when omitted (the extension only where the
    /// content is none of the formats).
    #[arg(long, value_enum)]
    pub format: Option<Format>,
    /// HTML report. Default: `<input>.offline.html` next to the input.
    #[arg(long, value_name = "OUT.html")]
    pub report: Option<PathBuf>,
    /// Write the calibrated table as the daemon's configuration (a copy of --config's file).
    #[arg(long, value_name = "OUT.toml")]
    pub export_toml: Option<PathBuf>,
    /// Write the calibrated table as URDF joint origins.
    #[arg(long, value_name = "OUT.urdf")]
    pub export_urdf: Option<PathBuf>,
    /// Write the replayed frames as a `candump -L` log (frame inputs only).
    #[arg(long, value_name = "OUT.log")]
    pub export_candump: Option<PathBuf>,
    /// Write the aligned samples the calibration was given as CSV
    /// (`t,q1…qn,x,y,z,qw,qx,qy,qz` for the configured arm of n joints, the format `offline`
    /// reads), whatever the verdict.
    #[arg(long, value_name = "OUT.csv")]
    pub export_csv: Option<PathBuf>,
    /// Print only the verdict (the summary's last line) on stdout, and no progress.
    #[arg(long, short = 'q', conflicts_with = "json")]
    pub quiet: bool,
    /// Print the result as one JSON object on stdout (verdict, exit status, expected error,
    /// held-out errors, the calibrated table in SI units, per-node push results, refusals),
    /// and no progress: for scripts.
    #[arg(long)]
    pub json: bool,
}

/// Options shared by `calibrate` and `run`.
#[derive(Debug, Args)]
pub struct SessionArgs {
    /// CAN interface, overriding `can.interface` (e.g. vcan0).
    #[arg(long, short = 'i', value_name = "IFACE")]
    pub interface: Option<String>,
    /// Folder for the session's MCAP log, overriding `output.directory`.
    #[arg(long, short = 'o', value_name = "DIR")]
    pub output: Option<PathBuf>,
    /// Calibrate and validate, but push nothing.
    #[arg(long)]
    pub dry_run: bool,
}

/// Options of `demo`.
#[cfg(feature = "demo")]
#[derive(Debug, Args)]
pub struct DemoArgs {
    /// Seed of the emulated suit (motion, drift, noise): the same seed gives the same table.
    #[arg(long, default_value_t = 2024)]
    pub seed: u64,
    /// At most this many simulated seconds per real second (the paper's 60 s scenario takes at
    /// least 60/speed s). The run is on simulated time: the speed and the machine's load never
    /// change the result; the same seed and configuration give the same table every run.
    #[arg(long, default_value_t = 10.0, allow_negative_numbers = true, value_parser = positive)]
    pub speed: f64,
    /// Folder for the session's MCAP log and report, and the emulated nodes' flash (DIR/flash).
    #[arg(long, short = 'o', value_name = "DIR", default_value = "exocal-demo")]
    pub output: PathBuf,
    /// Serve the session over the Foxglove WebSocket protocol on `[live] listen`
    /// (127.0.0.1:8765 by default) and keep serving after it until Ctrl-C: open Foxglove,
    /// connect to ws://127.0.0.1:8765 and watch the arm, the progress and the result.
    #[arg(long)]
    pub live: bool,
    /// Serve the live view on this loopback address and port instead (implies --live), e.g.
    /// 127.0.0.1:8766 when 8765 is taken. For other hosts, use `[live] listen` with
    /// `allow_remote = true` in a --config file.
    #[arg(long, value_name = "ADDR", value_parser = loopback)]
    pub listen: Option<std::net::SocketAddr>,
    /// Print only the verdict (the summary's last line) on stdout, and no progress.
    #[arg(long, short = 'q', conflicts_with = "json")]
    pub quiet: bool,
    /// Print the result as one JSON object on stdout (verdict, exit status, expected error,
    /// held-out errors, the calibrated table in SI units, per-node push results, refusals),
    /// and no progress: for scripts.
    #[arg(long)]
    pub json: bool,
    /// After the session, power the emulated nodes up again from their flash and ask them what
    /// they hold, as `exocald nodes` asks a suit's nodes on a bus (its listing, on stdout).
    #[arg(long)]
    pub nodes: bool,
    /// Calibrate an arm of the configuration's first N joints (1–7; the emulated suit has N
    /// joint nodes), as a configuration whose `[nodes] joints` lists N nodes would.
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u8).range(1..=7))]
    pub joints: Option<u8>,
}

/// A finite number above zero (`--speed`): a negative one reaches this parser, which names it.
#[cfg(feature = "demo")]
fn positive(text: &str) -> Result<f64, String> {
    match text.parse::<f64>() {
        Ok(v) if v.is_finite() && v > 0.0 => Ok(v),
        Ok(v) => Err(format!("{v} is not a speed: it must be finite and above 0")),
        Err(e) => Err(format!("`{text}` is not a number: {e}")),
    }
}

/// A loopback address and port (`--listen`): the live view has no authentication.
#[cfg(feature = "demo")]
fn loopback(text: &str) -> Result<std::net::SocketAddr, String> {
    let addr: std::net::SocketAddr = text
        .parse()
        .map_err(|_| format!("`{text}` is not an address and port (e.g. 127.0.0.1:8766)"))?;
    if !addr.ip().is_loopback() {
        return Err(format!(
            "{addr} is reachable from other hosts and the live view has no authentication: \
             use a loopback address (127.0.0.1), or `[live] listen` with allow_remote = true \
             in a --config file"
        ));
    }
    Ok(addr)
}

/// Options of `check-config`.
#[derive(Debug, Args)]
pub struct CheckConfigArgs {
    /// Print the built-in default configuration (a commented TOML file) and exit.
    #[arg(long)]
    pub print_default: bool,
}

/// What the input file is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Format {
    /// The daemon's MCAP session log (`/can/rx` frames).
    Mcap,
    /// A `candump -L` log.
    Candump,
    /// CSV samples: `t,q1,…,qn,x,y,z,qw,qx,qy,qz` for the configured arm of n joints.
    Csv,
}

impl std::fmt::Display for Format {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Format::Mcap => "MCAP",
            Format::Candump => "candump",
            Format::Csv => "CSV",
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::CommandFactory;

    #[test]
    fn the_cli_is_consistent() {
        Cli::command().debug_assert();
    }

    #[test]
    fn calibrate_takes_a_config_and_overrides() {
        let cli = Cli::try_parse_from([
            "exocald",
            "calibrate",
            "--config",
            "x.toml",
            "-i",
            "vcan0",
            "--dry-run",
        ])
        .unwrap();
        assert_eq!(cli.config, Some(PathBuf::from("x.toml")));
        match cli.command {
            Command::Calibrate(a) => {
                assert_eq!(a.interface.as_deref(), Some("vcan0"));
                assert!(a.dry_run);
                assert_eq!(a.output, None);
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn offline_takes_an_input_a_format_and_outputs() {
        let cli = Cli::try_parse_from([
            "exocald",
            "offline",
            "--input",
            "s.mcap",
            "--format",
            "candump",
            "--report",
            "r.html",
            "--export-urdf",
            "a.urdf",
            "--export-csv",
            "a.csv",
        ])
        .unwrap();
        match cli.command {
            Command::Offline(a) => {
                assert_eq!(a.input, PathBuf::from("s.mcap"));
                assert_eq!(a.format, Some(Format::Candump));
                assert_eq!(a.report, Some(PathBuf::from("r.html")));
                assert_eq!(a.export_urdf, Some(PathBuf::from("a.urdf")));
                assert_eq!(a.export_csv, Some(PathBuf::from("a.csv")));
                assert_eq!(a.export_toml, None);
            }
            other => panic!("{other:?}"),
        }
        assert!(Cli::try_parse_from(["exocald", "offline"]).is_err());
        assert!(
            Cli::try_parse_from(["exocald", "offline", "-i", "x", "--format", "pcap"]).is_err()
        );
    }

    #[test]
    fn recover_takes_in_and_out() {
        let cli = Cli::try_parse_from(["exocald", "recover", "cut.mcap", "whole.mcap"]).unwrap();
        match cli.command {
            Command::Recover(a) => {
                assert_eq!(a.input, PathBuf::from("cut.mcap"));
                assert_eq!(a.output, PathBuf::from("whole.mcap"));
            }
            other => panic!("{other:?}"),
        }
        assert!(Cli::try_parse_from(["exocald", "recover", "cut.mcap"]).is_err());
    }

    #[test]
    fn nodes_takes_an_interface_a_log_and_json() {
        let cli = Cli::try_parse_from(["exocald", "nodes", "-i", "vcan0", "--json"]).unwrap();
        match cli.command {
            Command::Nodes(a) => {
                assert_eq!(a.interface.as_deref(), Some("vcan0"));
                assert!(a.json);
                assert_eq!((a.output, a.log), (None, None));
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn a_subcommand_is_required_and_typos_are_errors() {
        assert!(Cli::try_parse_from(["exocald"]).is_err());
        assert!(Cli::try_parse_from(["exocald", "calibrat"]).is_err());
        assert!(Cli::try_parse_from(["exocald", "demo", "--sed", "3"]).is_err());
    }

    #[test]
    fn help_mentions_the_demo_and_exit_codes() {
        let help = Cli::command().render_long_help().to_string();
        assert!(help.contains("exocald demo"), "{help}");
        let mut cmd = Cli::command();
        let cal = cmd.find_subcommand_mut("calibrate").unwrap();
        let cal_help = cal.render_long_help().to_string();
        assert!(cal_help.contains("78 bad configuration"), "{cal_help}");
    }

    /// Every subcommand's `--help` lists its exit statuses, each of them a status
    /// `exit::code` defines; 64 is everyone's (a wrong command line).
    #[test]
    fn every_subcommand_lists_its_exit_statuses() {
        use crate::exit::code;
        let known = [
            code::OK,
            code::USAGE,
            code::DATAERR,
            code::NOINPUT,
            code::UNAVAILABLE,
            code::SOFTWARE,
            code::IOERR,
            code::TEMPFAIL,
            code::CONFIG,
        ];
        let mut cli = Cli::command();
        for sub in cli.get_subcommands_mut() {
            let name = sub.get_name().to_string();
            // As narrow as a small terminal: the statuses must be found however clap wraps.
            let help = sub.clone().term_width(50).render_long_help().to_string();
            // Paragraphs with their line breaks undone: clap wraps at the terminal's width.
            let para = help
                .split("\n\n")
                .map(|p| p.split_whitespace().collect::<Vec<_>>().join(" "))
                .find_map(|p| p.find("Exit status:").map(|at| p[at..].to_string()))
                .unwrap_or_else(|| panic!("{name} --help lists no exit status:\n{help}"));
            let statuses: Vec<u8> = para
                .split(|c: char| !c.is_ascii_digit())
                .filter_map(|w| w.parse().ok())
                .filter(|n| *n == 0 || *n >= 64)
                .collect();
            assert!(statuses.contains(&0), "{name}: {statuses:?}");
            for s in &statuses {
                assert!(
                    known.contains(s),
                    "{name}: exit status {s} is not in exit::code"
                );
            }
        }
    }

    #[cfg(feature = "demo")]
    #[test]
    fn a_negative_speed_reaches_the_parser_and_is_named() {
        let e = Cli::try_parse_from(["exocald", "demo", "--speed", "-1"]).unwrap_err();
        let shown = e.to_string();
        assert!(shown.contains("-1 is not a speed"), "{shown}");
        assert!(Cli::try_parse_from(["exocald", "demo", "--speed", "0"]).is_err());
        let ok = Cli::try_parse_from(["exocald", "demo", "--speed", "2.5"]).unwrap();
        assert!(matches!(ok.command, Command::Demo(DemoArgs { speed, .. }) if speed == 2.5));
    }
}
