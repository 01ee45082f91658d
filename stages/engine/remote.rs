//! A remote cache behind the local one: an object store (S3, Google Cloud Storage, Azure Blob
//! Storage, or a folder) that many machines share, laid out as the local cache is:
//!
//! ```text
//! <prefix>/blobs/ab/abcdef…               output bytes, named by their blake3 hash
//! <prefix>/manifests/<stage>/<key>.json   the manifest, as the local cache holds it
//! ```
//! **Read-through:** a local miss asks the remote for the manifest. It is checked as a local one
//! is (stage, key, unit, inputs, digest; a digest is required), each blob it names that the local
//! cache lacks or holds corrupt is downloaded and re-hashed against its name and size *before*
//! it is written locally, then the manifest is written locally: the lookup is a hit, fetched. A
//! remote blob that does not hash to its name makes the entry untrusted (one warning naming the
//! stage, the patient and the remote object); the stage computes locally, and its write-back
//! replaces the bad blob.
//!
//! **Write-back:** a result this process computes, or finds cached locally but absent from the
//! remote, is uploaded: its blobs first (content-addressed, so overwriting is safe; a blob the
//! remote already holds at the right size is skipped, unless it was just found bad), then its
//! manifest, create-only (`PutMode::Create`, `If-None-Match: *` on S3), after a HEAD that finds
//! none. A manifest already there is never replaced: another process computed the same key, and
//! keys name deterministic results. The HEAD keeps that true on a store that ignores the
//! condition; the condition closes the window between HEAD and PUT where the store honours it.
//!
//! **Errors:** a remote that fails mid-run (network, credentials, quota) costs no local work. The
//! first error switches the remote off for the rest of the process, with one warning naming the
//! URL (never credentials) and the error; the run goes on with the local cache alone. A remote
//! that cannot be reached when a run *starts* is a different matter, see [`RemoteCache::probe`].
//!
//! **Credentials** come only from the environment, read by object_store's builders
//! (`AWS_ACCESS_KEY_ID`, `AWS_SECRET_ACCESS_KEY`, `AWS_SESSION_TOKEN`, `AWS_ENDPOINT`,
//! `AWS_REGION`, `AWS_ALLOW_HTTP`; `GOOGLE_SERVICE_ACCOUNT`, …; `AZURE_STORAGE_ACCOUNT_NAME`,
//! `AZURE_STORAGE_ACCOUNT_KEY`, …). A URL holding credentials is refused, and every message this
//! module writes has the values of the credential variables blanked out ([`redact`]).

use super::files::write_atomic;
use super::key::Hash;
use super::store::{manifest_mismatch, Expected, Lookup, Manifest, OutputRef, Remote, Store};
use object_store::path::Path as ObjectPath;
use object_store::{ObjectStore, ObjectStoreExt, ObjectStoreScheme, PutMode, PutOptions, PutPayload};
use std::collections::{HashMap, HashSet};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// The URL forms a remote cache takes, for messages.
pub const SCHEMES: &str = "s3://bucket/prefix (or s3a://), gs://bucket/prefix, az://container/prefix (or \
                           azure://, abfs://, abfss://, adl://, https://ACCOUNT.blob.core.windows.net/container), \
                           or file:///absolute/folder";

/// A remote cache: the object store, the prefix the cache lives under, and a current-thread
/// runtime the synchronous engine blocks on (from any of its worker threads).
pub struct RemoteCache {
    store: Arc<dyn ObjectStore>,
    prefix: ObjectPath,
    /// The URL as messages show it: scheme, host and path only.
    shown: String,
    runtime: tokio::runtime::Runtime,
    /// Set by the first error: no further request is made.
    off: AtomicBool,
    /// Blobs found corrupt or missing on the remote this run, with what was found: not fetched
    /// again, and uploaded again whatever a HEAD says.
    damaged: Mutex<HashMap<Hash, String>>,
    /// The (stage, key) entries this process fetched.
    fetched: Mutex<HashSet<(String, Hash)>>,
    /// Warnings not yet handed to the run ([`Remote::take_notices`]).
    notices: Mutex<Vec<String>>,
}

