//! The engine on toy stages (it knows nothing about CT): caching, invalidation, early cutoff,
//! forced runs, corrupt blobs, failure isolation, cohort fan-in, stopping a run and pruning.

use aret_pipe::engine::preview::{self, State};
use aret_pipe::engine::progress::Progress;
use aret_pipe::engine::run::{self, Outcome, Publish, RunOptions, RunSummary, StopRequest, Unit};
use aret_pipe::engine::store::Store;
use aret_pipe::engine::{Hash, Stage, StageGraph};
use std::collections::HashSet;
use std::path::Path;

mod support;
use support::toy_stages::{Concat, Counters, Length, Report};

struct World {
    dir: tempfile::TempDir,
    counters: Counters,
    stop: StopRequest,
}

impl World {
    fn new(patients: &[(&str, &[(&str, &str)])]) -> World {
        let dir = tempfile::tempdir().unwrap();
        for (p, files) in patients {
            for (name, text) in *files {
                let path = dir.path().join("data").join(p).join(name);
                std::fs::create_dir_all(path.parent().unwrap()).unwrap();
                std::fs::write(path, text).unwrap();
            }
        }
        World { dir, counters: Counters::default(), stop: StopRequest::default() }
    }

    fn graph(&self, sep: &str, parity_only: bool) -> StageGraph {
        StageGraph::new(vec![
            Box::new(Concat { sep: sep.into(), runs: self.counters.concat.clone(), stop: self.stop.clone() }),
            Box::new(Length { parity_only, runs: self.counters.length.clone() }),
            Box::new(Report { runs: self.counters.report.clone() }),
        ])
        .unwrap()
    }

    fn units(&self) -> Vec<Unit> {
        let mut units: Vec<Unit> = std::fs::read_dir(self.dir.path().join("data"))
            .unwrap()
            .map(|e| {
                let e = e.unwrap();
                Unit::folder(e.file_name().to_string_lossy(), e.path())
            })
            .collect();
        units.sort_by(|a, b| a.id.cmp(&b.id));
        units
    }

    fn store(&self) -> Store {
        Store::open(&self.dir.path().join("cache")).unwrap()
    }

    /// Options with one worker per stage: units pass each stage strictly in order.
    fn one_worker_each(&self) -> RunOptions {
        RunOptions {
            verify: false,
            force: vec![],
            workers: Default::default(),
            default_workers: 1,
            out_dir: self.path("out"),
            publish: Publish::Links,
            stop: self.stop.clone(),
        }
    }

    fn run(&self, graph: &StageGraph, force: &[&str], verify: bool) -> RunSummary {
        let options = RunOptions {
            verify,
            force: force.iter().map(|s| s.to_string()).collect(),
            workers: [("length".to_string(), 3)].into_iter().collect(),
            default_workers: 2,
            out_dir: self.dir.path().join("out"),
            publish: Publish::Links,
            stop: self.stop.clone(),
        };
        run::run(graph, &self.store(), &self.units(), &options, &Progress::hidden(&[]))
    }

    fn out(&self, rel: &str) -> String {
        std::fs::read_to_string(self.dir.path().join("out").join(rel)).unwrap()
    }

    fn path(&self, rel: &str) -> std::path::PathBuf {
        self.dir.path().join(rel)
    }
}

fn two_patients() -> World {
    World::new(&[("P1", &[("a.txt", "ab"), ("b.txt", "cde")]), ("P2", &[("x.txt", "xyz")])])
}

/// Two patients after one full run of the plain graph, its counters reset.
fn two_patients_cached() -> (World, StageGraph) {
    let w = two_patients();
    let g = w.graph("", false);
    w.run(&g, &[], false);
    w.counters.take();
    (w, g)
}

