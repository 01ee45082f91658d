//! `[select]` and its variants' tables: the rules' parameters, and the canonical form of those
//! in use (the stage's cache key).

use anyhow::bail;
use serde::{Deserialize, Serialize};

/// The blind search's learned ranking (`blind_tie_break = "learned"`,
/// [`super::find::BlobRanker`]) as the repository holds it: a parameter of the stage like any key.
pub const BLOB_RANKER_JSON: &str = include_str!("../../../models/blob_ranker.json");

/// Which rule a selection is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Rule {
    Guided,
    BlindLargest,
    BlindPersistent,
}

impl Rule {
    /// The name in `[select] primary` and `blind`.
    pub fn name(self) -> &'static str {
        match self {
            Rule::Guided => "guided",
            Rule::BlindLargest => "blind_largest",
            Rule::BlindPersistent => "blind_persistent",
        }
    }
}

/// How each rule finds the nodule's centre before it sizes it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Localize {
    None,
    Origin,
    Blob,
}

/// Among blobs that answer alike, which a search takes.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TieBreak {
    /// The strongest response, however close the next comes.
    #[default]
    Response,
    /// Among the strongest accepted blob and every other object answering at `rival_ratio` of
    /// it or more, the one whose region is roundest: a nodule is compact, the blobs that rival it
    /// (vessel junctions, the hilum) are drawn out. Needs a sizing that cuts regions.
    Roundness,
    /// The accepted blob that the ranking learned on phantom anatomies scores highest
    /// ([`super::find::BlobRanker`], `models/blob_ranker.json`): the blind search's only.
    /// Needs a sizing that cuts regions.
    Learned,
}

/// `[select]`: which rule is the result, how each finds the nodule's centre (`localize`, with
/// `[select.blob]`) and how it sizes it there (`sizing`, with `[select.half_max]`). The defaults
/// are the shipped method.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// The selection written as `nodule_mask` and `nodule.obj`, and reported as "ours".
    pub primary: Rule,
    /// The blind rule reported beside the guided one in the cohort table.
    pub blind: Rule,
    /// How the nodule is found before it is sized.
    pub localize: Localize,
    /// How a rule sizes the nodule at its centre.
    pub sizing: Sizing,
    /// `localize = "blob"`: the blob search.
    pub blob: BlobParams,
    /// `sizing = "half_max"` or `"shadows"`: the half-maximum region.
    pub half_max: HalfMaxParams,
}

/// `[select.blob]`: the search for the strongest bright blob of σ inside the lung field.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct BlobParams {
    /// Scales (mm) of the blind search.
    pub scales_mm: Vec<f64>,
    /// A blob centre lies more than this (mm) inside the lung field.
    pub inside_mm: f64,
    /// A centre whose runner-up (the strongest other blob the search would have accepted)
    /// answers at this fraction of its response or more is ambiguous (above 1: never).
    pub rival_ratio: f64,
    /// Among blobs answering alike (at `rival_ratio` of the strongest or more), which the
    /// guided search takes ([`TieBreak`]).
    pub tie_break: TieBreak,
    /// The blind search's own tie-break.
    pub blind_tie_break: TieBreak,
    /// With an annotated diameter: where the guided search finds no blob it can size, the
    /// guided rule takes the blind centre if it passes the guided size check
    /// ([`Centres::fall_back_to_blind`]).
    pub guided_fallback: bool,
    /// `guided_fallback`: the guided rule also takes the blind centre where its own centre's
    /// region peaks below this fraction of the blind centre's local contrast (0: never).
    pub guided_faint_ratio: f64,
}

/// `[select.half_max]`: the region around a centre where the sweep's score is at least a
/// fraction of its peak.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct HalfMaxParams {
    /// The fraction of the peak the region is cut at.
    pub fraction: f64,
    /// With `localize = "blob"`: the guided search passes over a blob whose region at half its
    /// peak has an equivalent diameter outside [lo, hi] × the annotated diameter.
    pub guided_diameter_ratio: [f64; 2],
    /// The guided rule's region holds no node farther from its peak than this many annotated
    /// diameters (what lies farther is attached to the nodule, not of it).
    pub guided_reach_diameters: f64,
}

/// How a rule sizes the nodule once it has chosen where it is.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Sizing {
    /// The paper: every rule picks a candidate of the sweep (holding its centre, if any).
    Candidates,
    /// The connected region of the sweep's score at `[select.half_max] fraction` of its peak at
    /// the rule's centre ([`half_max`]): both blind rules then size the blind centre alike.
    HalfMax,
    /// The half-maximum region finds the nodule; the ellipsoid fitted to its shadows in the
    /// three DRRs sizes it ([`shadows`]).
    #[default]
    Shadows,
}

impl Sizing {
    /// Whether the rules cut a half-maximum region around their centres (to keep it, or to
    /// size it by its shadows).
    pub(super) fn cuts_half_max(self) -> bool {
        matches!(self, Sizing::HalfMax | Sizing::Shadows)
    }

    /// The name in `[select] sizing`.
    pub(super) fn name(self) -> &'static str {
        match self {
            Sizing::Candidates => "candidates",
            Sizing::HalfMax => "half_max",
            Sizing::Shadows => "shadows",
        }
    }
}

