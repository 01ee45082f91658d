//! The cache on disk: content-addressed blobs plus one manifest per (stage, key).
//!
//! ```text
//! cache/blobs/ab/abcdef…         output bytes, named by their blake3 hash, read-only
//! cache/manifests/<stage>/<key>.json   inputs, parameters, outputs, wall time, tool version
//! cache/latest/<stage>/<unit>.json     the manifest last used for a patient (for "why stale")
//! cache/sources/<unit>.json            stat fingerprints of a patient's files → their hashes
//! ```
//! Every file is written to a temporary name in its own directory and renamed into place, and
//! a manifest is written only after all its blobs: a run killed at any moment leaves either
//! nothing or temporary files no reader trusts. A manifest is trusted only when each blob it
//! names exists with its recorded size (and, with `verify`, re-hashes to its name).

use super::key::Hash;
use anyhow::Context as _;
use serde::{Deserialize, Serialize};
use std::collections::HashSet;
use std::fs;
use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

/// A stored output: its file name and the content hash of its bytes.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct OutputRef {
    pub name: String,
    pub hash: Hash,
    pub size: u64,
}

/// Everything recorded about one computed (stage, key).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Manifest {
    pub stage: String,
    pub version: u32,
    pub key: Hash,
    /// The patient (or `cohort`) it was computed for.
    pub unit: String,
    pub params: serde_json::Value,
    pub inputs: Vec<InputRef>,
    pub outputs: Vec<OutputRef>,
    pub wall_seconds: f64,
    pub tool_version: String,
    pub created_unix: u64,
}

/// One input of a manifest: output `name` of stage `stage`, with its content hash.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct InputRef {
    pub stage: String,
    pub name: String,
    pub hash: Hash,
}

/// Whether a (stage, key) can be served from the cache.
pub enum Lookup {
    Hit(Manifest),
    Miss,
    /// A manifest exists but cannot be trusted; the reason says why.
    Broken(String),
}

pub struct Store {
    root: PathBuf,
}

static TMP_COUNTER: AtomicU64 = AtomicU64::new(0);

impl Store {
    /// Opens (creating if needed) the cache at `root`.
    pub fn open(root: &Path) -> anyhow::Result<Store> {
        for sub in ["blobs", "manifests", "latest", "sources", "locks"] {
            fs::create_dir_all(root.join(sub))
                .with_context(|| format!("creating cache directory {}", root.join(sub).display()))?;
        }
        Ok(Store { root: root.to_path_buf() })
    }

    pub fn root(&self) -> &Path {
        &self.root
    }

    pub fn blob_path(&self, hash: &Hash) -> PathBuf {
        let hex = hash.hex();
        self.root.join("blobs").join(&hex[..2]).join(hex)
    }

    fn manifest_path(&self, stage: &str, key: &Hash) -> PathBuf {
        self.root.join("manifests").join(stage).join(format!("{}.json", key.hex()))
    }

    fn latest_path(&self, stage: &str, unit: &str) -> PathBuf {
        self.root.join("latest").join(stage).join(format!("{unit}.json"))
    }

    pub fn sources_path(&self, unit: &str) -> PathBuf {
        self.root.join("sources").join(format!("{unit}.json"))
    }

    pub fn lock_path(&self, name: &str) -> PathBuf {
        self.root.join("locks").join(format!("{name}.lock"))
    }

    pub fn global_lock_path(&self) -> PathBuf {
        self.root.join(".lock")
    }

    /// Stores `bytes` under their hash and returns the reference.
    pub fn put_blob(&self, name: &str, bytes: &[u8]) -> anyhow::Result<OutputRef> {
        let hash = Hash::of(bytes);
        let path = self.blob_path(&hash);
        // Always (re)write: a blob we recompute may be replacing a corrupt copy.
        write_atomic(&path, bytes, true)?;
        Ok(OutputRef { name: name.to_string(), hash, size: bytes.len() as u64 })
    }

