//! Publishing results: `out_dir/<patient>/<name>` entries show the cache blobs' bytes, each
//! replaced atomically. By default an entry is a hard link to its blob, read-only (mode 0444)
//! like the blob, so that editing it in place takes a deliberate `chmod` (and the next run's
//! digest check then finds the blob changed and computes it again); where the filesystem
//! refuses links it is a read-only copy. [`Publish::Copies`] writes independent, writable
//! copies instead. Stale `.tmp-*` entries a killed process left in a folder are removed before
//! publishing into it (see [`crate::leftovers`]).

use super::files::{remove_if_present, set_read_only, temp_name};
use super::leftovers::{describe, remove_stale_temps};
use super::store::{hash_file, OutputRef, Store};
use anyhow::Context as _;
use std::fs;
use std::path::Path;

/// How results reach `out_dir`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum Publish {
    /// Read-only hard links to the cache blobs (read-only copies where links fail).
    #[default]
    Links,
    /// Independent copies, writable by their owner: editing one leaves the cache as it is.
    Copies,
}

/// Makes `dir/<output name>` show each output's bytes. Stale temporary files it removes from
/// `dir` are told to `say` in one line.
pub fn publish(
    store: &Store,
    dir: &Path,
    outputs: &[OutputRef],
    how: Publish,
    say: &dyn Fn(String),
) -> anyhow::Result<()> {
    fs::create_dir_all(dir).with_context(|| format!("creating output folder {}", dir.display()))?;
    let removed = remove_stale_temps(store, dir)?;
    if !removed.is_empty() {
        say(describe(&removed, "removed", &dir.display().to_string()));
    }
    for output in outputs {
        let blob = store.blob_path(&output.hash);
        let target = dir.join(&output.name);
        let linked = same_file(&blob, &target);
        if how == Publish::Links && linked {
            ensure_read_only(&target)?;
            continue;
        }
        if how == Publish::Copies && !linked && holds(&target, output) {
            continue;
        }
        replace(how, &blob, &dir.join(temp_name()), &target)
            .with_context(|| format!("publishing {} as {}", blob.display(), target.display()))?;
    }
    Ok(())
}

/// Puts `blob`'s bytes at `target` as `how` publishes them, through the temporary name `tmp`,
/// which is gone afterwards whatever happened.
fn replace(how: Publish, blob: &Path, tmp: &Path, target: &Path) -> anyhow::Result<()> {
    if let Err(e) = place(how, blob, tmp).and_then(|()| fs::rename(tmp, target)) {
        let _ = fs::remove_file(tmp);
        return Err(e.into());
    }
    // Renaming a link onto another link to the same file does nothing and succeeds (POSIX), so
    // `tmp` stays when another process published the same blob at `target` meanwhile.
    remove_if_present(tmp)
}

/// Writes `blob`'s bytes at `tmp` as `how` publishes them.
fn place(how: Publish, blob: &Path, tmp: &Path) -> std::io::Result<()> {
    match how {
        Publish::Links if fs::hard_link(blob, tmp).is_ok() => set_read_only(tmp),
        Publish::Links => fs::copy(blob, tmp).and_then(|_| set_read_only(tmp)),
        Publish::Copies => fs::copy(blob, tmp).and_then(|_| set_writable(tmp)),
    }
}

/// Makes `path` read-only for everyone if it is not (a hard link shares its blob's mode).
fn ensure_read_only(path: &Path) -> anyhow::Result<()> {
    if fs::metadata(path).is_ok_and(|m| is_writable(&m)) {
        set_read_only(path).with_context(|| format!("making {} read-only", path.display()))?;
    }
    Ok(())
}

/// Whether `path` holds exactly `output`'s bytes (size, then content hash).
fn holds(path: &Path, output: &OutputRef) -> bool {
    fs::metadata(path).is_ok_and(|m| m.is_file() && m.len() == output.size)
        && hash_file(path).is_ok_and(|h| h == output.hash)
}

#[cfg(unix)]
fn is_writable(meta: &fs::Metadata) -> bool {
    std::os::unix::fs::PermissionsExt::mode(&meta.permissions()) & 0o222 != 0
}

#[cfg(not(unix))]
fn is_writable(meta: &fs::Metadata) -> bool {
    !meta.permissions().readonly()
}

/// An independent copy's mode: 0644 on Unix.
fn set_writable(path: &Path) -> std::io::Result<()> {
    #[cfg(unix)]
    let perms = std::os::unix::fs::PermissionsExt::from_mode(0o644);
    #[cfg(not(unix))]
    let perms = {
        let mut perms = fs::metadata(path)?.permissions();
        #[allow(clippy::permissions_set_readonly_false)]
        perms.set_readonly(false);
        perms
    };
    fs::set_permissions(path, perms)
}

#[cfg(unix)]
fn same_file(a: &Path, b: &Path) -> bool {
    use std::os::unix::fs::MetadataExt;
    match (fs::metadata(a), fs::metadata(b)) {
        (Ok(x), Ok(y)) => x.dev() == y.dev() && x.ino() == y.ino(),
        _ => false,
    }
}

#[cfg(not(unix))]
fn same_file(_a: &Path, _b: &Path) -> bool {
    false
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_link_renamed_onto_a_link_to_the_same_blob_leaves_no_temporary_name() {
        let dir = tempfile::tempdir().unwrap();
        let (blob, tmp, target) = (dir.path().join("blob"), dir.path().join(".tmp-x-1-0-0"), dir.path().join("out"));
        fs::write(&blob, "abcde").unwrap();
        // Another process published the blob at `target` after this one found it absent.
        fs::hard_link(&blob, &target).unwrap();
        replace(Publish::Links, &blob, &tmp, &target).unwrap();
        assert!(same_file(&blob, &target) && !tmp.exists());
        // The usual case: a copy replaced by a link.
        fs::remove_file(&target).unwrap();
        fs::write(&target, "old").unwrap();
        replace(Publish::Links, &blob, &tmp, &target).unwrap();
        assert!(same_file(&blob, &target) && !tmp.exists());
    }
}
