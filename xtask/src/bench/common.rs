//! What the benchmarks share: the context, a part's section of the report, running commands
//! (echoed, and rendered for the report as they were run), reading JSON result lines, the
//! benchmark venv.
//!
//! A leaf: it imports no other xtask module.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use anyhow::{bail, Context, Result};
use serde_json::Value;

/// What the parts share.
pub struct Ctx {
    /// The cargo that runs us.
    pub cargo: String,
    pub root: PathBuf,
    pub target: PathBuf,
    pub quick: bool,
    /// `taskset -c 0` when taskset exists.
    pub pin: Vec<String>,
}

/// A goal (BENCHMARKS.md, "Goals") and whether this run met it.
pub struct Goal {
    pub what: String,
    pub met: bool,
    pub detail: String,
}

/// One part's contribution to the report.
pub struct Section {
    pub title: &'static str,
    pub body: String,
    pub goals: Vec<Goal>,
}

// ---------------------------------------------------------------------------------------------
// Running things

/// Shell-like rendering of a command for the report.
pub fn show(cmd: &Command) -> String {
    let mut s = String::new();
    for (k, v) in cmd.get_envs() {
        if let Some(v) = v {
            let v = v.to_string_lossy();
            if v.contains(' ') {
                let _ = write!(s, "{}='{v}' ", k.to_string_lossy());
            } else {
                let _ = write!(s, "{}={v} ", k.to_string_lossy());
            }
        }
    }
    let program = Path::new(cmd.get_program());
    if program.file_name().is_some_and(|n| n == "cargo") {
        s.push_str("cargo");
    } else {
        s.push_str(&program.to_string_lossy());
    }
    for a in cmd.get_args() {
        let a = a.to_string_lossy();
        if a.contains(' ') {
            let _ = write!(s, " '{a}'");
        } else {
            let _ = write!(s, " {a}");
        }
    }
    s
}

/// `cargo <verb> --release -p <package> <more…>`, run in the workspace root.
pub fn cargo_release(ctx: &Ctx, verb: &str, package: &str, more: &[&str]) -> Command {
    let mut c = Command::new(&ctx.cargo);
    c.current_dir(&ctx.root)
        .args([verb, "--release", "-p", package])
        .args(more);
    c
}

/// Runs `cmd`, stderr passed through, and returns its stdout; fails on a non-zero status.
pub fn capture(cmd: &mut Command) -> Result<String> {
    eprintln!("    $ {}", show(cmd));
    let out = cmd
        .stderr(Stdio::inherit())
        .output()
        .with_context(|| format!("starting {}", show(cmd)))?;
    if !out.status.success() {
        bail!("{} failed with {}", show(cmd), out.status);
    }
    Ok(String::from_utf8_lossy(&out.stdout).into_owned())
}

/// Runs `cmd` with stdout and stderr passed through; fails on a non-zero status.
pub fn run(cmd: &mut Command) -> Result<()> {
    eprintln!("    $ {}", show(cmd));
    let status = cmd
        .status()
        .with_context(|| format!("starting {}", show(cmd)))?;
    if !status.success() {
        bail!("{} failed with {status}", show(cmd));
    }
    Ok(())
}

/// The JSON objects among `text`'s lines.
pub fn json_lines(text: &str) -> Vec<Value> {
    text.lines()
        .filter(|l| l.trim_start().starts_with('{'))
        .filter_map(|l| serde_json::from_str(l).ok())
        .collect()
}

/// A command pinned to CPU 0 (when taskset exists).
pub fn pinned(ctx: &Ctx, program: impl AsRef<std::ffi::OsStr>) -> Command {
    match ctx.pin.split_first() {
        Some((first, rest)) => {
            let mut c = Command::new(first);
            c.args(rest).arg(program);
            c
        }
        None => Command::new(program),
    }
}

pub fn f(v: &Value, key: &str) -> f64 {
    v.get(key).and_then(Value::as_f64).unwrap_or(f64::NAN)
}

/// The value at `key` as JSON text (empty when missing).
pub fn json(v: &Value, key: &str) -> String {
    v.get(key).map(Value::to_string).unwrap_or_default()
}

pub fn s<'a>(v: &'a Value, key: &str) -> &'a str {
    v.get(key).and_then(Value::as_str).unwrap_or("?")
}

pub fn ms(secs: f64) -> String {
    if secs < 0.01 {
        format!("{:.2}", secs * 1e3)
    } else {
        format!("{:.1}", secs * 1e3)
    }
}

/// The venv's python, creating the venv and installing `benches/requirements.txt` if needed.
pub fn venv_python(ctx: &Ctx) -> Result<(PathBuf, Vec<String>)> {
    let venv = ctx.target.join("bench-venv");
    let python = venv.join("bin/python");
    let mut commands = Vec::new();
    if !python.exists() {
        let mut c = Command::new("python3");
        c.args(["-m", "venv"]).arg(&venv);
        commands.push(show(&c));
        run(&mut c).context("creating the benchmark venv (python3 -m venv)")?;
    }
    let mut c = Command::new(&python);
    c.args([
        "-m",
        "pip",
        "install",
        "--disable-pip-version-check",
        "-q",
        "-r",
    ])
    .arg(ctx.root.join("benches/requirements.txt"));
    commands.push(show(&c));
    run(&mut c).context("installing benches/requirements.txt from PyPI")?;
    Ok((python, commands))
}

/// A tool from the first of `candidates` that runs.
pub fn tool(candidates: &[&str]) -> Result<String> {
    for c in candidates {
        if Command::new(c)
            .arg("--version")
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .status()
            .is_ok_and(|s| s.success())
        {
            return Ok((*c).to_string());
        }
    }
    bail!("none of {candidates:?} is installed (apt-get install binutils-arm-none-eabi llvm)")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn json_lines_skip_other_output() {
        let v = json_lines("hello\n{\"a\": 1}\n  {\"b\": 2}\nnot {json\n");
        assert_eq!(v.len(), 2);
        assert_eq!(f(&v[0], "a"), 1.0);
    }
}
