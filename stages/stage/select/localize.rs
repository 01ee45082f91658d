//! Where the nodule is, before any candidate is sized (issue 8: "find first, then size").
//! Each rule then chooses only among the candidates that hold its centre.
//!
//! - `none` (the paper): no centre; every candidate competes.
//! - `origin` (assistance A): the scene origin, which `roi_center = "nodule"` puts at the
//!   nodule's consensus centroid — no more assisted than the ROI itself, and meaningless
//!   otherwise (the stage says so in its verdict's localization line).
//! - `blob` (assistance B for the guided rule, C for the blind ones): the strongest bright-blob
//!   response of σ (`blob_filter`: the Laplacian or the Hessian of Gaussian) more than
//!   `inside_mm` inside the lung field found in σ. The guided rule
//!   uses the one scale matched to the annotated diameter (s = d / (2√3): a ball of radius
//!   √3·s answers most at s); the blind rules the maximum over `blob_scales_mm`.

use super::Params;
use crate::kernels::lung_mask::{blob_sites, lung_field, strongest_blob, BlobPeak};
use crate::volume::Volume;
use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Localize {
    None,
    Origin,
    Blob,
}

/// The centres found for the guided and the blind rules.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Centres {
    pub guided: Option<Centre>,
    pub blind: Option<Centre>,
    /// Why there is no centre, when `localize` asked for one.
    pub note: Option<String>,
}

/// One centre, and whether it lies on the nodule (coverage > 0; diagnostic only).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Centre {
    pub voxel: [usize; 3],
    pub position_mm: [f64; 3],
    /// The blob response and its scale, for `blob`.
    pub blob: Option<BlobPeak>,
    pub on_nodule: Option<bool>,
}

impl Centre {
    pub fn linear(&self, dims: [usize; 3]) -> usize {
        self.voxel[0] + dims[0] * (self.voxel[1] + dims[1] * self.voxel[2])
    }
}

/// Finds the centres `params.localize` asks for in `density`, whose lung field is `lungs` when
/// the caller has it (else it is found here, for `blob`). `origin_mm` is the scene origin,
/// `annotated_diameter_mm` the guided rule's diameter, `coverage` the ground truth's
/// per-cell coverage (only to report whether a centre is on the nodule).
pub fn centres(
    params: &Params,
    density: &Volume<f32>,
    lungs: Option<&[bool]>,
    origin_mm: [f64; 3],
    annotated_diameter_mm: Option<f64>,
    coverage: Option<&[f32]>,
) -> Centres {
    let Params { localize, blob_filter, ref blob_scales_mm, inside_mm, .. } = *params;
    let geometry = &density.geometry;
    let (dims, spacing) = (geometry.dims, geometry.spacing_mm);
    let centre = |voxel: [usize; 3], blob: Option<BlobPeak>| Centre {
        voxel,
        position_mm: geometry.voxel_to_patient_mm(voxel.map(|v| v as f64)),
        blob,
        on_nodule: coverage.map(|c| c[voxel[0] + dims[0] * (voxel[1] + dims[1] * voxel[2])] > 0.0),
    };
    match localize {
        Localize::None => Centres::default(),
        Localize::Origin => {
            let voxel = geometry.nearest_voxel(origin_mm);
            Centres { guided: Some(centre(voxel, None)), blind: Some(centre(voxel, None)), note: None }
        }
        Localize::Blob => {
            let found;
            let lungs = match lungs {
                Some(lungs) => lungs,
                None => match lung_field(&density.data, dims, spacing) {
                    Some(l) => {
                        found = l.field;
                        &found
                    }
                    None => {
                        return Centres {
                            note: Some("no lung field found in the density".into()),
                            ..Centres::default()
                        }
                    }
                },
            };
            // Both rules search the same sites.
            let sites = blob_sites(lungs, dims, spacing, inside_mm);
            let peak = |scales: &[f64]| {
                strongest_blob(&density.data, dims, spacing, blob_filter, scales, &sites)
                    .map(|p| centre(p.voxel, Some(p)))
            };
            let matched = annotated_diameter_mm.map(|d| [0.5 * d / 3f64.sqrt()]);
            // Independent searches: on two cores, side by side beats each one's own parallelism.
            let (guided, blind) = rayon::join(|| matched.and_then(|s| peak(&s)), || peak(blob_scales_mm));
            let note = (guided.is_none() && blind.is_none())
                .then(|| format!("no blob more than {inside_mm} mm inside the lung field"));
            Centres { guided, blind, note }
        }
    }
}
