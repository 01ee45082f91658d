//! Where the target lies: enclosed by the lung, or against its wall (juxtapleural, or on the
//! mediastinum or the spine). Three views show a nodule fused with the wall worst, so the
//! metrics report hit rates by site beside size and texture. Computed from the CT and the
//! target's consensus mask only, and never used by a rule. Written as `target_site.json`.

use crate::kernels::lung_field::{filled_lung_field, LUNG_THRESHOLD_HU};
use crate::volume::Volume;
use anyhow::ensure;
use serde::{Deserialize, Serialize};

/// The fraction of the consensus outside the filled lung field from which the target counts as
/// attached. On the phantom cohort an enclosed target has none outside (17 of 19 patients) and
/// the two on the wall 23 % and 37 %; the margin keeps a voxel or two of partial volume on a
/// real scan from making a free nodule attached.
pub const ATTACHED_FRACTION: f64 = 0.01;

/// What `target_site.json` holds.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TargetSite {
    /// The lung field: voxels below this enclosed by the body on their axial slice, with their
    /// holes filled slice by slice across z, y and x.
    pub lung_threshold_hu: i16,
    pub attached_fraction: f64,
    /// Of the target's consensus voxels, the fraction outside that field; `None` without a target.
    pub outside_lung_fraction: Option<f64>,
    /// `outside_lung_fraction` ≥ `attached_fraction`; `None` without a target.
    pub attached: Option<bool>,
}

/// The site of the target whose consensus is `gt_mask` (on the CT's grid) in `ct_hu`.
pub fn target_site(ct_hu: &Volume<i16>, gt_mask: Option<&Volume<u8>>) -> anyhow::Result<TargetSite> {
    let outside_lung_fraction = match gt_mask {
        Some(mask) => {
            ensure!(
                mask.geometry.dims == ct_hu.geometry.dims,
                "the target's mask ({:?}) is not on the CT's grid ({:?})",
                mask.geometry.dims,
                ct_hu.geometry.dims
            );
            let field = filled_lung_field(ct_hu, LUNG_THRESHOLD_HU);
            let on_target = mask.data.iter().filter(|&&m| m > 0).count();
            let outside = mask.data.iter().zip(&field).filter(|&(&m, &inside)| m > 0 && !inside).count();
            (on_target > 0).then(|| outside as f64 / on_target as f64)
        }
        None => None,
    };
    Ok(TargetSite {
        lung_threshold_hu: LUNG_THRESHOLD_HU,
        attached_fraction: ATTACHED_FRACTION,
        outside_lung_fraction,
        attached: outside_lung_fraction.map(|f| f >= ATTACHED_FRACTION),
    })
}
