//! The streaming executor.
//!
//! Patients flow through the per-patient stages concurrently: each stage has its own pool of
//! worker threads and a bounded channel in front of it, so a slow stage holds back only as many
//! patients as it has workers. A patient that fails at one stage is reported and skipped by the
//! stages after it; the others go on. Cohort stages run once every patient is through.
//!
//! A run asked to stop ([`StopRequest`], Ctrl-C or SIGTERM from the command line) starts no
//! further stage: the ones in progress finish and are cached, the rest are recorded as
//! [`Outcome::Interrupted`], so that running the same command again goes on where it stopped.
//!
//! A cache entry that fails a check (a blob that does not re-hash to its name, a manifest that
//! does not match its key or digest) is computed again, with a one-line warning naming the
//! stage, the patient and the file ([`RunSummary::notices`]). A stage that waits more than a
//! second for another process's lock on its key says so, and the wait is counted
//! ([`RunSummary::key_lock_wait_seconds`]).
//!
//! A stage may fan a patient out into replicas ([`Stage::replica_names`]): a splitter hands
//! each replica on as its own job, and a collector in front of the gathering stage waits for
//! all of a patient's replicas and merges them back into one job.

use super::export::publish;
pub use super::export::Publish;
use super::lease::Lease;
use super::lock::FileLock;
use super::plan::{self, Decision};
use super::progress::Progress;
pub use super::source::Unit;
use super::source::{self, SourceFile};
use super::stage::{Context, Finished, OutputRef, ReplicaSpan, Stage, StageGraph, SOURCE};
use super::store::{InputRef, Manifest, Store};
pub use super::summary::{Outcome, Record, RunSummary};
use crossbeam_channel::{bounded, Receiver};
use std::collections::{BTreeMap, HashMap};
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// The unit a cohort stage runs for, and its folder name under `out_dir` (none: `out_dir` itself).
pub const COHORT: &str = "cohort";

pub struct RunOptions {
    /// Re-hash every source file instead of trusting its fingerprint, and distrust manifests
    /// that record no digest. (Every cached blob is re-hashed before use either way, unless the
    /// store checks sizes only: [`Store::check_sizes_only`].)
    pub verify: bool,
    /// Stages recomputed even when cached.
    pub force: Vec<String>,
    /// Worker threads per stage name; stages not listed get `default_workers`.
    pub workers: HashMap<String, usize>,
    pub default_workers: usize,
    /// Where results are published (`out_dir/<patient>/<output>`).
    pub out_dir: PathBuf,
    /// As read-only hard links to the cache (the default) or as independent copies.
    pub publish: Publish,
    /// Set while the run works to have it start no further stage.
    pub stop: StopRequest,
}

/// A request that a run start no further stage; clones share it. The stages in progress when
/// it comes finish and are cached.
#[derive(Debug, Clone, Default)]
pub struct StopRequest(Arc<AtomicBool>);

impl StopRequest {
    pub fn request(&self) {
        self.0.store(true, Ordering::SeqCst);
    }

    pub fn requested(&self) -> bool {
        self.0.load(Ordering::SeqCst)
    }
}

impl RunOptions {
    fn workers_for(&self, stage: &str) -> usize {
        self.workers.get(stage).copied().unwrap_or(self.default_workers).max(1)
    }
}

/// A patient (or one of its replicas) travelling through the stages.
struct Job {
    unit: Unit,
    /// Which replica this job is, between a fan-out and its gathering.
    replica: Option<usize>,
    sources: Option<Vec<SourceFile>>,
    finished: Finished,
    /// After a gathering: every replica's outputs, in replica order.
    replicas: Vec<Finished>,
    failed_at: Option<String>,
    records: Vec<Record>,
}

impl Job {
    fn new(unit: Unit) -> Job {
        Job {
            unit,
            replica: None,
            sources: None,
            finished: Finished::new(),
            replicas: vec![],
            failed_at: None,
            records: vec![],
        }
    }

