//! Data flows one way: within each crate of the workspace, no two top-level modules import each
//! other, directly or in a loop, and the shared helpers a crate names ([`LEAVES`]) import none of
//! its modules. Read from the sources as rustc resolves them: a module depends on every module a
//! `crate::` or `super::` path in its code (not its comments or unit tests) lands in; a nested
//! module's dependencies count as its top-level module's. A cycle fails naming its modules.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

const CRATES: &[&str] = &[
    "calib-core",
    "dbc",
    "bus",
    "hil",
    "session",
    "daemon",
    "report",
    "log",
    "tests",
    "xtask",
];

/// Per crate, modules that import no other module of it: shared helpers stay leaves (rtic's
/// xtask layout).
const LEAVES: &[(&str, &[&str])] = &[(
    "xtask",
    &[
        "host",
        "paths",
        "process",
        "libtest",
        "harness::request",
        "bench::common",
    ],
)];

fn workspace() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .unwrap()
        .to_path_buf()
}

/// Module path (`""` for the crate root) → its source, for the crate whose `src` is `src`.
fn sources(src: &Path) -> BTreeMap<String, String> {
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
                    "main" | "lib" | "mod" => prefix.to_string(),
                    _ => child,
                };
                out.insert(name, std::fs::read_to_string(&path).unwrap());
            }
        }
    }
    let mut out = BTreeMap::new();
    walk(src, "", &mut out);
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

/// Module → every module (at any depth) its code's paths land in.
fn graph(src: &Path) -> BTreeMap<String, BTreeSet<String>> {
    let sources = sources(src);
    let modules: BTreeSet<String> = sources.keys().cloned().collect();
    let mut graph: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    for (module, text) in &sources {
        let deps = graph.entry(module.clone()).or_default();
        let code = code(text);
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

/// `graph` folded onto top-level modules (the crate root left out: it declares them all).
fn top_level(graph: &BTreeMap<String, BTreeSet<String>>) -> BTreeMap<String, BTreeSet<String>> {
    let top = |m: &str| m.split("::").next().unwrap_or("").to_string();
    let mut out: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    for (m, deps) in graph.iter().filter(|(m, _)| !m.is_empty()) {
        let from = top(m);
        let tops: Vec<String> = deps.iter().map(|d| top(d)).collect();
        let entry = out.entry(from.clone()).or_default();
        entry.extend(tops.into_iter().filter(|d| !d.is_empty() && *d != from));
    }
    out
}

/// A cycle in `graph`, if there is one (depth-first search).
fn cycle(graph: &BTreeMap<String, BTreeSet<String>>) -> Option<Vec<String>> {
    fn visit(
        v: &str,
        graph: &BTreeMap<String, BTreeSet<String>>,
        path: &mut Vec<String>,
        done: &mut BTreeSet<String>,
    ) -> Option<Vec<String>> {
        if let Some(at) = path.iter().position(|p| p == v) {
            let mut c = path[at..].to_vec();
            c.push(v.to_string());
            return Some(c);
        }
        if done.contains(v) {
            return None;
        }
        path.push(v.to_string());
        for w in graph.get(v).into_iter().flatten() {
            if let Some(c) = visit(w, graph, path, done) {
                return Some(c);
            }
        }
        path.pop();
        done.insert(v.to_string());
        None
    }
    let mut done = BTreeSet::new();
    graph
        .keys()
        .find_map(|v| visit(v, graph, &mut Vec::new(), &mut done))
}

#[test]
fn no_two_modules_import_each_other() {
    let mut cycles = Vec::new();
    for krate in CRATES {
        let g = graph(&workspace().join(krate).join("src"));
        assert!(!g.is_empty(), "{krate}: no sources found");
        if let Some(c) = cycle(&top_level(&g)) {
            cycles.push(format!("{krate}: {}", c.join(" -> ")));
        }
    }
    assert!(cycles.is_empty(), "module cycles:\n{}", cycles.join("\n"));
}

#[test]
fn the_shared_helpers_are_leaves() {
    for (krate, leaves) in LEAVES {
        let g = graph(&workspace().join(krate).join("src"));
        for leaf in *leaves {
            let deps = g
                .get(*leaf)
                .unwrap_or_else(|| panic!("{krate}: no module {leaf}"));
            assert!(deps.is_empty(), "{krate}: {leaf} imports {deps:?}");
        }
    }
}

/// The module table of a crate root's docs (`//! | module | … |`): its first column's names.
fn module_table(root: &str) -> Option<Vec<String>> {
    let rows: Vec<&str> = root
        .lines()
        .filter_map(|l| l.strip_prefix("//! |"))
        .collect();
    let header = rows.first()?;
    if header.split('|').next()?.trim() != "module" {
        return None;
    }
    Some(
        rows.iter()
            .skip(2)
            .filter_map(|r| r.split('|').next())
            // `[`name`]`, or `[`name`](mod@name)` where a macro shares the name.
            .map(|c| {
                let c = c.trim();
                c.split('`').nth(1).unwrap_or(c).to_string()
            })
            .collect(),
    )
}

#[test]
fn every_module_table_names_every_module_and_only_modules() {
    let mut checked = 0;
    for krate in CRATES {
        let src = workspace().join(krate).join("src");
        let Ok(root) = std::fs::read_to_string(src.join("lib.rs")) else {
            continue;
        };
        let Some(table) = module_table(&root) else {
            continue;
        };
        checked += 1;
        let modules: BTreeSet<String> = sources(&src).into_keys().collect();
        for name in &table {
            assert!(
                modules.contains(name),
                "{krate}/src/lib.rs: the module table names {name}, which is no module"
            );
        }
        for m in modules
            .iter()
            .filter(|m| !m.is_empty() && !m.contains("::"))
        {
            assert!(
                table.contains(m),
                "{krate}/src/lib.rs: module {m} is missing from the module table"
            );
        }
    }
    assert!(checked >= 3, "only {checked} module tables found");
}

#[test]
fn a_cycle_is_found_and_named() {
    let mut g: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    g.insert("a".into(), BTreeSet::from(["b::x".into()]));
    g.insert("b::x".into(), BTreeSet::from(["c".into()]));
    g.insert("c".into(), BTreeSet::new());
    assert_eq!(cycle(&top_level(&g)), None);
    g.get_mut("c").unwrap().insert("a".into());
    assert_eq!(
        cycle(&top_level(&g)).unwrap(),
        ["a", "b", "c", "a"].map(String::from).to_vec()
    );
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

/// Crates that do I/O (runtimes, sockets, files, compression): the data path must reach none.
const IO_CRATES: &[&str] = &["tokio", "socketcan", "mcap", "libc", "zstd", "mio", "nix"];

#[test]
fn the_session_crate_reaches_no_io_crate() {
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let out = std::process::Command::new(cargo)
        .current_dir(workspace())
        .args([
            "tree",
            "-p",
            "exocal-session",
            "-e",
            "normal",
            "--prefix",
            "none",
        ])
        .output()
        .expect("cargo tree");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let tree = String::from_utf8_lossy(&out.stdout);
    let crates: BTreeSet<&str> = tree.lines().filter_map(|l| l.split(' ').next()).collect();
    assert!(
        crates.contains("calib-core") && crates.contains("exocal-dbc"),
        "{tree}"
    );
    let io: Vec<&&str> = IO_CRATES.iter().filter(|c| crates.contains(**c)).collect();
    assert!(io.is_empty(), "exocal-session reaches {io:?}:\n{tree}");
}
