//! The one trait through which the engine calls stages, and the graph they form.

use super::key::Hash;
use super::source::SourceFile;
pub use super::store::OutputRef;
use super::store::Store;
use anyhow::{anyhow, Context as _};
use std::collections::BTreeMap;
use std::path::PathBuf;

/// The pseudo-stage naming a patient's own input files (its dataset folder).
pub const SOURCE: &str = "source";

/// A named output a stage returns; the engine hashes and stores the bytes.
pub struct Output {
    pub name: String,
    pub bytes: Vec<u8>,
}

impl Output {
    pub fn new(name: impl Into<String>, bytes: impl Into<Vec<u8>>) -> Output {
        Output { name: name.into(), bytes: bytes.into() }
    }
}

/// An input file: its name (relative path for source files) and where to read it.
#[derive(Debug, Clone)]
pub struct InputFile {
    pub name: String,
    pub path: PathBuf,
}

/// A pure function of its inputs and its own parameters.
pub trait Stage: Send + Sync {
    /// Unique name; also the name of its table in the configuration.
    fn name(&self) -> &'static str;
    /// Bumped whenever the stage's semantics change, so old cache entries stop matching.
    fn version(&self) -> u32;
    /// Upstream stages whose outputs this one reads ([`SOURCE`] for the patient's own files).
    fn inputs(&self) -> &'static [&'static str];
    /// This stage's own parameters, and nothing else.
    fn params(&self) -> serde_json::Value;
    /// A cohort stage runs once, after every patient has passed all per-patient stages.
    fn is_cohort(&self) -> bool {
        false
    }
    /// Whether this stage reads output `output` of its input `stage`. Only outputs it reads
    /// enter its cache key, so a change elsewhere in that stage's outputs (a log with wall
    /// times, say) does not make it rerun. All are read unless a stage says otherwise.
    fn reads(&self, _stage: &str, _output: &str) -> bool {
        true
    }
    /// Whether output `name` is published to `out_dir` (all are, unless a stage says otherwise).
    fn publishes(&self, _name: &str) -> bool {
        true
    }
    /// The replicas this stage fans each patient out into (none: empty). It and every
    /// per-patient stage after it then run once per replica, each as unit
    /// `<patient>/<replica>` with its own cache key and `out_dir/<patient>/<replica>/` folder,
    /// until the stage that [gathers](Stage::gathers_replicas) them.
    fn replica_names(&self) -> Vec<String> {
        Vec::new()
    }
    /// Whether this stage runs once per patient over every replica's outputs
    /// ([`Context::replica_count`], [`Context::in_replica`]). Without a fan-out it sees one.
    fn gathers_replicas(&self) -> bool {
        false
    }
    /// Compute the outputs. Must not read anything the context does not hand it.
    fn run(&self, ctx: &Context) -> anyhow::Result<Vec<Output>>;
}

/// Where a graph fans patients out into replicas, and where it gathers them again (indices
/// into the per-patient stages, in order).
#[derive(Debug, Clone, PartialEq)]
pub struct ReplicaSpan {
    pub fan_out: usize,
    /// The gathering stage; none when the graph was cut (`--until`) before it.
    pub gather: Option<usize>,
    pub names: Vec<String>,
}

impl ReplicaSpan {
    /// Whether the per-patient stage at `index` runs once per replica.
    pub fn replicates(&self, index: usize) -> bool {
        index >= self.fan_out && self.gather.is_none_or(|g| index < g)
    }

    /// The unit a replica's stages are keyed and published under.
    pub fn unit(&self, patient: &str, replica: usize) -> String {
        format!("{patient}/{}", self.names[replica])
    }
}

/// The stages in an order where each comes after all of its inputs.
pub struct StageGraph {
    stages: Vec<Box<dyn Stage>>,
}

impl StageGraph {
    /// Checks that names are unique and every input is declared earlier.
    pub fn new(stages: Vec<Box<dyn Stage>>) -> anyhow::Result<StageGraph> {
        let mut seen: Vec<&str> = vec![SOURCE];
        for s in &stages {
            if seen.contains(&s.name()) {
                return Err(anyhow!("stage `{}` is declared twice", s.name()));
            }
            for input in s.inputs() {
                if !seen.contains(input) {
                    return Err(anyhow!("stage `{}` reads `{input}`, which is not declared before it", s.name()));
                }
            }
            if !s.replica_names().is_empty() && s.is_cohort() {
                return Err(anyhow!("cohort stage `{}` cannot fan out into replicas", s.name()));
            }
            let cohort_input = s.inputs().iter().any(|i| stages.iter().any(|t| t.name() == *i && t.is_cohort()));
            if cohort_input && !s.is_cohort() {
                return Err(anyhow!("per-patient stage `{}` cannot read a cohort stage", s.name()));
            }
            seen.push(s.name());
        }
        let fanning = stages.iter().filter(|s| !s.replica_names().is_empty()).count();
        if fanning > 1 {
            return Err(anyhow!("only one stage may fan out into replicas ({fanning} do)"));
        }
        let graph = StageGraph { stages };
        if let Some(span) = graph.replica_span() {
            if span.gather.is_none() {
                let name = graph.per_patient()[span.fan_out].name();
                return Err(anyhow!(
                    "stage `{name}` fans out into replicas, and no later per-patient stage gathers them"
                ));
            }
        }
        Ok(graph)
    }

