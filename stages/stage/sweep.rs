//! `sweep`: nodule candidates from a percentile threshold sweep of the density (SPEC §3 sweep).
//!
//! Input: `grid/density.mhd/.raw`. At each percentile p of the non-zero density (numpy's
//! linear rule): mask = σ ≥ t; connected components; drop those under `min_voxels`; binary
//! closing with a radius-`closing_radius` ball on the zero-padded mask; components again; keep
//! those whose equivalent-sphere diameter is within `diameter_mm`. Outputs: `sweep.csv` (one
//! row per threshold × candidate) and `sweep.json` (the same, with the parameters, for select,
//! which regenerates candidate masks with [`levels`]), and `lung_field.mhd/.raw` when the
//! region is the lung field.
//!
//! Two switches (the paper's sweep is `score = "density"`, `region = "box"`): the
//! thresholded `score` may be the local contrast σ − G(σ, `background_mm`) instead of σ, and
//! the `region` may be the lung field found in σ itself ([`lung_field`]): percentiles are then
//! taken over the region's values and candidates lie inside it.

use crate::artifacts::{DENSITY, LUNG_FIELD, SWEEP, SWEEP_CSV};
use crate::engine::{Context, Output, Stage};
use crate::kernels::components::{label, Components, Connectivity};
use crate::kernels::lung_mask::{local_contrast, lung_field};
use crate::kernels::{morphology, stats};
use crate::volume::{Geometry, Volume};
use anyhow::bail;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::fmt::Write as _;

// 3: writes the lung field it swept.
pub const VERSION: u32 = 4;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Percentiles of the non-zero density used as thresholds.
    pub percentiles: Vec<f64>,
    /// Neighbourhood of the connected components: 6, 18 or 26.
    pub connectivity: Connectivity,
    /// Components smaller than this (voxels) are dropped before the closing.
    pub min_voxels: usize,
    /// Radius (voxels) of the ball the mask is closed with; 0 skips the closing.
    pub closing_radius: usize,
    /// Candidates keep an equivalent-sphere diameter within [min, max] mm.
    pub diameter_mm: [f64; 2],
    /// What is thresholded.
    pub score: Score,
    /// Width (mm) of the Gaussian background subtracted by `score = "local_contrast"`.
    pub background_mm: f64,
    /// Where thresholds are measured and candidates may lie.
    pub region: Region,
}

/// What the sweep thresholds.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Score {
    /// σ itself (the paper).
    Density,
    /// σ minus its Gaussian-blurred self: bright relative to the surroundings.
    LocalContrast,
}

/// Where the sweep looks.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Region {
    /// The whole box; percentiles of the non-zero values (the paper).
    Box,
    /// The lung field found in σ; percentiles of the values inside it.
    LungField,
}

impl Default for Params {
    fn default() -> Self {
        let mut percentiles = vec![85.0, 88.0];
        percentiles.extend((90..=99).map(f64::from));
        Params {
            percentiles,
            connectivity: Connectivity::TwentySix,
            min_voxels: 10,
            closing_radius: 2,
            diameter_mm: [5.0, 80.0],
            score: Score::LocalContrast,
            background_mm: 10.0,
            region: Region::LungField,
        }
    }
}

impl Params {
    pub fn check(&self) -> anyhow::Result<()> {
        if self.percentiles.is_empty() || self.percentiles.iter().any(|p| !(0.0..=100.0).contains(p)) {
            bail!("[sweep] percentiles must be a non-empty list of numbers in [0, 100]");
        }
        let [lo, hi] = self.diameter_mm;
        if lo.is_nan() || hi.is_nan() || lo > hi {
            bail!("[sweep] diameter_mm must be [min, max] with min ≤ max");
        }
        if !(self.background_mm.is_finite() && self.background_mm > 0.0) {
            bail!("[sweep] background_mm must be positive (got {})", self.background_mm);
        }
        Ok(())
    }
}

/// One surviving component at one threshold.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Candidate {
    pub percentile: f64,
    pub threshold: f64,
    /// Its label among the survivors at this threshold (1-based, scipy order).
    pub label: u32,
    pub voxels: usize,
    pub volume_mm3: f64,
    pub diameter_mm: f64,
    pub centroid_mm: [f64; 3],
}

/// One threshold's survivors: their summaries and their labels on the grid.
pub struct Level {
    pub percentile: f64,
    pub threshold: f64,
    pub candidates: Vec<Candidate>,
    pub components: Components,
}

/// What `sweep.json` holds.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SweepFile {
    pub params: Params,
    pub candidates: Vec<Candidate>,
}