/// Whether `url` names a remote cache this build can use: `Ok` with the URL as messages show it
/// (no credentials), or why not. Reads no environment and makes no request.
pub fn check_url(url: &str) -> Result<String, String> {
    let parsed = url::Url::parse(url).map_err(|e| format!("`{}` is not a URL ({e})", redact(url)))?;
    let shown = shown_url(&parsed);
    if !parsed.username().is_empty() || parsed.password().is_some() || parsed.query().is_some() {
        return Err(format!(
            "`{shown}` carries credentials or a query: give credentials in the environment (AWS_*, GOOGLE_*, AZURE_*)"
        ));
    }
    match ObjectStoreScheme::parse(&parsed) {
        Ok((
            ObjectStoreScheme::AmazonS3
            | ObjectStoreScheme::GoogleCloudStorage
            | ObjectStoreScheme::MicrosoftAzure
            | ObjectStoreScheme::Local,
            _,
        )) => Ok(shown),
        Ok(_) | Err(_) => Err(format!("`{shown}` is not a remote cache URL")),
    }
}

/// `url` without user, password, query or fragment.
fn shown_url(url: &url::Url) -> String {
    let host = url.host_str().unwrap_or("");
    let port = url.port().map(|p| format!(":{p}")).unwrap_or_default();
    format!("{}://{host}{port}{}", url.scheme(), url.path())
}

/// `text` with the value of every credential variable in the environment blanked out: any
/// `AWS_*`, `GOOGLE_*`, `AZURE_*` or `SERVICE_ACCOUNT` variable whose name says key, secret,
/// token, password, SAS or credential, and the access key id.
pub fn redact(text: &str) -> String {
    let mut out = text.to_string();
    for (name, value) in std::env::vars() {
        let cloud =
            ["AWS_", "GOOGLE_", "AZURE_", "GCS_"].iter().any(|p| name.starts_with(p)) || name == "SERVICE_ACCOUNT";
        let secret = ["KEY", "SECRET", "TOKEN", "PASSWORD", "SAS", "CREDENTIAL", "SERVICE_ACCOUNT"]
            .iter()
            .any(|w| name.contains(w));
        if cloud && secret && value.len() >= 4 {
            out = out.replace(&value, "[redacted]");
        }
    }
    out
}

impl RemoteCache {
    /// The remote cache at `url`, with credentials and endpoint from the environment. Makes no
    /// request ([`RemoteCache::probe`] does).
    pub fn open(url: &str) -> anyhow::Result<RemoteCache> {
        let shown = check_url(url).map_err(|e| anyhow::anyhow!("remote cache: {e}; it takes {SCHEMES}"))?;
        let parsed = url::Url::parse(url)?;
        let (scheme, prefix) = ObjectStoreScheme::parse(&parsed)?;
        // Few, quick retries: a remote that is down should cost a run seconds, not minutes.
        let retry = object_store::RetryConfig {
            backoff: object_store::BackoffConfig::default(),
            max_retries: 3,
            retry_timeout: Duration::from_secs(30),
        };
        let built: object_store::Result<Arc<dyn ObjectStore>> = match scheme {
            ObjectStoreScheme::AmazonS3 => object_store::aws::AmazonS3Builder::from_env()
                .with_url(url)
                .with_retry(retry)
                .build()
                .map(|s| Arc::new(s) as _),
            ObjectStoreScheme::GoogleCloudStorage => object_store::gcp::GoogleCloudStorageBuilder::from_env()
                .with_url(url)
                .with_retry(retry)
                .build()
                .map(|s| Arc::new(s) as _),
            ObjectStoreScheme::MicrosoftAzure => object_store::azure::MicrosoftAzureBuilder::from_env()
                .with_url(url)
                .with_retry(retry)
                .build()
                .map(|s| Arc::new(s) as _),
            ObjectStoreScheme::Local => Ok(Arc::new(object_store::local::LocalFileSystem::new()) as _),
            _ => unreachable!("check_url accepts no other scheme"),
        };
        let store = built.map_err(|e| anyhow::anyhow!("remote cache {shown}: {}", redact(&e.to_string())))?;
        let runtime = tokio::runtime::Builder::new_current_thread().enable_all().build()?;
        Ok(RemoteCache {
            store,
            prefix,
            shown,
            runtime,
            off: AtomicBool::new(false),
            damaged: Mutex::new(HashMap::new()),
            fetched: Mutex::new(HashSet::new()),
            notices: Mutex::new(Vec::new()),
        })
    }

    /// The URL, as messages show it.
    pub fn url(&self) -> &str {
        &self.shown
    }

