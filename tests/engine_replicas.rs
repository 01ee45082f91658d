//! The engine's replicas on toy stages: a stage fans each patient out into replicas, the stages
//! after it run once per replica (own keys, own folders), and one stage gathers them again.

use aret_pipe::engine::preview::{self, State};
use aret_pipe::engine::progress::Progress;
use aret_pipe::engine::run::{self, Outcome, Publish, RunOptions, RunSummary, Unit};
use aret_pipe::engine::store::Store;
use aret_pipe::engine::{Context, Output, Stage, StageGraph, SOURCE};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;

type Counter = Arc<AtomicUsize>;

/// The patient's one file, as text.
struct Text;
impl Stage for Text {
    fn name(&self) -> &'static str {
        "text"
    }
    fn version(&self) -> u32 {
        1
    }
    fn inputs(&self) -> &'static [&'static str] {
        &[SOURCE]
    }
    fn params(&self) -> serde_json::Value {
        serde_json::json!({})
    }
    fn run(&self, ctx: &Context) -> anyhow::Result<Vec<Output>> {
        Ok(vec![Output::new("text.txt", std::fs::read(&ctx.source_files()[0].path)?)])
    }
}

/// Fans out into `parts` replicas; replica r keeps every `parts`-th character from the r-th.
struct Slice {
    parts: usize,
    runs: Counter,
}
impl Stage for Slice {
    fn name(&self) -> &'static str {
        "slice"
    }
    fn version(&self) -> u32 {
        1
    }
    fn inputs(&self) -> &'static [&'static str] {
        &["text"]
    }
    fn params(&self) -> serde_json::Value {
        serde_json::json!({ "parts": self.parts })
    }
    fn replica_names(&self) -> Vec<String> {
        if self.parts < 2 {
            return vec![];
        }
        (0..self.parts).map(|r| format!("part{r}")).collect()
    }
    fn run(&self, ctx: &Context) -> anyhow::Result<Vec<Output>> {
        self.runs.fetch_add(1, Ordering::SeqCst);
        let text = String::from_utf8(ctx.read("text", "text.txt")?)?;
        let (r, n) = (ctx.replica().unwrap_or(0), self.parts.max(1));
        let kept: String = text.chars().skip(r).step_by(n).collect();
        Ok(vec![Output::new("slice.txt", kept)])
    }
}

/// Upper-cases its replica's slice; fails on a slice holding `!`.
struct Shout {
    runs: Counter,
}
impl Stage for Shout {
    fn name(&self) -> &'static str {
        "shout"
    }
    fn version(&self) -> u32 {
        1
    }
    fn inputs(&self) -> &'static [&'static str] {
        &["slice"]
    }
    fn params(&self) -> serde_json::Value {
        serde_json::json!({})
    }
    fn run(&self, ctx: &Context) -> anyhow::Result<Vec<Output>> {
        self.runs.fetch_add(1, Ordering::SeqCst);
        let slice = String::from_utf8(ctx.read("slice", "slice.txt")?)?;
        anyhow::ensure!(!slice.contains('!'), "a slice may not shout `!`");
        Ok(vec![Output::new("shout.txt", slice.to_uppercase())])
    }
}

/// Gathers every replica's shout, joined by `|`, with the text read from before the fan-out.
struct Join {
    runs: Counter,
}
impl Stage for Join {
    fn name(&self) -> &'static str {
        "join"
    }
    fn version(&self) -> u32 {
        1
    }
    fn inputs(&self) -> &'static [&'static str] {
        &["text", "shout"]
    }
    fn params(&self) -> serde_json::Value {
        serde_json::json!({})
    }
    fn gathers_replicas(&self) -> bool {
        true
    }
    fn run(&self, ctx: &Context) -> anyhow::Result<Vec<Output>> {
        self.runs.fetch_add(1, Ordering::SeqCst);
        let text = String::from_utf8(ctx.read("text", "text.txt")?)?;
        let mut parts = Vec::new();
        for r in 0..ctx.replica_count() {
            parts.push(String::from_utf8(ctx.in_replica(r)?.read("shout", "shout.txt")?)?);
        }
        Ok(vec![Output::new("join.txt", format!("{text}: {}", parts.join("|")))])
    }
}

