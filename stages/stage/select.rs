//! `select`: which candidate is the nodule, and how sure we are that it is (SPEC §3 select).
//!
//! Inputs: `grid/density` (the lattice), `sweep/sweep.json` (candidates and the parameters to
//! regenerate their masks), `ingest/ground_truth.json` (the annotated diameter the guided rule
//! uses) and `ingest/gt_mask` (localization only: never used to choose).
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
//! the selection, with the selection and the ground truth outlined).

use crate::engine::{Context, Output, Stage};
use crate::formats::obj;
use crate::kernels::components::Components;
use crate::kernels::localization::{ground_truth_on_grid, GroundTruthOnGrid, Localization};
use crate::kernels::marching_cubes::mesh_mask;
use crate::kernels::mesh::{enclosed_volume_mm3, vertex_normals};
use crate::stage::ingest::truth::GroundTruth;
use crate::stage::sweep::{levels, Candidate, Level, SweepFile};
use crate::volume::{Geometry, Volume};
use anyhow::{bail, Context as _};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

pub const VERSION: u32 = 1;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// The selection written as `nodule_mask` and `nodule.obj`, and reported as "ours":
    /// "guided", "blind_largest" or "blind_persistent".
    pub primary: Rule,
    /// The blind rule reported beside the guided one in the cohort table.
    pub blind: Rule,
}

impl Default for Params {
    fn default() -> Self {
        Params { primary: Rule::Guided, blind: Rule::BlindPersistent }
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
    pub guided: Option<Selection>,
    pub blind_largest: Option<Selection>,
    pub blind_persistent: Option<Selection>,
    pub oracle: Option<Oracle>,
    /// The primary selection's voxel volume and its mesh's enclosed volume (mm³).
    pub voxel_volume_mm3: Option<f64>,
    pub mesh_volume_mm3: Option<f64>,
    pub mesh_triangles: usize,
    pub candidates: usize,
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
        &["ingest", "grid", "sweep"]
    }
    fn params(&self) -> serde_json::Value {
        super::params_json(&self.params)
    }
    fn reads(&self, stage: &str, output: &str) -> bool {
        match stage {
            "ingest" => output == "ground_truth.json" || output.starts_with("gt_mask."),
            "grid" => output == "density.mhd" || output == "density.raw",
            "sweep" => output == "sweep.json",
            _ => false,
        }
    }
    fn run(&self, ctx: &Context) -> anyhow::Result<Vec<Output>> {
        let density: Volume<f32> = super::read_volume(ctx, "grid", "density")?;
        let sweep: SweepFile = serde_json::from_slice(&ctx.read("sweep", "sweep.json")?)?;
        let truth: GroundTruth =
            serde_json::from_slice(&ctx.read("ingest", "ground_truth.json")?).context("ingest/ground_truth.json")?;
        let target = truth.target.map(|t| &truth.nodules[t]);
        let gt = match target {
            Some(_) => Some(ground_truth_on_grid(&super::read_volume(ctx, "ingest", "gt_mask")?, &density.geometry)?),
            None => None,
        };
        let levels = levels(&density, &sweep.params)?;
        let found: Vec<Candidate> = levels.iter().flat_map(|l| l.candidates.iter().cloned()).collect();
        let key = |c: &Candidate| (c.label, c.voxels);
        if !found.iter().map(key).eq(sweep.candidates.iter().map(key)) {
            bail!("sweep.json does not match the density it was made from: rerun with --force sweep");
        }
        let analysis = Analysis::new(&levels, gt.as_ref(), &density.geometry);
        let annotated = target.map(|t| t.annotated_diameter_mm);
        let report = |rule| analysis.choose(rule, annotated).map(|at| analysis.describe(rule, at));
        let (guided, blind_largest, blind_persistent) =
            (report(Rule::Guided), report(Rule::BlindLargest), report(Rule::BlindPersistent));
        let primary_at = analysis.choose(self.params.primary, annotated);
        let primary_mask = primary_at.map(|(i, label)| levels[i].components.mask_of(label));
        let primary_sel = [&guided, &blind_largest, &blind_persistent]
            .into_iter()
            .flatten()
            .find(|s| s.rule == self.params.primary)
            .cloned();
        let mesh = primary_mask.as_ref().map(|m| mesh_mask(m, &density.geometry));
        let mesh_volume_mm3 = mesh.as_ref().map(enclosed_volume_mm3);
        let result = SelectResult {
            patient: ctx.patient().to_string(),
            verdict: verdict(primary_sel.as_ref(), gt.is_some()),
            primary: self.params.primary,
            blind_rule: self.params.blind,
            gt_volume_mm3: target.map(|t| t.volume_mm3),
            annotated_diameter_mm: target.map(|t| t.annotated_diameter_mm),
            oracle: analysis.oracle(),
            guided,
            blind_largest,
            blind_persistent,
            voxel_volume_mm3: primary_sel.as_ref().map(|s| s.candidate.volume_mm3),
            mesh_volume_mm3,
            mesh_triangles: mesh.as_ref().map_or(0, |m| m.triangles.len()),
            candidates: found.len(),
        };
        let mask_volume = Volume {
            geometry: density.geometry.clone(),
            data: primary_mask
                .unwrap_or_else(|| vec![false; density.data.len()])
                .iter()
                .map(|&b| u8::from(b))
                .collect(),
        };
        let (header, raw) = crate::formats::mhd::encode(&mask_volume, "nodule_mask.raw");
        let mesh = mesh.unwrap_or_default();
        let comments = [
            format!("aret-pipe nodule surface of {} ({:?} selection)", ctx.patient(), self.params.primary),
            "units: mm, patient LPS (DICOM) coordinates".to_string(),
        ];
        let comment_refs: Vec<&str> = comments.iter().map(String::as_str).collect();
        let obj_text = obj::encode(&mesh.vertices, Some(&vertex_normals(&mesh)), &mesh.triangles, &comment_refs);
        Ok(vec![
            Output::new("result.json", serde_json::to_vec_pretty(&result)?),
            Output::new("nodule_mask.mhd", header),
            Output::new("nodule_mask.raw", raw),
            Output::new("nodule.obj", obj_text),
        ])
    }
}

