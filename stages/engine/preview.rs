//! What a run would do, without running anything: for `run --dry-run` and `status`.

use super::key::Hash;
use super::plan::{self, Decision};
use super::run::{Unit, COHORT};
use super::source;
use super::stage::{Finished, Stage, StageGraph, SOURCE};
use super::store::Store;
use std::collections::BTreeMap;

/// The fate of one (unit, stage) if the pipeline ran now.
#[derive(Debug, Clone, PartialEq)]
pub enum State {
    /// Served from the cache: the manifest of (stage, key).
    Cached { key: Hash },
    /// Would compute, for these reasons.
    Compute(Vec<String>),
    /// Depends on an upstream stage that would compute first; whether this one then recomputes
    /// depends on whether that output's bytes change (early cutoff). Own reasons listed if any.
    AfterUpstream { upstream: String, own: Vec<String> },
    /// Its inputs cannot be read (e.g. the patient's folder is gone).
    Blocked(String),
}

#[derive(Debug, Clone)]
pub struct Row {
    pub unit: String,
    pub stage: String,
    pub state: State,
    /// The stage's cache key for this unit as things stand: known when every input it reads is
    /// (it is cached, or would compute from cached inputs); `None` after an upstream stage that
    /// would compute first, or when its inputs cannot be read.
    pub key: Option<Hash>,
}

/// One unit's (or replica's) way through the per-patient stages while previewing.
#[derive(Clone)]
struct Lane {
    unit: String,
    finished: Finished,
    /// The first stage of this lane that would not be cached.
    pending: Option<String>,
}

pub fn preview(graph: &StageGraph, store: &Store, units: &[Unit], verify: bool, force: &[String]) -> Vec<Row> {
    let mut rows = Vec::new();
    let mut cohort: BTreeMap<String, Finished> = BTreeMap::new();
    let mut cohort_replicas: BTreeMap<String, Vec<Finished>> = BTreeMap::new();
    let mut cohort_blocker: Option<String> = None;
    let span = graph.replica_span();
    for unit in units {
        let sources = source::scan(store, unit, verify);
        let files = sources.as_deref().unwrap_or(&[]);
        let mut base = Lane { unit: unit.id.clone(), finished: Finished::new(), pending: None };
        let mut replicas: Vec<Lane> = Vec::new();
        for (index, stage) in graph.per_patient().into_iter().enumerate() {
            let in_span = span.as_ref().is_some_and(|sp| sp.replicates(index));
            if let Some(sp) = span.as_ref().filter(|sp| sp.fan_out == index) {
                replicas = (0..sp.names.len()).map(|r| Lane { unit: sp.unit(&unit.id, r), ..base.clone() }).collect();
            }
            // A gathering stage is keyed by every replica's outputs, and waits for any of them.
            let mut gathered = None;
            if let Some(sp) = span.as_ref().filter(|_| stage.gathers_replicas() && !replicas.is_empty()) {
                let finished: Vec<Finished> = replicas.iter().map(|l| l.finished.clone()).collect();
                gathered = Some(plan::gathered_inputs(stage, files, &base.finished, &finished, &sp.names));
                base.pending = base.pending.take().or_else(|| replicas.iter().find_map(|l| l.pending.clone()));
            }
            let lanes: Vec<&mut Lane> = if in_span { replicas.iter_mut().collect() } else { vec![&mut base] };
            let forced = force.iter().any(|f| f == stage.name());
            for lane in lanes {
                let (state, key) = match (&sources, &lane.pending) {
                    (Err(e), _) if stage.inputs().contains(&SOURCE) => (State::Blocked(format!("{e:#}")), None),
                    (_, Some(up)) if depends_on(graph, stage, up) => {
                        let own = own_changes(store, stage, &lane.unit, forced);
                        (State::AfterUpstream { upstream: up.clone(), own }, None)
                    }
                    _ => {
                        let inputs =
                            gathered.clone().unwrap_or_else(|| plan::patient_inputs(stage, files, &lane.finished));
                        let keyed = plan::key(stage, &lane.unit, inputs);
                        let state = match plan::decide(store, stage, &lane.unit, &keyed, verify, forced) {
                            Decision::Cached(m) | Decision::Fetched(m) => {
                                lane.finished.insert(stage.name(), m.outputs);
                                State::Cached { key: keyed.key }
                            }
                            Decision::Compute(reasons) => State::Compute(reasons),
                            Decision::Distrusted(why) => State::Compute(vec![why]),
                        };
                        (state, Some(keyed.key))
                    }
                };
                if !matches!(state, State::Cached { .. }) && lane.pending.is_none() {
                    lane.pending = Some(stage.name().to_string());
                }
                rows.push(Row { unit: lane.unit.clone(), stage: stage.name().into(), state, key });
            }
        }
        // A graph cut inside the span ends on the replicas.
        if let Some(p) = base.pending.or_else(|| replicas.iter().find_map(|l| l.pending.clone())) {
            cohort_blocker.get_or_insert(format!("{}/{p}", unit.id));
        }
        cohort.insert(unit.id.clone(), base.finished);
        cohort_replicas.insert(unit.id.clone(), replicas.into_iter().map(|l| l.finished).collect());
    }
    let mut cohort_finished = Finished::new();
    for stage in graph.stages().iter().filter(|s| s.is_cohort()) {
        let stage = stage.as_ref();
        let forced = force.iter().any(|f| f == stage.name());
        let (state, key) = if let Some(up) = &cohort_blocker {
            (State::AfterUpstream { upstream: up.clone(), own: own_changes(store, stage, COHORT, forced) }, None)
        } else {
            let names = span.as_ref().map_or(&[][..], |s| &s.names[..]);
            let replicas = plan::CohortReplicas { finished: &cohort_replicas, names };
            let keyed = plan::key(stage, COHORT, plan::cohort_inputs(stage, &cohort, &replicas, &cohort_finished, &[]));
            let state = match plan::decide(store, stage, COHORT, &keyed, verify, forced) {
                Decision::Cached(m) | Decision::Fetched(m) => {
                    cohort_finished.insert(stage.name(), m.outputs);
                    State::Cached { key: keyed.key }
                }
                Decision::Compute(reasons) => {
                    cohort_blocker = Some(stage.name().to_string());
                    State::Compute(reasons)
                }
                Decision::Distrusted(why) => {
                    cohort_blocker = Some(stage.name().to_string());
                    State::Compute(vec![why])
                }
            };
            (state, Some(keyed.key))
        };
        rows.push(Row { unit: COHORT.into(), stage: stage.name().into(), state, key });
    }
    rows
}

