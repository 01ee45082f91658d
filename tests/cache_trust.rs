//! The cache against bytes and files that changed behind its back, on toy stages: flipped bytes
//! in blobs, manifests pointing at other valid blobs, edits through published links, the
//! temporary files of killed runs, and waits for other processes' locks.

use aret_pipe::engine::lock::FileLock;
use aret_pipe::engine::preview::{self, State};
use aret_pipe::engine::progress::{self, Progress};
use aret_pipe::engine::run::{self, Publish, RunOptions, RunSummary, StopRequest, Unit};
use aret_pipe::engine::store::{Manifest, Store};
use aret_pipe::engine::{files, lease, leftovers};
use aret_pipe::engine::{Context, Hash, Output, Stage, StageGraph};
use std::path::{Path, PathBuf};
use std::time::Duration;

mod support;
use support::leases::pretend_lease;
use support::toy_stages::{ended_pid, Concat, Counters, Length, Report};

/// Two patients (P1: "ab" + "cde", P2: "xyz") and a cache, counting each stage's runs.
struct World {
    dir: tempfile::TempDir,
    counters: Counters,
}

/// Every file the first run publishes, with its bytes.
const PUBLISHED: [(&str, &str); 7] = [
    ("P1/all.txt", "abcde"),
    ("P1/files.txt", "2"),
    ("P1/len.txt", "5"),
    ("P2/all.txt", "xyz"),
    ("P2/files.txt", "1"),
    ("P2/len.txt", "3"),
    ("report.txt", "P1 5\nP2 3\n"),
];

impl World {
    fn new() -> World {
        let dir = tempfile::tempdir().unwrap();
        for (rel, text) in [("P1/a.txt", "ab"), ("P1/b.txt", "cde"), ("P2/x.txt", "xyz")] {
            let path = dir.path().join("data").join(rel);
            std::fs::create_dir_all(path.parent().unwrap()).unwrap();
            std::fs::write(path, text).unwrap();
        }
        World { dir, counters: Counters::default() }
    }

    /// A world after one full run, its counters reset.
    fn cached() -> World {
        let w = World::new();
        w.run(Publish::Links, false);
        w.take();
        w
    }

    fn graph(&self) -> StageGraph {
        let c = &self.counters;
        StageGraph::new(vec![
            Box::new(Concat { sep: String::new(), runs: c.concat.clone(), stop: StopRequest::default() }),
            Box::new(Length { parity_only: false, runs: c.length.clone() }),
            Box::new(Report { runs: c.report.clone() }),
        ])
        .unwrap()
    }

    fn units(&self) -> Vec<Unit> {
        ["P1", "P2"].iter().map(|p| Unit::folder(*p, self.path(&format!("data/{p}")))).collect()
    }

    fn store(&self) -> Store {
        Store::open(&self.path("cache")).unwrap()
    }

    fn run(&self, publish: Publish, verify: bool) -> RunSummary {
        let options = RunOptions {
            verify,
            force: vec![],
            workers: Default::default(),
            default_workers: 2,
            out_dir: self.path("out"),
            publish,
            stop: StopRequest::default(),
        };
        let s = run::run(&self.graph(), &self.store(), &self.units(), &options, &Progress::hidden(&[]));
        assert_eq!(s.failures().count(), 0, "{:?}", s.records);
        s
    }

    /// How many times concat, length and report ran since the last call.
    fn take(&self) -> [usize; 3] {
        self.counters.take()
    }

    fn path(&self, rel: &str) -> PathBuf {
        self.dir.path().join(rel)
    }

    fn assert_published_right(&self) {
        for (rel, text) in PUBLISHED {
            assert_eq!(std::fs::read_to_string(self.path("out").join(rel)).unwrap(), text, "out/{rel}");
        }
    }

    /// Every manifest in the cache with its path.
    fn manifests(&self) -> Vec<(PathBuf, Manifest)> {
        let mut out = Vec::new();
        for stage in ["concat", "length", "report"] {
            for entry in std::fs::read_dir(self.path("cache/manifests").join(stage)).unwrap() {
                let path = entry.unwrap().path();
                out.push((path.clone(), serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap()));
            }
        }
        out
    }

    fn manifest(&self, stage: &str, unit: &str) -> (PathBuf, Manifest) {
        self.manifests().into_iter().find(|(_, m)| m.stage == stage && m.unit == unit).unwrap()
    }

