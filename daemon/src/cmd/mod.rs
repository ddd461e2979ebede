//! What each subcommand does, as functions returning a typed [`DaemonError`] (the binary maps
//! it to an exit status): `calibrate` here, the others in a module each.

#[cfg(feature = "demo")]
pub mod demo;
pub mod nodes;
pub mod offline;
pub mod serve;

use std::path::{Path, PathBuf};

use exocal_bus::{Clock, SocketCan};
use tokio::signal::unix::{signal, SignalKind};

use crate::cli::{
    CheckConfigArgs, Cli, Command, NodesArgs, RecoverArgs, SessionArgs, SYSTEM_CONFIG,
};
use crate::config::{Config, ConfigError, DEFAULT_TOML};
use crate::exit::DaemonError;
use crate::shell::notify::{Notifier, Reporter};
use crate::shell::runner::run_session;
use crate::shell::shutdown::Shutdown;
use crate::shell::summary::{finish, Output};

/// Where a configuration came from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ConfigSource {
    /// Loaded from this file.
    File(PathBuf),
    /// The built-in defaults ([`crate::config::DEFAULT_TOML`]).
    BuiltIn,
}

impl std::fmt::Display for ConfigSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ConfigSource::File(p) => write!(f, "{}", p.display()),
            ConfigSource::BuiltIn => write!(f, "built-in defaults"),
        }
    }
}

/// Loads `explicit` if given; otherwise `system` if it exists; otherwise the built-in defaults.
pub fn resolve_config(
    explicit: Option<&Path>,
    system: &Path,
) -> Result<(Config, ConfigSource), ConfigError> {
    match explicit {
        Some(p) => Ok((Config::load(p)?, ConfigSource::File(p.to_path_buf()))),
        None if system.exists() => Ok((Config::load(system)?, ConfigSource::File(system.into()))),
        None => Ok((Config::default_config(), ConfigSource::BuiltIn)),
    }
}

/// Applies the command-line overrides of `calibrate`/`run` to `config`.
pub fn apply_overrides(config: &mut Config, args: &SessionArgs) {
    if let Some(i) = &args.interface {
        config.interface = i.clone();
    }
    if let Some(o) = &args.output {
        config.output.directory = o.clone();
    }
}

/// Checks that the network interface `name` exists, with an error saying how to create it
/// ([`exocal_bus::interface::missing`]).
pub fn require_interface(name: &str) -> Result<(), DaemonError> {
    match exocal_bus::interface::missing(name) {
        None => Ok(()),
        Some(reason) => Err(DaemonError::Interface {
            name: name.to_string(),
            reason,
        }),
    }
}

/// Runs the parsed command line.
pub fn run(cli: Cli) -> Result<(), DaemonError> {
    match cli.command {
        Command::CheckConfig(args) => check_config(cli.config.as_deref(), &args),
        Command::Calibrate(args) => {
            let mut config = session_config(cli.config.as_deref(), &args)?;
            attach_keys(&mut config, false)?;
            runtime()?.block_on(calibrate_on_can(config, args.dry_run))
        }
        Command::Run(args) => {
            let mut config = session_config(cli.config.as_deref(), &args)?;
            attach_keys(&mut config, true)?;
            runtime()?.block_on(serve_on_can(config, args.dry_run))
        }
        Command::Offline(args) => {
            let output = Output::from_flags(args.quiet, args.json);
            let mut printed = false;
            let result = offline(cli.config.as_deref(), args, output, &mut printed);
            json_error_unless(result, output, printed)
        }
        Command::Recover(args) => recover_log(&args),
        Command::Completions(args) => completions(args.shell),
        Command::Man(args) => man(args.dir.as_deref()),
        Command::Nodes(args) => {
            let result = nodes(cli.config.as_deref(), &args);
            match &result {
                // The listing (printed) names the missing nodes; any other failure leaves
                // stdout empty, so a script gets it as JSON there too.
                Err(e) if args.json && !matches!(e, DaemonError::NoAnswer(_)) => {
                    println!("{}", error_json(e));
                }
                _ => {}
            }
            result
        }
        #[cfg(feature = "demo")]
        Command::Demo(args) => {
            let output = Output::from_flags(args.quiet, args.json);
            let mut printed = false;
            let result = demo(cli.config.as_deref(), &args, output, &mut printed);
            json_error_unless(result, output, printed)
        }
    }
}

