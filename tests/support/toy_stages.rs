//! Toy stages for the engine's tests (it knows nothing about CT): a patient's files joined,
//! their length, and a cohort report of the lengths, each counting its runs.
#![allow(dead_code)] // shared by several test crates; each uses a subset

use aret_pipe::engine::run::StopRequest;
use aret_pipe::engine::{Context, Output, Stage, SOURCE};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;

pub type Counter = Arc<AtomicUsize>;

/// Joins the patient's files (sorted by name) with `sep`. Fails on a file named `poison`; a
/// file named `stop` asks the run to stop while this stage works (as Ctrl-C would).
pub struct Concat {
    pub sep: String,
    pub runs: Counter,
    pub stop: StopRequest,
}
impl Stage for Concat {
    fn name(&self) -> &'static str {
        "concat"
    }
    fn version(&self) -> u32 {
        1
    }
    fn inputs(&self) -> &'static [&'static str] {
        &[SOURCE]
    }
    fn params(&self) -> serde_json::Value {
        serde_json::json!({ "sep": self.sep })
    }
    fn run(&self, ctx: &Context) -> anyhow::Result<Vec<Output>> {
        self.runs.fetch_add(1, Ordering::SeqCst);
        let mut parts = Vec::new();
        for f in ctx.source_files() {
            if f.rel == "poison" {
                anyhow::bail!("file `poison` is not allowed");
            }
            if f.rel == "panic" {
                panic!("deliberate panic");
            }
            if f.rel == "stop" {
                self.stop.request();
            }
            parts.push(std::fs::read_to_string(&f.path)?);
        }
        let count = parts.len().to_string();
        Ok(vec![Output::new("all.txt", parts.join(&self.sep)), Output::new("files.txt", count)])
    }
}

/// Length of `concat/all.txt`, or only its parity. Reads nothing else of `concat`.
pub struct Length {
    pub parity_only: bool,
    pub runs: Counter,
}
impl Stage for Length {
    fn name(&self) -> &'static str {
        "length"
    }
    fn version(&self) -> u32 {
        1
    }
    fn inputs(&self) -> &'static [&'static str] {
        &["concat"]
    }
    fn params(&self) -> serde_json::Value {
        serde_json::json!({ "parity_only": self.parity_only })
    }
    fn reads(&self, _stage: &str, output: &str) -> bool {
        output == "all.txt"
    }
    fn run(&self, ctx: &Context) -> anyhow::Result<Vec<Output>> {
        self.runs.fetch_add(1, Ordering::SeqCst);
        let n = ctx.read("concat", "all.txt")?.len();
        let v = if self.parity_only { n % 2 } else { n };
        Ok(vec![Output::new("len.txt", v.to_string())])
    }
}

/// Cohort: one line per patient that got through.
pub struct Report {
    pub runs: Counter,
}
impl Stage for Report {
    fn name(&self) -> &'static str {
        "report"
    }
    fn version(&self) -> u32 {
        1
    }
    fn inputs(&self) -> &'static [&'static str] {
        &["length"]
    }
    fn params(&self) -> serde_json::Value {
        serde_json::json!({})
    }
    fn is_cohort(&self) -> bool {
        true
    }
    fn run(&self, ctx: &Context) -> anyhow::Result<Vec<Output>> {
        self.runs.fetch_add(1, Ordering::SeqCst);
        let mut text = String::new();
        for p in ctx.cohort_patients() {
            let len = String::from_utf8(ctx.read_patient(p, "length", "len.txt")?)?;
            text.push_str(&format!("{p} {len}\n"));
        }
        Ok(vec![Output::new("report.txt", text)])
    }
}

#[derive(Default)]
pub struct Counters {
    pub concat: Counter,
    pub length: Counter,
    pub report: Counter,
}

impl Counters {
    pub fn take(&self) -> [usize; 3] {
        [&self.concat, &self.length, &self.report].map(|c| c.swap(0, Ordering::SeqCst))
    }
}

/// The id of a process that has ended.
pub fn ended_pid() -> u32 {
    let mut child = std::process::Command::new("true").spawn().unwrap();
    let pid = child.id();
    child.wait().unwrap();
    pid
}
