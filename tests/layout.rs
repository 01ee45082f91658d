//! The house's rules on imports (docs/architecture.md): no module of the crate reaches, through
//! its imports, back to itself; and the numeric code, the GPU backend, the formats and the
//! engine know no stage and no configuration.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// Every module of the crate (`a::b`) and its file.
fn modules() -> BTreeMap<String, PathBuf> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("stages");
    let mut modules = BTreeMap::new();
    let mut folders = vec![root.clone()];
    while let Some(dir) = folders.pop() {
        for entry in std::fs::read_dir(&dir).unwrap() {
            let path = entry.unwrap().path();
            if path.is_dir() {
                folders.push(path);
            } else if path.extension().is_some_and(|e| e == "rs") {
                let rel = path.strip_prefix(&root).unwrap().with_extension("");
                let mut parts: Vec<String> = rel.iter().map(|p| p.to_string_lossy().into_owned()).collect();
                if matches!(parts.last().map(String::as_str), Some("mod" | "lib" | "main")) {
                    parts.pop();
                }
                modules.insert(parts.join("::"), path);
            }
        }
    }
    modules
}

/// The code of a file without comments and without its unit tests.
fn code(path: &Path) -> String {
    let text = std::fs::read_to_string(path).unwrap();
    let text = match text.find("#[cfg(test)]\nmod tests") {
        Some(at) => &text[..at],
        None => &text,
    };
    text.lines().map(|l| l.split("//").next().unwrap_or("")).collect::<Vec<_>>().join("\n")
}

/// The module a path written in `module` names (the longest module prefix), if it is the crate's.
fn target(modules: &BTreeMap<String, PathBuf>, module: &str, path: &[&str]) -> Option<String> {
    let (mut base, rest): (Vec<&str>, &[&str]) = match *path.first()? {
        // The engine is a crate of its own under stages/engine: its `crate` is `engine`.
        "crate" if module == "engine" || module.starts_with("engine::") => (vec!["engine"], &path[1..]),
        "crate" => (vec![], &path[1..]),
        "super" => {
            let mut base: Vec<&str> = module.split("::").filter(|s| !s.is_empty()).collect();
            let mut rest = path;
            while rest.first() == Some(&"super") {
                base.pop();
                rest = &rest[1..];
            }
            (base, rest)
        }
        _ => return None,
    };
    base.extend(rest);
    (1..=base.len()).rev().map(|n| base[..n].join("::")).find(|m| modules.contains_key(m))
}

/// Each module's imports of other modules (not of the modules it lies in).
fn imports() -> BTreeMap<String, BTreeSet<String>> {
    let modules = modules();
    let mut edges = BTreeMap::new();
    for (module, path) in &modules {
        let code = code(path);
        let mut to = BTreeSet::new();
        // `use a::{b, c::d}` names a::b and a::c::d; any other path `crate::x::y` or `super::x`.
        for statement in
            code.split(';').filter_map(|s| s.trim().strip_prefix("use ").or(s.find(" use ").map(|i| &s[i + 5..])))
        {
            let statement: String = statement.split_whitespace().collect();
            let (head, tail) = match statement.split_once("::{") {
                Some((head, tail)) => (head.to_string(), tail.trim_end_matches('}').to_string()),
                None => (statement.clone(), String::new()),
            };
            let items: Vec<String> = if tail.is_empty() {
                vec![head]
            } else {
                tail.split(',').map(|item| format!("{head}::{}", item.split('{').next().unwrap())).collect()
            };
            for item in items {
                let parts: Vec<&str> = item.split("::").filter(|p| !p.is_empty()).collect();
                to.extend(target(&modules, module, &parts));
            }
        }
        for (at, _) in code.match_indices("crate::").chain(code.match_indices("super::")) {
            let path: String =
                code[at..].chars().take_while(|c| c.is_alphanumeric() || *c == '_' || *c == ':').collect();
            let parts: Vec<&str> = path.split("::").filter(|p| !p.is_empty()).collect();
            to.extend(target(&modules, module, &parts));
        }
        to.retain(|t| t != module && !module.starts_with(&format!("{t}::")));
        edges.insert(module.clone(), to);
    }
    edges
}

#[test]
fn no_module_imports_itself_through_others() {
    let edges = imports();
    // Each module's reach; a module in its own reach is on a circle.
    let mut circles = Vec::new();
    for start in edges.keys() {
        let mut seen = BTreeSet::new();
        let mut stack: Vec<(String, Vec<String>)> = vec![(start.clone(), vec![start.clone()])];
        while let Some((at, trail)) = stack.pop() {
            for next in &edges[&at] {
                if next == start {
                    circles.push(trail.join(" → ") + " → " + start);
                } else if seen.insert(next.clone()) {
                    stack.push((next.clone(), [trail.clone(), vec![next.clone()]].concat()));
                }
            }
        }
    }
    assert!(circles.is_empty(), "import circles:\n{}", circles.join("\n"));
}

#[test]
fn numeric_code_formats_and_the_engine_know_no_stage_and_no_configuration() {
    let edges = imports();
    let high = ["stage", "config", "commands", "pipeline", "dataset", "kernel_command"];
    let low = ["engine", "kernels", "train", "gpu", "formats", "backend", "volume", "geometry"];
    let mut wrong = Vec::new();
    for (module, to) in &edges {
        if !low.iter().any(|l| module == l || module.starts_with(&format!("{l}::"))) {
            continue;
        }
        for t in to {
            if high.iter().any(|h| t == h || t.starts_with(&format!("{h}::"))) {
                wrong.push(format!("{module} → {t}"));
            }
        }
    }
    assert!(wrong.is_empty(), "low-level modules importing stages or configuration:\n{}", wrong.join("\n"));
}