/// Whether `stage` reads `upstream`, directly or through other stages.
fn depends_on(graph: &StageGraph, stage: &dyn Stage, upstream: &str) -> bool {
    stage.inputs().iter().any(|&i| i == upstream || graph.get(i).is_some_and(|s| depends_on(graph, s, upstream)))
}

/// Changes of the stage itself since it last ran for `unit` ("never run" if it never did); a
/// forced stage runs whatever they are, as `plan::decide` says.
fn own_changes(store: &Store, stage: &dyn Stage, unit: &str, forced: bool) -> Vec<String> {
    if forced {
        return vec![plan::FORCED.into()];
    }
    match store.latest(stage.name(), unit) {
        None => vec!["never run".into()],
        Some(last) => plan::own_changes(&last, stage, &stage.params()),
    }
}

/// One line per (unit, stage), for `run --dry-run`.
pub fn describe(rows: &[Row]) -> String {
    let width = rows.iter().map(|r| r.unit.len()).max().unwrap_or(0);
    let mut out = String::new();
    for r in rows {
        let what = match &r.state {
            State::Cached { .. } => "cached".to_string(),
            State::Compute(reasons) => format!("would run: {}", reasons.join("; ")),
            State::AfterUpstream { upstream, own } if own.is_empty() => {
                format!("would run after `{upstream}` unless its outputs come out unchanged")
            }
            State::AfterUpstream { upstream, own } => {
                format!("would run: {} (and after `{upstream}`)", own.join("; "))
            }
            State::Blocked(why) => format!("cannot run: {why}"),
        };
        out.push_str(&format!("{:<width$}  {:<8} {what}\n", r.unit, r.stage));
    }
    out
}
