//! What each subcommand does, as functions returning a typed [`DaemonError`] (the binary maps
//! it to an exit status).

use std::path::{Path, PathBuf};

use crate::cli::{CheckConfigArgs, Cli, Command, SessionArgs, SYSTEM_CONFIG};
use crate::config::{Config, ConfigError, DEFAULT_TOML};
use crate::exit::DaemonError;

/// Where a configuration came from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ConfigSource {
    File(PathBuf),
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

/// Checks that the network interface `name` exists, with an error saying how to create it.
pub fn require_interface(name: &str) -> Result<(), DaemonError> {
    let valid = !name.is_empty() && name.len() <= 15 && !name.contains('/') && name != "..";
    if !valid || !Path::new("/sys/class/net").join(name).exists() {
        let hint = if name.starts_with("vcan") {
            format!(
                "no such interface; on a bench create it with `ip link add {name} type vcan && \
                 ip link set {name} up` (or install systemd/80-vcan0.netdev)"
            )
        } else {
            "no such interface; check the CAN adapter and its systemd-networkd file \
             (systemd/80-can0.network), or pass --interface"
                .to_string()
        };
        return Err(DaemonError::Interface {
            name: name.to_string(),
            reason: hint,
        });
    }
    Ok(())
}

/// Runs the parsed command line.
pub fn run(cli: Cli) -> Result<(), DaemonError> {
    match cli.command {
        Command::CheckConfig(args) => check_config(cli.config.as_deref(), &args),
        Command::Calibrate(args) | Command::Run(args) => {
            let (mut config, source) =
                resolve_config(cli.config.as_deref(), Path::new(SYSTEM_CONFIG))?;
            apply_overrides(&mut config, &args);
            eprintln!("exocald: configuration from {source}");
            require_interface(&config.interface)?;
            Err(DaemonError::Unsupported(
                "CAN sessions need the exocal-bus/exocal-dbc integration, not wired yet".into(),
            ))
        }
        Command::Demo(_) => Err(DaemonError::Unsupported(
            "the demo needs the exocal-hil integration, not wired yet".into(),
        )),
    }
}

fn check_config(path: Option<&Path>, args: &CheckConfigArgs) -> Result<(), DaemonError> {
    if args.print_default {
        print!("{DEFAULT_TOML}");
        return Ok(());
    }
    let (config, source) = resolve_config(path, Path::new(SYSTEM_CONFIG))?;
    println!("configuration from {source}: valid");
    println!("{config:#?}");
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