/// Facts about every level that the rules and the report use, each found in one pass.
pub struct Analysis<'a> {
    pub levels: &'a [Level],
    /// `touches_border[i][label − 1]`: the candidate has a voxel on a face of the lattice.
    touches_border: Vec<Vec<bool>>,
    /// `shared[i]`: voxels shared by (label at level i, label at level i + 1).
    shared: Vec<BTreeMap<(u32, u32), usize>>,
    /// `localization[i][label − 1]`, when there is a ground truth.
    localization: Option<Vec<Vec<Localization>>>,
}

impl<'a> Analysis<'a> {
    pub fn new(levels: &'a [Level], gt: Option<&GroundTruthOnGrid>, geometry: &Geometry) -> Analysis<'a> {
        let touches_border = levels.iter().map(|l| border_labels(&l.components)).collect();
        let shared = levels
            .windows(2)
            .map(|pair| {
                let mut table = BTreeMap::new();
                for (&a, &b) in pair[0].components.labels.iter().zip(&pair[1].components.labels) {
                    if a != 0 && b != 0 {
                        *table.entry((a, b)).or_insert(0) += 1;
                    }
                }
                table
            })
            .collect();
        let localization = gt.map(|gt| {
            levels.iter().map(|l| gt.compare_labels(&l.components.labels, l.components.count(), geometry)).collect()
        });
        Analysis { levels, touches_border, shared, localization }
    }

    fn interior(&self, (i, label): (usize, u32)) -> bool {
        !self.touches_border[i][label as usize - 1]
    }

    /// The candidate at level `i + 1` sharing the most voxels with `label` at level `i`
    /// (ties: the lowest label).
    fn next(&self, (i, label): (usize, u32)) -> Option<(usize, u32)> {
        let table = self.shared.get(i)?;
        let best = table.range((label, 0)..=(label, u32::MAX)).max_by(|x, y| x.1.cmp(y.1).then(y.0 .1.cmp(&x.0 .1)));
        best.map(|(&(_, b), _)| (i + 1, b))
    }

    /// The candidate at level `i − 1` sharing the most voxels with `label` at level `i`.
    fn previous(&self, (i, label): (usize, u32)) -> Option<(usize, u32)> {
        let table = self.shared.get(i.checked_sub(1)?)?;
        let best = table.iter().filter(|((_, b), _)| *b == label).max_by(|x, y| x.1.cmp(y.1).then(y.0 .0.cmp(&x.0 .0)));
        best.map(|(&(a, _), _)| (i - 1, a))
    }

    fn candidate(&self, (i, label): (usize, u32)) -> &Candidate {
        &self.levels[i].candidates[label as usize - 1]
    }

    fn all(&self) -> impl Iterator<Item = (usize, u32)> + '_ {
        self.levels.iter().enumerate().flat_map(|(i, l)| l.candidates.iter().map(move |c| (i, c.label)))
    }