/// With `--json`, an error no result was printed for (a bad configuration, an unreadable
/// input) still gives stdout one JSON object, `{"error": …, "exit": N}`, as `nodes --json`.
fn json_error_unless(
    result: Result<(), DaemonError>,
    output: Output,
    printed: bool,
) -> Result<(), DaemonError> {
    if let (Err(e), Output::Json, false) = (&result, output, printed) {
        println!("{}", error_json(e));
    }
    result
}

/// `exocald offline`: the configuration, then the replay and its result (`printed` once it
/// is on stdout).
fn offline(
    config_path: Option<&Path>,
    args: crate::cli::OfflineArgs,
    output: Output,
    printed: &mut bool,
) -> Result<(), DaemonError> {
    let (config, source) = resolve_config(config_path, Path::new(SYSTEM_CONFIG))?;
    if output == Output::Text {
        eprintln!("exocald: configuration from {source}");
    }
    let text = match &source {
        ConfigSource::File(p) => std::fs::read_to_string(p).map_err(|source| DaemonError::Io {
            what: format!("reading {}", p.display()),
            source,
        })?,
        ConfigSource::BuiltIn => DEFAULT_TOML.to_string(),
    };
    let opts = crate::cmd::offline::OfflineOptions {
        input: args.input,
        format: args.format,
        report: args.report,
        export_toml: args.export_toml,
        export_urdf: args.export_urdf,
        export_candump: args.export_candump,
        export_csv: args.export_csv,
        quiet: !matches!(output, crate::shell::summary::Output::Text),
    };
    let result = crate::cmd::offline::run(&config, &text, &opts).map_err(|e| *e);
    *printed = true;
    finish(result, output)
}

/// `exocald demo`: the emulated suit and the daemon, then the result, the flash check and,
/// with `--nodes`, the nodes' listing (`printed` once the result is on stdout).
#[cfg(feature = "demo")]
fn demo(
    config_path: Option<&Path>,
    args: &crate::cli::DemoArgs,
    output: Output,
    printed: &mut bool,
) -> Result<(), DaemonError> {
    let (config, source) = resolve_config(config_path, Path::new(SYSTEM_CONFIG))?;
    let quiet = output != Output::Text;
    if !quiet {
        eprintln!("exocald: configuration from {source}");
    }
    let mut config = crate::cmd::demo::demo_config(config, &args.output, 1.0);
    if let Some(n) = args.joints.map(usize::from) {
        let arm = config.calibration.joints;
        if n > arm {
            return Err(DaemonError::Usage(format!(
                "--joints {n}: the configuration's arm has {arm} joints ([nodes] joints)"
            )));
        }
        config.calibration = config.calibration.first(n);
    }
    // The emulated suit puts joint i on node i.
    let arm = config.calibration.joints;
    let nodes = &config.calibration.joint_nodes[..arm.min(crate::config::MAX_JOINTS)];
    if !nodes.iter().copied().eq(1..=arm as u8) {
        return Err(DaemonError::Usage(format!(
            "the emulated suit's joints are on nodes 1 to {arm} in order; the configuration's \
             [nodes] joints = {nodes:?}"
        )));
    }
    config.live.enabled |= args.live;
    if let Some(listen) = args.listen {
        config.live.enabled = true;
        config.live.listen = listen;
    }
    if config.push.authenticate && !quiet {
        eprintln!(
            "exocald: demo keys: one AES-128 key per node derived in-process from the seed \
             ({}): not secret, for the emulated suit only",
            args.seed
        );
    }
    let opts = crate::cmd::demo::DemoOptions {
        seed: args.seed,
        speed: args.speed,
        output: args.output.clone(),
        hold: args.live || args.listen.is_some(),
        quiet,
        wearer: Default::default(),
        drift: Default::default(),
    };
    let result = match crate::cmd::demo::run(&config, &opts).map_err(|e| *e) {
        Ok(result) => result,
        Err(e) => {
            *printed = true;
            return finish(Err(e), output);
        }
    };
    let mut check = crate::cmd::demo::check_flash(&result, config.calibration.joints);
    let mut extra: Vec<String> = result
        .flash_crc
        .iter()
        .map(|(node, crc)| {
            let crc = crc.map_or_else(|| "none".into(), |c| format!("{c:#010x}"));
            format!("flash {node}: table CRC {crc}")
        })
        .collect();
    if check.is_ok() {
        extra.push("every node persisted the pushed table (CRC match)".into());
        if args.nodes {
            let flash = args.output.join("flash");
            match crate::cmd::demo::ask_nodes(&config, args.seed, &flash, &[], None) {
                Ok(listing) => extra.extend(listing.lines()),
                Err(e) => check = Err(e),
            }
        }
    }
    *printed = true;
    crate::shell::summary::print_result(
        Some(&result.summary),
        check.as_ref().err(),
        &extra,
        output,
    );
    check
}