    /// The stages run once per patient, in order.
    pub fn per_patient(&self) -> Vec<&dyn Stage> {
        self.stages.iter().filter(|s| !s.is_cohort()).map(|s| s.as_ref()).collect()
    }

    /// Where the per-patient stages fan out into replicas and gather again, if they do.
    pub fn replica_span(&self) -> Option<ReplicaSpan> {
        let stages = self.per_patient();
        let fan_out = stages.iter().position(|s| !s.replica_names().is_empty())?;
        let gather = stages.iter().skip(fan_out + 1).position(|s| s.gathers_replicas()).map(|g| g + fan_out + 1);
        Some(ReplicaSpan { fan_out, gather, names: stages[fan_out].replica_names() })
    }

    /// How many times each stage runs for `patients` patients (replicated stages once per replica).
    pub fn runs_per_stage(&self, patients: usize) -> Vec<(&'static str, u64)> {
        let span = self.replica_span();
        let mut index = 0;
        let mut out = Vec::new();
        for s in &self.stages {
            let runs = if s.is_cohort() {
                1
            } else {
                let replicas = span.as_ref().filter(|sp| sp.replicates(index)).map_or(1, |sp| sp.names.len());
                index += 1;
                patients * replicas
            };
            out.push((s.name(), runs as u64));
        }
        out
    }

    pub fn stages(&self) -> &[Box<dyn Stage>] {
        &self.stages
    }

    pub fn names(&self) -> Vec<&'static str> {
        self.stages.iter().map(|s| s.name()).collect()
    }

    pub fn get(&self, name: &str) -> Option<&dyn Stage> {
        self.stages.iter().find(|s| s.name() == name).map(|s| s.as_ref())
    }

    /// The per-patient stages alone: what one shard of a cohort runs.
    pub fn without_cohort(self) -> StageGraph {
        StageGraph { stages: self.stages.into_iter().filter(|s| !s.is_cohort()).collect() }
    }

    /// The graph cut after `last`: `last` and every stage it depends on, in order.
    pub fn until(self, last: &str) -> anyhow::Result<StageGraph> {
        if self.get(last).is_none() {
            return Err(anyhow!("--until {last}: no such stage (stages: {})", self.names().join(", ")));
        }
        let mut needed = vec![last];
        for s in self.stages.iter().rev() {
            if needed.contains(&s.name()) {
                needed.extend(s.inputs().iter().copied());
            }
        }
        // A graph cut inside a replica span has no gathering stage: each replica ends on its own.
        let stages = self.stages.into_iter().filter(|s| needed.contains(&s.name())).collect();
        Ok(StageGraph { stages })
    }
}

/// The outputs a stage finished with, per upstream stage name.
pub type Finished = BTreeMap<&'static str, Vec<OutputRef>>;

/// What a stage's `run` may read: its inputs, nothing else.
pub struct Context<'a> {
    /// The stage being run: what it may read.
    pub(crate) stage: &'a dyn Stage,
    pub(crate) unit: &'a str,
    /// The replica this run is for (replicated stages only).
    pub(crate) replica: Option<usize>,
    /// A gathering stage's view of every replica's outputs (empty: no fan-out happened).
    pub(crate) replicas: &'a [Finished],
    pub(crate) store: &'a Store,
    pub(crate) sources: &'a [SourceFile],
    pub(crate) inputs: &'a Finished,
    pub(crate) cohort: &'a BTreeMap<String, Finished>,
    /// Each patient's replicas' outputs, for a cohort stage (patients not fanned out: none).
    pub(crate) cohort_replicas: &'a BTreeMap<String, Vec<Finished>>,
    /// Patients that failed before a cohort stage (it reports them; they are in its key).
    pub(crate) failed: &'a [String],
}

impl<'a> Context<'a> {
    /// The patient this run is for (`"cohort"` for a cohort stage).
    pub fn patient(&self) -> &str {
        self.unit
    }

    /// The replica this run is for, when the stage runs once per replica.
    pub fn replica(&self) -> Option<usize> {
        self.replica
    }

    /// How many replicas a gathering stage reads (1 when the patient was not fanned out).
    pub fn replica_count(&self) -> usize {
        self.replicas.len().max(1)
    }

