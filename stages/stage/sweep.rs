//! `sweep`: nodule candidates from a percentile threshold sweep of the density (SPEC §3 sweep).
//!
//! Input: `grid/density.mhd/.raw`. At each percentile p of the non-zero density (numpy's
//! linear rule): mask = σ ≥ t; connected components; drop those under `min_voxels`; binary
//! closing with a radius-`closing_radius` ball on the zero-padded mask; components again; keep
//! those whose equivalent-sphere diameter is within `diameter_mm`. Outputs: `sweep.csv` (one
//! row per threshold × candidate) and `sweep.json` (the same, with the parameters, for select,
//! which regenerates candidate masks with [`levels`]).

use crate::engine::{Context, Output, Stage};
use crate::kernels::components::{label, Components, Connectivity};
use crate::kernels::{morphology, stats};
use crate::volume::{Geometry, Volume};
use anyhow::bail;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::fmt::Write as _;

pub const VERSION: u32 = 1;

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

/// Every threshold's candidates (pure: the same density and parameters give the same levels).
pub fn levels(density: &Volume<f32>, params: &Params) -> anyhow::Result<Vec<Level>> {
    let nonzero: Vec<f64> = density.data.iter().filter(|&&v| v != 0.0).map(|&v| f64::from(v)).collect();
    if nonzero.is_empty() {
        bail!("the density is zero everywhere: nothing to threshold (did training fail?)");
    }
    let thresholds = stats::percentiles(&nonzero, &params.percentiles)?;
    // Levels are independent: one task each (collected in percentile order).
    Ok(params
        .percentiles
        .par_iter()
        .zip(thresholds)
        .map(|(&percentile, threshold)| level(density, params, percentile, threshold))
        .collect())
}

fn level(density: &Volume<f32>, params: &Params, percentile: f64, threshold: f64) -> Level {
    let geometry = &density.geometry;
    let dims = geometry.dims;
    let mask: Vec<bool> = density.data.iter().map(|&v| f64::from(v) >= threshold).collect();
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

/// Each component's centroid in patient mm.
fn summarize(components: &Components, geometry: &Geometry) -> Vec<[f64; 3]> {
    let [nx, ny, _] = geometry.dims;
    let mut sums = vec![[0f64; 3]; components.count()];
    for (i, &l) in components.labels.iter().enumerate().filter(|(_, &l)| l != 0) {
        let s = &mut sums[l as usize - 1];
        for (a, c) in [i % nx, (i / nx) % ny, i / (nx * ny)].into_iter().enumerate() {
            s[a] += c as f64;
        }
    }
    sums.iter().zip(&components.sizes).map(|(s, &n)| geometry.voxel_to_patient_mm(s.map(|v| v / n as f64))).collect()
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
        output == "density.mhd" || output == "density.raw"
    }
    fn run(&self, ctx: &Context) -> anyhow::Result<Vec<Output>> {
        self.params.check()?;
        let density: Volume<f32> = super::read_volume(ctx, "grid", "density")?;
        let candidates: Vec<Candidate> =
            levels(&density, &self.params)?.into_iter().flat_map(|l| l.candidates).collect();
        let file = SweepFile { params: self.params.clone(), candidates };
        Ok(vec![
            Output::new("sweep.csv", sweep_csv(&file.candidates)),
            Output::new("sweep.json", serde_json::to_vec_pretty(&file)?),
        ])
    }
}
