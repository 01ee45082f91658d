//! `select`: which candidate is the nodule, and how sure we are that it is (SPEC §3 select).
//!
//! Inputs: `grid/density` (the lattice), `sweep/sweep.json` (candidates and the parameters to
//! regenerate their masks), `ingest/ground_truth.json` (the annotated diameter the guided rule
//! uses), `ingest/gt_mask` (localization only: never used to choose) and `drr/cameras.json`
//! (the scene origin, for `localize = "origin"`); with `sizing = "shadows"` also the three
//! `drr/drr_<view>.exr` ([`shadows`]).
//!
//! With `localize` ([`localize`]), each rule first finds the nodule's centre and then chooses
//! only among the candidates holding it.
//!
//! Three selections, all reported:
//! - `guided` (the paper's, semi-assisted): the candidate whose equivalent diameter is closest
//!   to the annotated diameter;
//! - `blind_largest` (the paper's blind rule): the largest candidate over all thresholds;
//! - `blind_persistent` (ours, no annotation): see [`persistent`].
//!
//! Every selection carries Dice, centroid distance and hit against the consensus mask
//! resampled to the grid; the oracle says whether any candidate was a hit. Outputs:
//! `result.json`, the primary selection's `nodule_mask.mhd/.raw` (uint8) and `nodule.obj`
//! (watertight marching-cubes surface, patient mm), and `nodule.png` (density slices through
//! the selection, the nodule and an ambiguous search's rival, each outlined); with `sizing = "shadows"`
//! also `shadows.png` (the primary selection's fitted ellipsoid over its three shadows).

use crate::artifacts::{
    drr_image, CAMERAS, DENSITY, GROUND_TRUTH, GT_MASK, LUNG_FIELD, NODULE_MASK, NODULE_MESH, NODULE_PREVIEW, RESULT,
    SHADOWS_PREVIEW, SWEEP,
};
use crate::engine::{Context, Output, Stage};
use crate::formats::obj;
use crate::kernels::localization::{ground_truth_on_grid, GroundTruthOnGrid, Localization};
use crate::kernels::marching_cubes::mesh_mask;
use crate::kernels::mesh::{enclosed_volume_mm3, vertex_normals};
use crate::stage::drr::CameraSet;
use crate::stage::ingest::truth::GroundTruth;
use crate::stage::sweep::{levels_of, scored, Candidate, Region, SweepFile};
use crate::volume::Volume;
use anyhow::{bail, Context as _};
use half_max::Cut;
use serde::{Deserialize, Serialize};

mod half_max;
mod localize;
mod preview;
mod rules;
mod shadows;
mod tiles;

pub use localize::{blob_score, centres, Centre, Centres, Localize, RegionShape, RunnerUp, Search, TieBreak, Weighed};
pub use rules::Analysis;
pub use shadows::ShadowFit;
pub use tiles::TileScore;

pub const VERSION: u32 = 18;

/// The fraction of its peak at which a search judges whether a blob is of a nodule's size: its
/// full width at half maximum. `[select.half_max] fraction` then only sets where the nodule is
/// cut (its volume), not which blob is the nodule: a lower fraction grows every region, and
/// judged at that fraction a search passes over nodules.
const BLOB_WIDTH_FRACTION: f64 = 0.5;

/// How a search with half-maximum sizing judges a blob: the cut of its region (at
/// [`BLOB_WIDTH_FRACTION`]; the guided region within its reach of the peak) and, for the guided
/// search, the range its equivalent diameter must lie in (mm).
fn blob_check(search: Search, cut: &HalfMaxParams, annotated_mm: Option<f64>) -> (Cut, Option<[f64; 2]>) {
    match search {
        Search::Guided => (
            Cut { fraction: BLOB_WIDTH_FRACTION, reach_mm: cut.guided_reach_mm(annotated_mm) },
            annotated_mm.map(|d| cut.guided_diameter_ratio.map(|r| r * d)),
        ),
        Search::Blind => (Cut::at(BLOB_WIDTH_FRACTION), None),
    }
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
    /// `tie_break = "score"`: the weight of roundness beside ln(response / peak score).
    pub score_roundness: f64,
    /// `tie_break = "score"`: how many of the strongest accepted blobs it ranks.
    pub score_top: usize,
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
    fn cuts_half_max(self) -> bool {
        matches!(self, Sizing::HalfMax | Sizing::Shadows)
    }

    /// The name in `[select] sizing`.
    fn name(self) -> &'static str {
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
            blind_tie_break: TieBreak::Score,
            score_roundness: 3.0,
            score_top: 5,
            guided_fallback: true,
            guided_faint_ratio: 0.2,
        }
    }
}

