//! A patient's own input files: listed, fingerprinted and content-hashed.
//!
//! Hashing every DICOM file on every run would cost seconds, so each file's hash is remembered
//! beside its (size, modification time) fingerprint and recomputed only when that changes, or
//! always with `--verify`. A file touched but unchanged re-hashes to the same bytes, and early
//! cutoff keeps everything downstream cached.

use super::files::write_atomic;
use super::key::Hash;
use super::store::{hash_file, Store};
use anyhow::{anyhow, Context as _};
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::path::PathBuf;

/// One patient: an ID and its own files.
#[derive(Debug, Clone)]
pub struct Unit {
    pub id: String,
    /// The folder holding the patient's files.
    pub source_dir: PathBuf,
    /// When set, only these files (relative to `source_dir`) are the patient's; otherwise every
    /// file under the folder is.
    pub source_files: Option<Vec<String>>,
}

impl Unit {
    /// A patient whose files are everything under `dir`.
    pub fn folder(id: impl Into<String>, dir: PathBuf) -> Unit {
        Unit { id: id.into(), source_dir: dir, source_files: None }
    }
}

/// One input file of a patient.
#[derive(Debug, Clone)]
pub struct SourceFile {
    /// Path relative to the patient's folder, `/`-separated.
    pub rel: String,
    pub path: PathBuf,
    pub size: u64,
    pub hash: Hash,
}

#[derive(Serialize, Deserialize)]
struct Fingerprint {
    rel: String,
    size: u64,
    mtime_ns: i128,
    hash: Hash,
}

/// Lists the unit's files (every regular file under its folder, hidden names skipped, or its
/// explicit list), sorted, with content hashes; remembered hashes are reused while the file's
/// fingerprint still matches.
pub fn scan(store: &Store, unit: &Unit, verify: bool) -> anyhow::Result<Vec<SourceFile>> {
    let dir = &unit.source_dir;
    if !dir.is_dir() {
        return Err(anyhow!("patient folder {} does not exist or is not a folder", dir.display()));
    }
    let remembered: HashMap<String, Fingerprint> = std::fs::read(store.sources_path(&unit.id))
        .ok()
        .and_then(|t| serde_json::from_slice::<Vec<Fingerprint>>(&t).ok())
        .map(|v| v.into_iter().map(|f| (f.rel.clone(), f)).collect())
        .unwrap_or_default();
    let (mut files, mut prints, mut changed) = (Vec::new(), Vec::new(), false);
    for (rel, path) in list(unit)? {
        let meta = std::fs::metadata(&path).with_context(|| format!("reading {}", path.display()))?;
        let mtime_ns = meta
            .modified()
            .ok()
            .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
            .map(|d| d.as_nanos() as i128)
            .unwrap_or(-1);
        let known = remembered.get(&rel).filter(|f| !verify && f.size == meta.len() && f.mtime_ns == mtime_ns);
        let hash = match known {
            Some(f) => f.hash,
            None => {
                changed = true;
                hash_file(&path).with_context(|| format!("reading {}", path.display()))?
            }
        };
        prints.push(Fingerprint { rel: rel.clone(), size: meta.len(), mtime_ns, hash });
        files.push(SourceFile { rel, path, size: meta.len(), hash });
    }
    if changed || prints.len() != remembered.len() {
        write_atomic(&store.sources_path(&unit.id), &serde_json::to_vec(&prints)?, false)?;
    }
    Ok(files)
}

/// `(relative name, path)` of the unit's files, sorted by name.
fn list(unit: &Unit) -> anyhow::Result<Vec<(String, PathBuf)>> {
    let dir = &unit.source_dir;
    if let Some(names) = &unit.source_files {
        let mut out: Vec<(String, PathBuf)> = names.iter().map(|n| (n.clone(), dir.join(n))).collect();
        out.sort();
        if let Some((_, missing)) = out.iter().find(|(_, p)| !p.is_file()) {
            return Err(anyhow!("input file {} does not exist", missing.display()));
        }
        return Ok(out);
    }
    let walker = walkdir::WalkDir::new(dir)
        .follow_links(true)
        .sort_by_file_name()
        .into_iter()
        .filter_entry(|e| e.depth() == 0 || !e.file_name().to_string_lossy().starts_with('.'));
    let mut out = Vec::new();
    for entry in walker {
        let entry = entry.with_context(|| format!("listing {}", dir.display()))?;
        if !entry.file_type().is_file() {
            continue;
        }
        let rel = entry
            .path()
            .strip_prefix(dir)
            .expect("walkdir stays under its root")
            .components()
            .map(|c| c.as_os_str().to_string_lossy())
            .collect::<Vec<_>>()
            .join("/");
        out.push((rel, entry.path().to_path_buf()));
    }
    Ok(out)
}