#[test]
fn first_run_computes_everything_and_publishes() {
    let w = two_patients();
    let s = w.run(&w.graph("", false), &[], false);
    assert_eq!(w.counters.take(), [2, 2, 1]);
    assert_eq!(s.failures().count(), 0);
    assert_eq!(w.out("P1/all.txt"), "abcde");
    assert_eq!(w.out("P1/len.txt"), "5");
    assert_eq!(w.out("report.txt"), "P1 5\nP2 3\n");
}

#[test]
fn unchanged_inputs_recompute_nothing() {
    let (w, g) = two_patients_cached();
    let s = w.run(&g, &[], false);
    assert_eq!(w.counters.take(), [0, 0, 0]);
    assert!(s.records.iter().all(|r| matches!(r.outcome, Outcome::Cached { .. })));
}

#[test]
fn editing_a_parameter_recomputes_that_stage_and_downstream_only() {
    let w = two_patients();
    w.run(&w.graph("", false), &[], false);
    w.counters.take();
    w.run(&w.graph("", true), &[], false);
    assert_eq!(w.counters.take(), [0, 2, 1], "only length (and the cohort reading it) recompute");
    assert_eq!(w.out("P1/len.txt"), "1");
}

#[test]
fn early_cutoff_stops_at_identical_bytes() {
    let w = two_patients();
    w.run(&w.graph("", true), &[], false);
    w.counters.take();
    // Same length parity: concat recomputes, length recomputes to identical bytes, report cached.
    std::fs::write(w.path("data/P1/a.txt"), "zz").unwrap();
    w.run(&w.graph("", true), &[], false);
    assert_eq!(w.counters.take(), [1, 1, 0]);
    // A touched but unchanged file re-hashes to the same content: nothing recomputes.
    std::fs::write(w.path("data/P2/x.txt"), "xyz").unwrap();
    w.run(&w.graph("", true), &[], false);
    assert_eq!(w.counters.take(), [0, 0, 0]);
}

#[test]
fn force_recomputes_only_the_forced_stage() {
    let w = two_patients();
    let g = w.graph("-", false);
    w.run(&g, &[], false);
    w.counters.take();
    let s = w.run(&g, &["concat"], false);
    assert_eq!(w.counters.take(), [2, 0, 0]);
    assert_eq!(s.count("concat", |o| matches!(o, Outcome::Computed { .. })), 2);
}

#[test]
fn truncated_or_corrupt_blob_is_recomputed_never_used() {
    let (w, g) = two_patients_cached();
    let store = w.store();
    let blob = |text: &str| store.blob_path(&aret_pipe::engine::Hash::of(text.as_bytes()));
    // Truncate P1's concat output: the size check catches it on the next run.
    let path = blob("abcde");
    make_writable(&path);
    std::fs::write(&path, "abc").unwrap();
    w.run(&g, &[], false);
    assert_eq!(w.counters.take(), [1, 0, 0], "concat recomputed, its identical bytes keep length cached");
    assert_eq!(std::fs::read_to_string(&path).unwrap(), "abcde");
    // Same-size corruption passes the size check; every run re-hashes the blob and catches it.
    make_writable(&path);
    std::fs::write(&path, "abcdX").unwrap();
    let s = w.run(&g, &[], false);
    assert_eq!(w.counters.take(), [1, 0, 0]);
    assert_eq!(std::fs::read_to_string(&path).unwrap(), "abcde");
    assert_eq!(w.out("P1/all.txt"), "abcde");
    assert_eq!(s.notices.len(), 1, "{:?}", s.notices);
    // A deleted blob is recomputed too.
    std::fs::remove_file(blob("5")).unwrap();
    w.run(&g, &[], false);
    assert_eq!(w.counters.take(), [0, 1, 0]);
}

fn make_writable(path: &Path) {
    let mut perms = std::fs::metadata(path).unwrap().permissions();
    #[allow(clippy::permissions_set_readonly_false)]
    perms.set_readonly(false);
    std::fs::set_permissions(path, perms).unwrap();
}