    /// The same context reading replica `r`'s outputs (for a gathering stage; replica 0 is the
    /// context itself when the patient was not fanned out).
    pub fn in_replica(&self, r: usize) -> anyhow::Result<Context<'a>> {
        let inputs = match self.replicas {
            [] if r == 0 => self.inputs,
            [] => return Err(anyhow!("replica {r} asked for, and this patient was not fanned out")),
            all => all.get(r).ok_or_else(|| anyhow!("replica {r} asked for, and there are {}", all.len()))?,
        };
        Ok(Context { inputs, replica: Some(r), replicas: &[], ..*self })
    }

    /// The patient's own files (when the stage reads [`SOURCE`]), sorted by relative path.
    pub fn source_files(&self) -> &[SourceFile] {
        self.sources
    }

    /// Bytes of output `name` of upstream stage `stage` for this patient.
    pub fn read(&self, stage: &str, name: &str) -> anyhow::Result<Vec<u8>> {
        self.read_from(self.inputs, stage, name)
    }

    /// The patients that failed before this cohort stage, in order.
    pub fn failed_patients(&self) -> &[String] {
        self.failed
    }

    /// The patients that reached a cohort stage, in order.
    pub fn cohort_patients(&self) -> Vec<&str> {
        self.cohort.keys().map(|k| k.as_str()).collect()
    }

    /// Bytes of output `name` of stage `stage` for `patient` (cohort stages only).
    pub fn read_patient(&self, patient: &str, stage: &str, name: &str) -> anyhow::Result<Vec<u8>> {
        let finished =
            self.cohort.get(patient).ok_or_else(|| anyhow!("patient `{patient}` did not reach this cohort stage"))?;
        if !finished.contains_key(stage) && self.patient_replica_count(patient) > 1 {
            return Err(anyhow!("stage `{stage}` ran once per replica for patient `{patient}`: read one replica's"));
        }
        self.read_from(finished, stage, name)
    }

    /// How many replicas `patient` was fanned out into (1: none), for a cohort stage.
    pub fn patient_replica_count(&self, patient: &str) -> usize {
        self.cohort_replicas.get(patient).map_or(1, |r| r.len().max(1))
    }

    /// Bytes of output `name` of stage `stage` for replica `r` of `patient` (cohort stages only;
    /// replica 0 of a patient not fanned out is the patient itself).
    pub fn read_patient_replica(&self, patient: &str, r: usize, stage: &str, name: &str) -> anyhow::Result<Vec<u8>> {
        match self.cohort_replicas.get(patient).filter(|all| !all.is_empty()) {
            None if r == 0 => self.read_patient(patient, stage, name),
            None => Err(anyhow!("replica {r} of patient `{patient}` asked for, and it was not fanned out")),
            Some(all) => {
                let finished =
                    all.get(r).ok_or_else(|| anyhow!("patient `{patient}` has {} replicas, not {r}", all.len()))?;
                self.read_from(finished, stage, name)
            }
        }
    }

    /// The files of input `stage` as named paths: the patient's own files for [`SOURCE`], else
    /// that stage's stored outputs. Lets a stage read a file set wherever it came from. The
    /// stored ones were re-hashed by the lookup that served them this run, as for [`Context::path`].
    pub fn input_files(&self, stage: &str) -> anyhow::Result<Vec<InputFile>> {
        if stage == SOURCE {
            let files = self.sources.iter();
            return Ok(files.map(|f| InputFile { name: f.rel.clone(), path: f.path.clone() }).collect());
        }
        let outputs = self.inputs.get(stage).ok_or_else(|| anyhow!("stage `{stage}` is not an input here"))?;
        let store = self.store;
        let read = outputs.iter().filter(|o| self.stage.reads(stage, &o.name));
        Ok(read.map(|o| InputFile { name: o.name.clone(), path: store.blob_path(&o.hash) }).collect())
    }

    /// Path of a stored upstream output, for stages that stream a large file. The lookup that
    /// served it this run re-hashed the file; what the stage then reads is not checked again.
    pub fn path(&self, stage: &str, name: &str) -> anyhow::Result<PathBuf> {
        Ok(self.store.blob_path(&self.find(self.inputs, stage, name)?.hash))
    }

    fn find<'f>(&self, finished: &'f Finished, stage: &str, name: &str) -> anyhow::Result<&'f OutputRef> {
        if !self.stage.reads(stage, name) {
            return Err(anyhow!("stage `{}` reads `{stage}/{name}` but does not declare it", self.stage.name()));
        }
        finished
            .get(stage)
            .ok_or_else(|| anyhow!("stage `{stage}` is not an input here"))?
            .iter()
            .find(|o| o.name == name)
            .ok_or_else(|| anyhow!("stage `{stage}` has no output `{name}`"))
    }

    /// The bytes of a stored output, checked against its hash once more (the lookup that served
    /// it checked the file; this checks the very bytes the stage gets).
    fn read_from(&self, finished: &Finished, stage: &str, name: &str) -> anyhow::Result<Vec<u8>> {
        let output = self.find(finished, stage, name)?;
        let path = self.store.blob_path(&output.hash);
        let bytes = std::fs::read(&path)
            .with_context(|| format!("reading {stage}/{name} from the cache ({})", path.display()))?;
        if Hash::of(&bytes) != output.hash {
            return Err(anyhow!(
                "{stage}/{name} in the cache ({}) changed after it was checked; run again to compute it anew",
                path.display()
            ));
        }
        Ok(bytes)
    }
}