impl Default for HalfMaxParams {
    fn default() -> Self {
        HalfMaxParams { fraction: 0.5, guided_diameter_ratio: [0.5, 2.0], guided_reach_diameters: 1.0 }
    }
}

impl BlobParams {
    /// How `search` judges between blobs that answer alike.
    pub fn tie_break_of(&self, search: Search) -> TieBreak {
        match search {
            Search::Guided => self.tie_break,
            Search::Blind => self.blind_tie_break,
        }
    }

    fn check(&self, sizing: Sizing) -> anyhow::Result<()> {
        if self.scales_mm.is_empty() || self.scales_mm.iter().any(|s| !(s.is_finite() && *s > 0.0)) {
            bail!("[select.blob] scales_mm must be a non-empty list of positive numbers");
        }
        if !(self.inside_mm.is_finite() && self.inside_mm >= 0.0) {
            bail!("[select.blob] inside_mm must be a number ≥ 0 (got {})", self.inside_mm);
        }
        if !(self.rival_ratio.is_finite() && self.rival_ratio > 0.0) {
            bail!("[select.blob] rival_ratio must be a number > 0 (got {})", self.rival_ratio);
        }
        for (key, tie_break) in [("tie_break", self.tie_break), ("blind_tie_break", self.blind_tie_break)] {
            let name = match tie_break {
                TieBreak::Roundness => "roundness",
                TieBreak::Score => "score",
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
        if !(self.guided_faint_ratio.is_finite() && (0.0..=1.0).contains(&self.guided_faint_ratio)) {
            bail!("[select.blob] guided_faint_ratio must be a number from 0 to 1 (got {})", self.guided_faint_ratio);
        }
        if !(self.score_roundness.is_finite() && self.score_roundness >= 0.0) {
            bail!("[select.blob] score_roundness must be a number ≥ 0 (got {})", self.score_roundness);
        }
        if self.score_top == 0 {
            bail!("[select.blob] score_top must be at least 1");
        }
        Ok(())
    }
}

impl HalfMaxParams {
    /// How far from its peak the guided region reaches, mm: `guided_reach_diameters` × the
    /// annotated diameter (none without an annotation).
    fn guided_reach_mm(&self, annotated_mm: Option<f64>) -> Option<f64> {
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
        }
        if self.sizing.cuts_half_max() {
            table.insert("half_max".into(), serde_json::to_value(&self.half_max).expect("parameters serialise"));
        }
        key
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Rule {
    Guided,
    BlindLargest,
    BlindPersistent,
}

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
    /// The primary selection's voxel volume and its mesh's enclosed volume (mm³).
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

pub struct Select {
    pub params: Params,
}

impl Stage for Select {
    fn name(&self) -> &'static str {
        "select"
    }
    fn version(&self) -> u32 {
        VERSION
    }
    fn inputs(&self) -> &'static [&'static str] {
        &["ingest", "drr", "grid", "sweep"]
    }
    fn params(&self) -> serde_json::Value {
        self.params.key()
    }
    fn reads(&self, stage: &str, output: &str) -> bool {
        match stage {
            "ingest" => output == GROUND_TRUTH.file || GT_MASK.holds(output),
            "grid" => DENSITY.holds(output),
            "sweep" => output == SWEEP.file || LUNG_FIELD.holds(output),
            "drr" => {
                output == CAMERAS.file
                    || (self.params.sizing == Sizing::Shadows && output.starts_with("drr_") && output.ends_with(".exr"))
            }
            _ => false,
        }
    }
    fn gathers_replicas(&self) -> bool {
        true
    }
    /// Selects in each box the patient was fanned out into (one unless `roi_center = "tiles"`),
    /// then keeps, per rule, the box whose centre answers most ([`tiles`]).
    fn run(&self, ctx: &Context) -> anyhow::Result<Vec<Output>> {
        self.params.check()?;
        let boxes = ctx.replica_count();
        if boxes > 1 && self.params.localize != Localize::Blob {
            bail!(
                "[select] comparing the {boxes} boxes of [drr] roi_center = \"tiles\" needs localize = \"blob\" \
                 (the boxes are ranked by their blob centres)"
            );
        }
        let mut chosen = Vec::with_capacity(boxes);
        for r in 0..boxes {
            chosen.push(self.choose(&ctx.in_replica(r)?).with_context(|| format!("box {r}"))?);
        }
        let chosen = match chosen.len() {
            1 => chosen.pop().expect("one box"),
            _ => tiles::combine(chosen, self.params.primary),
        };
        self.write(ctx.patient(), chosen)
    }
}

/// One box's selections, with what its outputs are drawn from.
struct Chosen {
    /// Complete but for the verdict and the mesh, which [`Select::write`] adds.
    result: SelectResult,
    primary_mask: Option<Vec<bool>>,
    density: Volume<f32>,
    gt: Option<GroundTruthOnGrid>,
    views: Option<shadows::Views>,
    /// The box's name ("tileNN"), from how its scene origin was chosen.
    box_name: String,
}

impl Select {
    /// Every rule's selection in one box (the inputs `ctx` reads).
    fn choose(&self, ctx: &Context) -> anyhow::Result<Chosen> {
        let density: Volume<f32> = super::read_volume(ctx, DENSITY)?;
        let cameras: CameraSet = super::read_json(ctx, CAMERAS)?;
        let sweep: SweepFile = super::read_json(ctx, SWEEP)?;
        let truth: GroundTruth = super::read_json(ctx, GROUND_TRUTH)?;
        let target = truth.target.map(|t| &truth.nodules[t]);
        let gt = match target {
            Some(_) => Some(ground_truth_on_grid(&super::read_volume(ctx, GT_MASK)?, &density.geometry)?),
            None => None,
        };
        // The sweep's lung field, when it swept one: the same σ gives the same field.
        let lungs = match sweep.params.region {
            Region::LungField => {
                let field: Volume<u8> = super::read_volume(ctx, LUNG_FIELD)?;
                Some(field.data.iter().map(|&v| v != 0).collect::<Vec<bool>>())
            }
            Region::Box => None,
        };
        let scored = scored(&density, &sweep.params, lungs)?;
        let levels = levels_of(&scored, &sweep.params)?;
        let found: Vec<Candidate> = levels.iter().flat_map(|l| l.candidates.iter().cloned()).collect();
        let key = |c: &Candidate| (c.label, c.voxels);
        if !found.iter().map(key).eq(sweep.candidates.iter().map(key)) {
            bail!("sweep.json does not match the density it was made from: rerun with --force sweep");
        }
        let analysis = Analysis::new(&levels, gt.as_ref(), &density.geometry);
        let annotated = target.map(|t| t.annotated_diameter_mm);
        let p = &self.params;
        // With half-maximum sizing a search passes over blobs whose region cannot be the nodule,
        // judged at the blob's full width at half maximum whatever fraction the nodule is then
        // cut at. The guided rule's region reaches no farther than the annotated diameter allows.
        let guided_cut = Cut { fraction: p.half_max.fraction, reach_mm: p.half_max.guided_reach_mm(annotated) };
        let blind_cut = Cut::at(p.half_max.fraction);
        let accept = |search: Search, centre: &Centre| match p.sizing {
            Sizing::Candidates => Weighed::Accepted { region: None },
            Sizing::HalfMax | Sizing::Shadows => {
                let (cut, range) = blob_check(search, &p.half_max, annotated);
                match half_max::plausible(&scored, &sweep.params, centre, cut, range) {
                    Some(region) => Weighed::Accepted { region: Some(region) },
                    None => Weighed::PassedOver,
                }
            }
        };
        let mut centres = localize::centres(
            p,
            &density,
            scored.region.as_deref(),
            cameras.frame.roi_center_mm,
            annotated,
            gt.as_ref().map(|g| g.coverage.as_slice()),
            &accept,
        );
        if p.blob.guided_fallback && p.localize == Localize::Blob && annotated.is_some() {
            centres.fall_back_to_blind(p.blob.guided_faint_ratio, |blind| accept(Search::Guided, blind));
        }
        let dims = density.geometry.dims;
        // Some(None): any candidate; Some(Some(cell)): those holding the centre; None: the
        // rule's centre was not found, so it cannot choose.
        let through = |rule: Rule| match p.localize {
            Localize::None => Some(None),
            _ => centres.of(rule).map(|c| Some(c.linear(dims))),
        };
        let views = match p.sizing {
            Sizing::Shadows => Some(read_views(ctx, &cameras)?),
            _ => None,
        };
        // Each rule's selection and its mask, in `Rule` order: guided, blind_largest, blind_persistent.
        let mut chosen = match p.sizing {
            Sizing::Candidates => [Rule::Guided, Rule::BlindLargest, Rule::BlindPersistent].map(|rule| {
                through(rule)
                    .and_then(|cell| analysis.choose(rule, annotated, cell))
                    .map(|at| (analysis.describe(rule, at), levels[at.0].components.mask_of(at.1)))
            }),
            Sizing::HalfMax | Sizing::Shadows => {
                let at = |rule, centre: &Option<Centre>, cut: Cut| {
                    let centre = centre.as_ref()?;
                    let region = half_max::half_max_selection(&scored, &sweep.params, centre, cut, gt.as_ref(), rule)?;
                    match &views {
                        // The shadows say how much; σ's own shape at that volume says where.
                        Some(views) => shadows::shadow_selection(
                            views,
                            (&region.0, &region.1),
                            &density,
                            scored.region.as_deref(),
                            gt.as_ref(),
                            |v| half_max::region_of_volume(&scored, &sweep.params, centre, cut.reach_mm, v),
                        ),
                        None => Some(region),
                    }
                };
                // Both blind rules size the blind centre: one region, reported under each name.
                let blind = at(Rule::BlindLargest, &centres.blind, blind_cut);
                let persistent = blind.clone().map(|(s, m)| (Selection { rule: Rule::BlindPersistent, ..s }, m));
                [at(Rule::Guided, &centres.guided, guided_cut), blind, persistent]
            }
        };
        let primary_index = match self.params.primary {
            Rule::Guided => 0,
            Rule::BlindLargest => 1,
            Rule::BlindPersistent => 2,
        };
        let primary_mask = chosen[primary_index].as_mut().map(|(_, mask)| std::mem::take(mask));
        let [guided, blind_largest, blind_persistent] = chosen.map(|c| c.map(|(selection, _)| selection));
        let primary_sel = [&guided, &blind_largest, &blind_persistent][primary_index].clone();
        let result = SelectResult {
            patient: ctx.patient().to_string(),
            verdict: String::new(),
            primary: self.params.primary,
            blind_rule: self.params.blind,
            gt_volume_mm3: target.map(|t| t.volume_mm3),
            annotated_diameter_mm: target.map(|t| t.annotated_diameter_mm),
            reader_volumes_mm3: target.map(|t| t.annotation_volumes_mm3.clone()).unwrap_or_default(),
            oracle: analysis.oracle(),
            guided,
            blind_largest,
            blind_persistent,
            voxel_volume_mm3: primary_sel.as_ref().map(|s| s.candidate.volume_mm3),
            mesh_volume_mm3: None,
            mesh_triangles: 0,
            candidates: found.len(),
            localize: p.localize,
            sizing: p.sizing,
            centres,
            tiles: vec![],
        };
        Ok(Chosen { result, primary_mask, density, gt, views, box_name: cameras.roi_center_mode })
    }

