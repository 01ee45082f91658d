//! Temporary files a killed process left: `.tmp-<host>-<pid>-…` entries (see
//! [`temp_name`](super::files::temp_name)) in the cache and in the folders results are
//! published into.
//!
//! Whether the process that named a temporary file may still be writing it is decided by the
//! cache's leases ([`crate::lease`]), not by guessing from process ids: every process that
//! writes temporary files holds a lease for as long as it may. A `.tmp-*` entry is stale when
//! no live lease names its host and pid. An entry of a live process, this one included, is
//! never touched.

use super::files::{remove_if_present, temp_owner, Owner};
use super::lease::live_owners;
use super::store::{links, Doomed, Store};
use anyhow::Context as _;
use std::collections::HashSet;
use std::path::Path;

/// The `.tmp-*` entries under `dir` (down to `depth` folders below it; 1: only its own entries)
/// whose process has ended. Folders named `.tmp-*` are not entered.
pub fn stale_temps(store: &Store, dir: &Path, depth: usize) -> anyhow::Result<Vec<Doomed>> {
    let mut stale = Vec::new();
    // Read once, at the first temporary file found: most folders have none.
    let mut live: Option<HashSet<Owner>> = None;
    let walker = walkdir::WalkDir::new(dir).min_depth(1).max_depth(depth).into_iter();
    let enters =
        |e: &walkdir::DirEntry| !(e.file_type().is_dir() && e.file_name().to_string_lossy().starts_with(".tmp-"));
    for entry in walker.filter_entry(enters) {
        let entry = match entry {
            Ok(e) => e,
            Err(e) if e.io_error().is_some_and(|io| io.kind() == std::io::ErrorKind::NotFound) => continue,
            Err(e) => return Err(e).with_context(|| format!("listing {}", dir.display())),
        };
        let name = entry.file_name().to_string_lossy();
        let Some(owner) = temp_owner(&name) else { continue };
        if !entry.file_type().is_file() {
            continue;
        }
        if live.is_none() {
            live = Some(live_owners(store.root())?.into_iter().collect());
        }
        if live.as_ref().is_some_and(|live| live.contains(&owner)) {
            continue;
        }
        let meta = entry.metadata()?;
        stale.push(Doomed { path: entry.path().to_path_buf(), bytes: meta.len(), linked: links(&meta) > 1 });
    }
    Ok(stale)
}

/// Deletes the stale `.tmp-*` entries of `dir` itself; returns what it deleted.
pub fn remove_stale_temps(store: &Store, dir: &Path) -> anyhow::Result<Vec<Doomed>> {
    let stale = stale_temps(store, dir, 1)?;
    delete(&stale)?;
    Ok(stale)
}

/// "N stale .tmp-* file(s) …, freeing X MiB" with the bytes that were links to blobs that stay
/// said apart: `verb` is "removed" or "would remove", `folders` where they were.
pub fn describe(stale: &[Doomed], verb: &str, folders: &str) -> String {
    let mib = |linked: bool| {
        stale.iter().filter(|d| d.linked == linked).map(|d| d.bytes).sum::<u64>() as f64 / (1024.0 * 1024.0)
    };
    let mut line = format!(
        "{verb} {} stale .tmp-* file(s) killed runs left in {folders}, freeing {:.1} MiB",
        stale.len(),
        mib(false)
    );
    if mib(true) > 0.0 {
        line.push_str(&format!(" ({:.1} MiB more were links to blobs that stay)", mib(true)));
    }
    line
}

/// Deletes what [`stale_temps`] found (one already gone is no error).
pub fn delete(stale: &[Doomed]) -> anyhow::Result<()> {
    stale.iter().try_for_each(|doomed| remove_if_present(&doomed.path))
}
