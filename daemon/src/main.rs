//! The `exocald` binary: parses the command line, runs it, maps errors to sysexits statuses.

use std::process::ExitCode;

use clap::Parser;
use exocald::exit::code;

fn main() -> ExitCode {
    let cli = match exocald::cli::Cli::try_parse() {
        Ok(cli) => cli,
        Err(e) => {
            // --help and --version are not failures; anything else is EX_USAGE (64).
            let status = if e.use_stderr() {
                code::USAGE
            } else {
                code::OK
            };
            let _ = e.print();
            return ExitCode::from(status);
        }
    };
    match exocald::cmd::run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("exocald: {e}");
            ExitCode::from(e.exit_code())
        }
    }
}
