//! The blob search: the strongest bright blobs of σ inside the lung field, weighed by the
//! sizing and ranked ([`super::rank`]).

use super::rank::pick;
use super::{Centre, Centres, Localize, Search, Weighed, MAX_WEIGHED};
use crate::kernels::filters::distance_inside_mm;
use crate::kernels::lung_mask::{blob_sites, lung_field, ranked_blobs, BlobPeak};
use crate::stage::select::params::Params;
use crate::volume::Volume;

/// Finds the centres `params.localize` asks for in `density`, whose lung field is `lungs` when
/// the caller has it (else it is found here, for `blob`). `origin_mm` is the scene origin,
/// `annotated_diameter_mm` the guided rule's diameter, `coverage` the ground truth's
/// per-cell coverage (only to report whether a centre is on the nodule). A blob search takes
/// among the blobs that `accept` accepts as `tie_break` says; the origin has no alternative
/// and is taken as is.
pub fn centres(
    params: &Params,
    density: &Volume<f32>,
    lungs: Option<&[bool]>,
    origin_mm: [f64; 3],
    annotated_diameter_mm: Option<f64>,
    coverage: Option<&[f32]>,
    accept: &(dyn Fn(Search, &Centre) -> Weighed + Sync),
) -> Centres {
    let (localize, blob) = (params.localize, &params.blob);
    let (scales_mm, inside_mm) = (&blob.scales_mm, blob.inside_mm);
    let geometry = &density.geometry;
    let (dims, spacing) = (geometry.dims, geometry.spacing_mm);
    let centre = |voxel: [usize; 3], blob: Option<BlobPeak>, rank: usize| Centre {
        blob,
        rank,
        on_nodule: coverage.map(|c| c[voxel[0] + dims[0] * (voxel[1] + dims[1] * voxel[2])] > 0.0),
        ..Centre::at(voxel, geometry.voxel_to_patient_mm(voxel.map(|v| v as f64)))
    };
    match localize {
        Localize::None => Centres::default(),
        Localize::Origin => {
            let voxel = geometry.nearest_voxel(origin_mm);
            Centres { guided: Some(centre(voxel, None, 0)), blind: Some(centre(voxel, None, 0)), ..Centres::default() }
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
            let depth_mm = distance_inside_mm(lungs, dims, spacing);
            let sites = blob_sites(&depth_mm, dims, spacing, inside_mm);
            // How many blobs each search found, and the one it took, with its runner-up.
            let search = |scales: &[f64], which: Search| {
                let ranked = ranked_blobs(&density.data, dims, spacing, scales, &sites);
                let accepted: Vec<Centre> = ranked
                    .iter()
                    .take(MAX_WEIGHED)
                    .enumerate()
                    .filter_map(|(rank, p)| {
                        let c = centre(p.voxel, Some(*p), rank);
                        match accept(which, &c) {
                            Weighed::PassedOver => None,
                            Weighed::Accepted { region } => {
                                Some(Centre { region, depth_mm: Some(depth_mm[c.linear(dims)]), ..c })
                            }
                        }
                    })
                    .collect();
                (ranked.len(), accepted.clone(), pick(accepted, blob, blob.tie_break_of(which)))
            };
            // The scale a ball of the annotated diameter answers most at: radius √3·s.
            let matched: Option<Vec<f64>> = annotated_diameter_mm.map(|d| vec![0.5 * d / 3f64.sqrt()]);
            // Independent searches: on two cores, side by side beats each one's own parallelism.
            let ((guided_found, guided_accepted, guided), (blind_found, blind_accepted, blind)) = rayon::join(
                || matched.as_deref().map_or((0, Vec::new(), None), |s| search(s, Search::Guided)),
                || search(scales_mm, Search::Blind),
            );
            let note = match (guided.is_none() && blind.is_none(), guided_found.max(blind_found)) {
                (false, _) => None,
                (true, 0) => Some(format!("no blob more than {inside_mm} mm inside the lung field")),
                (true, found) => Some(format!(
                    "none of the {} strongest of {found} blobs more than {inside_mm} mm inside the lung field \
                     could be sized",
                    found.min(MAX_WEIGHED)
                )),
            };
            Centres { guided, blind, note, guided_accepted, blind_accepted }
        }
    }
}
