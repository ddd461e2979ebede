//! The static stack bound: per-function frames from a nightly `-Z emit-stack-sizes` build
//! (`llvm-readobj --stack-sizes`), walked over the call graph read from the disassembly.

use std::collections::{HashMap, HashSet};
use std::path::Path;
use std::process::Command;

use anyhow::{Context, Result};

use super::common::{capture, tool};

/// Per-function frames (`.stack_sizes`, mangled names) from `llvm-readobj --stack-sizes`.
pub fn stack_sizes(readobj: &str, elf: &Path) -> Result<HashMap<String, u64>> {
    let out = capture(Command::new(readobj).arg("--stack-sizes").arg(elf))?;
    let mut map = HashMap::new();
    let mut names: Vec<String> = Vec::new();
    for l in out.lines() {
        let l = l.trim();
        if let Some(list) = l
            .strip_prefix("Functions: [")
            .and_then(|r| r.strip_suffix(']'))
        {
            names = list.split(',').map(|n| n.trim().to_string()).collect();
        } else if let Some(size) = l.strip_prefix("Size: 0x") {
            let size = u64::from_str_radix(size, 16).context("stack size")?;
            for n in names.drain(..) {
                map.insert(n, size);
            }
        }
    }
    Ok(map)
}

/// The disassembly as a call graph: per function, its direct callees (calls and tail calls),
/// whether it makes indirect calls, and the frame its prologue allocates (for functions
/// without a `.stack_sizes` entry: precompiled compiler-builtins).
#[derive(Default)]
pub struct Func {
    pub callees: HashSet<String>,
    pub indirect: bool,
    pub prologue_bytes: u64,
    pub instructions: usize,
}

pub fn call_graph(objdump: &str, elf: &Path) -> Result<HashMap<String, Func>> {
    let out = capture(
        Command::new(objdump)
            .args(["-d", "--no-show-raw-insn"])
            .arg(elf),
    )?;
    let mut graph: HashMap<String, Func> = HashMap::new();
    let mut current: Option<String> = None;
    for line in out.lines() {
        if let Some(name) = line
            .strip_suffix(">:")
            .and_then(|l| l.split_once(" <"))
            .map(|(_, n)| n.to_string())
        {
            graph.entry(name.clone()).or_default();
            current = Some(name);
            continue;
        }
        let Some(cur) = &current else { continue };
        let mut fields = line.split('\t').map(str::trim).filter(|f| !f.is_empty());
        let (Some(_addr), Some(op)) = (fields.next(), fields.next()) else {
            continue;
        };
        let operands = fields.next().unwrap_or("");
        let func = graph.get_mut(cur).expect("inserted above");
        func.instructions += 1;
        if func.instructions <= 8 {
            func.prologue_bytes += prologue_bytes(op, operands);
        }
        let mnemonic = op.split('.').next().unwrap_or(op);
        let is_branch = mnemonic == "bl"
            || mnemonic == "blx"
            || mnemonic.starts_with('b')
                && mnemonic.len() <= 3
                && mnemonic != "bic"
                && mnemonic != "bkpt";
        if !is_branch {
            continue;
        }
        if mnemonic == "blx" && operands.starts_with('r') {
            func.indirect = true;
            continue;
        }
        if let Some(target) = operands
            .split_once('<')
            .and_then(|(_, t)| t.strip_suffix('>'))
        {
            let target = target.split('+').next().unwrap_or(target);
            if target != cur {
                func.callees.insert(target.to_string());
            }
        }
    }
    Ok(graph)
}

/// Bytes a prologue instruction moves the stack pointer by.
pub fn prologue_bytes(op: &str, operands: &str) -> u64 {
    let regs = |s: &str| -> u64 {
        let inner = s
            .split_once('{')
            .and_then(|(_, r)| r.split_once('}'))
            .map(|(r, _)| r)
            .unwrap_or("");
        inner
            .split(',')
            .map(|r| {
                let r = r.trim();
                match r.split_once('-') {
                    Some((a, b)) => {
                        let n = |x: &str| {
                            x.trim_start_matches(|c: char| c.is_alphabetic())
                                .parse::<u64>()
                                .unwrap_or(0)
                        };
                        n(b).saturating_sub(n(a)) + 1
                    }
                    None if r.is_empty() => 0,
                    None => 1,
                }
            })
            .sum()
    };
    let op = op.split('.').next().unwrap_or(op);
    match op {
        "push" => 4 * regs(operands),
        "stmdb" if operands.starts_with("sp!") => 4 * regs(operands),
        "vpush" => 8 * regs(operands),
        "sub" | "subw" if operands.starts_with("sp,") => operands
            .rsplit('#')
            .next()
            .and_then(|n| n.trim().parse::<u64>().ok())
            .unwrap_or(0),
        _ => 0,
    }
}

pub struct StackBound {
    pub bytes: u64,
    pub path: Vec<(String, u64, bool)>,
    pub cycles: Vec<String>,
    pub indirect: Vec<String>,
}

/// Depth-first walk of the call graph, memoised: per function, its deepest stack and the
/// callee that makes it.
pub struct Walk<'a> {
    graph: &'a HashMap<String, Func>,
    frames: &'a HashMap<String, u64>,
    skip: &'a dyn Fn(&str) -> bool,
    memo: HashMap<String, (u64, Option<String>)>,
    on_path: Vec<String>,
    cycles: Vec<String>,
    indirect: HashSet<String>,
}

