//! A configuration as layers, each over the one before: the file a configuration `extends` (and
//! what that extends), the file itself, then each `--set section.key=value`. Tables merge key by
//! key; a value replaces the one below. A layer that picks another variant (`[train] model`,
//! `[select] sizing`, …) drops the tables and keys below it that only the old variant read; a
//! key of a variant not picked, written in the configuration itself, is an error.
//!
//! Errors name the file and line of the key they are about, found again in that layer's text.

use super::Config;
use anyhow::{anyhow, bail, Context as _};
use std::path::{Path, PathBuf};
use toml::{Table, Value};

/// The key naming the file a configuration extends.
const EXTENDS: &str = "extends";

/// Keys holding paths: relative ones are taken from the folder of the file that gives them.
const PATH_KEYS: [(&str, &str); 4] =
    [("pipeline", "cache_dir"), ("pipeline", "out_dir"), ("dataset", "root"), ("dataset", "cohort")];

/// A key that picks one variant of a table, and what each variant reads of that table: its
/// sub-tables and keys. A member listed under some variant is read by those variants only.
struct Variants {
    table: &'static str,
    selector: &'static str,
    /// What a list in place of a word picks (`roi_center = [x, y, z]`: a position in mm), if
    /// the selector takes one; it must be one of `reads`' names.
    list: Option<&'static str>,
    reads: &'static [(&'static str, &'static [&'static str])],
}

const VARIANTS: &[Variants] = &[
    Variants {
        table: "train",
        selector: "model",
        list: None,
        reads: &[("dense_tv", &["dense_tv"]), ("vm", &["vm"]), ("truth", &[])],
    },
    Variants {
        table: "select",
        selector: "localize",
        list: None,
        reads: &[("none", &[]), ("origin", &[]), ("blob", &["blob"])],
    },
    Variants {
        table: "select",
        selector: "sizing",
        list: None,
        reads: &[("candidates", &[]), ("half_max", &["half_max"]), ("shadows", &["half_max"])],
    },
    Variants {
        table: "drr",
        selector: "roi_center",
        list: Some("a position in mm"),
        reads: &[("nodule", &[]), ("lungs", &[]), ("tiles", &["tiles"]), ("a position in mm", &[])],
    },
    Variants {
        table: "dataset",
        selector: "kind",
        list: None,
        reads: &[("phantom", &["phantom", "cohort"]), ("dicom", &["root"]), ("lidc", &["root"])],
    },
];

impl Variants {
    /// Every member some variant reads.
    fn members(&self) -> impl Iterator<Item = &'static str> + '_ {
        self.reads.iter().flat_map(|(_, members)| members.iter().copied())
    }

    /// The variants that read `member`, as `"a"` or `"a" or "b"`.
    fn readers_of(&self, member: &str) -> String {
        let names: Vec<String> = self
            .reads
            .iter()
            .filter(|(_, members)| members.contains(&member))
            .map(|(name, _)| format!("\"{name}\""))
            .collect();
        names.join(" or ")
    }

    /// Whether the variant `picked` reads `member`.
    fn reads(&self, picked: &str, member: &str) -> bool {
        self.reads.iter().any(|(name, members)| *name == picked && members.contains(&member))
    }
}

/// Where a layer came from: a file (with its text, to find lines in) or one `--set`.
enum Origin {
    File { path: PathBuf, text: String },
    Set(String),
}

struct Layer {
    origin: Origin,
    table: Table,
}

/// The layers of one configuration, the lowest first.
pub(super) struct Stack {
    layers: Vec<Layer>,
}

impl Stack {
    /// `path` and, first, every file it extends.
    pub(super) fn read(path: &Path) -> anyhow::Result<Stack> {
        let mut layers = Vec::new();
        let mut next = Some(path.to_path_buf());
        let mut seen: Vec<PathBuf> = Vec::new();
        while let Some(path) = next.take() {
            let text = std::fs::read_to_string(&path)
                .with_context(|| format!("cannot read configuration {}", path.display()))?;
            let mut table: Table = toml::from_str(&text).map_err(|e| anyhow!("{}: {e}", path.display()))?;
            let dir = path.parent().map(Path::to_path_buf).unwrap_or_default();
            let canonical = std::fs::canonicalize(&path).unwrap_or_else(|_| path.clone());
            if seen.contains(&canonical) {
                bail!(
                    "{}: `extends` comes back to this file: configurations extend in a line, not a circle",
                    path.display()
                );
            }
            seen.push(canonical);
            next = match table.remove(EXTENDS) {
                None => None,
                Some(Value::String(parent)) => Some(dir.join(parent)),
                Some(other) => bail!(
                    "{}: `extends` names the configuration this one builds on, as a path string (got {other})",
                    path.display()
                ),
            };
            // The configuration itself keeps its paths relative (to its folder, as `Config`
            // resolves them); a file it extends gives them from its own folder.
            if !layers.is_empty() {
                relocate_paths(&mut table, &dir)?;
            }
            layers.push(Layer { origin: Origin::File { path, text }, table });
        }
        layers.reverse();
        Ok(Stack { layers })
    }

