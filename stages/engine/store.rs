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
//! nothing or temporary files no reader trusts. A manifest is trusted only when it describes
//! the (stage, key, patient, inputs) it is looked up for, its digest binds its outputs to that
//! key, and each blob it names re-hashes to its name, or for a gather has its size (see
//! [`Store::lookup`], [`Store::check_sizes_only`]).

use super::files::{remove_if_present, write_atomic};
use super::key::Hash;
use anyhow::Context as _;
use serde::{Deserialize, Serialize};
use std::collections::HashSet;
use std::fs;
use std::io::Read;
use std::path::{Path, PathBuf};
use std::sync::Arc;

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
    /// [`Manifest::digest_of`] its stage, version, key, unit, inputs and outputs when written;
    /// `None` in manifests written before digests were recorded.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub digest: Option<Hash>,
}

impl Manifest {
    /// blake3 over the fields that say what this result is and where its bytes are: stage,
    /// version, key, unit, inputs and outputs, each length-prefixed. It leaves out the floats
    /// (parameters, wall time), whose text need not parse back to the same bits; the key
    /// covers the parameters.
    pub fn digest_of(&self) -> Hash {
        let mut h = blake3::Hasher::new();
        let mut field = |bytes: &[u8]| {
            h.update(&(bytes.len() as u64).to_le_bytes());
            h.update(bytes);
        };
        field(b"aret-pipe manifest v1");
        field(self.stage.as_bytes());
        field(&self.version.to_le_bytes());
        field(&self.key.0);
        field(self.unit.as_bytes());
        for input in &self.inputs {
            field(input.stage.as_bytes());
            field(input.name.as_bytes());
            field(&input.hash.0);
        }
        for output in &self.outputs {
            field(output.name.as_bytes());
            field(&output.hash.0);
            field(&output.size.to_le_bytes());
        }
        Hash(*h.finalize().as_bytes())
    }

    /// The manifest with its digest recorded.
    pub fn sealed(mut self) -> Manifest {
        self.digest = Some(self.digest_of());
        self
    }
}

/// What a lookup expects a manifest to describe: the unit and the inputs the key was computed
/// from (the key itself names the manifest's file).
pub struct Expected<'a> {
    pub unit: &'a str,
    pub inputs: &'a [(String, String, Hash)],
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
    Hit(Box<Manifest>),
    /// A hit served by the remote cache: fetched, checked and now held locally too.
    Fetched(Box<Manifest>),
    Miss,
    /// A manifest exists but cannot be trusted; the reason says why, naming the stage, the
    /// patient and the file.
    Broken(String),
}

pub struct Store {
    root: PathBuf,
    remote: Option<Arc<dyn Remote>>,
    /// Whether a cache hit re-hashes its blobs (the default) or checks their sizes only
    /// ([`Store::check_sizes_only`]).
    hash_hits: bool,
}

/// A shared cache behind the local one (`crate::remote::RemoteCache`): asked on every local
/// miss, and handed every result a run computes or serves locally.
pub trait Remote: Send + Sync {
    /// On a local miss: the entry fetched into `store` ([`Lookup::Fetched`]), a miss, or why the
    /// remote's entry cannot be trusted ([`Lookup::Broken`]).
    fn read_through(&self, store: &Store, stage: &str, key: &Hash, expected: &Expected) -> Lookup;
    /// Uploads `manifest` and its blobs from `store` where the remote lacks them. Never fails:
    /// an error becomes a notice.
    fn share(&self, store: &Store, manifest: &Manifest);
    /// Whether this process fetched (stage, key) from the remote (so a local hit on it is
    /// reported as fetched too: a gather's check for missing patients fetches before it runs).
    fn fetched(&self, stage: &str, key: &Hash) -> bool;
    /// The warnings since the last call, one line each.
    fn take_notices(&self) -> Vec<String>;
}

impl Store {
    /// Opens (creating if needed) the cache at `root`.
    pub fn open(root: &Path) -> anyhow::Result<Store> {
        for sub in ["blobs", "manifests", "latest", "sources", "locks", "leases"] {
            fs::create_dir_all(root.join(sub))
                .with_context(|| format!("creating cache directory {}", root.join(sub).display()))?;
        }
        Ok(Store { root: root.to_path_buf(), remote: None, hash_hits: true })
    }

    /// The store with `remote` behind it: lookups read through to it ([`Store::lookup`]).
    pub fn with_remote(self, remote: Arc<dyn Remote>) -> Store {
        Store { remote: Some(remote), ..self }
    }