    /// The verdict on `result`'s primary selection, with notes on its centre.
    fn verdict_of(&self, result: &SelectResult, has_truth: bool) -> String {
        let rule = self.params.primary;
        let primary = result.selection(rule);
        let line = verdict(rule, primary, has_truth, result.annotated_diameter_mm.is_some(), &self.params);
        let centre = result.centres.of(rule);
        let tiled = (!result.tiles.is_empty()).then(|| tiles::margin_note(&result.tiles, rule)).flatten();
        let notes = [centre.and_then(rival_note), centre.and_then(fallback_note), tiled];
        match primary {
            Some(_) => std::iter::once(line).chain(notes.into_iter().flatten()).collect::<Vec<_>>().join("; "),
            None => line,
        }
    }

    /// `result.json`, the primary selection's mask, mesh and previews.
    fn write(&self, patient: &str, chosen: Chosen) -> anyhow::Result<Vec<Output>> {
        let Chosen { mut result, primary_mask, density, gt, views, .. } = chosen;
        let mesh = primary_mask.as_ref().map(|m| mesh_mask(m, &density.geometry));
        result.mesh_volume_mm3 = mesh.as_ref().map(enclosed_volume_mm3);
        result.mesh_triangles = mesh.as_ref().map_or(0, |m| m.triangles.len());
        result.verdict = self.verdict_of(&result, gt.is_some());
        let primary_sel = result.selection(self.params.primary).cloned();
        let mask_volume = Volume {
            geometry: density.geometry.clone(),
            data: primary_mask
                .unwrap_or_else(|| vec![false; density.data.len()])
                .iter()
                .map(|&b| u8::from(b))
                .collect(),
        };

        let mesh = mesh.unwrap_or_default();
        let comments = [
            format!("aret-pipe nodule surface of {patient} ({:?} selection)", self.params.primary),
            "units: mm, patient LPS (DICOM) coordinates".to_string(),
        ];
        let comment_refs: Vec<&str> = comments.iter().map(String::as_str).collect();
        let obj_text = obj::encode(&mesh.vertices, Some(&vertex_normals(&mesh)), &mesh.triangles, &comment_refs);
        // The preview cuts through the selection, then through the nodule, then through an
        // ambiguous search's rival.
        let rival = result.centres.of(self.params.primary).filter(|c| c.ambiguous).and_then(|c| c.runner_up.as_ref());
        let cut_points: Vec<[usize; 3]> = [
            primary_sel.as_ref().map(|s| s.candidate.centroid_mm),
            gt.as_ref().map(|gt| gt.centroid_mm),
            rival.map(|r| r.position_mm),
        ]
        .into_iter()
        .flatten()
        .map(|c| density.geometry.nearest_voxel(c))
        .collect();
        let middle = density.geometry.dims.map(|d| d / 2);
        let centers = if cut_points.is_empty() { vec![middle] } else { cut_points };
        let truth_cells: Option<Vec<bool>> = gt.as_ref().map(|gt| gt.coverage.iter().map(|&c| c >= 0.5).collect());
        let selected: Vec<bool> = mask_volume.data.iter().map(|&b| b != 0).collect();
        let rival_ball = rival.map(|r| density.geometry.ball_mask(r.position_mm, 3f64.sqrt() * r.scale_mm));
        let outlines =
            preview::Outlines { selected: &selected, truth: truth_cells.as_deref(), rival: rival_ball.as_deref() };
        let preview = preview::nodule_png(&density, &outlines, &centers);
        let mut outputs = vec![
            Output::new(RESULT.file, serde_json::to_vec_pretty(&result)?),
            Output::new(NODULE_PREVIEW.file, preview),
            Output::new(NODULE_MESH.file, obj_text),
        ];
        outputs.extend(super::volume_outputs(NODULE_MASK, &mask_volume));
        if let (Some(views), Some(fit)) = (&views, primary_sel.as_ref().and_then(|s| s.shadows)) {
            outputs.push(Output::new(SHADOWS_PREVIEW.file, shadows::shadows_png(views, &fit)));
        }
        Ok(outputs)
    }
}

/// The three DRRs with their nominal cameras (the ones training fitted), for sizing by shadows.
fn read_views(ctx: &Context, cameras: &CameraSet) -> anyhow::Result<shadows::Views> {
    let images = cameras
        .cameras
        .iter()
        .map(|camera| {
            let name = drr_image(camera.view.name());
            crate::formats::exr_image::decode(&ctx.read(CAMERAS.stage, &name)?).with_context(|| format!("drr/{name}"))
        })
        .collect::<anyhow::Result<Vec<_>>>()?;
    shadows::Views::new(&cameras.cameras, &images, cameras.frame, cameras.aabb)
}

/// What the verdict adds when `centre` is ambiguous: where its rival lies and how strongly it
/// answers.
fn rival_note(centre: &Centre) -> Option<String> {
    let rival = centre.runner_up.as_ref().filter(|_| centre.ambiguous)?;
    Some(format!(
        "ambiguous: another blob {:.0} mm away answers at {:.2} of this one's response ([select.blob] rival_ratio)",
        rival.distance_mm, rival.ratio
    ))
}

fn fallback_note(centre: &Centre) -> Option<String> {
    let why = match (centre.from_blind, centre.replaced_guided_peak) {
        (false, _) => return None,
        (true, None) => "the guided search found no blob of the annotated size".to_string(),
        (true, Some(peak)) => format!(
            "the guided search's blob barely stands out (peak contrast {peak:.3}, under [select.blob] \
             guided_faint_ratio of this one's)"
        ),
    };
    Some(format!("{why}: this is the blind search's centre ([select.blob] guided_fallback)"))
}

/// One line saying whether `primary` can be trusted: "hit", or why not ("MISS: …").
pub fn verdict(
    rule: Rule,
    primary: Option<&Selection>,
    has_truth: bool,
    has_diameter: bool,
    params: &Params,
) -> String {
    match (primary, has_truth) {
        (None, _) if rule == Rule::Guided && !has_diameter => {
            "unverified: no annotated diameter, so the guided rule cannot choose (set [select] primary to a blind rule)"
                .into()
        }
        (None, _) if params.sizing.cuts_half_max() => "MISS: no nodule centre was found whose half-maximum \
             region is of a nodule's size ([sweep] diameter_mm; for the guided rule also \
             [select.half_max] guided_diameter_ratio × the annotated diameter)"
            .into(),
        (None, _) if params.localize != Localize::None => {
            "MISS: no nodule centre was found, or no candidate of the sweep holds it".into()
        }
        (None, _) => "MISS: no candidate survived the sweep".into(),
        (Some(_), false) => "unverified: no ground truth to localise against".into(),
        (Some(s), true) => match s.localization {
            Some(l) if l.hit => "hit".into(),
            Some(l) => format!(
                "MISS: the selected component does not touch the nodule (Dice {:.2}, centroid {:.1} mm away); \
                 its volume measures something else",
                l.dice, l.centroid_distance_mm
            ),
            None => "unverified".into(),
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_blob_is_judged_at_half_its_peak_whatever_fraction_sizes_the_nodule() {
        for fraction in [0.3, 0.5, 0.7] {
            let cut = HalfMaxParams { fraction, ..HalfMaxParams::default() };
            let (guided, range) = blob_check(Search::Guided, &cut, Some(20.0));
            assert_eq!(guided.fraction, 0.5);
            assert_eq!(guided.reach_mm, Some(20.0));
            assert_eq!(range, Some([10.0, 40.0]));
            let (blind, range) = blob_check(Search::Blind, &cut, Some(20.0));
            assert_eq!((blind.fraction, blind.reach_mm, range), (0.5, None, None));
        }
    }

    #[test]
    fn region_tie_breaks_need_regions_and_the_rival_ratio_a_positive_number() {
        let blob = |b: BlobParams| Params { blob: b, ..Params::default() };
        let response =
            BlobParams { tie_break: TieBreak::Response, blind_tie_break: TieBreak::Response, ..BlobParams::default() };
        let p = Params {
            sizing: Sizing::Candidates,
            ..blob(BlobParams { tie_break: TieBreak::Roundness, ..response.clone() })
        };
        let e = p.check().unwrap_err().to_string();
        assert!(e.contains("tie_break = \"roundness\"") && e.contains("sizing = \"candidates\""), "{e}");
        assert!(Params { sizing: Sizing::Shadows, ..p }.check().is_ok());
        let p = Params {
            sizing: Sizing::Candidates,
            ..blob(BlobParams { blind_tie_break: TieBreak::Score, ..response.clone() })
        };
        assert!(p.check().unwrap_err().to_string().contains("blind_tie_break = \"score\""));
        let p = Params { sizing: Sizing::HalfMax, ..p };
        assert!(p.check().is_ok());
        assert_eq!(
            (p.blob.tie_break_of(Search::Guided), p.blob.tie_break_of(Search::Blind)),
            (TieBreak::Response, TieBreak::Score)
        );
        assert!(blob(BlobParams { score_top: 0, ..BlobParams::default() })
            .check()
            .unwrap_err()
            .to_string()
            .contains("score_top"));
        for bad in [-1.0, f64::NAN] {
            let p = blob(BlobParams { score_roundness: bad, ..BlobParams::default() });
            assert!(p.check().unwrap_err().to_string().contains("score_roundness"));
        }
        for bad in [0.0, -1.0, f64::NAN] {
            let p = blob(BlobParams { rival_ratio: bad, ..BlobParams::default() });
            assert!(p.check().unwrap_err().to_string().contains("[select.blob] rival_ratio"));
        }
    }

    #[test]
    fn the_key_holds_the_variants_in_use_and_nothing_else() {
        let shipped = Params::default().key();
        assert!(shipped.get("blob").is_some() && shipped.get("half_max").is_some(), "{shipped}");
        let paper = Params { localize: Localize::None, sizing: Sizing::Candidates, ..Params::default() };
        assert_eq!(paper.key().as_object().unwrap().len(), 4, "{}", paper.key());
        // A key of an unused variant changes nothing.
        let other = Params { half_max: HalfMaxParams { fraction: 0.3, ..HalfMaxParams::default() }, ..paper.clone() };
        assert_eq!(paper.key(), other.key());
        assert_ne!(Params { half_max: other.half_max.clone(), ..Params::default() }.key(), shipped);
    }
}