/// `exocald completions SHELL`: the completion script, from the CLI definition.
fn completions(shell: clap_complete::Shell) -> Result<(), DaemonError> {
    use clap::CommandFactory;
    let mut out = Vec::new();
    clap_complete::generate(shell, &mut Cli::command(), "exocald", &mut out);
    write_stdout(&out, "the completion script")
}

/// `exocald man [--dir DIR]`: the manual page on stdout, or one per subcommand into `dir`.
fn man(dir: Option<&Path>) -> Result<(), DaemonError> {
    use clap::CommandFactory;
    let io = |what: String| move |source| DaemonError::Io { what, source };
    let Some(dir) = dir else {
        let mut out = Vec::new();
        clap_mangen::Man::new(Cli::command())
            .render(&mut out)
            .map_err(io("rendering the manual page".into()))?;
        return write_stdout(&out, "the manual page");
    };
    std::fs::create_dir_all(dir).map_err(io(format!("creating {}", dir.display())))?;
    clap_mangen::generate_to(Cli::command(), dir).map_err(io(format!(
        "writing the manual pages into {}",
        dir.display()
    )))
}

/// Writes `bytes` to stdout (a closed pipe is an I/O error, 74, never a panic).
fn write_stdout(bytes: &[u8], what: &str) -> Result<(), DaemonError> {
    use std::io::Write;
    let mut stdout = std::io::stdout().lock();
    stdout
        .write_all(bytes)
        .and_then(|()| stdout.flush())
        .map_err(|source| DaemonError::Io {
            what: format!("writing {what} to stdout"),
            source,
        })
}

/// `exocald nodes`: the configuration, the keys if provisioned, then the listing.
fn nodes(config_path: Option<&Path>, args: &NodesArgs) -> Result<(), DaemonError> {
    let (mut config, source) = resolve_config(config_path, Path::new(SYSTEM_CONFIG))?;
    apply_overrides(
        &mut config,
        &SessionArgs {
            interface: args.interface.clone(),
            output: args.output.clone(),
            dry_run: true,
        },
    );
    eprintln!("exocald: configuration from {source}");
    require_interface(&config.interface)?;
    if config.push.authenticate {
        let nodes = config.joint_node_ids();
        match crate::keys::load_if_present(&nodes)? {
            Some(keys) => config.push.keys = keys,
            None => eprintln!(
                "exocald: no credential {}: the nodes' answers are not authenticated \
                 (each line says so)",
                crate::keys::CREDENTIAL
            ),
        }
    }
    runtime()?.block_on(nodes_on_can(&config, args))
}

/// A failure as one JSON object, `{"error": "...", "exit": N}`, for `--json` callers.
fn error_json(e: &DaemonError) -> String {
    serde_json::json!({ "error": e.to_string(), "exit": e.exit_code() }).to_string()
}

fn session_config(path: Option<&Path>, args: &SessionArgs) -> Result<Config, DaemonError> {
    let (mut config, source) = resolve_config(path, Path::new(SYSTEM_CONFIG))?;
    apply_overrides(&mut config, args);
    eprintln!("exocald: configuration from {source}");
    require_interface(&config.interface)?;
    Ok(config)
}

/// With `push.authenticate`, loads the keys from the `exocal-keys` credential into `config`
/// (a key for every joint node, and the trigger key for `run`) and takes the state directory
/// (`$STATE_DIRECTORY`, [`crate::state`]), or fails (exit 78) before the bus is touched; says
/// on stderr (the journal) which way it is, never the keys.
pub fn attach_keys(config: &mut Config, trigger: bool) -> Result<(), DaemonError> {
    if !config.push.authenticate {
        eprintln!(
            "exocald: WARNING: authentication is off ([push] authenticate = false): nodes of \
             protocol exocal-3 and later install no unauthenticated table, any sender on the bus can forge \
             their answers, and the sensor streams are taken unverified{}",
            if trigger { " or start a session" } else { "" }
        );
        return Ok(());
    }
    let mut nodes = config.joint_node_ids();
    // The end effector signs its stream (session::gate) with a key of its own.
    nodes.push(exocal_dbc::NodeId::END_EFFECTOR);
    config.push.keys = crate::keys::load_credential(&nodes, trigger)?;
    let Some(state) = crate::state::from_env() else {
        return Err(DaemonError::Keys(crate::keys::KeyError::NoState));
    };
    if let Some(w) = crate::keys::credential_warning() {
        eprintln!("exocald: {w}");
    }
    config.push.state_dir = Some(state);
    eprintln!(
        "exocald: table transfers{} and sensor streams are authenticated (AES-128-CMAC, \
         freshness counters, stream digests): keys of {} node(s){} from the credential {}",
        if trigger { ", triggers" } else { "" },
        nodes.len(),
        if trigger { " and the trigger key" } else { "" },
        crate::keys::CREDENTIAL
    );
    Ok(())
}