    /// The remote cache behind this one, if any.
    pub fn remote(&self) -> Option<&dyn Remote> {
        self.remote.as_deref()
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

    /// Stores `bytes` under their hash and returns the reference.
    pub fn put_blob(&self, name: &str, bytes: &[u8]) -> anyhow::Result<OutputRef> {
        let hash = Hash::of(bytes);
        let path = self.blob_path(&hash);
        let output = OutputRef { name: name.to_string(), hash, size: bytes.len() as u64 };
        // A copy that checks out stays: another host may be reading it, and replacing a file
        // under an NFS reader fails its read. A corrupt copy is replaced.
        if self.blob_fault(&output, true).is_some() {
            write_atomic(&path, bytes, true)?;
        }
        Ok(output)
    }

    /// Why a stored output cannot be used, or `None` when it can: the blob must exist, have its
    /// recorded size and re-hash to its name (unless [`Store::check_sizes_only`]).
    pub fn check_blob(&self, output: &OutputRef) -> Option<String> {
        self.blob_fault(output, self.hash_hits)
    }

    /// From now on, a cache hit checks that each blob exists at its recorded size, and does not
    /// re-hash it. For a gather over a cluster's cache (`run --gather`): the shards hashed what
    /// they computed and served, every byte a stage reads is hashed as it is read
    /// ([`crate::stage::Context::read`]), and re-hashing all of a large cohort's upstream blobs
    /// would read hundreds of gigabytes from the file server. `--verify` keeps the full check.
    pub fn check_sizes_only(&mut self) {
        self.hash_hits = false;
    }

    /// Why `output` cannot be used: missing, of another size, or (with `hash`) corrupt.
    fn blob_fault(&self, output: &OutputRef, hash: bool) -> Option<String> {
        let path = self.blob_path(&output.hash);
        let name = &output.name;
        match fs::metadata(&path) {
            Err(_) => return Some(format!("cached output `{name}` ({}) is missing", path.display())),
            Ok(m) if m.len() != output.size => {
                return Some(format!(
                    "cached output `{name}` ({}) has {} bytes, its manifest says {}",
                    path.display(),
                    m.len(),
                    output.size
                ))
            }
            Ok(_) if !hash => return None,
            Ok(_) => {}
        }
        match hash_file(&path) {
            Ok(h) if h == output.hash => None,
            Ok(h) => {
                Some(format!("cached output `{name}` ({}) is corrupt: its bytes hash to {}", path.display(), h.short()))
            }
            Err(e) => Some(format!("cached output `{name}` ({}) cannot be read: {e}", path.display())),
        }
    }

    /// Looks up (stage, key): a hit only when the manifest parses, describes this stage, key,
    /// unit and inputs, its digest matches (with `verify`, it must have one), and every blob it
    /// names passes [`Store::check_blob`]. A broken entry's reason names the stage, the unit and the
    /// file. A local miss reads through to the remote cache, if there is one.
    pub fn lookup(&self, stage: &str, key: &Hash, expected: &Expected, verify: bool) -> Lookup {
        let path = self.manifest_path(stage, key);
        let text = match fs::read(&path) {
            Ok(t) => t,
            Err(_) => return self.remote().map_or(Lookup::Miss, |r| r.read_through(self, stage, key, expected)),
        };
        let broken = |why: String| Lookup::Broken(format!("{stage} · {}: {why}", expected.unit));
        let manifest: Manifest = match serde_json::from_slice(&text) {
            Ok(m) => m,
            Err(e) => return broken(format!("manifest {} is unreadable: {e}", path.display())),
        };
        if let Some(why) = manifest_mismatch(&manifest, stage, key, expected, verify) {
            return broken(format!("manifest {} {why}", path.display()));
        }
        for output in &manifest.outputs {
            if let Some(why) = self.check_blob(output) {
                return broken(why);
            }
        }
        match self.remote() {
            Some(remote) if remote.fetched(stage, key) => Lookup::Fetched(Box::new(manifest)),
            _ => Lookup::Hit(Box::new(manifest)),
        }
    }

    /// Records a computed stage: manifest last, after its blobs are in place.
    /// Call it with a [sealed](Manifest::sealed) manifest.
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

/// Why `manifest`, found under (stage, key), does not describe that entry, or `None`.
pub(crate) fn manifest_mismatch(
    manifest: &Manifest,
    stage: &str,
    key: &Hash,
    expected: &Expected,
    verify: bool,
) -> Option<String> {
    if manifest.key != *key || manifest.stage != stage {
        return Some(format!("describes {} {}, not this key", manifest.stage, manifest.key.short()));
    }
    if manifest.unit != expected.unit {
        return Some(format!("was computed for `{}`", manifest.unit));
    }
    let same_inputs = manifest.inputs.len() == expected.inputs.len()
        && manifest
            .inputs
            .iter()
            .zip(expected.inputs)
            .all(|(i, (s, n, h))| i.stage == *s && i.name == *n && i.hash == *h);
    if !same_inputs {
        return Some("records other inputs than its key was computed from".into());
    }
    match manifest.digest {
        Some(d) if d != manifest.digest_of() => {
            let names: Vec<&str> = manifest.outputs.iter().map(|o| o.name.as_str()).collect();
            Some(format!(
                "does not match its digest: its outputs ({}) or inputs were changed after it was written",
                names.join(", ")
            ))
        }
        None if verify => {
            Some("records no digest (written by an older aret-pipe), so its outputs cannot be verified".into())
        }
        _ => None,
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
    /// Call only while holding the cache's gc lease with no other lease live ([`crate::lease`]).
    pub fn delete(&self) -> anyhow::Result<()> {
        self.manifests.iter().chain(self.files.iter().map(|f| &f.path)).try_for_each(|path| remove_if_present(path))
    }

    /// Bytes deleting it frees on disk, and bytes it unlinks that out dirs still hold.
    pub fn bytes(&self) -> (u64, u64) {
        let sum = |linked: bool| self.files.iter().filter(|f| f.linked == linked).map(|f| f.bytes).sum();
        (sum(false), sum(true))
    }
}

#[cfg(unix)]
pub(crate) fn links(meta: &fs::Metadata) -> u64 {
    std::os::unix::fs::MetadataExt::nlink(meta)
}

#[cfg(not(unix))]
pub(crate) fn links(_meta: &fs::Metadata) -> u64 {
    1
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
