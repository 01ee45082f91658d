//! `phantom`: generates a cohort patient's synthetic CT (SPEC: the embedded default dataset).
//!
//! Input: the patient's `<id>.scan.json` (real scan geometry) and `<id>.xml` (real LIDC reads).
//! Outputs: the CT series `series/NNNNNN.dcm` and the XML, unchanged — read back by `ingest`
//! through the same DICOM + XML path a real LIDC scan takes — plus PNG previews
//! (`phantom_axial.png`, `phantom_coronal.png`, `phantom_projection.png`), the only outputs
//! published to `out_dir`.

use crate::engine::{Context, Output, Stage, SOURCE};
use crate::phantom::patient;
use crate::phantom::PhantomParams;
use anyhow::anyhow;

pub const VERSION: u32 = 3;

pub struct Phantom {
    pub params: PhantomParams,
}

impl Stage for Phantom {
    fn name(&self) -> &'static str {
        "phantom"
    }
    fn version(&self) -> u32 {
        VERSION
    }
    fn inputs(&self) -> &'static [&'static str] {
        &[SOURCE]
    }
    fn params(&self) -> serde_json::Value {
        super::params_json(&self.params)
    }
    fn publishes(&self, name: &str) -> bool {
        name.ends_with(".png")
    }
    fn run(&self, ctx: &Context) -> anyhow::Result<Vec<Output>> {
        let files = ctx.source_files();
        let find = |suffix: &str| {
            files
                .iter()
                .find(|f| f.rel.ends_with(suffix))
                .map(|f| f.path.as_path())
                .ok_or_else(|| anyhow!("patient {} has no *{suffix} file", ctx.patient()))
        };
        let generated = patient::generate_from_files(find(".scan.json")?, find(".xml")?, &self.params)?;
        let mut outputs: Vec<Output> =
            generated.series.into_iter().map(|(name, bytes)| Output::new(format!("series/{name}"), bytes)).collect();
        outputs.push(Output::new(generated.annotations.0, generated.annotations.1));
        outputs.extend(generated.previews.into_iter().map(|(name, bytes)| Output::new(name, bytes)));
        Ok(outputs)
    }
}