/// The daemon's runtime: one thread drives the bus, the timers and the log, polling the socket
/// itself. With worker threads, a worker would wake from epoll for every batch of frames and
/// wake the loop's thread in turn: in the emulated guest that handoff (context switches,
/// futexes) is a quarter of the daemon's CPU while ingesting (perf, benches/ingest.sh's load).
/// Calibration and the in-collection estimates run on tokio's blocking pool (`spawn_blocking`),
/// the live view on a runtime of its own.
fn runtime() -> Result<tokio::runtime::Runtime, DaemonError> {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .map_err(|source| DaemonError::Io {
            what: "starting the async runtime".into(),
            source,
        })
}

fn open_can(config: &Config) -> Result<SocketCan, DaemonError> {
    SocketCan::open(&config.interface).map_err(|e| DaemonError::Interface {
        name: config.interface.clone(),
        reason: exocal_bus::interface::open_failure(
            &config.interface,
            &e,
            exocal_bus::interface::kernel_has_can(),
        ),
    })
}

/// `exocald calibrate`: one session on the configured CAN interface.
pub async fn calibrate_on_can(config: Config, dry_run: bool) -> Result<(), DaemonError> {
    let shutdown = Shutdown::on_signals();
    let mut bus = open_can(&config)?;
    let mut notifier = Notifier::from_env();
    let mut reporter = Reporter::detect(&notifier);
    let clock = Clock::Wall;
    let result = run_session(
        &mut bus,
        &clock,
        &config,
        dry_run,
        shutdown.wait(),
        &mut notifier,
        &mut reporter,
    )
    .await;
    finish(result, Output::Text)
}

/// `exocald run`: wait for an authentic `Trigger` frame (StartCalibration) or SIGUSR1, run a
/// session, and wait again, until SIGTERM/SIGINT; at most one session per cooldown
/// ([`crate::cmd::serve`]).
/// Each state change is a line on stderr (`idle: …`, `trigger received (…)`), which is what
/// a supervisor or a test waits on.
pub async fn serve_on_can(config: Config, dry_run: bool) -> Result<(), DaemonError> {
    let shutdown = Shutdown::on_signals();
    let mut bus = open_can(&config)?;
    let mut notifier = Notifier::from_env();
    let mut reporter = Reporter::detect(&notifier);
    let mut usr1 = signal(SignalKind::user_defined1()).map_err(|source| DaemonError::Io {
        what: "installing the SIGUSR1 handler".into(),
        source,
    })?;
    let (tx, mut local) = tokio::sync::mpsc::channel(1);
    tokio::spawn(async move {
        while usr1.recv().await.is_some() {
            let _ = tx.try_send(());
        }
    });
    crate::cmd::serve::serve(
        &mut bus,
        &Clock::Wall,
        &config,
        dry_run,
        &shutdown,
        &mut local,
        &mut notifier,
        &mut reporter,
    )
    .await
    .map(|_| ())
}

/// `exocald nodes`: the listing on stdout (a table, or JSON), then 69 if a node is missing.
async fn nodes_on_can(config: &Config, args: &NodesArgs) -> Result<(), DaemonError> {
    let mut bus = open_can(config)?;
    let listing =
        crate::cmd::nodes::list(&mut bus, &Clock::Wall, config, args.log.as_deref()).await?;
    if args.json {
        let text = serde_json::to_string_pretty(&listing).map_err(|e| DaemonError::Internal {
            what: "formatting the listing as JSON".into(),
            source: Box::new(e),
        })?;
        println!("{text}");
    } else {
        for line in listing.lines() {
            println!("{line}");
        }
    }
    if listing.missing.is_empty() {
        Ok(())
    } else {
        Err(DaemonError::NoAnswer(listing.missing))
    }
}