    /// The unit this job's stages are keyed and published under.
    fn key_unit(&self, span: Option<&ReplicaSpan>) -> String {
        match (self.replica, span) {
            (Some(r), Some(span)) => span.unit(&self.unit.id, r),
            _ => self.unit.id.clone(),
        }
    }
}

/// Shared state of a run.
struct Shared<'a> {
    store: &'a Store,
    options: &'a RunOptions,
    progress: &'a Progress,
    span: Option<ReplicaSpan>,
    /// Warnings and waits, in the order they happened.
    notices: Mutex<Vec<String>>,
    /// Time stages spent waiting for other processes' key locks, summed over workers.
    key_lock_wait: Mutex<Duration>,
}

impl Shared<'_> {
    /// Shows `line` now (above any progress bars) and keeps it for the summary.
    fn notice(&self, line: String) {
        self.progress.notice(&line);
        self.notices.lock().expect("notices").push(line);
    }
}

/// Runs `graph` for every unit, then its cohort stages. Never stops early for a failure.
pub fn run(graph: &StageGraph, store: &Store, units: &[Unit], options: &RunOptions, progress: &Progress) -> RunSummary {
    let started = Instant::now();
    let shared = Shared {
        store,
        options,
        progress,
        span: graph.replica_span(),
        notices: Mutex::new(Vec::new()),
        key_lock_wait: Mutex::new(Duration::ZERO),
    };
    // Marks this process's temporary files in out dirs as in use (see `leftovers`).
    let _alive = match Lease::take(store.root(), "aret-pipe run") {
        Ok(lock) => Some(lock),
        Err(e) => {
            shared.notice(format!("warning: {e:#}; another process may take this run's temporary files for litter"));
            None
        }
    };
    let mut jobs = stream_patients(&shared, &graph.per_patient(), units);
    jobs.sort_by(|a, b| a.unit.id.cmp(&b.unit.id));

    let mut records: Vec<Record> = jobs.iter_mut().flat_map(|j| std::mem::take(&mut j.records)).collect();
    let failed: Vec<String> = jobs.iter().filter(|j| j.failed_at.is_some()).map(|j| j.unit.id.clone()).collect();
    jobs.retain(|j| j.failed_at.is_none());
    let replicas: BTreeMap<String, Vec<Finished>> =
        jobs.iter_mut().map(|j| (j.unit.id.clone(), std::mem::take(&mut j.replicas))).collect();
    let patients: BTreeMap<String, Finished> = jobs.into_iter().map(|j| (j.unit.id, j.finished)).collect();
    let names = shared.span.as_ref().map_or(&[][..], |s| &s.names[..]);
    let cohort_replicas = plan::CohortReplicas { finished: &replicas, names };
    // Cohort stages run in order; each may read the patients' outputs and earlier cohort stages.
    let mut cohort_finished = Finished::new();
    let mut cohort_failed: Option<String> = None;
    for stage in graph.stages().iter().filter(|s| s.is_cohort()) {
        let stage = stage.as_ref();
        let outcome = if let Some(up) = &cohort_failed {
            Outcome::Skipped { upstream: up.clone() }
        } else if options.stop.requested() {
            Outcome::Interrupted
        } else {
            progress.started(stage.name(), COHORT);
            let inputs = plan::cohort_inputs(stage, &patients, &cohort_replicas, &cohort_finished, &failed);
            let ctx = Context {
                stage,
                unit: COHORT,
                replica: None,
                replicas: &[],
                store,
                sources: &[],
                inputs: &cohort_finished,
                cohort: &patients,
                cohort_replicas: &replicas,
                failed: &failed,
            };
            let (outcome, outputs) = run_stage(&shared, stage, COHORT, inputs, &ctx, &options.out_dir);
            match outputs {
                Some(outputs) => drop(cohort_finished.insert(stage.name(), outputs)),
                None => cohort_failed = Some(stage.name().to_string()),
            }
            outcome
        };
        progress.finished(stage.name(), COHORT, &outcome);
        records.push(Record { unit: COHORT.into(), stage: stage.name().into(), outcome });
    }
    RunSummary {
        records,
        wall_seconds: started.elapsed().as_secs_f64(),
        notices: shared.notices.into_inner().expect("notices"),
        gc_wait_seconds: 0.0,
        key_lock_wait_seconds: shared.key_lock_wait.into_inner().expect("lock wait").as_secs_f64(),
        fetched_from_remote: 0,
    }
    .counted()
}