    /// Lists the prefix once: an error when the remote cannot be reached, the bucket does not
    /// exist or the credentials are refused.
    ///
    /// A run calls it before it starts and stops on its error. A remote configured but
    /// unreachable at the start is nearly always a mistake of configuration (endpoint, bucket,
    /// credentials) rather than an outage, and on a cluster it is made by every shard at once:
    /// failing in seconds, with a message saying how to run without the remote, costs nothing,
    /// whereas computing for hours into node-local caches that the gather never sees loses the
    /// work. Errors after the start are outages: the run goes on locally ([`RemoteCache`]).
    pub fn probe(&self) -> anyhow::Result<()> {
        let listed = self.runtime.block_on(self.store.list_with_delimiter(Some(&self.prefix)));
        listed.map(drop).map_err(|e| {
            anyhow::anyhow!("the remote cache {} cannot be read: {}", self.shown, redact(&e.to_string()).trim_end())
        })
    }

    fn path(&self, rel: &str) -> ObjectPath {
        rel.split('/').fold(self.prefix.clone(), |p, part| p.join(part))
    }

    fn blob_rel(hash: &Hash) -> String {
        let hex = hash.hex();
        format!("blobs/{}/{hex}", &hex[..2])
    }

    fn manifest_rel(stage: &str, key: &Hash) -> String {
        format!("manifests/{stage}/{}.json", key.hex())
    }

    /// `rel` as a full URL, for messages.
    fn shown_object(&self, rel: &str) -> String {
        format!("{}/{rel}", self.shown.trim_end_matches('/'))
    }

    /// Switches the remote off after its first error, with one warning.
    fn fail(&self, doing: &str, e: &object_store::Error) {
        if !self.off.swap(true, Ordering::SeqCst) {
            let error = redact(&e.to_string());
            self.notices.lock().expect("remote notices").push(format!(
                "warning: the remote cache {} failed {doing}: {}; this run goes on with the local cache alone",
                self.shown,
                error.trim_end()
            ));
        }
    }

    fn is_off(&self) -> bool {
        self.off.load(Ordering::SeqCst)
    }

    /// The object's bytes; `Ok(None)` when there is none.
    fn get(&self, rel: &str) -> object_store::Result<Option<Vec<u8>>> {
        let path = self.path(rel);
        self.runtime.block_on(async {
            match self.store.get(&path).await {
                Ok(found) => Ok(Some(found.bytes().await?.to_vec())),
                Err(object_store::Error::NotFound { .. }) => Ok(None),
                Err(e) => Err(e),
            }
        })
    }

    /// The object's size; `Ok(None)` when there is none.
    fn head(&self, rel: &str) -> object_store::Result<Option<u64>> {
        match self.runtime.block_on(self.store.head(&self.path(rel))) {
            Ok(meta) => Ok(Some(meta.size)),
            Err(object_store::Error::NotFound { .. }) => Ok(None),
            Err(e) => Err(e),
        }
    }

    fn put(&self, rel: &str, bytes: Vec<u8>, mode: PutMode) -> object_store::Result<()> {
        let opts = PutOptions { mode, ..Default::default() };
        self.runtime.block_on(self.store.put_opts(&self.path(rel), PutPayload::from(bytes), opts)).map(drop)
    }

    /// The blob `output` names, fetched, checked and written into `store`; `Err` with why the
    /// entry cannot be used, `Ok(false)` when the remote failed (it is off now).
    fn fetch_blob(&self, store: &Store, output: &OutputRef) -> Result<bool, String> {
        let rel = Self::blob_rel(&output.hash);
        let shown = self.shown_object(&rel);
        if let Some(why) = self.damaged.lock().expect("damaged blobs").get(&output.hash) {
            return Err(why.clone());
        }
        let bad = |why: String| {
            self.damaged.lock().expect("damaged blobs").insert(output.hash, why.clone());
            Err(why)
        };
        let bytes = match self.get(&rel) {
            Ok(Some(bytes)) => bytes,
            Ok(None) => return bad(format!("remote object {shown} (`{}`) is missing", output.name)),
            Err(e) => {
                self.fail(&format!("reading {shown}"), &e);
                return Ok(false);
            }
        };
        let hash = Hash::of(&bytes);
        if hash != output.hash || bytes.len() as u64 != output.size {
            return bad(format!(
                "remote object {shown} (`{}`) is corrupt: its {} bytes hash to {} (its manifest says {} bytes)",
                output.name,
                bytes.len(),
                hash.short(),
                output.size
            ));
        }
        write_atomic(&store.blob_path(&output.hash), &bytes, true).map_err(|e| format!("{e:#}"))?;
        Ok(true)
    }
}