/// `exocald recover IN OUT`: the complete file, and one line saying what was kept.
/// `exocald recover IN OUT`: the recovered log is written to a temporary file beside OUT and
/// renamed to OUT once complete and synced, so a failed recovery leaves no OUT (nor a
/// half-written one, nor the temporary file).
fn recover_log(args: &RecoverArgs) -> Result<(), DaemonError> {
    let io = |what: String| move |source| DaemonError::Io { what, source };
    let same = match (args.input.canonicalize(), args.output.canonicalize()) {
        (Ok(a), Ok(b)) => a == b,
        _ => false,
    };
    if same {
        return Err(DaemonError::Usage(format!(
            "OUT {} is IN: write the recovered log to another file",
            args.output.display()
        )));
    }
    let input = std::fs::File::open(&args.input)
        .map_err(io(format!("reading {}", args.input.display())))?;
    let name = args
        .output
        .file_name()
        .map_or_else(|| "recovered".into(), |n| n.to_string_lossy().into_owned());
    let temp = args
        .output
        .with_file_name(format!(".{name}.{}.partial", std::process::id()));
    let written = (|| {
        let file =
            std::fs::File::create(&temp).map_err(io(format!("creating {}", temp.display())))?;
        let (recovery, out) = exocal_log::recover::recover(
            std::io::BufReader::new(input),
            std::io::BufWriter::new(file),
            Some(mcap::Compression::Zstd),
        )
        .map_err(|e| match e {
            exocal_log::recover::RecoverError::NotMcap => {
                DaemonError::Input(format!("{}: {e}", args.input.display()))
            }
            exocal_log::recover::RecoverError::Write(e) => DaemonError::Log {
                what: format!("writing {}", temp.display()),
                source: exocal_log::write::LogError::Mcap(e),
            },
        })?;
        out.into_inner()
            .map_err(|e| e.into_error())
            .and_then(|f| f.sync_all())
            .map_err(io(format!("writing {}", temp.display())))?;
        std::fs::rename(&temp, &args.output).map_err(io(format!(
            "renaming {} to {}",
            temp.display(),
            args.output.display()
        )))?;
        Ok(recovery)
    })();
    let recovery = match written {
        Ok(r) => r,
        Err(e) => {
            let _ = std::fs::remove_file(&temp);
            return Err(e);
        }
    };
    println!("{}: recovered {recovery}", args.input.display());
    println!(
        "wrote {}: {} messages, with summary, indexes and footer",
        args.output.display(),
        recovery.messages
    );
    Ok(())
}

fn check_config(path: Option<&Path>, args: &CheckConfigArgs) -> Result<(), DaemonError> {
    if args.print_default {
        print!("{DEFAULT_TOML}");
        return Ok(());
    }
    let (config, source) = resolve_config(path, Path::new(SYSTEM_CONFIG))?;
    println!("# configuration from {source}: valid");
    println!("# the effective values, in the file's units (degrees, seconds, metres):");
    print!("{}", config.to_toml());
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn config_resolution_prefers_explicit_then_system_then_builtin() {
        let none = Path::new("/nonexistent/exocald.toml");
        let (c, s) = resolve_config(None, none).unwrap();
        assert_eq!(s, ConfigSource::BuiltIn);
        assert_eq!(c, Config::default_config());

        let dir = std::env::temp_dir().join(format!("exocald-app-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let sys = dir.join("sys.toml");
        std::fs::write(&sys, DEFAULT_TOML.replace("\"can0\"", "\"vcan7\"")).unwrap();
        let (c, s) = resolve_config(None, &sys).unwrap();
        assert_eq!(
            (c.interface.as_str(), s),
            ("vcan7", ConfigSource::File(sys.clone()))
        );

        let err = resolve_config(Some(&dir.join("missing.toml")), &sys).unwrap_err();
        assert!(matches!(err, ConfigError::Io { .. }));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_missing_interface_is_a_clear_error() {
        let e = require_interface("vcan93").unwrap_err();
        assert_eq!(e.exit_code(), crate::exit::code::UNAVAILABLE);
        let shown = e.to_string();
        assert!(
            shown.contains("vcan93") && shown.contains("ip link add"),
            "{shown}"
        );
        assert!(require_interface("../etc").is_err());
        assert!(require_interface("lo").is_ok());
    }

    #[test]
    fn overrides_replace_interface_and_output() {
        let mut c = Config::default_config();
        apply_overrides(
            &mut c,
            &SessionArgs {
                interface: Some("vcan0".into()),
                output: Some("/tmp/x".into()),
                dry_run: false,
            },
        );
        assert_eq!(c.interface, "vcan0");
        assert_eq!(c.output.directory, PathBuf::from("/tmp/x"));
    }
}
