//! `blobs`: the bright blobs of σ inside the lung field, strongest first, that `select`'s blob
//! search chooses among (`[select] localize = "blob"`; SPEC §3 select).
//!
//! Inputs: `grid/density`, `sweep/lung_field` (the lung field found in σ, when the sweep swept
//! one; else it is found here) and `ingest/ground_truth.json` (the annotated diameter, which
//! sets the guided search's scale). Output: `blobs.json` ([`BlobSearches`]): per search its
//! scales, how many blobs it found and the [`MAX_WEIGHED`] strongest, each with its depth in
//! the lung field.
//!
//! The responses (the Hessian of Gaussian's at every node and scale) are most of what finding
//! a nodule costs, and they depend on σ and the scales alone. Kept apart from the choice among
//! the blobs, an edit of how `select` chooses or sizes reuses them.

use crate::artifacts::{BLOBS, DENSITY, GROUND_TRUTH, LUNG_FIELD, SWEEP};
use crate::engine::{Context, Output, Stage};
use crate::kernels::filters::distance_inside_mm;
use crate::kernels::lung_mask::{blob_sites, lung_field, ranked_blobs, BlobPeak};
use crate::stage::ingest::truth::GroundTruth;
use crate::stage::sweep::{swept_lung_field, SweepFile};
use crate::volume::Volume;
use anyhow::bail;
use serde::{Deserialize, Serialize};

pub const VERSION: u32 = 1;

/// How many of the strongest blobs a search keeps for `select` to weigh: a bound on the work,
/// far beyond the ranks at which a nodule still stands out.
pub const MAX_WEIGHED: usize = 16;

/// What finds the blobs (`[select.blob]`'s `scales_mm` and `inside_mm`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Params {
    /// Scales (mm) of the blind search.
    pub scales_mm: Vec<f64>,
    /// A blob centre lies more than this (mm) inside the lung field.
    pub inside_mm: f64,
}

impl Params {
    pub fn check(&self) -> anyhow::Result<()> {
        if self.scales_mm.is_empty() || self.scales_mm.iter().any(|s| !(s.is_finite() && *s > 0.0)) {
            bail!("[select.blob] scales_mm must be a non-empty list of positive numbers");
        }
        if !(self.inside_mm.is_finite() && self.inside_mm >= 0.0) {
            bail!("[select.blob] inside_mm must be a number ≥ 0 (got {})", self.inside_mm);
        }
        Ok(())
    }
}

/// `blobs.json`: what each search found.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BlobSearches {
    /// The guided search's, at the scale a ball of the annotated diameter answers most at
    /// (none without an annotated diameter).
    pub guided: Option<BlobSearch>,
    /// The blind search's, the maximum over `scales_mm`.
    pub blind: Option<BlobSearch>,
    /// Why neither search ran: no lung field in σ.
    pub note: Option<String>,
}

/// One search's blobs.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BlobSearch {
    pub scales_mm: Vec<f64>,
    /// How many blobs lie more than `inside_mm` inside the lung field.
    pub found: usize,
    /// The [`MAX_WEIGHED`] strongest of them, strongest first.
    pub strongest: Vec<Blob>,
}

/// A blob and how deep (mm) its centre lies in the lung field.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Blob {
    pub peak: BlobPeak,
    pub depth_mm: f64,
}

/// The scale a ball of diameter `d` mm answers most at: radius √3·s.
pub fn matched_scale_mm(diameter_mm: f64) -> f64 {
    0.5 * diameter_mm / 3f64.sqrt()
}

/// Both searches in `density`, whose lung field is `lungs` when the caller has it (else it is
/// found here); the guided one only with an annotated diameter.
pub fn search(
    params: &Params,
    density: &Volume<f32>,
    lungs: Option<&[bool]>,
    annotated_diameter_mm: Option<f64>,
) -> BlobSearches {
    let (dims, spacing) = (density.geometry.dims, density.geometry.spacing_mm);
    let found;
    let lungs = match lungs {
        Some(lungs) => lungs,
        None => match lung_field(&density.data, dims, spacing) {
            Some(l) => {
                found = l.field;
                &found
            }
            None => {
                let note = Some("no lung field found in the density".into());
                return BlobSearches { guided: None, blind: None, note };
            }
        },
    };
    // Both searches look at the same sites.
    let depth_mm = distance_inside_mm(lungs, dims, spacing);
    let sites = blob_sites(&depth_mm, dims, spacing, params.inside_mm);
    let one = |scales_mm: Vec<f64>| {
        let ranked = ranked_blobs(&density.data, dims, spacing, &scales_mm, &sites);
        let strongest = ranked
            .iter()
            .take(MAX_WEIGHED)
            .map(|&peak| {
                let [x, y, z] = peak.voxel;
                Blob { peak, depth_mm: depth_mm[x + dims[0] * (y + dims[1] * z)] }
            })
            .collect();
        BlobSearch { scales_mm, found: ranked.len(), strongest }
    };
    // Independent searches: on two cores, side by side beats each one's own parallelism.
    let (guided, blind) =
        rayon::join(|| annotated_diameter_mm.map(|d| one(vec![matched_scale_mm(d)])), || one(params.scales_mm.clone()));
    BlobSearches { guided, blind: Some(blind), note: None }
}

pub struct Blobs {
    pub params: Params,
}

impl Stage for Blobs {
    fn name(&self) -> &'static str {
        "blobs"
    }
    fn version(&self) -> u32 {
        VERSION
    }
    fn inputs(&self) -> &'static [&'static str] {
        &["ingest", "grid", "sweep"]
    }
    fn params(&self) -> serde_json::Value {
        super::params_json(&self.params)
    }
    fn reads(&self, stage: &str, output: &str) -> bool {
        match stage {
            "ingest" => output == GROUND_TRUTH.file,
            "grid" => DENSITY.holds(output),
            "sweep" => output == SWEEP.file || LUNG_FIELD.holds(output),
            _ => false,
        }
    }
    fn run(&self, ctx: &Context) -> anyhow::Result<Vec<Output>> {
        self.params.check()?;
        let density: Volume<f32> = super::read_volume(ctx, DENSITY)?;
        let sweep: SweepFile = super::read_json(ctx, SWEEP)?;
        let truth: GroundTruth = super::read_json(ctx, GROUND_TRUTH)?;
        let annotated = truth.target.map(|t| truth.nodules[t].annotated_diameter_mm);
        let lungs = swept_lung_field(ctx, &sweep.params)?;
        let searches = search(&self.params, &density, lungs.as_deref(), annotated);
        Ok(vec![Output::new(BLOBS.file, serde_json::to_vec_pretty(&searches)?)])
    }
}