/// Cohort: one line per patient that got through, with its replicas' count and last slice.
struct Report;
impl Stage for Report {
    fn name(&self) -> &'static str {
        "report"
    }
    fn version(&self) -> u32 {
        1
    }
    fn inputs(&self) -> &'static [&'static str] {
        &["join", "slice"]
    }
    fn params(&self) -> serde_json::Value {
        serde_json::json!({})
    }
    fn is_cohort(&self) -> bool {
        true
    }
    fn run(&self, ctx: &Context) -> anyhow::Result<Vec<Output>> {
        let mut text = String::new();
        for p in ctx.cohort_patients() {
            let n = ctx.patient_replica_count(p);
            let last = String::from_utf8(ctx.read_patient_replica(p, n - 1, "slice", "slice.txt")?)?;
            if n > 1 {
                let whole = ctx.read_patient(p, "slice", "slice.txt").unwrap_err().to_string();
                anyhow::ensure!(whole.contains("ran once per replica"), "{whole}");
            }
            let join = String::from_utf8(ctx.read_patient(p, "join", "join.txt")?)?;
            text.push_str(&format!("{join} ({n}, {last})\n"));
        }
        Ok(vec![Output::new("report.txt", text)])
    }
}

struct World {
    dir: tempfile::TempDir,
    slices: Counter,
    shouts: Counter,
    joins: Counter,
}

impl World {
    fn new(patients: &[(&str, &str)]) -> World {
        let dir = tempfile::tempdir().unwrap();
        for (p, text) in patients {
            std::fs::create_dir_all(dir.path().join("data").join(p)).unwrap();
            std::fs::write(dir.path().join("data").join(p).join("t.txt"), text).unwrap();
        }
        World { dir, slices: Counter::default(), shouts: Counter::default(), joins: Counter::default() }
    }

    fn graph(&self, parts: usize) -> StageGraph {
        StageGraph::new(vec![
            Box::new(Text),
            Box::new(Slice { parts, runs: self.slices.clone() }),
            Box::new(Shout { runs: self.shouts.clone() }),
            Box::new(Join { runs: self.joins.clone() }),
            Box::new(Report),
        ])
        .unwrap()
    }

    fn units(&self) -> Vec<Unit> {
        ["P1", "P2"].iter().map(|p| Unit::folder(*p, self.dir.path().join("data").join(p))).collect()
    }

    fn store(&self) -> Store {
        Store::open(&self.dir.path().join("cache")).unwrap()
    }

    fn run(&self, graph: &StageGraph) -> RunSummary {
        let options = RunOptions {
            verify: false,
            force: vec![],
            workers: [("shout".to_string(), 3)].into_iter().collect(),
            default_workers: 2,
            out_dir: self.dir.path().join("out"),
            publish: Publish::Links,
            stop: Default::default(),
        };
        run::run(graph, &self.store(), &self.units(), &options, &Progress::hidden(&[]))
    }

    fn out(&self, rel: &str) -> String {
        std::fs::read_to_string(self.dir.path().join("out").join(rel)).unwrap()
    }

    /// Runs of slice, shout and join since the last call.
    fn take(&self) -> [usize; 3] {
        [&self.slices, &self.shouts, &self.joins].map(|c| c.swap(0, Ordering::SeqCst))
    }
}

#[test]
fn replicas_run_once_each_publish_in_their_own_folder_and_gather_in_order() {
    let w = World::new(&[("P1", "abcdefg"), ("P2", "xyz")]);
    let s = w.run(&w.graph(3));
    assert_eq!(s.failures().count(), 0);
    assert_eq!(w.take(), [6, 6, 2]);
    assert_eq!(w.out("P1/part0/slice.txt"), "adg");
    assert_eq!(w.out("P1/part2/shout.txt"), "CF");
    assert_eq!(w.out("P1/join.txt"), "abcdefg: ADG|BE|CF");
    assert_eq!(w.out("report.txt"), "abcdefg: ADG|BE|CF (3, cf)\nxyz: X|Y|Z (3, z)\n");
    let units: Vec<&str> = s.records.iter().filter(|r| r.stage == "shout").map(|r| r.unit.as_str()).collect();
    assert_eq!(units, ["P1/part0", "P1/part1", "P1/part2", "P2/part0", "P2/part1", "P2/part2"]);
    assert_eq!(w.graph(3).runs_per_stage(2), [("text", 2), ("slice", 6), ("shout", 6), ("join", 2), ("report", 1)]);
}