    /// One configuration given as text (no `extends`; paths stay as they are).
    pub(super) fn from_text(text: &str) -> anyhow::Result<Stack> {
        let table: Table = toml::from_str(text).map_err(|e| anyhow!("{}", e.to_string().trim_end()))?;
        if table.contains_key(EXTENDS) {
            bail!("`extends` needs a configuration file to be relative to: load it from a file");
        }
        let origin = Origin::File { path: PathBuf::new(), text: text.to_string() };
        Ok(Stack { layers: vec![Layer { origin, table }] })
    }

    /// `section.key=value` (`section.sub.key=value` for a variant's table) over the layers. The
    /// value is TOML (`3`, `[1, 2]`, `"text"`); a bare word is a string (`model=vm`).
    pub(super) fn push_set(&mut self, set: &str) -> anyhow::Result<()> {
        let (path, text) = set
            .split_once('=')
            .ok_or_else(|| anyhow!("--set {set}: expected section.key=value, e.g. train.grid=64"))?;
        let keys: Vec<&str> = path.trim().split('.').map(str::trim).collect();
        if keys.len() < 2 || keys.iter().any(|k| k.is_empty()) {
            bail!("--set {set}: expected section.key=value, e.g. train.grid=64 (a key belongs to a table)");
        }
        let text = text.trim();
        let value = match toml::from_str::<Table>(&format!("v = {text}")) {
            Ok(mut t) => t.remove("v").expect("parsed"),
            Err(_) if !text.is_empty() && text.chars().all(|c| c.is_alphanumeric() || "_-./".contains(c)) => {
                Value::String(text.to_string())
            }
            Err(e) => bail!("--set {set}: `{text}` is not a TOML value: {}", e.message()),
        };
        let mut table = Table::new();
        let mut inner = &mut table;
        for key in &keys[..keys.len() - 1] {
            inner = inner
                .entry(key.to_string())
                .or_insert_with(|| Value::Table(Table::new()))
                .as_table_mut()
                .expect("a table");
        }
        inner.insert(keys[keys.len() - 1].to_string(), value);
        self.layers.push(Layer { origin: Origin::Set(set.to_string()), table });
        Ok(())
    }

    /// The layers merged, typed and checked.
    pub(super) fn resolve(&self) -> anyhow::Result<Config> {
        let mut merged = Table::new();
        for layer in &self.layers {
            merge(&mut merged, &layer.table);
        }
        self.check_variants(&merged)?;
        super::ranges::check(&merged, |keys| self.where_is(keys))?;
        let config: Config = Value::Table(merged).try_into().map_err(|e: toml::de::Error| self.located(&e))?;
        config.check()?;
        config.check_cache_remote(|keys| self.where_is(keys))?;
        Ok(config)
    }

    /// A member of a variant's table that the picked variant does not read is an error.
    fn check_variants(&self, merged: &Table) -> anyhow::Result<()> {
        for v in VARIANTS {
            let Some(table) = merged.get(v.table).and_then(Value::as_table) else { continue };
            let picked = match table.get(v.selector) {
                Some(Value::String(s)) => s.clone(),
                Some(Value::Array(_)) if v.list.is_some() => v.list.expect("checked").to_string(),
                Some(_) => continue, // a wrong type: deserialising names it
                None => default_of(v.table, v.selector).unwrap_or_default(),
            };
            if !v.reads.iter().any(|(name, _)| *name == picked) {
                continue; // an unknown variant: deserialising names it
            }
            for member in v.members() {
                if table.contains_key(member) && !v.reads(&picked, member) {
                    let what = if table.get(member).is_some_and(Value::is_table) {
                        format!("[{}.{member}]", v.table)
                    } else {
                        format!("[{}] {member}", v.table)
                    };
                    bail!(
                        "{}{what} is read only by {} = {}, and this configuration has {} = \"{picked}\": remove it, \
                         or set {} to a variant that reads it",
                        self.where_is(&[v.table, member]).map_or(String::new(), |w| format!("{w}: ")),
                        v.selector,
                        v.readers_of(member),
                        v.selector,
                        v.selector
                    );
                }
            }
        }
        Ok(())
    }

