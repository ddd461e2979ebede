//! `cargo xtask`: exocal's long commands.
//!
//! ```text
//! cargo xtask test                 everything: unit + doc tests, vcan suites, power-up, cross-builds,
//!                                  README figures
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
//! [`targets`] (what ships where). No two modules import each other, directly or in a loop: the
//! test `module_graph` below checks it.

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
            Cmd::Figures(figures::Args { write: true })
        ));
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

/// The rule this layout keeps: no two modules import each other, directly or in a loop, and the
/// shared helpers import no xtask module at all. Read from the sources: a module depends on its
/// declared children and on every module a `crate::` or `super::` path in its code (not its
/// comments or unit tests) names.
#[cfg(test)]
mod module_graph {
    use std::collections::{BTreeMap, BTreeSet};
    use std::path::Path;

    /// Modules that import no other xtask module.
    const LEAVES: &[&str] = &[
        "host",
        "paths",
        "process",
        "libtest",
        "harness::request",
        "bench::common",
    ];

    /// Module path (`""` for the crate root) → its source.
    fn sources() -> BTreeMap<String, String> {
        fn walk(dir: &Path, prefix: &str, out: &mut BTreeMap<String, String>) {
            for entry in std::fs::read_dir(dir).unwrap() {
                let path = entry.unwrap().path();
                let stem = path.file_stem().unwrap().to_string_lossy().into_owned();
                let child = if prefix.is_empty() {
                    stem.clone()
                } else {
                    format!("{prefix}::{stem}")
                };
                if path.is_dir() {
                    walk(&path, &child, out);
                } else if path.extension().is_some_and(|e| e == "rs") {
                    let name = match stem.as_str() {
                        "main" | "mod" => prefix.to_string(),
                        _ => child,
                    };
                    out.insert(name, std::fs::read_to_string(&path).unwrap());
                }
            }
        }
        let mut out = BTreeMap::new();
        walk(
            &Path::new(env!("CARGO_MANIFEST_DIR")).join("src"),
            "",
            &mut out,
        );
        out
    }

    /// The code of a source: no comment lines, no `#[cfg(test)]` tail.
    fn code(src: &str) -> String {
        let src = src.split("#[cfg(test)]").next().unwrap_or(src);
        src.lines()
            .filter(|l| !l.trim_start().starts_with("//"))
            .collect::<Vec<_>>()
            .join("\n")
    }

    /// Every path that follows `anchor` (`crate::` or `super::`), braces expanded.
    fn paths_after(code: &str, anchor: &str) -> Vec<String> {
        fn ident(s: &str) -> &str {
            let end = s
                .find(|c: char| !(c.is_alphanumeric() || c == '_'))
                .unwrap_or(s.len());
            &s[..end]
        }
        fn expand(rest: &str, prefix: &str, out: &mut Vec<String>) {
            let rest = rest.trim_start();
            if let Some(inner) = rest.strip_prefix('{') {
                let mut depth = 1;
                let mut start = 0;
                for (i, c) in inner.char_indices() {
                    match c {
                        '{' => depth += 1,
                        '}' | ',' if depth == 1 => {
                            expand(&inner[start..], prefix, out);
                            start = i + 1;
                            if c == '}' {
                                return;
                            }
                        }
                        '}' => depth -= 1,
                        _ => {}
                    }
                }
                return;
            }
            let name = ident(rest);
            if name.is_empty() {
                return;
            }
            let path = if prefix.is_empty() {
                name.to_string()
            } else {
                format!("{prefix}::{name}")
            };
            match rest[name.len()..].strip_prefix("::") {
                Some(more) => expand(more, &path, out),
                None => out.push(path),
            }
        }
        let mut out = Vec::new();
        for (i, _) in code.match_indices(anchor) {
            let before = code[..i].chars().next_back();
            if before.is_some_and(|c| c.is_alphanumeric() || c == '_' || c == ':') {
                continue;
            }
            let mut rest = &code[i + anchor.len()..];
            let mut prefix = anchor.trim_end_matches("::").to_string();
            // `super::super::x`
            while let Some(more) = rest.strip_prefix("super::") {
                prefix.push_str("::super");
                rest = more;
            }
            expand(rest, &prefix, &mut out);
        }
        out
    }

