//! `cargo xtask`: exocal's long commands.
//!
//! ```text
//! cargo xtask test                 everything: unit + doc tests, vcan suites, power-up, cross-builds,
//!                                  README figures
//! cargo xtask test --quick         the host suites only, as plain `cargo test` runs them
//! cargo xtask vcan -- CMD [ARG..]  run CMD with real vcan0 and vcan1 up (native netns or QEMU guest)
//! cargo xtask setup [--check]      install what `test` needs (root, Debian), then self-check
//! cargo xtask clean-root           run `setup` in a freshly bootstrapped Debian root
//! cargo xtask figures [--write]    check (or regenerate) every figure the READMEs quote
//! ```
//!
//! `cargo xtask help COMMAND` tells the rest. Exit status: `vcan` returns the command's own status
//! (128 + signal if it was killed); `test` returns 0 only when every suite passed; 2 means the
//! harness itself could not run (or the command line was wrong).
//!
//! Layout: one module per command (each with its `Args`), shared helpers in leaf modules that
//! import no other xtask module ([`host`]: apt, rustup, `PATH`; [`paths`]; [`process`];
//! [`libtest`]), and between them [`harness`] (the vcan harness: native and VM paths) and
//! [`targets`] (what ships where). No two modules import each other, directly or in a loop:
//! `xtask/tests/layering.rs` checks it, for every crate of the workspace.

mod bench;
mod clean_root;
mod cross;
mod deb;
mod figures;
mod harness;
mod host;
mod libtest;
mod paths;
mod powerup;
mod process;
mod run_suites;
mod setup;
mod targets;
mod test;
mod vcan;

use std::process::ExitCode;

use clap::{Parser, Subcommand};

/// exocal's long commands: the vcan harness, the test suite, setup, cross-builds, packages,
/// benchmarks.
#[derive(Debug, Parser)]
#[command(
    name = "cargo xtask",
    bin_name = "cargo xtask",
    arg_required_else_help = true
)]
struct Cli {
    #[command(subcommand)]
    command: Cmd,
}

#[derive(Debug, Subcommand)]
enum Cmd {
    Test(test::Args),
    Vcan(vcan::Args),
    Setup(setup::Args),
    CleanRoot(clean_root::Args),
    Figures(figures::Args),
    Cross(cross::Args),
    Powerup(powerup::Args),
    Deb(deb::Args),
    Bench(bench::Args),
    #[command(hide = true)]
    RunSuites(run_suites::Args),
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Cmd::Test(a) => test::run(a),
        Cmd::Vcan(a) => vcan::run(a),
        Cmd::Setup(a) => setup::run(a),
        Cmd::CleanRoot(a) => clean_root::run(a),
        Cmd::Figures(a) => figures::run(a),
        Cmd::Cross(a) => cross::run(a),
        Cmd::Powerup(a) => powerup::run(a),
        Cmd::Deb(a) => deb::run(a),
        Cmd::Bench(a) => bench::run(a),
        Cmd::RunSuites(a) => run_suites::run(a),
    };
    match result {
        Ok(code) => ExitCode::from(code),
        Err(err) => {
            eprintln!("xtask: error: {err:#}");
            ExitCode::from(2)
        }
    }
}

/// The command lines the README, `.ci/run` and the suites use still parse as they did.
#[cfg(test)]
mod cli {
    use super::*;

    fn parse(line: &str) -> Cmd {
        let argv = std::iter::once("xtask").chain(line.split_whitespace());
        Cli::try_parse_from(argv)
            .unwrap_or_else(|e| panic!("{line}: {e}"))
            .command
    }

    #[test]
    fn documented_command_lines_parse() {
        let Cmd::Vcan(v) = parse(
            "vcan --mode vm --timeout 60 -- target/debug/deps/x --test-threads=1 --nocapture",
        ) else {
            panic!()
        };
        assert_eq!(v.harness.mode, harness::Mode::Vm);
        assert_eq!(v.harness.timeout, 60);
        assert_eq!(
            v.command,
            ["target/debug/deps/x", "--test-threads=1", "--nocapture"]
        );
        let Cmd::Vcan(v) = parse("vcan candump -L vcan0") else {
            panic!()
        };
        assert_eq!(v.command, ["candump", "-L", "vcan0"]);
        let Cmd::Vcan(v) = parse("vcan --systemd --setup s.sh -v -- sh -c true") else {
            panic!()
        };
        assert!(v.systemd && v.harness.verbose && v.setup.is_some());
        let Cmd::Bench(b) = parse("bench --quick --only calib,firmware --out /tmp/B.md") else {
            panic!()
        };
        assert_eq!(b.only, [bench::Part::Calib, bench::Part::Firmware]);
        let Cmd::Deb(d) = parse("deb --target arm64 --target armhf") else {
            panic!()
        };
        assert_eq!(d.targets.len(), 2);
        assert!(matches!(
            parse("setup --check"),
            Cmd::Setup(setup::Args { check: true })
        ));
        assert!(matches!(
            parse("figures --write"),
            Cmd::Figures(figures::Args {
                write: true,
                slow: false
            })
        ));
        let Cmd::Test(t) = parse("test --quick") else {
            panic!()
        };
        assert!(t.quick);
        for line in [
            "test",
            "powerup --timeout 900",
            "clean-root",
            "cross",
            "run-suites a b",
        ] {
            parse(line);
        }
    }

    #[test]
    fn wrong_command_lines_are_refused() {
        for line in [
            "vcan",
            "vcan --mode kvm -- true",
            "bench --only gpu",
            "deb --target mips",
            "test extra",
            "setup --chek",
        ] {
            let argv = std::iter::once("xtask").chain(line.split_whitespace());
            assert!(Cli::try_parse_from(argv).is_err(), "{line}");
        }
    }
}