    /// The reason `status --verify` gives for (unit, stage), or `None` when it is cached.
    fn status_reason(&self, unit: &str, stage: &str) -> Option<String> {
        let rows = preview::preview(&self.graph(), &self.store(), &self.units(), true, &[]);
        match &rows.iter().find(|r| r.unit == unit && r.stage == stage).unwrap().state {
            State::Cached { .. } => None,
            State::Compute(reasons) => Some(reasons.join("; ")),
            other => panic!("{unit} · {stage}: {other:?}"),
        }
    }
}

fn make_writable(path: &Path) {
    let mut perms = std::fs::metadata(path).unwrap().permissions();
    #[allow(clippy::permissions_set_readonly_false)]
    perms.set_readonly(false);
    std::fs::set_permissions(path, perms).unwrap();
}

fn flip_byte(path: &Path, at: usize) {
    make_writable(path);
    let mut bytes = std::fs::read(path).unwrap();
    bytes[at] ^= 0x01;
    std::fs::write(path, bytes).unwrap();
}

fn write_manifest(path: &Path, manifest: &Manifest) {
    std::fs::write(path, serde_json::to_vec_pretty(manifest).unwrap()).unwrap();
}

#[cfg(unix)]
fn mode(path: &Path) -> u32 {
    std::os::unix::fs::PermissionsExt::mode(&std::fs::metadata(path).unwrap().permissions()) & 0o777
}

#[cfg(unix)]
fn inode(path: &Path) -> u64 {
    std::os::unix::fs::MetadataExt::ino(&std::fs::metadata(path).unwrap())
}

/// The stage's counter index in [`World::take`].
fn index(stage: &str) -> usize {
    ["concat", "length", "report"].iter().position(|s| *s == stage).unwrap()
}

#[test]
fn a_flipped_byte_in_any_blob_is_found_and_its_stage_computed_again() {
    // Every blob of every result, flipped at its first, middle and last byte (once when those
    // coincide): 13 corruptions.
    let mut cases = Vec::new();
    for (_, m) in World::cached().manifests() {
        for output in &m.outputs {
            let mut at = vec![0, output.size as usize / 2, output.size as usize - 1];
            at.dedup();
            cases.extend(at.into_iter().map(|at| (m.stage.clone(), m.unit.clone(), output.clone(), at)));
        }
    }
    assert_eq!(cases.len(), 13);
    for (stage, unit, output, at) in cases {
        let w = World::cached();
        let blob = w.store().blob_path(&output.hash);
        flip_byte(&blob, at);
        let case = format!("{stage} · {unit}: `{}` flipped at byte {at}", output.name);
        let reason = w.status_reason(&unit, &stage).unwrap_or_else(|| panic!("status calls it cached: {case}"));
        assert!(reason.contains(&blob.display().to_string()), "{case}: {reason}");
        let s = w.run(Publish::Links, false);
        let mut expected = [0; 3];
        expected[index(&stage)] = 1;
        assert_eq!(w.take(), expected, "{case}: only its stage recomputes (to the same bytes)");
        assert_eq!(s.notices.len(), 1, "{case}: {:?}", s.notices);
        let warning = &s.notices[0];
        for part in ["warning", &stage, &unit, &output.name, &blob.display().to_string()] {
            assert!(warning.contains(part), "{case}: the warning names {part}: {warning}");
        }
        assert_eq!(Hash::of(&std::fs::read(&blob).unwrap()), output.hash, "{case}: the blob is replaced");
        w.assert_published_right();
        assert_eq!(w.status_reason(&unit, &stage), None, "{case}");
    }
}