    /// Why a stored output cannot be used, or `None` when it can.
    pub fn check_blob(&self, output: &OutputRef, verify: bool) -> Option<String> {
        let path = self.blob_path(&output.hash);
        match fs::metadata(&path) {
            Err(_) => return Some(format!("cached output `{}` is missing", output.name)),
            Ok(m) if m.len() != output.size => {
                return Some(format!(
                    "cached output `{}` has {} bytes, its manifest says {}",
                    output.name,
                    m.len(),
                    output.size
                ))
            }
            Ok(_) => {}
        }
        if verify {
            match hash_file(&path) {
                Ok(h) if h == output.hash => {}
                Ok(_) => return Some(format!("cached output `{}` is corrupt (hash mismatch)", output.name)),
                Err(e) => return Some(format!("cached output `{}` cannot be read: {e}", output.name)),
            }
        }
        None
    }

    /// Looks up (stage, key): a hit only when the manifest parses and every blob checks out.
    pub fn lookup(&self, stage: &str, key: &Hash, verify: bool) -> Lookup {
        let path = self.manifest_path(stage, key);
        let text = match fs::read(&path) {
            Ok(t) => t,
            Err(_) => return Lookup::Miss,
        };
        let manifest: Manifest = match serde_json::from_slice(&text) {
            Ok(m) => m,
            Err(e) => return Lookup::Broken(format!("manifest {} is unreadable: {e}", path.display())),
        };
        if manifest.key != *key || manifest.stage != stage {
            return Lookup::Broken(format!("manifest {} does not describe this key", path.display()));
        }
        for output in &manifest.outputs {
            if let Some(why) = self.check_blob(output, verify) {
                return Lookup::Broken(why);
            }
        }
        Lookup::Hit(manifest)
    }

    /// Records a computed stage: manifest last, after its blobs are in place.
    pub fn put_manifest(&self, manifest: &Manifest) -> anyhow::Result<()> {
        let bytes = serde_json::to_vec_pretty(manifest)?;
        write_atomic(&self.manifest_path(&manifest.stage, &manifest.key), &bytes, false)
    }

    /// The manifest last used for `unit` at `stage`, if any.
    pub fn latest(&self, stage: &str, unit: &str) -> Option<Manifest> {
        let text = fs::read(self.latest_path(stage, unit)).ok()?;
        serde_json::from_slice(&text).ok()
    }

    /// Remembers `manifest` as the last one used for its unit (skipped when unchanged).
    pub fn set_latest(&self, manifest: &Manifest) -> anyhow::Result<()> {
        if self.latest(&manifest.stage, &manifest.unit).is_some_and(|m| m.key == manifest.key) {
            return Ok(());
        }
        let bytes = serde_json::to_vec_pretty(manifest)?;
        write_atomic(&self.latest_path(&manifest.stage, &manifest.unit), &bytes, false)
    }

    /// What `gc` deletes: first every manifest of a stage in `forget`, and with `keep` every
    /// manifest whose (stage, key) `keep` lacks (results no configuration uses now); then every
    /// blob no remaining manifest references, leftover temporary files and lock files. Deletes
    /// nothing itself.
    pub fn garbage(&self, keep: Option<&HashSet<(String, Hash)>>, forget: &[String]) -> anyhow::Result<Garbage> {
        let mut garbage = Garbage::default();
        let mut referenced = HashSet::new();
        for entry in walkdir::WalkDir::new(self.root.join("manifests")).min_depth(2).max_depth(2) {
            let entry = entry?;
            let name = entry.file_name().to_string_lossy();
            let Some(stem) = name.strip_suffix(".json").filter(|_| !name.starts_with(".tmp-")) else {
                continue;
            };
            let stage = entry.path().parent().and_then(|d| d.file_name()).map(|d| d.to_string_lossy().to_string());
            let live = match (keep, stage, Hash::from_hex(stem)) {
                (_, Some(stage), _) if forget.contains(&stage) => false,
                (None, ..) => true,
                (Some(keep), Some(stage), Some(key)) => keep.contains(&(stage, key)),
                (Some(_), ..) => false,
            };
            if !live {
                garbage.manifests.push(entry.path().to_path_buf());
            } else if let Ok(m) = serde_json::from_slice::<Manifest>(&fs::read(entry.path())?) {
                referenced.extend(m.outputs.iter().map(|o| o.hash));
            }
        }
        for entry in walkdir::WalkDir::new(&self.root).min_depth(1) {
            let entry = entry?;
            if !entry.file_type().is_file() {
                continue;
            }
            let name = entry.file_name().to_string_lossy().to_string();
            let rel = entry.path().strip_prefix(&self.root).unwrap_or(entry.path());
            let in_blobs = rel.starts_with("blobs");
            if name.starts_with(".tmp-")
                || rel.starts_with("locks")
                || (in_blobs && Hash::from_hex(&name).is_none_or(|h| !referenced.contains(&h)))
            {
                let meta = entry.metadata()?;
                garbage.files.push(Doomed {
                    path: entry.path().to_path_buf(),
                    bytes: meta.len(),
                    linked: links(&meta) > 1,
                });
            }
        }
        Ok(garbage)
    }
}

