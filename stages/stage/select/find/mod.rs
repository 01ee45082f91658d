//! Where the nodule is, before any candidate is sized ("find first, then size").
//! Each rule then chooses only among the candidates that hold its centre.
//!
//! - `none` (the paper): no centre; every candidate competes.
//! - `origin` (assistance A): the scene origin, which `roi_center = "nodule"` puts at the
//!   nodule's consensus centroid — no more assisted than the ROI itself, and meaningless
//!   otherwise (the stage says so in its verdict's localization line).
//! - `blob` (assistance B for the guided rule, C for the blind ones): the strongest bright-blob
//!   response of σ (the Hessian of Gaussian's, [`crate::kernels::filters::hessian_blob_response`])
//!   more than `inside_mm` inside the lung field found in σ, as the `blobs` stage found them.
//!   The guided rule uses the scale matched to the annotated diameter (s = d / (2√3): a ball of
//!   radius √3·s answers most at s); the blind rules the maximum over `scales_mm`.
//!
//! A search may pass over blobs its caller cannot size (`accept`: with `sizing = "half_max"`,
//! a blob whose half-maximum region is not of the nodule's size) and take the strongest one
//! left, among the [`MAX_WEIGHED`] strongest; with `tie_break = "roundness"`, the roundest of
//! those that answer about as strongly as it; with `"learned"` (the blind search's, shipped),
//! the best by the ranking learned on phantom anatomies ([`BlobRanker`]) ([`TieBreak`]). Every blob a search accepted
//! is recorded ([`Centres`]). Where the guided search finds nothing, its rule may take the blind
//! centre ([`Centres::fall_back_to_blind`]).
//!
//! A search also reports its runner-up: the strongest other blob it would have accepted, away
//! from the one it took. A rival that answers nearly as strongly says the choice is a toss-up
//! between two objects: at `rival_ratio` of the taken blob's response or more, the centre is
//! `ambiguous`, and the verdict says so.

use super::params::{Localize, Rule};
use crate::kernels::lung_mask::BlobPeak;
use serde::{Deserialize, Serialize};

mod blob;
mod fallback;
mod learned;
mod rank;

pub use blob::centres;
pub use learned::BlobRanker;

pub use crate::stage::blobs::MAX_WEIGHED;

/// Which search a centre is for: the guided rule's (the scale matched to the annotated
/// diameter) or the blind rules' (`scales_mm`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Search {
    Guided,
    Blind,
}

/// The centres found for the guided and the blind rules.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Centres {
    pub guided: Option<Centre>,
    pub blind: Option<Centre>,
    /// Why there is no centre, when `localize` asked for one.
    pub note: Option<String>,
    /// Every blob the guided search accepted among the [`MAX_WEIGHED`] strongest, strongest
    /// first, the one it took included: the other places a reader may look, and what a rule
    /// that judges between blobs is measured on (`lab/scripts/blob_ranker.py`).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub guided_accepted: Vec<Centre>,
    /// The same for the blind search.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub blind_accepted: Vec<Centre>,
}

/// One centre, and whether it lies on the nodule (coverage > 0; diagnostic only).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Centre {
    pub voxel: [usize; 3],
    pub position_mm: [f64; 3],
    /// The blob response and its scale, for `blob`.
    pub blob: Option<BlobPeak>,
    /// How many stronger blobs the search passed over (0: the strongest).
    #[serde(default)]
    pub rank: usize,
    pub on_nodule: Option<bool>,
    /// The strongest other blob the search would have accepted, for `blob` (none: no rival
    /// among the [`MAX_WEIGHED`] strongest).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub runner_up: Option<RunnerUp>,
    /// The runner-up answers at `rival_ratio` of this blob's response or more: two objects
    /// are nearly as likely, and the search's pick between them is a toss-up.
    #[serde(default)]
    pub ambiguous: bool,
    /// The region the search judged the blob by (its roundness, `half_max::roundness`: 1 for
    /// a ball; its size; its peak), when the search cut one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub region: Option<RegionShape>,
    /// The score the search's tie-break ranked the blob by, with `"learned"` (every accepted
    /// blob): the highest is taken.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ranking_score: Option<f64>,
    /// How far inside the lung field the centre lies, for `blob`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub depth_mm: Option<f64>,
    /// The guided rule's centre is the blind search's: the guided search found no blob it could
    /// size, or one fainter than `guided_faint_ratio` allows, and the blind centre passed the
    /// guided size check (`guided_fallback`).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub from_blind: bool,
    /// With `from_blind`: the peak local contrast of the guided search's own centre, which was
    /// fainter than `guided_faint_ratio` × the blind centre's (none: it found no centre).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub replaced_guided_peak: Option<f32>,
}