impl Remote for RemoteCache {
    fn read_through(&self, store: &Store, stage: &str, key: &Hash, expected: &Expected) -> Lookup {
        if self.is_off() {
            return Lookup::Miss;
        }
        let rel = Self::manifest_rel(stage, key);
        let shown = self.shown_object(&rel);
        let text = match self.get(&rel) {
            Ok(Some(text)) => text,
            Ok(None) => return Lookup::Miss,
            Err(e) => {
                self.fail(&format!("reading {shown}"), &e);
                return Lookup::Miss;
            }
        };
        let broken = |why: String| Lookup::Broken(format!("{stage} · {}: {why}", expected.unit));
        let manifest: Manifest = match serde_json::from_slice(&text) {
            Ok(m) => m,
            Err(e) => return broken(format!("remote manifest {shown} is unreadable: {e}")),
        };
        // A remote manifest always needs a digest: every aret-pipe that writes one records it.
        if let Some(why) = manifest_mismatch(&manifest, stage, key, expected, true) {
            return broken(format!("remote manifest {shown} {why}"));
        }
        for output in &manifest.outputs {
            if store.check_blob(output).is_none() {
                continue;
            }
            match self.fetch_blob(store, output) {
                Ok(true) => {}
                Ok(false) => return Lookup::Miss,
                Err(why) => return broken(why),
            }
        }
        match store.put_manifest(&manifest) {
            Ok(()) => {
                self.fetched.lock().expect("fetched entries").insert((stage.to_string(), *key));
                Lookup::Fetched(Box::new(manifest))
            }
            Err(e) => broken(format!("fetched from the remote, but {e:#}")),
        }
    }

    fn share(&self, store: &Store, manifest: &Manifest) {
        if self.is_off() {
            return;
        }
        let rel = Self::manifest_rel(&manifest.stage, &manifest.key);
        let damaged: HashSet<Hash> = {
            let all = self.damaged.lock().expect("damaged blobs");
            manifest.outputs.iter().map(|o| o.hash).filter(|h| all.contains_key(h)).collect()
        };
        let present = match self.head(&rel) {
            Ok(size) => size.is_some(),
            Err(e) => return self.fail(&format!("looking up {}", self.shown_object(&rel)), &e),
        };
        // Whoever put the manifest put its blobs first: nothing to do unless one was found bad.
        if present && damaged.is_empty() {
            return;
        }
        for output in &manifest.outputs {
            let blob = Self::blob_rel(&output.hash);
            if !damaged.contains(&output.hash) {
                match self.head(&blob) {
                    Ok(Some(size)) if size == output.size => continue,
                    Ok(_) => {}
                    Err(e) => return self.fail(&format!("looking up {}", self.shown_object(&blob)), &e),
                }
            }
            let bytes = match std::fs::read(store.blob_path(&output.hash)) {
                Ok(bytes) => bytes,
                // The local blob went (gc): the next run that computes it shares it.
                Err(_) => return,
            };
            if let Err(e) = self.put(&blob, bytes, PutMode::Overwrite) {
                return self.fail(&format!("writing {}", self.shown_object(&blob)), &e);
            }
            self.damaged.lock().expect("damaged blobs").remove(&output.hash);
        }
        if present {
            return;
        }
        let bytes = match serde_json::to_vec_pretty(manifest) {
            Ok(bytes) => bytes,
            Err(_) => return,
        };
        match self.put(&rel, bytes, PutMode::Create) {
            // Another process shared the same key first: its result is this one.
            Ok(()) | Err(object_store::Error::AlreadyExists { .. }) => {}
            Err(e) => self.fail(&format!("writing {}", self.shown_object(&rel)), &e),
        }
    }

    fn fetched(&self, stage: &str, key: &Hash) -> bool {
        self.fetched.lock().expect("fetched entries").contains(&(stage.to_string(), *key))
    }