#[test]
fn one_failing_patient_does_not_stop_the_others() {
    let w = World::new(&[
        ("P1", &[("a.txt", "ab")]),
        ("P2", &[("poison", "!")]),
        ("P3", &[("panic", "!")]),
        ("P4", &[("d.txt", "dddd")]),
    ]);
    let s = w.run(&w.graph("", false), &[], false);
    let failed: Vec<(String, String)> = s.failures().map(|r| (r.unit.clone(), r.stage.clone())).collect();
    assert_eq!(failed, vec![("P2".into(), "concat".into()), ("P3".into(), "concat".into())]);
    let cause = |unit: &str| {
        s.records
            .iter()
            .find_map(|r| match (&r.outcome, r.unit == unit) {
                (Outcome::Failed { cause }, true) => Some(cause.clone()),
                _ => None,
            })
            .unwrap()
    };
    assert!(cause("P2").contains("`poison` is not allowed"));
    assert!(cause("P3").contains("panic") && cause("P3").contains("deliberate"));
    assert_eq!(s.count("length", |o| matches!(o, Outcome::Skipped { .. })), 2);
    assert_eq!(w.out("report.txt"), "P1 2\nP4 4\n", "the cohort sees the patients that got through");
}

#[test]
fn a_missing_patient_folder_is_a_failure_of_that_patient() {
    let w = two_patients();
    let mut units = w.units();
    units.push(Unit::folder("P9", w.path("data/P9")));
    let s = run::run(&w.graph("", false), &w.store(), &units, &w.one_worker_each(), &Progress::hidden(&[]));
    let failures: Vec<_> = s.failures().collect();
    assert_eq!(failures.len(), 1);
    assert_eq!(failures[0].unit, "P9");
}

#[test]
fn gc_deletes_only_unreferenced_blobs() {
    let (w, g) = two_patients_cached();
    let store = w.store();
    let stray = store.blob_path(&aret_pipe::engine::Hash::of(b"orphan"));
    std::fs::create_dir_all(stray.parent().unwrap()).unwrap();
    std::fs::write(&stray, "orphan").unwrap();
    let garbage = store.garbage(None, &[]).unwrap();
    assert!(garbage.manifests.is_empty(), "plain gc forgets no result");
    assert!(garbage.files.iter().any(|f| f.path == stray && f.bytes == 6));
    garbage.delete().unwrap();
    assert!(!stray.exists());
    w.counters.take();
    w.run(&g, &[], false);
    assert_eq!(w.counters.take(), [0, 0, 0], "gc kept everything manifests reference");
}

#[test]
fn pruning_keeps_exactly_the_results_a_configuration_uses_now() {
    let w = two_patients();
    let (old, new) = (w.graph("", false), w.graph("-", false));
    w.run(&old, &[], false);
    w.run(&new, &[], false);
    w.counters.take();
    let store = w.store();
    let keep: HashSet<(String, Hash)> = preview::preview(&new, &store, &w.units(), false, &[])
        .into_iter()
        .filter_map(|row| match row.state {
            State::Cached { key } => Some((row.stage, key)),
            _ => None,
        })
        .collect();
    assert_eq!(keep.len(), 5, "two concat, two length, one report");
    let garbage = store.garbage(Some(&keep), &[]).unwrap();
    // The old separator's concat for both patients, P1's length of "abcde" and the old report;
    // P2's length reads the same "xyz" under both, so both configurations use it.
    assert_eq!(garbage.manifests.len(), 4, "{:?}", garbage.manifests);
    assert!(garbage.manifests.iter().all(|m| m.exists()), "listing deletes nothing");
    let old_text = store.blob_path(&Hash::of(b"abcde"));
    assert!(garbage.files.iter().any(|f| f.path == old_text), "the old concat's output goes too");
    assert!(garbage.files.iter().all(|f| f.path != store.blob_path(&Hash::of(b"xyz"))), "a kept result's blob stays");
    garbage.delete().unwrap();
    assert!(!old_text.exists() && garbage.manifests.iter().all(|m| !m.exists()));
    w.run(&new, &[], false);
    assert_eq!(w.counters.take(), [0, 0, 0], "the kept configuration is wholly cached");
    w.run(&old, &[], false);
    assert_eq!(w.counters.take(), [2, 1, 1], "the forgotten results are computed again");
}