/// What `gc` would delete (see [`Store::garbage`]).
#[derive(Debug, Default)]
pub struct Garbage {
    /// Manifests of results no kept configuration uses.
    pub manifests: Vec<PathBuf>,
    /// Blobs nothing references, temporary and lock files.
    pub files: Vec<Doomed>,
}

/// One file `gc` deletes.
#[derive(Debug)]
pub struct Doomed {
    pub path: PathBuf,
    pub bytes: u64,
    /// Another name (an out dir's hard link) still holds its bytes, so deleting it frees none.
    pub linked: bool,
}

impl Garbage {
    /// Deletes it: manifests first, so no manifest ever names a deleted blob.
    /// Call only while holding the cache's exclusive lock.
    pub fn delete(&self) -> anyhow::Result<()> {
        for path in self.manifests.iter().chain(self.files.iter().map(|f| &f.path)) {
            match fs::remove_file(path) {
                Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
                    return Err(e).with_context(|| format!("deleting {}", path.display()))
                }
                _ => {}
            }
        }
        Ok(())
    }

    /// Bytes deleting it frees on disk, and bytes it unlinks that out dirs still hold.
    pub fn bytes(&self) -> (u64, u64) {
        let sum = |linked: bool| self.files.iter().filter(|f| f.linked == linked).map(|f| f.bytes).sum();
        (sum(false), sum(true))
    }
}

#[cfg(unix)]
fn links(meta: &fs::Metadata) -> u64 {
    std::os::unix::fs::MetadataExt::nlink(meta)
}

#[cfg(not(unix))]
fn links(_meta: &fs::Metadata) -> u64 {
    1
}

/// Writes `bytes` to `path` atomically: a temporary file in the same directory, flushed to
/// disk, then renamed over `path`.
pub fn write_atomic(path: &Path, bytes: &[u8], read_only: bool) -> anyhow::Result<()> {
    let dir = path.parent().expect("cache paths have a parent");
    fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let tmp = dir.join(temp_name());
    let result = (|| -> std::io::Result<()> {
        let mut f = fs::File::create(&tmp)?;
        f.write_all(bytes)?;
        f.sync_all()?;
        if read_only {
            let mut perms = f.metadata()?.permissions();
            perms.set_readonly(true);
            fs::set_permissions(&tmp, perms)?;
        }
        fs::rename(&tmp, path)
    })();
    if result.is_err() {
        let _ = fs::remove_file(&tmp);
    }
    result.with_context(|| format!("writing {}", path.display()))
}

/// A name no other process or thread is using at the same moment.
pub fn temp_name() -> String {
    let n = TMP_COUNTER.fetch_add(1, Ordering::Relaxed);
    let nanos = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_nanos()).unwrap_or(0);
    format!(".tmp-{}-{n}-{nanos}", std::process::id())
}

/// blake3 of a file's bytes, streamed.
pub fn hash_file(path: &Path) -> std::io::Result<Hash> {
    let mut f = fs::File::open(path)?;
    let mut h = blake3::Hasher::new();
    let mut buf = vec![0u8; 1 << 20];
    loop {
        let n = f.read(&mut buf)?;
        if n == 0 {
            break;
        }
        h.update(&buf[..n]);
    }
    Ok(Hash(*h.finalize().as_bytes()))
}