#[test]
fn a_manifest_that_does_not_match_its_key_or_digest_is_found() {
    // Each edit keeps the manifest valid JSON naming blobs that exist with their right sizes.
    type Edit = fn(&World, &mut Manifest);
    let edits: [(&str, &str, &str, Edit); 5] = [
        ("P1", "concat", "digest", |w, m| {
            // P1's all.txt → P2's all.txt blob.
            m.outputs[0] = w.manifest("concat", "P2").1.outputs[0].clone();
            m.outputs[0].name = "all.txt".into();
        }),
        ("P1", "length", "digest", |w, m| {
            // P1's length "5" → P2's "3", the same size.
            m.outputs[0].hash = w.manifest("length", "P2").1.outputs[0].hash;
        }),
        ("cohort", "report", "digest", |w, m| {
            m.outputs[0].hash = w.manifest("concat", "P1").1.outputs[0].hash;
            m.outputs[0].size = 5;
        }),
        ("P1", "concat", "computed for `P2`", |w, m| {
            // P2's manifest copied over P1's, its key rewritten.
            let key = m.key;
            *m = w.manifest("concat", "P2").1;
            m.key = key;
        }),
        ("P1", "length", "other inputs", |w, m| {
            m.inputs[0].hash = w.manifest("concat", "P2").1.outputs[0].hash;
        }),
    ];
    for (unit, stage, says, edit) in edits {
        let w = World::cached();
        let (path, mut manifest) = w.manifest(stage, unit);
        edit(&w, &mut manifest);
        write_manifest(&path, &manifest);
        let case = format!("{stage} · {unit} ({says})");
        let reason = w.status_reason(unit, stage).unwrap_or_else(|| panic!("status --verify calls it cached: {case}"));
        for part in [stage, unit, &path.display().to_string(), says] {
            assert!(reason.contains(part), "{case}: the reason names {part}: {reason}");
        }
        let s = w.run(Publish::Links, true);
        let mut expected = [0; 3];
        expected[index(stage)] = 1;
        assert_eq!(w.take(), expected, "{case}: only its stage recomputes");
        assert!(s.notices.len() == 1 && s.notices[0].contains(&path.display().to_string()), "{case}: {:?}", s.notices);
        w.assert_published_right();
        assert_eq!(w.status_reason(unit, stage), None, "{case}: its manifest is whole again");
    }
}

#[test]
fn a_manifest_without_a_digest_is_trusted_by_a_run_and_computed_again_by_verify() {
    let w = World::cached();
    let (path, mut manifest) = w.manifest("length", "P2");
    manifest.digest = None;
    write_manifest(&path, &manifest);
    assert!(!std::fs::read_to_string(&path).unwrap().contains("digest"), "written as an older aret-pipe would");
    let s = w.run(Publish::Links, false);
    assert_eq!((w.take(), s.notices.len()), ([0, 0, 0], 0), "its blobs re-hash to their names: trusted");
    let reason = w.status_reason("P2", "length").unwrap();
    assert!(reason.contains("records no digest") && reason.contains(&path.display().to_string()), "{reason}");
    let s = w.run(Publish::Links, true);
    assert_eq!(w.take(), [0, 1, 0]);
    assert!(s.notices[0].contains("records no digest"), "{:?}", s.notices);
    assert!(w.manifest("length", "P2").1.digest.is_some(), "recomputed with a digest");
}

#[cfg(unix)]
#[test]
fn published_files_are_read_only_links_and_an_edit_through_one_is_found() {
    let w = World::cached();
    let store = w.store();
    let out = w.path("out/P1/all.txt");
    let blob = store.blob_path(&Hash::of(b"abcde"));
    for (rel, _) in PUBLISHED {
        assert_eq!(mode(&w.path("out").join(rel)), 0o444, "out/{rel}");
    }
    assert_eq!(inode(&out), inode(&blob), "a hard link into the cache");
    // The user makes the link writable and edits it in place: the blob is edited with it.
    make_writable(&out);
    std::fs::write(&out, "abcdX").unwrap();
    let s = w.run(Publish::Links, false);
    assert_eq!(w.take(), [1, 0, 0]);
    assert!(s.notices.len() == 1 && s.notices[0].contains("concat · P1"), "{:?}", s.notices);
    w.assert_published_right();
    assert_eq!((mode(&out), inode(&out)), (0o444, inode(&blob)), "a read-only link to the new blob");

    // --copy: independent, writable copies; editing one leaves the cache alone, and the next
    // run puts the result back.
    w.run(Publish::Copies, false);
    assert_ne!(inode(&out), inode(&blob));
    assert_eq!(mode(&out), 0o644);
    w.assert_published_right();
    std::fs::write(&out, "abcdX").unwrap();
    let s = w.run(Publish::Copies, false);
    assert_eq!((w.take(), s.notices.len()), ([0, 0, 0], 0), "the cache was not touched");
    assert_eq!(std::fs::read_to_string(&blob).unwrap(), "abcde");
    w.assert_published_right();
    // Back to links.
    w.run(Publish::Links, false);
    assert_eq!((mode(&out), inode(&out)), (0o444, inode(&blob)));
}