impl Walk<'_> {
    fn deepest(&mut self, f: &str) -> u64 {
        if let Some((b, _)) = self.memo.get(f) {
            return *b;
        }
        if self.on_path.iter().any(|p| p == f) {
            self.cycles.push(f.to_string());
            return 0;
        }
        let node = self.graph.get(f);
        let own = self
            .frames
            .get(f)
            .copied()
            .or(node.map(|n| n.prologue_bytes))
            .unwrap_or(0);
        self.on_path.push(f.to_string());
        let mut best = (0, None);
        if let Some(n) = node {
            if n.indirect {
                self.indirect.insert(f.to_string());
            }
            let mut callees: Vec<&String> = n.callees.iter().filter(|c| !(self.skip)(c)).collect();
            callees.sort();
            for c in callees {
                let b = self.deepest(c);
                if b > best.0 {
                    best = (b, Some(c.clone()));
                }
            }
        }
        self.on_path.pop();
        self.memo.insert(f.to_string(), (own + best.0, best.1));
        own + best.0
    }
}

/// Worst-case stack from `entry` over the call graph, skipping functions for which `skip` is
/// true (paths that never return to the LS: panics, reporting).
pub fn stack_bound(
    graph: &HashMap<String, Func>,
    frames: &HashMap<String, u64>,
    entry: &str,
    skip: &dyn Fn(&str) -> bool,
) -> StackBound {
    let mut w = Walk {
        graph,
        frames,
        skip,
        memo: HashMap::new(),
        on_path: Vec::new(),
        cycles: Vec::new(),
        indirect: HashSet::new(),
    };
    let bytes = w.deepest(entry);
    let Walk {
        memo,
        cycles,
        indirect,
        ..
    } = w;
    let mut path = Vec::new();
    let mut f = Some(entry.to_string());
    while let Some(name) = f {
        let own = frames.get(&name).copied();
        let from_prologue = own.is_none();
        path.push((
            name.clone(),
            own.or(graph.get(&name).map(|n| n.prologue_bytes))
                .unwrap_or(0),
            from_prologue,
        ));
        f = memo.get(&name).and_then(|(_, next)| next.clone());
    }
    let mut indirect: Vec<String> = indirect.into_iter().collect();
    indirect.sort();
    StackBound {
        bytes,
        path,
        cycles,
        indirect,
    }
}

/// Demangles Rust symbol names with `c++filt` (binutils understands Rust v0 mangling).
pub fn demangle(names: &[String]) -> Vec<String> {
    let Ok(filt) = tool(&["arm-none-eabi-c++filt", "c++filt", "llvm-cxxfilt"]) else {
        return names.to_vec();
    };
    let Ok(out) = Command::new(&filt).args(names).output() else {
        return names.to_vec();
    };
    let lines: Vec<String> = String::from_utf8_lossy(&out.stdout)
        .lines()
        .map(|l| {
            // Drop crate disambiguators: `calib_core[3f...]::ls` → `calib_core::ls`.
            let mut s = String::new();
            let mut skip = false;
            for ch in l.chars() {
                match ch {
                    '[' => skip = true,
                    ']' if skip => skip = false,
                    _ if !skip => s.push(ch),
                    _ => {}
                }
            }
            s
        })
        .collect();
    if lines.len() == names.len() {
        lines
    } else {
        names.to_vec()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn prologue_sizes_are_read() {
        assert_eq!(prologue_bytes("push", "{r4, r5, r6, r7, lr}"), 20);
        assert_eq!(
            prologue_bytes("push.w", "{r4, r5, r6, r7, r8, r9, sl, fp, lr}"),
            36
        );
        assert_eq!(prologue_bytes("vpush", "{d8-d15}"), 64);
        assert_eq!(prologue_bytes("sub", "sp, #20"), 20);
        assert_eq!(prologue_bytes("sub.w", "sp, sp, #1024"), 1024);
        assert_eq!(prologue_bytes("stmdb", "sp!, {r4, lr}"), 8);
        assert_eq!(prologue_bytes("mov", "r7, sp"), 0);
        assert_eq!(prologue_bytes("sub", "r0, #4"), 0);
    }

    #[test]
    fn stack_bound_takes_the_deepest_path_and_skips() {
        let mut graph: HashMap<String, Func> = HashMap::new();
        let edge = |g: &mut HashMap<String, Func>, a: &str, b: &str| {
            g.entry(a.into()).or_default().callees.insert(b.into());
            g.entry(b.into()).or_default();
        };
        edge(&mut graph, "Reset", "main");
        edge(&mut graph, "main", "small");
        edge(&mut graph, "main", "big");
        edge(&mut graph, "main", "panic");
        edge(&mut graph, "big", "leaf");
        graph.get_mut("leaf").unwrap().prologue_bytes = 8;
        let frames: HashMap<String, u64> = [
            ("Reset", 0),
            ("main", 100),
            ("small", 500),
            ("big", 300),
            ("panic", 10_000),
        ]
        .into_iter()
        .map(|(k, v)| (k.to_string(), v))
        .collect();
        let b = stack_bound(&graph, &frames, "Reset", &|n| n == "panic");
        assert_eq!(b.bytes, 100 + 500);
        assert_eq!(
            b.path.iter().map(|p| p.0.as_str()).collect::<Vec<_>>(),
            ["Reset", "main", "small"]
        );
        assert!(b.cycles.is_empty());
        edge(&mut graph, "leaf", "big");
        let b = stack_bound(&graph, &frames, "Reset", &|n| n == "panic");
        assert_eq!(b.cycles, ["big"]);
    }
}
