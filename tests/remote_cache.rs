//! The remote cache (`[pipeline] cache_remote`) against a real S3-compatible server, s3s-fs,
//! started by the test on a free localhost port: a second machine (an empty local cache)
//! computes nothing and publishes the same bytes; a corrupt remote blob is found, computed again
//! and repaired; a gather on an empty cache fetches the shards' results; no credential reaches
//! any file or output; a bad URL and an unreachable remote are refused at the start.
//!
//! s3s-fs comes from `ARET_S3S_FS` or `PATH` (`cargo install s3s-fs --version 0.14.1 --features
//! binary --locked`); without it the server tests are skipped with a line saying so, and fail
//! when `CI` is `true`.

mod support;

use serde_json::Value;
use std::net::{TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};
use support::dicom_writer::{default_name, series, write_series};

const BIN: &str = env!("CARGO_BIN_EXE_aret-pipe");
const BUCKET: &str = "aret-cache";
const PREFIX: &str = "team/cache";
/// Distinctive credentials: no file or output of a run may contain them.
const ACCESS_KEY: &str = "ARETKEYID7Q2X9ZW";
const SECRET_KEY: &str = "aret-secret-5b4a3c2d1e0f9a8b";

/// The s3s-fs binary, or `None` (after saying why) when it is not installed and CI is not set.
fn s3s_fs() -> Option<PathBuf> {
    let found = std::env::var_os("ARET_S3S_FS").map(PathBuf::from).filter(|p| p.is_file()).or_else(|| {
        std::env::split_paths(&std::env::var_os("PATH").unwrap_or_default())
            .map(|dir| dir.join("s3s-fs"))
            .find(|p| p.is_file())
    });
    if found.is_none() {
        let why =
            "s3s-fs not found (ARET_S3S_FS or PATH): cargo install s3s-fs --version 0.14.1 --features binary --locked";
        assert!(std::env::var("CI").as_deref() != Ok("true"), "{why}");
        eprintln!("skipped: {why}");
    }
    found
}

/// An s3s-fs server on a free localhost port, serving a temporary folder with one bucket.
struct Server {
    child: Child,
    root: tempfile::TempDir,
    port: u16,
}

impl Server {
    fn start(binary: &Path) -> Server {
        let root = tempfile::tempdir().unwrap();
        std::fs::create_dir(root.path().join(BUCKET)).unwrap();
        let port = TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
        let child = Command::new(binary)
            .args(["--host", "127.0.0.1", "--port", &port.to_string()])
            .args(["--access-key", ACCESS_KEY, "--secret-key", SECRET_KEY])
            .arg(root.path())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        let server = Server { child, root, port };
        let started = Instant::now();
        while TcpStream::connect(("127.0.0.1", port)).is_err() {
            assert!(started.elapsed() < Duration::from_secs(20), "s3s-fs did not listen on port {port}");
            std::thread::sleep(Duration::from_millis(50));
        }
        server
    }