#[test]
fn temporary_files_of_ended_processes_go_and_a_live_process_keeps_its_own() {
    let w = World::cached();
    let store = w.store();
    let root = store.root().to_path_buf();
    // This process marks itself alive as `aret-pipe run` does around the run.
    let _me = lease::Lease::take(store.root(), "a test").unwrap();
    let here = files::this_host();
    let dead = ended_pid();
    // Not real processes: a live lease is what makes one live; one on another host lives until
    // its lease expires, whatever its pid means here.
    let alive = pretend_lease(&root, "node_7.cluster", dead, "aret-pipe run", 60);
    pretend_lease(&root, "node_8.cluster", 12, "aret-pipe run", -1);
    let blob = store.blob_path(&Hash::of(b"abcde"));
    // What a kill while publishing leaves: hard links to blobs under temporary names, in a
    // patient's folder and in the cohort's (out_dir itself), from this host (in the old form
    // without a host, too) and from one whose lease expired; and one of a live process.
    let stale = [
        w.path(&format!("out/P1/.tmp-{here}-{dead}-0-1")),
        w.path(&format!("out/.tmp-{dead}-3-1")),
        w.path("out/P1/.tmp-node_8.cluster-12-0-1"),
    ];
    let kept = w.path(&format!("out/P2/.tmp-node_7.cluster-{dead}-0-1"));
    for path in stale.iter().chain([&kept]) {
        std::fs::hard_link(&blob, path).unwrap();
    }
    let mine = w.path(&format!("out/P2/{}", files::temp_name()));
    std::fs::write(&mine, "in progress").unwrap();

    let listed = leftovers::stale_temps(&store, &w.path("out"), 3).unwrap();
    let mut paths: Vec<&PathBuf> = listed.iter().map(|d| &d.path).collect();
    paths.sort();
    let mut expected: Vec<&PathBuf> = stale.iter().collect();
    expected.sort();
    assert_eq!(paths, expected, "what gc would remove");
    assert!(listed.iter().all(|d| d.bytes == 5 && d.linked), "links to a blob that stays free nothing");

    let s = w.run(Publish::Links, false);
    assert!(stale.iter().all(|p| !p.exists()), "a run removes them from the folders it publishes into");
    assert_eq!(s.notices.len(), 2, "one line per folder: {:?}", s.notices);
    let said = "stale .tmp-* file(s) killed runs left in";
    assert!(s.notices.iter().all(|l| l.contains(said) && l.contains("links to blobs that stay")), "{:?}", s.notices);
    assert!(kept.exists() && mine.exists(), "a live process's temporary files stay, this one's too");
    // Its lease expires.
    pretend_lease(&root, "node_7.cluster", dead, "aret-pipe run", -1);
    assert_eq!(alive, lease::leases_dir(&root).join(format!("node_7.cluster-{dead}-0.json")));
    let listed = leftovers::stale_temps(&store, &w.path("out"), 3).unwrap();
    assert_eq!(listed.iter().map(|d| &d.path).collect::<Vec<_>>(), [&kept], "ended now");
    leftovers::delete(&listed).unwrap();
    assert!(!kept.exists());
}

/// Holds the lock at `path` exclusively as "a test holder" for `hold`, from another thread.
fn hold_lock(path: &Path, hold: Duration) -> std::thread::JoinHandle<()> {
    let lock = FileLock::exclusive(path).unwrap();
    lock.describe_holder("a test holder");
    std::thread::spawn(move || {
        std::thread::sleep(hold);
        drop(lock);
    })
}