/// The scored volume and the region of a sweep.
pub struct Scored {
    pub score: Volume<f32>,
    /// `None`: the whole box.
    pub region: Option<Vec<bool>>,
}

/// The lung field of `density` as the sweep uses it (`region = "lung_field"`), or an error
/// that says which key to change when there is none.
pub fn lung_field_of(density: &Volume<f32>) -> anyhow::Result<Vec<bool>> {
    match lung_field(&density.data, density.geometry.dims, density.geometry.spacing_mm) {
        Some(lungs) if lungs.field.iter().any(|&b| b) => Ok(lungs.field),
        _ => bail!(
            "no lung field found in the density (no band of parenchyma between air and tissue: \
             too coarse a grid or too short a fit?); use [sweep] region = \"box\" for such runs"
        ),
    }
}

/// What `params` thresholds, and where. `lungs` is the density's lung field when the caller
/// already has it (select reads the sweep's); otherwise it is found here when the region needs it.
pub fn scored(density: &Volume<f32>, params: &Params, lungs: Option<Vec<bool>>) -> anyhow::Result<Scored> {
    let (dims, spacing) = (density.geometry.dims, density.geometry.spacing_mm);
    let region = match params.region {
        Region::Box => None,
        Region::LungField => Some(match lungs {
            Some(lungs) => lungs,
            None => lung_field_of(density)?,
        }),
    };
    let data = match params.score {
        Score::Density => density.data.clone(),
        Score::LocalContrast => local_contrast(&density.data, dims, spacing, params.background_mm),
    };
    Ok(Scored { score: Volume { geometry: density.geometry.clone(), data }, region })
}

/// Every threshold's candidates (pure: the same density and parameters give the same levels).
pub fn levels(density: &Volume<f32>, params: &Params) -> anyhow::Result<Vec<Level>> {
    levels_of(&scored(density, params, None)?, params)
}

/// [`levels`] of an already scored density.
pub fn levels_of(scored: &Scored, params: &Params) -> anyhow::Result<Vec<Level>> {
    let Scored { score, region } = scored;
    let values: Vec<f64> = match (region, params.score) {
        (None, Score::Density) => score.data.iter().filter(|&&v| v != 0.0).map(|&v| f64::from(v)).collect(),
        (None, Score::LocalContrast) => score.data.iter().map(|&v| f64::from(v)).collect(),
        (Some(r), _) => score.data.iter().zip(r).filter(|(_, &inside)| inside).map(|(&v, _)| f64::from(v)).collect(),
    };
    if values.is_empty() || (params.score == Score::Density && values.iter().all(|&v| v == 0.0)) {
        bail!("the density is zero everywhere: nothing to threshold (did training fail?)");
    }
    let thresholds = stats::percentiles(&values, &params.percentiles)?;
    // Levels are independent: one task each (collected in percentile order).
    Ok(params
        .percentiles
        .par_iter()
        .zip(thresholds)
        .map(|(&percentile, threshold)| level(score, region.as_deref(), params, percentile, threshold))
        .collect())
}

fn level(score: &Volume<f32>, region: Option<&[bool]>, params: &Params, percentile: f64, threshold: f64) -> Level {
    let geometry = &score.geometry;
    let dims = geometry.dims;
    let inside = |i: usize| region.is_none_or(|r| r[i]);
    let mask: Vec<bool> = score.data.iter().enumerate().map(|(i, &v)| f64::from(v) >= threshold && inside(i)).collect();
    let kept = label(&mask, dims, params.connectivity).without_small(params.min_voxels).mask();
    let closed = if params.closing_radius > 0 { morphology::close(&kept, dims, params.closing_radius) } else { kept };
    let all = label(&closed, dims, params.connectivity);
    let voxel_mm3: f64 = geometry.spacing_mm.iter().product();
    let summaries = summarize(&all, geometry);
    let survivors: Vec<u32> = (1..=all.count() as u32)
        .filter(|&l| {
            let d = equivalent_diameter_mm(all.size(l) as f64 * voxel_mm3);
            d >= params.diameter_mm[0] && d <= params.diameter_mm[1]
        })
        .collect();
    let components = all.keep(&survivors);
    let candidates = survivors
        .iter()
        .enumerate()
        .map(|(i, &old)| {
            let voxels = all.size(old);
            let volume_mm3 = voxels as f64 * voxel_mm3;
            Candidate {
                percentile,
                threshold,
                label: i as u32 + 1,
                voxels,
                volume_mm3,
                diameter_mm: equivalent_diameter_mm(volume_mm3),
                centroid_mm: summaries[old as usize - 1],
            }
        })
        .collect();
    Level { percentile, threshold, candidates, components }
}