    fn take_notices(&self) -> Vec<String> {
        std::mem::take(&mut *self.notices.lock().expect("remote notices"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn check_url_takes_the_object_stores_and_shows_no_credentials() {
        for url in ["s3://bucket/prefix", "s3a://b/p", "gs://bucket/p", "az://c/p", "azure://c/p", "file:///tmp/c"] {
            assert!(check_url(url).is_ok(), "{url}");
        }
        assert_eq!(check_url("s3://bucket:9000/a/b").unwrap(), "s3://bucket:9000/a/b");
        for url in ["memory:///", "http://host/p", "ftp://h/p", "cache", "file://relative/p"] {
            assert!(check_url(url).is_err(), "{url}");
        }
        let e = check_url("s3://AKIDEXAMPLE:TOPSECRET@bucket/p?token=TOKENVALUE").unwrap_err();
        assert!(e.contains("s3://bucket/p") && !e.contains("TOPSECRET") && !e.contains("TOKENVALUE"), "{e}");
    }

    #[test]
    fn a_remote_behind_a_store_serves_a_miss_and_refuses_a_corrupt_blob() {
        let dir = std::env::temp_dir().join(format!("aret-remote-test-{}", std::process::id()));
        let (here, there) = (Store::open(&dir.join("here")).unwrap(), dir.join("there"));
        std::fs::create_dir_all(&there).unwrap();
        let remote = Arc::new(RemoteCache::open(&format!("file://{}", there.display())).unwrap());
        remote.probe().unwrap();
        let maker = Store::open(&dir.join("maker")).unwrap();
        let output = maker.put_blob("x.bin", b"remote bytes").unwrap();
        let inputs = vec![("source".to_string(), "a".to_string(), Hash::of(b"a"))];
        let manifest = Manifest {
            stage: "s".into(),
            version: 1,
            key: Hash::of(b"key"),
            unit: "P1".into(),
            params: serde_json::json!({}),
            inputs: vec![super::super::store::InputRef {
                stage: "source".into(),
                name: "a".into(),
                hash: Hash::of(b"a"),
            }],
            outputs: vec![output.clone()],
            wall_seconds: 1.0,
            tool_version: "test".into(),
            created_unix: 0,
            digest: None,
        }
        .sealed();
        remote.share(&maker, &manifest);
        assert!(remote.take_notices().is_empty());
        let expected = Expected { unit: "P1", inputs: &inputs };
        let here = here.with_remote(remote.clone());
        assert!(matches!(here.lookup("s", &manifest.key, &expected, false), Lookup::Fetched(_)));
        // Held locally now; this process still reports it as fetched, another would not.
        assert!(matches!(here.lookup("s", &manifest.key, &expected, false), Lookup::Fetched(_)));
        let later = Store::open(&dir.join("here")).unwrap();
        assert!(matches!(later.lookup("s", &manifest.key, &expected, false), Lookup::Hit(_)));
        // Corrupt on the remote: a fresh local cache refuses it, naming the object.
        let object = there.join(RemoteCache::blob_rel(&output.hash));
        std::fs::write(&object, b"remote bytez").unwrap();
        let fresh = Store::open(&dir.join("fresh")).unwrap().with_remote(remote.clone());
        match fresh.lookup("s", &manifest.key, &expected, false) {
            Lookup::Broken(why) => {
                assert!(why.starts_with("s · P1: remote object file://") && why.contains("corrupt"), "{why}")
            }
            _ => panic!("a corrupt remote blob was served"),
        }
        // Sharing the entry again repairs the blob, though the manifest is there already.
        remote.share(&maker, &manifest);
        assert_eq!(std::fs::read(&object).unwrap(), b"remote bytes");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_remote_that_fails_is_switched_off_with_one_warning() {
        let dir = std::env::temp_dir().join(format!("aret-remote-off-{}", std::process::id()));
        let there = dir.join("there");
        std::fs::create_dir_all(&there).unwrap();
        // A file where the blobs' folder should be: every upload fails.
        std::fs::write(there.join("blobs"), b"not a folder").unwrap();
        let remote = RemoteCache::open(&format!("file://{}", there.display())).unwrap();
        let store = Store::open(&dir.join("here")).unwrap();
        let made = |text: &[u8]| {
            let output = store.put_blob("x.bin", text).unwrap();
            Manifest {
                stage: "s".into(),
                version: 1,
                key: Hash::of(text),
                unit: "P1".into(),
                params: serde_json::json!({}),
                inputs: vec![],
                outputs: vec![output],
                wall_seconds: 1.0,
                tool_version: "test".into(),
                created_unix: 0,
                digest: None,
            }
            .sealed()
        };
        remote.share(&store, &made(b"one"));
        remote.share(&store, &made(b"two"));
        let notices = remote.take_notices();
        assert_eq!(notices.len(), 1, "{notices:?}");
        assert!(notices[0].contains(&format!("the remote cache file://{}", there.display())), "{notices:?}");
        assert!(notices[0].contains("goes on with the local cache alone"), "{notices:?}");
        // Off: no further request, so a lookup through it is a plain miss.
        std::fs::remove_file(there.join("blobs")).unwrap();
        let expected = Expected { unit: "P1", inputs: &[] };
        assert!(matches!(remote.read_through(&store, "s", &Hash::of(b"one"), &expected), Lookup::Miss));
        remote.share(&store, &made(b"three"));
        assert!(!there.join("blobs").exists() && remote.take_notices().is_empty());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