    /// (level index, label) of the candidate `rule` picks, if any candidate survived.
    pub fn choose(&self, rule: Rule, annotated_diameter_mm: Option<f64>) -> Option<(usize, u32)> {
        // Ties go to the first in sweep order (lowest percentile, then scipy label order).
        let first_min = |key: &dyn Fn(&Candidate) -> f64| {
            self.all().fold(None, |best: Option<((usize, u32), f64)>, at| {
                let k = key(self.candidate(at));
                match best {
                    Some((_, bk)) if bk <= k => best,
                    _ => Some((at, k)),
                }
            })
        };
        let pick = match rule {
            Rule::Guided => {
                let d = annotated_diameter_mm?;
                first_min(&|c| (c.diameter_mm - d).abs())
            }
            Rule::BlindLargest => first_min(&|c| -(c.voxels as f64)),
            Rule::BlindPersistent => return self.persistent(),
        };
        pick.map(|(at, _)| at)
    }

    /// Our blind rule. A nodule is a compact blob inside the lungs: it does not touch the box
    /// faces (the chest wall and mediastinum, cut by the box, do), and it survives a range of
    /// thresholds as one component whose size settles. Candidates touching the lattice border
    /// are set aside; each other is chained to the candidate at the next threshold overlapping
    /// it most, while that one is interior too; the longest chain wins (ties: the larger mean
    /// volume, then sweep order), and within it the level whose volume changes least (relative)
    /// to the next.
    pub fn persistent(&self) -> Option<(usize, u32)> {
        let mut best: Option<(usize, f64, (usize, u32))> = None;
        for start in self.all().filter(|&at| self.interior(at)) {
            // A candidate continuing an interior chain from the level before is not a start.
            if self.previous(start).is_some_and(|p| self.interior(p) && self.next(p) == Some(start)) {
                continue;
            }
            let mut chain = vec![start];
            while let Some(next) = self.next(*chain.last().expect("non-empty")).filter(|&n| self.interior(n)) {
                chain.push(next);
            }
            let volume = |at: (usize, u32)| self.candidate(at).volume_mm3;
            let mean_volume = chain.iter().map(|&at| volume(at)).sum::<f64>() / chain.len() as f64;
            let change = |k: usize| match chain.get(k + 1) {
                Some(&next) => (volume(next) - volume(chain[k])).abs() / volume(chain[k]),
                None => f64::INFINITY,
            };
            let settled = (0..chain.len()).min_by(|&a, &b| change(a).total_cmp(&change(b))).map(|k| chain[k]);
            let better = match best {
                None => true,
                Some((len, mean, _)) => chain.len() > len || (chain.len() == len && mean_volume > mean),
            };
            if better {
                best = Some((chain.len(), mean_volume, settled.expect("a chain has a first link")));
            }
        }
        best.map(|(_, _, at)| at)
    }

    /// The report of one rule's choice.
    pub fn describe(&self, rule: Rule, at: (usize, u32)) -> Selection {
        let candidate = self.candidate(at).clone();
        let mut interval = [candidate.volume_mm3; 2];
        for neighbour in [self.previous(at), self.next(at)].into_iter().flatten() {
            let v = self.candidate(neighbour).volume_mm3;
            interval = [interval[0].min(v), interval[1].max(v)];
        }
        let localization = self.localization.as_ref().map(|l| l[at.0][at.1 as usize - 1]);
        Selection { rule, candidate, volume_interval_mm3: interval, localization }
    }

    /// Whether any candidate touched the nodule, and the best Dice among those that did.
    pub fn oracle(&self) -> Option<Oracle> {
        let localization = self.localization.as_ref()?;
        let mut result = Oracle { any_hit: false, best_dice: 0.0, best: None };
        for at in self.all() {
            let l = localization[at.0][at.1 as usize - 1];
            if l.hit && (result.best.is_none() || l.dice > result.best_dice) {
                result.any_hit = true;
                result.best_dice = l.dice;
                result.best = Some(self.candidate(at).clone());
            }
        }
        Some(result)
    }
}

/// For each label of `c`, whether it has a voxel on a face of the lattice.
fn border_labels(c: &Components) -> Vec<bool> {
    let [nx, ny, nz] = c.dims;
    let mut touches = vec![false; c.count()];
    for (i, &l) in c.labels.iter().enumerate().filter(|(_, &l)| l != 0) {
        let (x, y, z) = (i % nx, (i / nx) % ny, i / (nx * ny));
        if x == 0 || y == 0 || z == 0 || x + 1 == nx || y + 1 == ny || z + 1 == nz {
            touches[l as usize - 1] = true;
        }
    }
    touches
}

/// One line saying whether `primary` can be trusted: "hit", or why not ("MISS: …").
pub fn verdict(primary: Option<&Selection>, has_truth: bool) -> String {
    match (primary, has_truth) {
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