/// `(6V/π)^(1/3)`: the diameter of the sphere of volume `volume_mm3`.
pub fn equivalent_diameter_mm(volume_mm3: f64) -> f64 {
    (6.0 * volume_mm3 / std::f64::consts::PI).cbrt()
}

/// The centroid (patient mm) of `voxels`, ascending: [`summarize`]'s of the component they are.
pub(crate) fn centroid_mm(voxels: &[usize], geometry: &Geometry) -> [f64; 3] {
    let mut sum = [0f64; 3];
    for &i in voxels {
        add_coordinates(&mut sum, i, geometry.dims);
    }
    mean_mm(sum, voxels.len(), geometry)
}

/// Each component's centroid in patient mm.
pub(crate) fn summarize(components: &Components, geometry: &Geometry) -> Vec<[f64; 3]> {
    let mut sums = vec![[0f64; 3]; components.count()];
    for (i, &l) in components.labels.iter().enumerate().filter(|(_, &l)| l != 0) {
        add_coordinates(&mut sums[l as usize - 1], i, geometry.dims);
    }
    sums.iter().zip(&components.sizes).map(|(&s, &n)| mean_mm(s, n, geometry)).collect()
}

/// Adds node `i`'s lattice coordinates to `sum`: every centroid here adds its nodes in index
/// order, so a component's centroid is the same bits however it was found.
fn add_coordinates(sum: &mut [f64; 3], i: usize, [nx, ny, _]: [usize; 3]) {
    for (a, c) in [i % nx, (i / nx) % ny, i / (nx * ny)].into_iter().enumerate() {
        sum[a] += c as f64;
    }
}

/// The patient-mm position of the mean of `count` nodes whose coordinates add up to `sum`.
fn mean_mm(sum: [f64; 3], count: usize, geometry: &Geometry) -> [f64; 3] {
    geometry.voxel_to_patient_mm(sum.map(|v| v / count as f64))
}

/// The lung field the sweep wrote, when it swept one (`region = "lung_field"`): the same σ gives
/// the same field, so the stages after it read it rather than find it again.
pub(crate) fn swept_lung_field(ctx: &Context, params: &Params) -> anyhow::Result<Option<Vec<bool>>> {
    Ok(match params.region {
        Region::LungField => {
            let field: Volume<u8> = super::read_volume(ctx, LUNG_FIELD)?;
            Some(field.data.iter().map(|&v| v != 0).collect())
        }
        Region::Box => None,
    })
}

/// `sweep.csv`: `percentile,threshold,candidate,voxels,volume_mm3,diameter_mm,centroid_mm`,
/// the centroid as `x y z` (patient mm) in one field.
pub fn sweep_csv(candidates: &[Candidate]) -> String {
    let mut s = String::from("percentile,threshold,candidate,voxels,volume_mm3,diameter_mm,centroid_mm\n");
    for c in candidates {
        let [x, y, z] = c.centroid_mm;
        let _ = writeln!(
            s,
            "{},{},{},{},{:.4},{:.4},{x:.3} {y:.3} {z:.3}",
            c.percentile, c.threshold, c.label, c.voxels, c.volume_mm3, c.diameter_mm
        );
    }
    s
}

pub struct Sweep {
    pub params: Params,
}

impl Stage for Sweep {
    fn name(&self) -> &'static str {
        "sweep"
    }
    fn version(&self) -> u32 {
        VERSION
    }
    fn inputs(&self) -> &'static [&'static str] {
        &["grid"]
    }
    fn params(&self) -> serde_json::Value {
        super::params_json(&self.params)
    }
    fn reads(&self, _stage: &str, output: &str) -> bool {
        DENSITY.holds(output)
    }
    fn run(&self, ctx: &Context) -> anyhow::Result<Vec<Output>> {
        self.params.check()?;
        let density: Volume<f32> = super::read_volume(ctx, DENSITY)?;
        let scored = scored(&density, &self.params, None)?;
        let candidates: Vec<Candidate> =
            levels_of(&scored, &self.params)?.into_iter().flat_map(|l| l.candidates).collect();
        let file = SweepFile { params: self.params.clone(), candidates };
        let mut outputs = vec![
            Output::new(SWEEP_CSV.file, sweep_csv(&file.candidates)),
            Output::new(SWEEP.file, serde_json::to_vec_pretty(&file)?),
        ];
        // The lung field, for select (which would otherwise find it again) and for viewing.
        if let Some(region) = &scored.region {
            let volume =
                Volume { geometry: density.geometry.clone(), data: region.iter().map(|&b| u8::from(b)).collect() };
            outputs.extend(super::volume_outputs(LUNG_FIELD, &volume));
        }
        Ok(outputs)
    }
}
