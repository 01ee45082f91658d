//! `result.json`: what each rule chose, how well it lies on the nodule, and the verdict. Data
//! only.

use super::find::Centres;
use super::params::{Localize, Rule, Sizing};
use crate::kernels::localization::Localization;
use crate::stage::sweep::Candidate;
use serde::{Deserialize, Serialize};

/// One rule's choice.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Selection {
    pub rule: Rule,
    pub candidate: Candidate,
    /// The volumes of the candidates overlapping it most at the neighbouring thresholds, with
    /// its own: `[min, max]` mm³.
    pub volume_interval_mm3: [f64; 2],
    /// Against the ground truth, when there is one.
    pub localization: Option<Localization>,
    /// With `sizing = "shadows"`: the ellipsoid fitted to the nodule's shadows.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub shadows: Option<ShadowFit>,
    /// With `roi_center = "tiles"`: the box it was found in.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tile: Option<String>,
}

/// The oracle diagnostic: could any candidate at any threshold have been right?
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Oracle {
    pub any_hit: bool,
    pub best_dice: f64,
    pub best: Option<Candidate>,
}

/// `result.json`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SelectResult {
    pub patient: String,
    /// "hit", or "MISS: …" when the primary selection does not touch the nodule — its volume
    /// then measures something else, whatever its error says.
    pub verdict: String,
    pub primary: Rule,
    pub blind_rule: Rule,
    pub gt_volume_mm3: Option<f64>,
    pub annotated_diameter_mm: Option<f64>,
    /// Each reader's own volume of the target (the consensus is their vote): how far the
    /// radiologists themselves lie from the ground truth. Empty without a target.
    #[serde(default)]
    pub reader_volumes_mm3: Vec<f64>,
    pub guided: Option<Selection>,
    pub blind_largest: Option<Selection>,
    pub blind_persistent: Option<Selection>,
    pub oracle: Option<Oracle>,
    /// The volume `nodule_mask` holds (its voxels × a voxel's volume) and its mesh's enclosed
    /// volume (mm³). The measured volume is the selection's `candidate.volume_mm3` (with
    /// `sizing = "shadows"`, the fitted ellipsoid's), which the mask is cut to approach: where
    /// the region cannot grow or shrink to it, the two differ, and both are reported.
    pub voxel_volume_mm3: Option<f64>,
    pub mesh_volume_mm3: Option<f64>,
    pub mesh_triangles: usize,
    pub candidates: usize,
    /// The centres the rules sized from (`localize`).
    pub localize: Localize,
    /// How the rules sized the nodule.
    #[serde(default)]
    pub sizing: Sizing,
    pub centres: Centres,
    /// With `roi_center = "tiles"`: every box's centres and scores, in box order ([`tiles`]).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub tiles: Vec<TileScore>,
}

impl SelectResult {
    /// The report of `rule`'s choice, if it chose.
    pub fn selection(&self, rule: Rule) -> Option<&Selection> {
        match rule {
            Rule::Guided => self.guided.as_ref(),
            Rule::BlindLargest => self.blind_largest.as_ref(),
            Rule::BlindPersistent => self.blind_persistent.as_ref(),
        }
    }
}

/// What `result.json` records of a shadow fit (patient mm).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ShadowFit {
    pub centre_mm: [f64; 3],
    /// Along the patient x, y and z axes.
    pub semi_axes_mm: [f64; 3],
    /// The nodule's attenuation over its background, in the density's units.
    pub contrast: f64,
}

/// One box of a tiling, as `result.json` lists it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TileScore {
    pub tile: String,
    /// The guided centre's response × depth (none: no guided centre in this box).
    pub guided_score: Option<f64>,
    /// The blind centre's response × depth (none: no blind centre in this box).
    pub blind_score: Option<f64>,
    /// Whether the blind centre lies on the nodule (diagnostic only: never used to choose).
    pub blind_on_nodule: Option<bool>,
}