#[test]
fn a_second_run_and_its_preview_serve_every_replica_from_the_cache() {
    let w = World::new(&[("P1", "abcdefg"), ("P2", "xyz")]);
    w.run(&w.graph(3));
    w.take();
    let preview = preview::preview(&w.graph(3), &w.store(), &w.units(), false, &[]);
    assert_eq!(preview.len(), 2 * (1 + 3 + 3 + 1) + 1);
    assert!(preview.iter().all(|r| matches!(r.state, State::Cached { .. })), "{}", preview::describe(&preview));
    let s = w.run(&w.graph(3));
    assert_eq!(w.take(), [0, 0, 0]);
    assert!(s.records.iter().all(|r| matches!(r.outcome, Outcome::Cached { .. })));
    // Another fan-out is another set of replicas: all of them, and the gathering, recompute,
    // except a replica whose input comes out the same (P2/part1's slice is "y" either way).
    let preview = preview::preview(&w.graph(2), &w.store(), &w.units(), false, &[]);
    let slice = preview.iter().find(|r| r.unit == "P1/part0" && r.stage == "slice").unwrap();
    assert!(matches!(&slice.state, State::Compute(why) if why[0].contains("parts")), "{:?}", slice.state);
    w.run(&w.graph(2));
    assert_eq!(w.take(), [4, 3, 2]);
    assert_eq!(w.out("P1/join.txt"), "abcdefg: ACEG|BDF");
}

#[test]
fn without_a_fan_out_the_gathering_stage_sees_one_replica_under_the_patient_itself() {
    let w = World::new(&[("P1", "abc"), ("P2", "de")]);
    let s = w.run(&w.graph(1));
    assert_eq!(w.take(), [2, 2, 2]);
    assert_eq!(w.out("P1/join.txt"), "abc: ABC");
    assert_eq!(w.out("report.txt"), "abc: ABC (1, abc)\nde: DE (1, de)\n");
    assert!(s.records.iter().all(|r| !r.unit.contains('/')));
}

#[test]
fn a_failing_replica_fails_its_patient_and_nothing_else() {
    let w = World::new(&[("P1", "abcdef"), ("P2", "x!z")]);
    let s = w.run(&w.graph(3));
    let failed: Vec<String> = s.failures().map(|r| format!("{}:{}", r.unit, r.stage)).collect();
    assert_eq!(failed, ["P2/part1:shout"]);
    let join = s.records.iter().find(|r| r.unit == "P2" && r.stage == "join").unwrap();
    assert!(matches!(&join.outcome, Outcome::Skipped { upstream } if upstream == "shout"));
    assert_eq!(w.out("report.txt"), "abcdef: AD|BE|CF (3, cf)\n");
}

#[test]
fn a_graph_cut_inside_the_span_ends_on_the_replicas() {
    let w = World::new(&[("P1", "abcd"), ("P2", "xy")]);
    let s = w.run(&w.graph(2).until("shout").unwrap());
    assert_eq!(w.take(), [4, 4, 0]);
    assert_eq!(s.failures().count(), 0);
    assert_eq!(w.out("P2/part1/shout.txt"), "Y");
}

#[test]
fn a_fan_out_needs_a_later_stage_that_gathers() {
    let runs = Counter::default();
    let err = StageGraph::new(vec![
        Box::new(Text),
        Box::new(Slice { parts: 2, runs: runs.clone() }),
        Box::new(Shout { runs }),
    ])
    .err()
    .unwrap();
    assert!(err.to_string().contains("`slice` fans out into replicas, and no later per-patient stage gathers them"));
}