    /// The module a path (`crate::…`, `super::…` seen from `from`) lands in: its longest prefix
    /// that is a module.
    fn resolve(path: &str, from: &str, modules: &BTreeSet<String>) -> String {
        let mut base: Vec<&str> = if from.is_empty() {
            Vec::new()
        } else {
            from.split("::").collect()
        };
        let mut segs = path.split("::").peekable();
        match segs.next() {
            Some("crate") => base.clear(),
            Some("super") => {
                base.pop();
                while segs.peek() == Some(&"super") {
                    segs.next();
                    base.pop();
                }
            }
            _ => unreachable!(),
        }
        let mut best = base.join("::");
        for seg in segs {
            if seg == "self" {
                break;
            }
            base.push(seg);
            let candidate = base.join("::");
            if modules.contains(&candidate) {
                best = candidate;
            } else {
                break;
            }
        }
        best
    }

    fn graph() -> BTreeMap<String, BTreeSet<String>> {
        let sources = sources();
        let modules: BTreeSet<String> = sources.keys().cloned().collect();
        let mut graph: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
        for (module, src) in &sources {
            let deps = graph.entry(module.clone()).or_default();
            // Declared children.
            for child in &modules {
                let parent = child.rsplit_once("::").map_or("", |(p, _)| p);
                if parent == module && !child.is_empty() {
                    deps.insert(child.clone());
                }
            }
            let code = code(src);
            for anchor in ["crate::", "super::"] {
                for path in paths_after(&code, anchor) {
                    let target = resolve(&path, module, &modules);
                    if &target != module {
                        deps.insert(target);
                    }
                }
            }
        }
        graph
    }

    #[test]
    fn reads_paths_as_rustc_would() {
        let p = paths_after(
            "use crate::{a, b::{self, C}};\nlet x = crate::d::e(); use super::super::f;",
            "crate::",
        );
        assert_eq!(
            p,
            ["crate::a", "crate::b::self", "crate::b::C", "crate::d::e"]
        );
        let modules: BTreeSet<String> = ["b", "x", "x::y", "x::z"].map(String::from).into();
        assert_eq!(resolve("crate::b::C", "x::y", &modules), "b");
        assert_eq!(resolve("super::z::Item", "x::y", &modules), "x::z");
        assert_eq!(resolve("super::Item", "x::y", &modules), "x");
        assert_eq!(
            paths_after("use super::super::request::Mode;", "super::"),
            ["super::super::request::Mode"]
        );
    }

    #[test]
    fn no_two_modules_import_each_other() {
        let graph = graph();
        // Depth-first search for a cycle; report it whole.
        fn visit<'a>(
            node: &'a str,
            graph: &'a BTreeMap<String, BTreeSet<String>>,
            stack: &mut Vec<&'a str>,
            done: &mut BTreeSet<&'a str>,
        ) -> Option<Vec<String>> {
            if let Some(at) = stack.iter().position(|n| *n == node) {
                let mut cycle: Vec<String> = stack[at..].iter().map(|s| s.to_string()).collect();
                cycle.push(node.to_string());
                return Some(cycle);
            }
            if !done.insert(node) {
                return None;
            }
            stack.push(node);
            for dep in graph.get(node).into_iter().flatten() {
                if let Some(c) = visit(dep, graph, stack, done) {
                    return Some(c);
                }
            }
            stack.pop();
            None
        }
        let mut done = BTreeSet::new();
        for node in graph.keys() {
            if let Some(cycle) = visit(node, &graph, &mut Vec::new(), &mut done) {
                panic!("modules import each other: {}", cycle.join(" -> "));
            }
        }
        assert!(graph.len() > 20, "{graph:?}");
    }

    #[test]
    fn the_shared_helpers_are_leaves() {
        let graph = graph();
        for leaf in LEAVES {
            let deps = graph
                .get(*leaf)
                .unwrap_or_else(|| panic!("no module {leaf}"));
            assert!(deps.is_empty(), "{leaf} imports {deps:?}");
        }
    }
}
