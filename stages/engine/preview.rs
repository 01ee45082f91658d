//! What a run would do, without running anything: for `run --dry-run` and `status`.

use super::plan::{self, Decision};
use super::run::{Unit, COHORT};
use super::source;
use super::stage::{Finished, Stage, StageGraph, SOURCE};
use super::store::Store;
use std::collections::BTreeMap;

/// The fate of one (unit, stage) if the pipeline ran now.
#[derive(Debug, Clone, PartialEq)]
pub enum State {
    Cached,
    /// Would compute, for these reasons.
    Compute(Vec<String>),
    /// Depends on an upstream stage that would compute first; whether this one then recomputes
    /// depends on whether that output's bytes change (early cutoff). Own reasons listed if any.
    AfterUpstream {
        upstream: String,
        own: Vec<String>,
    },
    /// Its inputs cannot be read (e.g. the patient's folder is gone).
    Blocked(String),
}

#[derive(Debug, Clone)]
pub struct Row {
    pub unit: String,
    pub stage: String,
    pub state: State,
}

pub fn preview(graph: &StageGraph, store: &Store, units: &[Unit], verify: bool, force: &[String]) -> Vec<Row> {
    let mut rows = Vec::new();
    let mut cohort: BTreeMap<String, Finished> = BTreeMap::new();
    let mut cohort_blocker: Option<String> = None;
    for unit in units {
        let mut finished = Finished::new();
        let mut pending: Option<String> = None; // first stage of this unit that would not be cached
        let sources = source::scan(store, unit, verify);
        for stage in graph.stages().iter().filter(|s| !s.is_cohort()) {
            let stage = stage.as_ref();
            let state = match (&sources, &pending) {
                (Err(e), _) if stage.inputs().contains(&SOURCE) => State::Blocked(format!("{e:#}")),
                (_, Some(up)) if depends_on(graph, stage, up) => {
                    State::AfterUpstream { upstream: up.clone(), own: own_changes(store, stage, &unit.id) }
                }
                _ => {
                    let files = sources.as_deref().unwrap_or(&[]);
                    let keyed = plan::key(stage, &unit.id, plan::patient_inputs(stage, files, &finished));
                    let forced = force.iter().any(|f| f == stage.name());
                    match plan::decide(store, stage, &unit.id, &keyed, verify, forced) {
                        Decision::Cached(m) => {
                            finished.insert(stage.name(), m.outputs);
                            State::Cached
                        }
                        Decision::Compute(reasons) => State::Compute(reasons),
                    }
                }
            };
            if !matches!(state, State::Cached) && pending.is_none() {
                pending = Some(stage.name().to_string());
            }
            rows.push(Row { unit: unit.id.clone(), stage: stage.name().into(), state });
        }
        if let Some(p) = pending {
            cohort_blocker.get_or_insert(format!("{}/{p}", unit.id));
        }
        cohort.insert(unit.id.clone(), finished);
    }
    let mut cohort_finished = Finished::new();
    for stage in graph.stages().iter().filter(|s| s.is_cohort()) {
        let stage = stage.as_ref();
        let state = if let Some(up) = &cohort_blocker {
            State::AfterUpstream { upstream: up.clone(), own: own_changes(store, stage, COHORT) }
        } else {
            let keyed = plan::key(stage, COHORT, plan::cohort_inputs(stage, &cohort, &cohort_finished, &[]));
            let forced = force.iter().any(|f| f == stage.name());
            match plan::decide(store, stage, COHORT, &keyed, verify, forced) {
                Decision::Cached(m) => {
                    cohort_finished.insert(stage.name(), m.outputs);
                    State::Cached
                }
                Decision::Compute(reasons) => {
                    cohort_blocker = Some(stage.name().to_string());
                    State::Compute(reasons)
                }
            }
        };
        rows.push(Row { unit: COHORT.into(), stage: stage.name().into(), state });
    }
    rows
}

/// Whether `stage` reads `upstream`, directly or through other stages.
fn depends_on(graph: &StageGraph, stage: &dyn Stage, upstream: &str) -> bool {
    stage.inputs().iter().any(|&i| i == upstream || graph.get(i).is_some_and(|s| depends_on(graph, s, upstream)))
}

/// Changes of the stage itself since it last ran for `unit` ("never run" if it never did).
fn own_changes(store: &Store, stage: &dyn Stage, unit: &str) -> Vec<String> {
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
            State::Cached => "cached".to_string(),
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
