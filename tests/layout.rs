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

/// Every path a file writes from `crate` or `super`, in its `use` items and in its code,
/// outside its `#[cfg(test)]` modules.
#[derive(Default)]
struct Paths(Vec<Vec<String>>);

impl Paths {
    /// The paths a `use` tree names, below `prefix`.
    fn add_tree(&mut self, prefix: &mut Vec<String>, tree: &syn::UseTree) {
        match tree {
            syn::UseTree::Path(p) => {
                prefix.push(p.ident.to_string());
                self.add_tree(prefix, &p.tree);
                prefix.pop();
            }
            syn::UseTree::Name(n) => self.add([prefix.clone(), vec![n.ident.to_string()]].concat()),
            syn::UseTree::Rename(r) => self.add([prefix.clone(), vec![r.ident.to_string()]].concat()),
            syn::UseTree::Glob(_) => self.add(prefix.clone()),
            syn::UseTree::Group(g) => g.items.iter().for_each(|t| self.add_tree(prefix, t)),
        }
    }

    fn add(&mut self, path: Vec<String>) {
        if matches!(path.first().map(String::as_str), Some("crate" | "super")) {
            self.0.push(path);
        }
    }
}

impl<'ast> syn::visit::Visit<'ast> for Paths {
    fn visit_item_mod(&mut self, module: &'ast syn::ItemMod) {
        let test_only = module
            .attrs
            .iter()
            .any(|a| a.path().is_ident("cfg") && a.parse_args::<syn::Ident>().is_ok_and(|i| i == "test"));
        if !test_only {
            syn::visit::visit_item_mod(self, module);
        }
    }

    fn visit_item_use(&mut self, item: &'ast syn::ItemUse) {
        self.add_tree(&mut Vec::new(), &item.tree);
    }

    fn visit_path(&mut self, path: &'ast syn::Path) {
        self.add(path.segments.iter().map(|s| s.ident.to_string()).collect());
        syn::visit::visit_path(self, path);
    }
}

/// Each module's imports of other modules (not of the modules it lies in).
fn imports() -> BTreeMap<String, BTreeSet<String>> {
    let modules = modules();
    let mut edges = BTreeMap::new();
    for (module, path) in &modules {
        let file = syn::parse_file(&std::fs::read_to_string(path).unwrap())
            .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        let mut paths = Paths::default();
        syn::visit::Visit::visit_file(&mut paths, &file);
        let mut to: BTreeSet<String> = paths
            .0
            .iter()
            .filter_map(|p| target(&modules, module, &p.iter().map(String::as_str).collect::<Vec<_>>()))
            .collect();
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