impl Default for Params {
    fn default() -> Self {
        Params {
            primary: Rule::Guided,
            blind: Rule::BlindPersistent,
            localize: Localize::Blob,
            sizing: Sizing::default(),
            blob: BlobParams::default(),
            half_max: HalfMaxParams::default(),
        }
    }
}

impl Default for BlobParams {
    fn default() -> Self {
        BlobParams {
            scales_mm: vec![6.0, 9.0, 13.0],
            inside_mm: 8.0,
            rival_ratio: 0.7,
            tie_break: TieBreak::Roundness,
            blind_tie_break: TieBreak::Learned,
            guided_fallback: true,
            guided_faint_ratio: 0.5,
        }
    }
}

impl Default for HalfMaxParams {
    fn default() -> Self {
        HalfMaxParams { fraction: 0.3, guided_diameter_ratio: [0.5, 2.0], guided_reach_diameters: 1.0 }
    }
}

impl BlobParams {
    /// What finds the blobs: the `blobs` stage's parameters.
    pub fn search(&self) -> crate::stage::blobs::Params {
        crate::stage::blobs::Params { scales_mm: self.scales_mm.clone(), inside_mm: self.inside_mm }
    }

    fn check(&self, sizing: Sizing) -> anyhow::Result<()> {
        self.search().check()?;
        if !(self.rival_ratio.is_finite() && self.rival_ratio > 0.0) {
            bail!("[select.blob] rival_ratio must be a number > 0 (got {})", self.rival_ratio);
        }
        for (key, tie_break) in [("tie_break", self.tie_break), ("blind_tie_break", self.blind_tie_break)] {
            let name = match tie_break {
                TieBreak::Roundness => "roundness",
                TieBreak::Learned => "learned",
                TieBreak::Response => continue,
            };
            if !sizing.cuts_half_max() {
                bail!(
                    "[select.blob] {key} = \"{name}\" judges the blobs' half-maximum regions, and [select] sizing = \
                     \"{}\" cuts none: set sizing to \"half_max\" or \"shadows\", or {key} to \"response\"",
                    sizing.name()
                );
            }
        }
        if self.tie_break == TieBreak::Learned {
            bail!(
                "[select.blob] tie_break = \"learned\": the learned ranking is trained on the blind search's blobs, \
                 which is told no diameter; set blind_tie_break = \"learned\" and tie_break to \"roundness\" \
                 or \"response\""
            );
        }
        if !(self.guided_faint_ratio.is_finite() && (0.0..=1.0).contains(&self.guided_faint_ratio)) {
            bail!("[select.blob] guided_faint_ratio must be a number from 0 to 1 (got {})", self.guided_faint_ratio);
        }
        Ok(())
    }
}

impl HalfMaxParams {
    /// How far from its peak the guided region reaches, mm: `guided_reach_diameters` × the
    /// annotated diameter (none without an annotation).
    pub(super) fn guided_reach_mm(&self, annotated_mm: Option<f64>) -> Option<f64> {
        annotated_mm.map(|d| self.guided_reach_diameters * d)
    }

    fn check(&self) -> anyhow::Result<()> {
        if !(self.fraction > 0.0 && self.fraction < 1.0) {
            bail!("[select.half_max] fraction must lie strictly between 0 and 1 (got {})", self.fraction);
        }
        let [lo, hi] = self.guided_diameter_ratio;
        if !(lo.is_finite() && hi.is_finite() && 0.0 <= lo && lo < hi) {
            bail!("[select.half_max] guided_diameter_ratio must be [lo, hi] with 0 ≤ lo < hi (got [{lo}, {hi}])");
        }
        if !(self.guided_reach_diameters.is_finite() && self.guided_reach_diameters > 0.0) {
            bail!(
                "[select.half_max] guided_reach_diameters must be a number > 0 (got {})",
                self.guided_reach_diameters
            );
        }
        Ok(())
    }
}

impl Params {
    pub fn check(&self) -> anyhow::Result<()> {
        if self.sizing.cuts_half_max() && self.localize == Localize::None {
            bail!(
                "[select] sizing = \"{}\" sizes around a centre, and localize = \"none\" finds none: \
                 set localize to \"blob\" or \"origin\"",
                self.sizing.name()
            );
        }
        if self.localize == Localize::Blob {
            self.blob.check(self.sizing)?;
        }
        if self.sizing.cuts_half_max() {
            self.half_max.check()?;
        }
        Ok(())
    }

    /// The canonical form of what the variants in use read: the stage's cache key.
    pub fn key(&self) -> serde_json::Value {
        let mut key = serde_json::json!({
            "primary": self.primary, "blind": self.blind, "localize": self.localize, "sizing": self.sizing,
        });
        let table = key.as_object_mut().expect("a table");
        if self.localize == Localize::Blob {
            table.insert("blob".into(), serde_json::to_value(&self.blob).expect("parameters serialise"));
            if self.blob.blind_tie_break == TieBreak::Learned {
                let ranker = serde_json::from_str(BLOB_RANKER_JSON).expect("the built-in ranking is JSON");
                table.insert("blob_ranker".into(), ranker);
            }
        }
        if self.sizing.cuts_half_max() {
            table.insert("half_max".into(), serde_json::to_value(&self.half_max).expect("parameters serialise"));
        }
        key
    }
}