#[test]
fn a_stage_waiting_for_another_process_on_its_key_says_so_and_the_wait_is_counted() {
    let w = World::new();
    let store = w.store();
    let rows = preview::preview(&w.graph(), &store, &w.units(), false, &[]);
    let key = rows.iter().find(|r| r.unit == "P1" && r.stage == "concat").unwrap().key.unwrap();
    let holder = hold_lock(&store.lock_path(&format!("concat-{}", key.hex())), Duration::from_millis(1500));
    let s = w.run(Publish::Links, false);
    holder.join().unwrap();
    assert_eq!(s.notices.len(), 1, "{:?}", s.notices);
    let line = &s.notices[0];
    for part in ["waiting for another aret-pipe process to release the lock on concat · P1", "held by a test holder"] {
        assert!(line.contains(part), "{line}");
    }
    assert!(s.key_lock_wait_seconds >= 1.4 && s.wall_seconds >= 1.4, "{s:?}");
    let table = progress::table(&s, &["concat", "length", "report"]);
    assert!(table.contains("stages waited 1."), "{table}");
    w.assert_published_right();
}

#[test]
fn waiting_for_a_gc_says_so_after_a_second_and_returns_the_wait() {
    let w = World::new();
    let root = w.store().root().to_path_buf();
    // A gc on another host, which deletes its lease when it ends.
    let gc_for = |hold: Duration| {
        let path = pretend_lease(&root, "node_2", 4242, "aret-pipe gc", 60);
        std::thread::spawn(move || {
            std::thread::sleep(hold);
            std::fs::remove_file(path).unwrap();
        })
    };
    let mut said = Vec::new();
    let gc = gc_for(Duration::from_millis(1300));
    let waited = lease::wait_while_gc(&root, &mut |l| said.push(l));
    gc.join().unwrap();
    assert!(waited >= Duration::from_millis(1250), "{waited:?}");
    assert_eq!(said.len(), 1, "{said:?}");
    let expected = "waiting for aret-pipe gc on node_2 (pid 4242), alive until ";
    assert!(said[0].contains(expected) && said[0].contains(&root.display().to_string()), "{}", said[0]);
    // A short wait says nothing; an expired gc lease (a gc killed elsewhere) is no wait at all.
    let mut said = Vec::new();
    let gc = gc_for(Duration::from_millis(300));
    let waited = lease::wait_while_gc(&root, &mut |l| said.push(l));
    gc.join().unwrap();
    assert!(waited >= Duration::from_millis(250) && said.is_empty(), "{waited:?} {said:?}");
    pretend_lease(&root, "node_2", 4242, "aret-pipe gc", -1);
    assert!(lease::wait_while_gc(&root, &mut |l| said.push(l)) < Duration::from_millis(50));
}

/// Rewrites `concat/all.txt` in the cache after the run checked it, then reads it.
struct Tamper;
impl Stage for Tamper {
    fn name(&self) -> &'static str {
        "tamper"
    }
    fn version(&self) -> u32 {
        1
    }
    fn inputs(&self) -> &'static [&'static str] {
        &["concat"]
    }
    fn params(&self) -> serde_json::Value {
        serde_json::json!({})
    }
    fn run(&self, ctx: &Context) -> anyhow::Result<Vec<Output>> {
        let path = ctx.path("concat", "all.txt")?;
        flip_byte(&path, 0);
        Ok(vec![Output::new("read.txt", ctx.read("concat", "all.txt")?)])
    }
}

#[test]
fn bytes_that_change_after_their_check_are_refused_when_a_stage_reads_them() {
    let w = World::cached();
    let graph = StageGraph::new(vec![
        Box::new(Concat { sep: String::new(), runs: w.counters.concat.clone(), stop: StopRequest::default() }),
        Box::new(Tamper),
    ])
    .unwrap();
    let options = RunOptions {
        verify: false,
        force: vec![],
        workers: Default::default(),
        default_workers: 1,
        out_dir: w.path("out"),
        publish: Publish::Links,
        stop: StopRequest::default(),
    };
    let s = run::run(&graph, &w.store(), &w.units(), &options, &Progress::hidden(&[]));
    let causes: Vec<String> = s
        .failures()
        .filter_map(|r| match &r.outcome {
            run::Outcome::Failed { cause } => Some(format!("{} · {}: {cause}", r.unit, r.stage)),
            _ => None,
        })
        .collect();
    assert_eq!(causes.len(), 2, "{causes:?}");
    assert!(causes
        .iter()
        .all(|c| c.contains("concat/all.txt in the cache") && c.contains("changed after it was checked")));
    assert!(!w.path("out/P1/read.txt").exists());
    // The next run finds the blobs corrupt and computes concat again.
    w.take();
    w.run(Publish::Links, false);
    assert_eq!(w.take(), [2, 0, 0]);
    w.assert_published_right();
}
