//! `select`: which candidate is the nodule, and how sure we are that it is (SPEC §3 select).
//!
//! Inputs: `grid/density` (the lattice), `sweep/sweep.json` (candidates and the parameters to
//! regenerate their masks), `ingest/ground_truth.json` (the annotated diameter the guided rule
//! uses), `ingest/gt_mask` (localization only: never used to choose) and `drr/cameras.json`
//! (the scene origin, for `localize = "origin"`); with `localize = "blob"` also
//! `blobs/blobs.json` (the blobs the search chooses among, [`crate::stage::blobs`]); with
//! `sizing = "shadows"` also the three `drr/drr_<view>.exr` ([`size::shadows`]).
//!
//! The rooms: [`find`] finds each rule's centre (`localize`: the blob search, its ranking and
//! the guided rule's fallback, a file each); [`size`] sizes the nodule there (`sizing`);
//! [`params`] holds `[select]` and its variants' tables; [`result`] is `result.json`'s schema;
//! [`verdict`] says whether the primary selection can be trusted; [`preview`] draws it;
//! [`tiles`] compares boxes.
//! A new rule is a search in `find` or a sizing in `size`, and one variant of [`Localize`] or
//! [`Sizing`].
//!
//! Three selections, all reported:
//! - `guided` (the paper's, semi-assisted): the candidate whose equivalent diameter is closest
//!   to the annotated diameter;
//! - `blind_largest` (the paper's blind rule): the largest candidate over all thresholds;
//! - `blind_persistent` (ours, no annotation): the candidate that persists over the most
//!   thresholds ([`Analysis`]).
//!
//! Every selection carries Dice, centroid distance and hit against the consensus mask
//! resampled to the grid; the oracle says whether any candidate was a hit. Outputs:
//! `result.json`, the primary selection's `nodule_mask.mhd/.raw` (uint8) and `nodule.obj`
//! (watertight marching-cubes surface, patient mm), and `nodule.png` (density slices through
//! the selection, the nodule and an ambiguous search's rival, each outlined); with `sizing = "shadows"`
//! also `shadows.png` (the primary selection's fitted ellipsoid over its three shadows).

use crate::artifacts::{
    is_drr_image, BLOBS, CAMERAS, DENSITY, GROUND_TRUTH, GT_MASK, LUNG_FIELD, NODULE_MASK, NODULE_MESH, NODULE_PREVIEW,
    RESULT, SHADOWS_PREVIEW, SWEEP,
};
use crate::engine::{Context, Output, Stage};
use crate::formats::obj;
use crate::kernels::localization::{ground_truth_on_grid, GroundTruthOnGrid};
use crate::kernels::marching_cubes::mesh_mask;
use crate::kernels::mesh::{enclosed_volume_mm3, vertex_normals};
use crate::stage::drr::CameraSet;
use crate::stage::ingest::truth::GroundTruth;
use crate::stage::sweep::{levels_of, scored, swept_lung_field, Candidate, SweepFile};
use crate::volume::Volume;
use anyhow::{bail, Context as _};
use size::shadows;

mod find;
mod params;
mod preview;
mod result;
mod size;
mod tiles;
mod verdict;

pub use find::{centres, BlobRanker, Centre, Centres, RegionShape, RunnerUp, Search, Weighed};
pub use params::{BlobParams, HalfMaxParams, Localize, Params, Rule, Sizing, TieBreak};
pub use result::{Oracle, SelectResult, Selection, ShadowFit, TileScore};
pub use size::candidates::Analysis;
pub use verdict::verdict;