/// What a search learns of a blob from the region it cut around it: what a ranker of blobs can
/// weigh besides the blob response. Recorded in `result.json` for every blob a search accepted.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct RegionShape {
    /// [`super::size::half_max::roundness`]: 1 for a ball, towards 0 for a rod or a plate.
    pub roundness: f64,
    /// The region's equivalent diameter.
    pub diameter_mm: f64,
    /// The score at the region's peak (σ's local contrast by default).
    pub peak_score: f32,
}

impl Centre {
    /// A centre at `voxel` (`position_mm` in patient mm) and nothing more known of it: no blob,
    /// the strongest, not compared with the nodule, no rival, no region.
    pub fn at(voxel: [usize; 3], position_mm: [f64; 3]) -> Centre {
        Centre {
            voxel,
            position_mm,
            blob: None,
            rank: 0,
            on_nodule: None,
            runner_up: None,
            ambiguous: false,
            region: None,
            ranking_score: None,
            depth_mm: None,
            from_blind: false,
            replaced_guided_peak: None,
        }
    }
}

/// What a search's caller says of one blob.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Weighed {
    /// It cannot be the nodule (e.g. its region is not of a nodule's size).
    PassedOver,
    /// It may be, and this is the region it was judged by (`None`: no region cut).
    Accepted { region: Option<RegionShape> },
}

impl From<bool> for Weighed {
    /// Accepted without a region measured, or passed over.
    fn from(accepted: bool) -> Weighed {
        if accepted {
            Weighed::Accepted { region: None }
        } else {
            Weighed::PassedOver
        }
    }
}

/// A search's second choice: the strongest blob after the one it took that it would also have
/// accepted, outside the ball the taken blob's scale is matched to (a ball of radius √3·s answers
/// most at scale s), so that it is another object and not the same blob's second peak.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RunnerUp {
    pub position_mm: [f64; 3],
    pub response: f32,
    /// The scale (mm) it answered at: a ball of radius √3 × this is the object it stands for.
    pub scale_mm: f64,
    /// From the taken centre.
    pub distance_mm: f64,
    /// Its response over the taken blob's: near 1, two objects answer alike.
    pub ratio: f64,
    /// Its place among every blob the search ranked (0: the strongest).
    pub rank: usize,
    /// How round its region is, as the taken centre's `roundness`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub roundness: Option<f64>,
}

impl Centres {
    /// The centre `rule` sized from: the guided one, or the blind one for both blind rules.
    pub fn of(&self, rule: Rule) -> Option<&Centre> {
        match rule {
            Rule::Guided => self.guided.as_ref(),
            Rule::BlindLargest | Rule::BlindPersistent => self.blind.as_ref(),
        }
    }
}

impl Centre {
    /// How round the region the search judged it by is, when it cut one.
    pub fn roundness(&self) -> Option<f64> {
        self.region.map(|r| r.roundness)
    }

    pub fn linear(&self, dims: [usize; 3]) -> usize {
        self.voxel[0] + dims[0] * (self.voxel[1] + dims[1] * self.voxel[2])
    }
}