/// Pushes every unit through the per-patient stages, each stage with its own worker pool.
fn stream_patients(shared: &Shared, stages: &[&dyn Stage], units: &[Unit]) -> Vec<Job> {
    let mut done = Vec::with_capacity(units.len());
    std::thread::scope(|scope| {
        let (feed_tx, mut rx) = bounded::<Job>(1);
        let span = shared.span.as_ref();
        for (index, &stage) in stages.iter().enumerate() {
            if let Some(span) = span.filter(|s| s.fan_out == index) {
                rx = split(scope, rx, span.names.len());
            }
            if let Some(span) = span.filter(|s| s.gather == Some(index)) {
                rx = gather(scope, rx, span.names.len(), replicated_names(stages, span));
            }
            let workers = shared.options.workers_for(stage.name());
            let (tx, next_rx) = bounded::<Job>(workers);
            for _ in 0..workers {
                let (rx, tx) = (rx.clone(), tx.clone());
                scope.spawn(move || {
                    for mut job in rx {
                        step(shared, stage, &mut job);
                        if tx.send(job).is_err() {
                            break;
                        }
                    }
                });
            }
            rx = next_rx;
        }
        // A graph cut inside the span (`--until`) still hands back one job per patient.
        if let Some(span) = span.filter(|s| s.gather.is_none()) {
            rx = gather(scope, rx, span.names.len(), replicated_names(stages, span));
        }
        scope.spawn(move || {
            for unit in units {
                if feed_tx.send(Job::new(unit.clone())).is_err() {
                    break;
                }
            }
        });
        done.extend(rx.iter());
    });
    done
}

/// The names of the stages that run once per replica.
fn replicated_names(stages: &[&dyn Stage], span: &ReplicaSpan) -> Vec<&'static str> {
    stages.iter().enumerate().filter(|(i, _)| span.replicates(*i)).map(|(_, s)| s.name()).collect()
}

/// Hands each job on as `count` replica jobs (a job that already failed goes on whole).
fn split<'s>(scope: &'s std::thread::Scope<'s, '_>, rx: Receiver<Job>, count: usize) -> Receiver<Job> {
    let (tx, out) = bounded::<Job>(count);
    scope.spawn(move || {
        for mut job in rx {
            if job.failed_at.is_some() {
                if tx.send(job).is_err() {
                    return;
                }
                continue;
            }
            let records = std::mem::take(&mut job.records);
            for r in 0..count {
                let replica = Job {
                    replica: Some(r),
                    sources: job.sources.clone(),
                    finished: job.finished.clone(),
                    records: if r == 0 { records.clone() } else { vec![] },
                    ..Job::new(job.unit.clone())
                };
                if tx.send(replica).is_err() {
                    return;
                }
            }
        }
    });
    out
}

/// Waits for all `count` replicas of a patient and hands them on as one job: the outputs of the
/// stages before the fan-out as its own, each replica's in `replicas`. A failed replica fails it.
fn gather<'s>(
    scope: &'s std::thread::Scope<'s, '_>,
    rx: Receiver<Job>,
    count: usize,
    replicated: Vec<&'static str>,
) -> Receiver<Job> {
    let (tx, out) = bounded::<Job>(1);
    scope.spawn(move || {
        let mut waiting: HashMap<String, Vec<Job>> = HashMap::new();
        for job in rx {
            let merged = match job.replica {
                None => job,
                Some(_) => {
                    let id = job.unit.id.clone();
                    let parts = waiting.entry(id.clone()).or_default();
                    parts.push(job);
                    if parts.len() < count {
                        continue;
                    }
                    let parts = waiting.remove(&id).expect("just filled");
                    merge(parts, &replicated)
                }
            };
            if tx.send(merged).is_err() {
                return;
            }
        }
    });
    out
}