pub const VERSION: u32 = 21;

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
        match self.params.localize {
            Localize::Blob => &["ingest", "drr", "grid", "sweep", "blobs"],
            Localize::None | Localize::Origin => &["ingest", "drr", "grid", "sweep"],
        }
    }
    fn params(&self) -> serde_json::Value {
        self.params.key()
    }
    fn reads(&self, stage: &str, output: &str) -> bool {
        match stage {
            "ingest" => output == GROUND_TRUTH.file || GT_MASK.holds(output),
            "grid" => DENSITY.holds(output),
            "sweep" => output == SWEEP.file || LUNG_FIELD.holds(output),
            "drr" => output == CAMERAS.file || (size::reads_views(self.params.sizing) && is_drr_image(output)),
            "blobs" => output == BLOBS.file,
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
        let lungs = swept_lung_field(ctx, &sweep.params)?;
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
        let views = match size::reads_views(p.sizing) {
            true => Some(read_views(ctx, &cameras)?),
            false => None,
        };
        let inputs = size::Inputs {
            params: p,
            density: &density,
            scored: &scored,
            sweep: &sweep.params,
            levels: &levels,
            analysis: &analysis,
            gt: gt.as_ref(),
            views: views.as_ref(),
            annotated_mm: annotated,
        };
        // A search passes over blobs the sizing cannot size (size::weigh).
        let accept = |search: Search, centre: &Centre| size::weigh(&inputs, search, centre);
        let blobs = match p.localize {
            Localize::Blob => Some(super::read_json(ctx, BLOBS)?),
            Localize::None | Localize::Origin => None,
        };
        let mut centres = find::centres(
            p,
            &density.geometry,
            blobs.as_ref(),
            cameras.frame.roi_center_mm,
            gt.as_ref().map(|g| g.coverage.as_slice()),
            &accept,
        );
        if p.blob.guided_fallback && p.localize == Localize::Blob && annotated.is_some() {
            centres.fall_back_to_blind(p.blob.guided_faint_ratio, |blind| accept(Search::Guided, blind));
        }
        // Each rule's selection and its mask, in `Rule` order: guided, blind_largest, blind_persistent.
        let mut chosen = size::size(&inputs, &centres);
        let primary_index = match self.params.primary {
            Rule::Guided => 0,
            Rule::BlindLargest => 1,
            Rule::BlindPersistent => 2,
        };
        let primary_mask = chosen[primary_index].as_mut().map(|(_, mask)| std::mem::take(mask));
        let [guided, blind_largest, blind_persistent] = chosen.map(|c| c.map(|(selection, _)| selection));
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
            voxel_volume_mm3: None,
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

    /// `result.json`, the primary selection's mask, mesh and previews.
    fn write(&self, patient: &str, chosen: Chosen) -> anyhow::Result<Vec<Output>> {
        let Chosen { mut result, primary_mask, density, gt, views, .. } = chosen;
        let voxel_mm3: f64 = density.geometry.spacing_mm.iter().product();
        result.voxel_volume_mm3 = primary_mask.as_ref().map(|m| m.iter().filter(|&&b| b).count() as f64 * voxel_mm3);
        let mesh = primary_mask.as_ref().map(|m| mesh_mask(m, &density.geometry));
        result.mesh_volume_mm3 = mesh.as_ref().map(enclosed_volume_mm3);
        result.mesh_triangles = mesh.as_ref().map_or(0, |m| m.triangles.len());
        result.verdict = verdict::verdict_of(&self.params, &result, gt.is_some());
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
        let rule = self.params.primary.name();
        let cuts: Vec<preview::Cut> = [
            primary_sel.as_ref().map(|s| (format!("through the {rule} selection"), s.candidate.centroid_mm)),
            gt.as_ref().map(|gt| ("through the ground truth's centroid".to_string(), gt.centroid_mm)),
            rival.map(|r| ("through the rival blob".to_string(), r.position_mm)),
        ]
        .into_iter()
        .flatten()
        .map(|(label, c)| preview::Cut { label, center: density.geometry.nearest_voxel(c) })
        .collect();
        let cuts = if cuts.is_empty() {
            let center = density.geometry.dims.map(|d| d / 2);
            vec![preview::Cut { label: "through the box's middle (nothing selected)".into(), center }]
        } else {
            cuts
        };
        let truth_cells: Option<Vec<bool>> = gt.as_ref().map(|gt| gt.coverage.iter().map(|&c| c >= 0.5).collect());
        let selected: Vec<bool> = mask_volume.data.iter().map(|&b| b != 0).collect();
        let rival_ball = rival.map(|r| density.geometry.ball_mask(r.position_mm, 3f64.sqrt() * r.scale_mm));
        let outlines =
            preview::Outlines { selected: &selected, truth: truth_cells.as_deref(), rival: rival_ball.as_deref() };
        let title = format!("{patient}: {rule} selection");
        let preview = preview::nodule_png(&density, &outlines, &cuts, &title, &result.verdict);
        let mut outputs = vec![
            Output::new(RESULT.file, serde_json::to_vec_pretty(&result)?),
            Output::new(NODULE_PREVIEW.file, preview),
            Output::new(NODULE_MESH.file, obj_text),
        ];
        outputs.extend(super::volume_outputs(NODULE_MASK, &mask_volume));
        if let (Some(views), Some(fit)) = (&views, primary_sel.as_ref().and_then(|s| s.shadows)) {
            let title = format!("{patient}: the {rule} selection's shadows");
            outputs.push(Output::new(SHADOWS_PREVIEW.file, shadows::shadows_png(views, &fit, &title)));
        }
        Ok(outputs)
    }
}

/// The three DRRs with their nominal cameras (the ones training fitted), for sizing by shadows.
fn read_views(ctx: &Context, cameras: &CameraSet) -> anyhow::Result<shadows::Views> {
    let images = cameras.read_images(|name| ctx.read(CAMERAS.stage, name))?;
    Ok(shadows::Views::new(&cameras.cameras, &images, cameras.frame, cameras.aabb))
}

#[cfg(test)]
mod tests {
    use super::*;

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
            ..blob(BlobParams { blind_tie_break: TieBreak::Learned, ..response.clone() })
        };
        assert!(p.check().unwrap_err().to_string().contains("blind_tie_break = \"learned\""));
        let p = Params { sizing: Sizing::HalfMax, ..p };
        assert!(p.check().is_ok());
        assert_eq!(
            (p.blob.tie_break_of(Search::Guided), p.blob.tie_break_of(Search::Blind)),
            (TieBreak::Response, TieBreak::Learned)
        );
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
        let other = Params { half_max: HalfMaxParams { fraction: 0.45, ..HalfMaxParams::default() }, ..paper.clone() };
        assert_eq!(paper.key(), other.key());
        assert_ne!(Params { half_max: other.half_max.clone(), ..Params::default() }.key(), shipped);
    }
}
