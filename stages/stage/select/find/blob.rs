//! The blob search: the strongest bright blobs of σ inside the lung field (the `blobs` stage's),
//! weighed by the sizing and ranked ([`super::rank`]).

use super::rank::{pick, with_ranking_scores};
use super::{Centre, Centres, Localize, Search, Weighed, MAX_WEIGHED};
use crate::stage::blobs::{BlobSearch, BlobSearches};
use crate::stage::select::params::Params;
use crate::volume::Geometry;

/// Finds the centres `params.localize` asks for on the lattice `geometry`: for `blob`, among
/// the blobs `blobs` found. `origin_mm` is the scene origin, `coverage` the ground truth's
/// per-cell coverage (only to report whether a centre is on the nodule). A blob search takes
/// among the blobs that `accept` accepts as `tie_break` says; the origin has no alternative
/// and is taken as is.
pub fn centres(
    params: &Params,
    geometry: &Geometry,
    blobs: Option<&BlobSearches>,
    origin_mm: [f64; 3],
    coverage: Option<&[f32]>,
    accept: &(dyn Fn(Search, &Centre) -> Weighed + Sync),
) -> Centres {
    let (localize, blob) = (params.localize, &params.blob);
    let dims = geometry.dims;
    let centre = |voxel: [usize; 3], rank: usize| Centre {
        rank,
        on_nodule: coverage.map(|c| c[voxel[0] + dims[0] * (voxel[1] + dims[1] * voxel[2])] > 0.0),
        ..Centre::at(voxel, geometry.voxel_to_patient_mm(voxel.map(|v| v as f64)))
    };
    match localize {
        Localize::None => Centres::default(),
        Localize::Origin => {
            let voxel = geometry.nearest_voxel(origin_mm);
            Centres { guided: Some(centre(voxel, 0)), blind: Some(centre(voxel, 0)), ..Centres::default() }
        }
        Localize::Blob => {
            let Some(blobs) = blobs else {
                return Centres { note: Some("the blob search did not run".into()), ..Centres::default() };
            };
            if blobs.note.is_some() {
                return Centres { note: blobs.note.clone(), ..Centres::default() };
            }
            // How many blobs each search found, and the one it took, with its runner-up.
            let search = |found: &BlobSearch, which: Search| {
                let accepted: Vec<Centre> = found
                    .strongest
                    .iter()
                    .enumerate()
                    .filter_map(|(rank, b)| {
                        let c = Centre { blob: Some(b.peak), ..centre(b.peak.voxel, rank) };
                        match accept(which, &c) {
                            Weighed::PassedOver => None,
                            Weighed::Accepted { region } => Some(Centre { region, depth_mm: Some(b.depth_mm), ..c }),
                        }
                    })
                    .collect();
                let tie_break = blob.tie_break_of(which);
                let accepted = with_ranking_scores(accepted, tie_break);
                (found.found, accepted.clone(), pick(accepted, blob, tie_break))
            };
            let none = || (0, Vec::new(), None);
            // Independent searches: on two cores, side by side beats each one's own parallelism.
            let ((guided_found, guided_accepted, guided), (blind_found, blind_accepted, blind)) = rayon::join(
                || blobs.guided.as_ref().map_or_else(none, |s| search(s, Search::Guided)),
                || blobs.blind.as_ref().map_or_else(none, |s| search(s, Search::Blind)),
            );
            let inside_mm = blob.inside_mm;
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