#[test]
fn forgetting_a_stage_recomputes_it_alone_when_its_bytes_come_out_the_same() {
    let (w, g) = two_patients_cached();
    let store = w.store();
    let garbage = store.garbage(None, &["concat".to_string()]).unwrap();
    assert_eq!(garbage.manifests.len(), 2, "both patients' concat: {:?}", garbage.manifests);
    garbage.delete().unwrap();
    assert!(!store.blob_path(&Hash::of(b"abcde")).exists());
    w.run(&g, &[], false);
    assert_eq!(w.counters.take(), [2, 0, 0], "length and report keep their keys: early cutoff");
    assert_eq!(w.out("P1/all.txt"), "abcde");
}

#[test]
fn graph_rejects_inputs_declared_later() {
    let c = Counters::default();
    let g = StageGraph::new(vec![
        Box::new(Length { parity_only: false, runs: c.length.clone() }) as Box<dyn Stage>,
        Box::new(Concat { sep: String::new(), runs: c.concat.clone(), stop: Default::default() }),
    ]);
    assert!(g.is_err());
}

#[test]
fn outputs_a_stage_does_not_read_do_not_invalidate_it() {
    let (w, g) = two_patients_cached();
    // An empty extra file: concat's all.txt is unchanged, its files.txt is not.
    std::fs::write(w.path("data/P1/c.txt"), "").unwrap();
    w.run(&g, &[], false);
    assert_eq!(w.counters.take(), [1, 0, 0], "length reads only all.txt");
    assert_eq!(w.out("P1/files.txt"), "3");
}

#[test]
fn a_stop_request_starts_no_further_stage_and_the_next_run_goes_on() {
    let mut w =
        World::new(&[("a", &[("1.txt", "x"), ("stop", "")]), ("b", &[("1.txt", "y")]), ("c", &[("1.txt", "z")])]);
    let graph = w.graph("+", false);
    // One worker a stage: the request comes while a's concat works and before anything else starts.
    let s = run::run(&graph, &w.store(), &w.units(), &w.one_worker_each(), &Progress::hidden(&[]));
    assert!(s.interrupted() && s.failures().next().is_none());
    let outcome = |s: &RunSummary, unit: &str, stage: &str| {
        s.records.iter().find(|r| r.unit == unit && r.stage == stage).map(|r| r.outcome.clone()).unwrap()
    };
    // The stage in progress finishes, is cached and published; nothing else starts.
    assert!(matches!(outcome(&s, "a", "concat"), Outcome::Computed { .. }));
    assert!(w.path("out/a/all.txt").exists());
    for (unit, stage) in [("a", "length"), ("b", "concat"), ("b", "length"), ("c", "concat"), ("c", "length")] {
        assert!(matches!(outcome(&s, unit, stage), Outcome::Interrupted), "{unit} · {stage}");
    }
    assert!(matches!(outcome(&s, "cohort", "report"), Outcome::Interrupted));
    assert_eq!(w.counters.take(), [1, 0, 0]);
    let table = aret_pipe::engine::progress::table(&s, &graph.names());
    assert!(table.contains("stopped") && table.contains("run the same command again"), "{table}");
    let report = serde_json::to_value(&s).unwrap();
    assert_eq!(report["records"][1]["outcome"], "interrupted");

    // The same command again, unasked to stop, goes on from the cache.
    w.stop = StopRequest::default();
    let graph = w.graph("+", false);
    let s = run::run(&graph, &w.store(), &w.units(), &w.one_worker_each(), &Progress::hidden(&[]));
    assert!(!s.interrupted() && s.failures().next().is_none());
    assert!(matches!(outcome(&s, "a", "concat"), Outcome::Cached { .. }));
    assert_eq!(w.counters.take(), [2, 3, 1]);
}