    /// The folder holding the cache's objects.
    fn objects(&self) -> PathBuf {
        self.root.path().join(BUCKET).join(PREFIX)
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A dataset of two small CT series and configurations that each name their own local cache.
struct Project {
    dir: tempfile::TempDir,
    endpoint: String,
}

impl Project {
    fn new(endpoint: String) -> Project {
        let p = Project { dir: tempfile::tempdir().unwrap(), endpoint };
        for (n, id) in ["P1", "P2"].iter().enumerate() {
            let mut specs = series(3);
            for s in &mut specs {
                s.intercept = Some(-1024.0 + n as f64);
            }
            let dir = p.path(&format!("data/{id}/series"));
            std::fs::create_dir_all(&dir).unwrap();
            write_series(&dir, &specs, default_name);
        }
        p
    }

    /// `<name>.toml`: a tiny run (the engine is under test) with cache `cache-<name>`, out dir
    /// `out-<name>`, the remote cache `remote` and `extra` tables.
    fn config(&self, name: &str, remote: &str, extra: &str) -> String {
        let text = format!(
            "[pipeline]\nname = \"test\"\ncache_dir = \"cache-{name}\"\nout_dir = \"out-{name}\"\nworkers = 2\n\
             cache_remote = \"{remote}\"\n\
             [dataset]\nkind = \"dicom\"\nroot = \"data\"\n\
             [drr]\nroi_center = [0.0, 0.0, 0.0]\nwidth_px = 32\nheight_px = 32\n\
             [train]\nmodel = \"vm\"\ngrid = 8\nlog_every = 1\n\
             [train.vm]\niterations = 3\nrank = 2\nbatch_rays = 64\n\
             [sweep]\nscore = \"density\"\nregion = \"box\"\n[select]\nlocalize = \"none\"\nsizing = \"candidates\"\n{extra}"
        );
        let file = format!("{name}.toml");
        std::fs::write(self.path(&file), text).unwrap();
        file
    }

    fn path(&self, rel: &str) -> PathBuf {
        self.dir.path().join(rel)
    }

    /// `aret-pipe ARGS` with the server's endpoint and the given credentials.
    fn aret(&self, args: &[&str], access_key: &str, secret_key: &str) -> Output {
        let mut command = Command::new(BIN);
        command.args(args).current_dir(self.dir.path()).env("CI", "true");
        for (name, _) in std::env::vars().filter(|(n, _)| n.starts_with("AWS_")) {
            command.env_remove(name);
        }
        command
            .env("AWS_ACCESS_KEY_ID", access_key)
            .env("AWS_SECRET_ACCESS_KEY", secret_key)
            .env("AWS_ENDPOINT", &self.endpoint)
            .env("AWS_ALLOW_HTTP", "true")
            .env("AWS_REGION", "us-east-1");
        command.output().unwrap()
    }

    /// A run that must succeed: its report, and its stdout and stderr.
    fn run(&self, name: &str, tables: &str, flags: &[&str]) -> (Value, String) {
        let file = self.config(name, &format!("s3://{BUCKET}/{PREFIX}"), tables);
        let mut args = vec!["run", file.as_str()];
        args.extend_from_slice(flags);
        let started = Instant::now();
        let out = self.aret(&args, ACCESS_KEY, SECRET_KEY);
        let said = format!("{}{}", text(&out.stdout), text(&out.stderr));
        assert!(out.status.success(), "run {name} failed:\n{said}");
        eprintln!("run {name} {flags:?}: {:.1} s", started.elapsed().as_secs_f64());
        let report = std::fs::read(self.path(&format!("out-{name}/run_report.json"))).unwrap();
        (serde_json::from_slice(&report).unwrap(), said)
    }
}

fn text(b: &[u8]) -> String {
    String::from_utf8_lossy(b).into_owned()
}

/// The report's outcomes, `(unit, stage) → outcome`.
fn outcomes(report: &Value) -> Vec<(String, String, String)> {
    let records = report["records"].as_array().unwrap();
    records
        .iter()
        .map(|r| {
            (
                r["unit"].as_str().unwrap().into(),
                r["stage"].as_str().unwrap().into(),
                r["outcome"].as_str().unwrap().into(),
            )
        })
        .collect()
}

/// Every file under `dir`, relative, with its bytes.
fn files(dir: &Path) -> Vec<(PathBuf, Vec<u8>)> {
    let mut out: Vec<(PathBuf, Vec<u8>)> = walkdir::WalkDir::new(dir)
        .into_iter()
        .map(|e| e.unwrap())
        .filter(|e| e.file_type().is_file())
        .map(|e| (e.path().strip_prefix(dir).unwrap().to_path_buf(), std::fs::read(e.path()).unwrap()))
        .collect();
    out.sort();
    out
}

/// The hash of `stage`'s largest output for `unit` (one no other entry holds), from a local
/// cache's manifests.
fn blob_of(cache: &Path, stage: &str, unit: &str) -> String {
    for entry in std::fs::read_dir(cache.join("manifests").join(stage)).unwrap() {
        let manifest: Value = serde_json::from_slice(&std::fs::read(entry.unwrap().path()).unwrap()).unwrap();
        if manifest["unit"] == unit {
            let outputs = manifest["outputs"].as_array().unwrap();
            let largest = outputs.iter().max_by_key(|o| o["size"].as_u64().unwrap()).unwrap();
            return largest["hash"].as_str().unwrap().to_string();
        }
    }
    panic!("no manifest of {stage} for {unit} in {}", cache.display());
}

#[test]
fn machines_share_results_through_s3_and_a_corrupt_remote_blob_is_recomputed_and_repaired() {
    let Some(binary) = s3s_fs() else { return };
    let server = Server::start(&binary);
    let p = Project::new(format!("http://127.0.0.1:{}", server.port));
    let mut said = Vec::new();

    // The first machine computes everything and uploads it.
    let (first, out) = p.run("a", "", &[]);
    said.push(out);
    let all = outcomes(&first);
    assert!(all.len() > 8 && all.iter().all(|(_, _, o)| o == "computed"), "{all:?}");
    assert!(server.objects().join("manifests").join("hu").is_dir(), "nothing uploaded");

    // A second machine, its local cache empty, computes nothing and publishes the same bytes.
    let (second, out) = p.run("b", "", &[]);
    let fetched = outcomes(&second);
    assert!(fetched.iter().all(|(_, _, o)| o == "fetched"), "{fetched:?}");
    assert_eq!(second["fetched_from_remote"], all.len());
    assert!(out.contains(&format!("{} fetched from the remote cache", all.len())), "{out}");
    said.push(out);
    let published = |name: &str| {
        let mut f = files(&p.path(&format!("out-{name}")));
        f.retain(|(path, _)| path != Path::new("run_report.json"));
        f
    };
    let (a, b) = (published("a"), published("b"));
    assert!(a.len() > 8, "{} files published", a.len());
    assert!(a == b, "the second machine's outputs differ from the first's");

    // A remote blob corrupted in place: a third machine finds it, computes that entry, and
    // uploads the right bytes over it.
    let hash = blob_of(&p.path("cache-a"), "hu", "P1");
    let object = server.objects().join("blobs").join(&hash[..2]).join(&hash);
    let mut bytes = std::fs::read(&object).unwrap();
    let middle = bytes.len() / 2;
    bytes[middle] ^= 0x5a;
    std::fs::write(&object, &bytes).unwrap();
    let (third, out) = p.run("c", "", &[]);
    let warning =
        out.lines().find(|l| l.contains("warning: hu · P1: remote object")).unwrap_or_else(|| panic!("{out}"));
    assert!(
        warning.contains(&format!("{PREFIX}/blobs/{}/{hash}", &hash[..2])) && warning.contains("is corrupt"),
        "{warning}"
    );
    assert!(warning.contains("computing it again"), "{warning}");
    let rows = outcomes(&third);
    let computed: Vec<_> = rows.iter().filter(|(_, _, o)| o == "computed").collect();
    assert_eq!(computed, [&("P1".to_string(), "hu".to_string(), "computed".to_string())], "{rows:?}");
    assert!(rows.iter().filter(|(_, _, o)| o == "fetched").count() == rows.len() - 1, "{rows:?}");
    let repaired = std::fs::read(&object).unwrap();
    assert_eq!(blake3::hash(&repaired).to_hex().as_str(), hash, "the remote blob was not repaired");
    assert!(published("c") == a, "the third machine's outputs differ from the first's");
    said.push(out);

    // Shards on two machines (another hu_min: hu and drr compute again, and the rest comes out
    // the same; another metrics seed: a new cohort result), then a gather on a third with an
    // empty cache: its check for missing patients and its cohort stage read the shards' results
    // from the remote.
    let edited = "[hu]\nhu_min = -900.0\n[metrics]\nseed = 7\n";
    let mut shards = Vec::new();
    for (name, shard) in [("s0", "0/2"), ("s1", "1/2")] {
        let (report, out) = p.run(name, edited, &["--shard", shard]);
        shards.extend(outcomes(&report));
        said.push(out);
    }
    for unit in ["P1", "P2"] {
        for (stage, want) in [("ingest", "fetched"), ("hu", "computed"), ("drr", "computed"), ("select", "fetched")] {
            let got = shards.iter().find(|(u, s, _)| u == unit && s == stage).map(|r| r.2.as_str());
            assert_eq!(got, Some(want), "{unit} · {stage} in the shards: {shards:?}");
        }
    }
    let (gathered, out) = p.run("g", edited, &["--gather"]);
    let rows = outcomes(&gathered);
    assert!(rows.iter().all(|(unit, _, o)| (unit == "cohort") == (o == "computed")), "{rows:?}");
    assert_eq!(rows.len(), 2 * 7 + 1, "{rows:?}");
    said.push(out);

    // A wrong secret: the run stops at once, naming the remote, and says neither key.
    let file = p.config("d", &format!("s3://{BUCKET}/{PREFIX}"), "");
    let wrong_secret = "aret-wrong-secret-77e1c0ffee";
    let out = p.aret(&["run", &file], ACCESS_KEY, wrong_secret);
    let refused = format!("{}{}", text(&out.stdout), text(&out.stderr));
    assert!(!out.status.success(), "{refused}");
    assert!(refused.contains(&format!("s3://{BUCKET}/{PREFIX}")) && refused.contains("cache_remote"), "{refused}");
    assert!(!refused.contains(wrong_secret), "{refused}");
    said.push(refused);

    // No credential in anything the runs wrote or said.
    for secret in [ACCESS_KEY, SECRET_KEY, wrong_secret] {
        for (i, output) in said.iter().enumerate() {
            assert!(!output.contains(secret), "output {i} holds a credential:\n{output}");
        }
        for (path, bytes) in files(p.dir.path()) {
            let holds = bytes.windows(secret.len()).any(|w| w == secret.as_bytes());
            assert!(!holds, "{} holds a credential", path.display());
        }
    }
}

#[test]
fn a_bad_cache_remote_is_refused_naming_the_key_the_file_and_the_schemes() {
    let p = Project::new("http://127.0.0.1:9".into());
    for url in ["ftp://host/cache", "bucket/prefix", "s3://KEYID:HUNTER22@bucket/p"] {
        let file = p.config("bad", url, "");
        let out = p.aret(&["run", &file], ACCESS_KEY, SECRET_KEY);
        let said = text(&out.stderr);
        assert!(!out.status.success(), "{url}: {said}");
        assert!(
            said.contains("bad.toml") && said.contains("line 6") && said.contains("[pipeline] cache_remote"),
            "{said}"
        );
        assert!(said.contains("s3://bucket/prefix") && said.contains("gs://") && said.contains("az://"), "{said}");
        assert!(!said.contains("HUNTER22"), "{said}");
    }
}

#[test]
fn an_unreachable_remote_stops_a_run_at_the_start_saying_how_to_run_without_it() {
    // A port nothing listens on.
    let port = TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let p = Project::new(format!("http://127.0.0.1:{port}"));
    let file = p.config("down", &format!("s3://{BUCKET}/{PREFIX}"), "");
    let started = Instant::now();
    let out = p.aret(&["run", &file], ACCESS_KEY, SECRET_KEY);
    let said = text(&out.stderr);
    assert!(!out.status.success(), "{said}");
    assert!(said.contains(&format!("the remote cache s3://{BUCKET}/{PREFIX} cannot be read")), "{said}");
    assert!(said.contains("--set pipeline.cache_remote=''"), "{said}");
    assert!(started.elapsed() < Duration::from_secs(60), "it took {:?} to give up", started.elapsed());
    assert!(!p.path("out-down").exists(), "it ran");
    // Without the remote it runs.
    let out = p.aret(&["run", &file, "--until", "hu", "--set", "pipeline.cache_remote=''"], ACCESS_KEY, SECRET_KEY);
    assert!(out.status.success(), "{}", text(&out.stderr));
}