fn merge(mut parts: Vec<Job>, replicated: &[&'static str]) -> Job {
    parts.sort_by_key(|j| j.replica);
    let failed_at = parts.iter().find_map(|j| j.failed_at.clone());
    let records = parts.iter_mut().flat_map(|j| std::mem::take(&mut j.records)).collect();
    let replicas: Vec<Finished> = parts.iter().map(|j| j.finished.clone()).collect();
    let first = parts.swap_remove(0);
    let mut finished = first.finished;
    finished.retain(|name, _| !replicated.contains(name));
    Job { sources: first.sources, finished, replicas, failed_at, records, ..Job::new(first.unit) }
}

/// One stage for one patient (or replica): serve from the cache or compute, then publish.
fn step(shared: &Shared, stage: &dyn Stage, job: &mut Job) {
    let unit = job.key_unit(shared.span.as_ref());
    let outcome = if let Some(up) = &job.failed_at {
        Outcome::Skipped { upstream: up.clone() }
    } else if shared.options.stop.requested() {
        Outcome::Interrupted
    } else {
        shared.progress.started(stage.name(), &unit);
        let outcome = match ensure_sources(shared, stage, job) {
            Err(cause) => Outcome::Failed { cause },
            Ok(()) => {
                let sources = job.sources.as_deref().unwrap_or(&[]);
                let replicas: &[Finished] = if stage.gathers_replicas() { &job.replicas } else { &[] };
                let inputs = match (replicas, &shared.span) {
                    ([], _) | (_, None) => plan::patient_inputs(stage, sources, &job.finished),
                    (replicas, Some(span)) => {
                        plan::gathered_inputs(stage, sources, &job.finished, replicas, &span.names)
                    }
                };
                let (no_cohort, no_replicas) = (BTreeMap::new(), BTreeMap::new());
                let ctx = Context {
                    stage,
                    unit: &job.unit.id,
                    replica: job.replica,
                    replicas,
                    store: shared.store,
                    sources,
                    inputs: &job.finished,
                    cohort: &no_cohort,
                    cohort_replicas: &no_replicas,
                    failed: &[],
                };
                let dir = shared.options.out_dir.join(&unit);
                let (outcome, outputs) = run_stage(shared, stage, &unit, inputs, &ctx, &dir);
                if let Some(outputs) = outputs {
                    job.finished.insert(stage.name(), outputs);
                }
                outcome
            }
        };
        if matches!(outcome, Outcome::Failed { .. }) {
            job.failed_at = Some(stage.name().to_string());
        }
        outcome
    };
    shared.progress.finished(stage.name(), &unit, &outcome);
    job.records.push(Record { unit, stage: stage.name().into(), outcome });
}

fn ensure_sources(shared: &Shared, stage: &dyn Stage, job: &mut Job) -> Result<(), String> {
    if job.sources.is_none() && stage.inputs().contains(&SOURCE) {
        let files = source::scan(shared.store, &job.unit, shared.options.verify).map_err(|e| format!("{e:#}"))?;
        job.sources = Some(files);
    }
    Ok(())
}

/// Looks the stage up in the cache, else computes it under its key's lock; publishes the outputs.
fn run_stage(
    shared: &Shared,
    stage: &dyn Stage,
    unit: &str,
    inputs: Vec<(String, String, crate::Hash)>,
    ctx: &Context,
    publish_dir: &std::path::Path,
) -> (Outcome, Option<Vec<OutputRef>>) {
    let store = shared.store;
    let forced = shared.options.force.iter().any(|f| f == stage.name());
    let keyed = plan::key(stage, unit, inputs);
    let served = |manifest: Box<Manifest>, fetched: bool| {
        let outcome = if fetched {
            Outcome::Fetched { seconds: manifest.wall_seconds }
        } else {
            // A result cached here before the remote was configured (or before it was reachable).
            share(shared, &manifest);
            Outcome::Cached { seconds: manifest.wall_seconds }
        };
        finish(shared, stage, &manifest, publish_dir).map(|()| (outcome, Some(manifest.outputs)))
    };
    let result = (|| -> anyhow::Result<(Outcome, Option<Vec<OutputRef>>)> {
        match plan::decide(store, stage, unit, &keyed, shared.options.verify, forced) {
            Decision::Cached(m) => return served(m, false),
            Decision::Fetched(m) => return served(m, true),
            _ => {}
        }
        let what = format!("the lock on {} · {unit}", stage.name());
        let lock_path = store.lock_path(&format!("{}-{}", stage.name(), keyed.key.hex()));
        let (lock, waited) = FileLock::wait(&lock_path, &what, &mut |line| shared.notice(line))?;
        *shared.key_lock_wait.lock().expect("lock wait") += waited;
        lock.describe_holder(&format!("aret-pipe computing {} for {unit}", stage.name()));
        // Another process may have computed it while we waited for the lock.
        match plan::decide(store, stage, unit, &keyed, shared.options.verify, forced) {
            Decision::Cached(m) => return served(m, false),
            Decision::Fetched(m) => return served(m, true),
            Decision::Distrusted(why) => shared.notice(format!("warning: {why}; computing it again")),
            Decision::Compute(_) => {}
        }
        let started = Instant::now();
        let outputs = match catch_unwind(AssertUnwindSafe(|| stage.run(ctx))) {
            Ok(Ok(outputs)) => outputs,
            Ok(Err(e)) => return Ok((Outcome::Failed { cause: format!("{e:#}") }, None)),
            Err(panic) => {
                return Ok((Outcome::Failed { cause: format!("internal error (panic): {}", panic_text(&panic)) }, None))
            }
        };
        let mut refs = Vec::with_capacity(outputs.len());
        for output in &outputs {
            if refs.iter().any(|r: &OutputRef| r.name == output.name) {
                anyhow::bail!("stage `{}` returned output `{}` twice", stage.name(), output.name);
            }
            refs.push(store.put_blob(&output.name, &output.bytes)?);
        }
        let seconds = started.elapsed().as_secs_f64();
        let manifest = Manifest {
            stage: stage.name().into(),
            version: stage.version(),
            key: keyed.key,
            unit: unit.into(),
            params: keyed.params.clone(),
            inputs: keyed
                .inputs
                .iter()
                .map(|(s, n, h)| InputRef { stage: s.clone(), name: n.clone(), hash: *h })
                .collect(),
            outputs: refs.clone(),
            wall_seconds: seconds,
            tool_version: concat!("aret-pipe ", env!("CARGO_PKG_VERSION")).into(),
            created_unix: std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map(|d| d.as_secs())
                .unwrap_or(0),
            digest: None,
        }
        .sealed();
        store.put_manifest(&manifest)?;
        share(shared, &manifest);
        finish(shared, stage, &manifest, publish_dir)?;
        Ok((Outcome::Computed { seconds }, Some(refs)))
    })();
    if let Some(remote) = store.remote() {
        remote.take_notices().into_iter().for_each(|line| shared.notice(line));
    }
    result.unwrap_or_else(|e| (Outcome::Failed { cause: format!("{e:#}") }, None))
}

/// Hands a result held locally to the remote cache, if there is one (it uploads what it lacks).
fn share(shared: &Shared, manifest: &Manifest) {
    if let Some(remote) = shared.store.remote() {
        remote.share(shared.store, manifest);
    }
}

/// Remembers the manifest as the unit's latest and publishes the outputs the stage shows.
fn finish(
    shared: &Shared,
    stage: &dyn Stage,
    manifest: &Manifest,
    publish_dir: &std::path::Path,
) -> anyhow::Result<()> {
    shared.store.set_latest(manifest)?;
    let shown: Vec<OutputRef> = manifest.outputs.iter().filter(|o| stage.publishes(&o.name)).cloned().collect();
    publish(shared.store, publish_dir, &shown, shared.options.publish, &|line| shared.notice(line))
}

fn panic_text(panic: &Box<dyn std::any::Any + Send>) -> String {
    panic
        .downcast_ref::<&str>()
        .map(|s| s.to_string())
        .or_else(|| panic.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "unknown panic".into())
}