    /// `e` with the file and line of the key it is about, and the key itself.
    fn located(&self, e: &toml::de::Error) -> anyhow::Error {
        let text = e.to_string();
        let (message, path) = match text.trim_end().rsplit_once("\nin `") {
            Some((message, path)) => (message.to_string(), path.trim_end_matches('`').to_string()),
            None => (text.trim_end().to_string(), String::new()),
        };
        let mut keys: Vec<&str> = path.split('.').filter(|k| !k.is_empty()).collect();
        // "unknown field `x`" is about the table's key `x`.
        if let Some(field) = message.strip_prefix("unknown field `").and_then(|m| m.split('`').next()) {
            keys.push(field);
        }
        let key = match keys.split_last() {
            None => String::new(),
            Some((key, [])) => format!("[{key}]: "),
            Some((key, table)) => format!("[{}] {key}: ", table.join(".")),
        };
        let place = self.where_is(&keys).map_or(String::new(), |w| format!("{w}, "));
        anyhow!("{place}{key}{message}")
    }

    /// "FILE, line N" (or "--set …") for the topmost layer that gives `keys`.
    fn where_is(&self, keys: &[&str]) -> Option<String> {
        let layer = self.layers.iter().rev().find(|layer| contains(&layer.table, keys))?;
        Some(match &layer.origin {
            Origin::Set(set) => format!("--set {set}"),
            Origin::File { path, text } => {
                let line = line_of(text, keys).map(|n| format!("line {n}"));
                let file = (!path.as_os_str().is_empty()).then(|| path.display().to_string());
                [file, line].into_iter().flatten().collect::<Vec<_>>().join(", ")
            }
        })
    }
}

/// `top` over `base`: tables merge key by key, other values replace. Where `top` picks a
/// variant, what only other variants read goes from `base` first.
fn merge(base: &mut Table, top: &Table) {
    for v in VARIANTS {
        let picked = match top.get(v.table).and_then(Value::as_table).and_then(|t| t.get(v.selector)) {
            Some(Value::String(s)) => Some(s.as_str()),
            Some(Value::Array(_)) => v.list,
            _ => None,
        };
        let (Some(picked), Some(Value::Table(below))) = (picked, base.get_mut(v.table)) else { continue };
        for member in v.members() {
            if !v.reads(picked, member) {
                below.remove(member);
            }
        }
    }
    merge_tables(base, top);
}

/// A table over another: key by key, recursively.
fn merge_tables(base: &mut Table, top: &Table) {
    for (key, value) in top {
        match (base.get_mut(key), value) {
            (Some(Value::Table(below)), Value::Table(above)) => merge_tables(below, above),
            _ => {
                base.insert(key.clone(), value.clone());
            }
        }
    }
}

/// Rewrites the relative paths of a file in `dir` as paths from the current folder.
fn relocate_paths(table: &mut Table, dir: &Path) -> anyhow::Result<()> {
    for (section, key) in PATH_KEYS {
        let Some(Value::String(path)) =
            table.get_mut(section).and_then(Value::as_table_mut).and_then(|t| t.get_mut(key))
        else {
            continue;
        };
        if Path::new(path.as_str()).is_relative() {
            let joined = lexically_normal(&std::path::absolute(dir.join(&*path)).context("the current folder")?);
            *path = joined.to_str().ok_or_else(|| anyhow!("[{section}] {key}: the path is not UTF-8"))?.to_string();
        }
    }
    Ok(())
}

/// `path` without `.` and with each `..` taking the folder before it away (an absolute path:
/// nothing climbs above its root).
fn lexically_normal(path: &Path) -> PathBuf {
    use std::path::Component;
    let mut normal = PathBuf::new();
    for part in path.components() {
        match part {
            Component::CurDir => {}
            Component::ParentDir => {
                normal.pop();
            }
            other => normal.push(other),
        }
    }
    normal
}

/// Whether `table` gives the key at `keys`.
fn contains(table: &Table, keys: &[&str]) -> bool {
    let Some((first, rest)) = keys.split_first() else { return false };
    match (table.get(*first), rest.is_empty()) {
        (Some(_), true) => true,
        (Some(Value::Table(inner)), false) => contains(inner, rest),
        _ => false,
    }
}

/// The line (from 1) where `text` gives the key at `keys`.
fn line_of(text: &str, keys: &[&str]) -> Option<usize> {
    let document: toml_edit::ImDocument<&str> = toml_edit::ImDocument::parse(text).ok()?;
    let mut table: &dyn toml_edit::TableLike = document.as_table();
    let mut span = None;
    for (i, key) in keys.iter().enumerate() {
        let (k, item) = table.get_key_value(key)?;
        span = k.span().or_else(|| item.span());
        if i + 1 < keys.len() {
            table = item.as_table_like()?;
        }
    }
    span.map(|s| text[..s.start].matches('\n').count() + 1)
}

/// The built-in default of `[table] key`, as a string (a selector's variant).
fn default_of(table: &str, key: &str) -> Option<String> {
    let value = match table {
        "train" => Value::try_from(crate::stage::train::Params::default()).ok()?,
        "select" => Value::try_from(crate::stage::select::Params::default()).ok()?,
        "drr" => Value::try_from(crate::stage::drr::Params::default()).ok()?,
        _ => return None,
    };
    value.get(key)?.as_str().map(str::to_string)
}
