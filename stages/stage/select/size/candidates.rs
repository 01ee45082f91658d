//! The selection rules over a sweep's levels ([`Analysis`]): guided, the paper's blind rule
//! and our persistence rule, each choice's report, and the oracle.

use super::{Inputs, Sized};
use crate::kernels::components::Components;
use crate::kernels::localization::{GroundTruthOnGrid, Localization};
use crate::stage::select::find::Centres;
use crate::stage::select::params::{Localize, Rule};
use crate::stage::select::result::{Oracle, Selection};
use crate::stage::sweep::{Candidate, Level};
use crate::volume::Geometry;
use std::collections::BTreeMap;

/// Each rule's candidate of the sweep: among all (`localize = "none"`) or among those holding
/// its centre (none when it found no centre).
pub fn size(inputs: &Inputs, centres: &Centres) -> [Sized; 3] {
    let dims = inputs.density.geometry.dims;
    // Some(None): any candidate; Some(Some(cell)): those holding the centre; None: the rule's
    // centre was not found, so it cannot choose.
    let through = |rule: Rule| match inputs.params.localize {
        Localize::None => Some(None),
        _ => centres.of(rule).map(|c| Some(c.linear(dims))),
    };
    [Rule::Guided, Rule::BlindLargest, Rule::BlindPersistent].map(|rule| {
        through(rule)
            .and_then(|cell| inputs.analysis.choose(rule, inputs.annotated_mm, cell))
            .map(|at| (inputs.analysis.describe(rule, at), inputs.levels[at.0].components.mask_of(at.1)))
    })
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
                // Counted as runs of the sorted pairs: a map's insert per voxel costs more.
                let mut pairs: Vec<(u32, u32)> = (pair[0].components.labels.iter().zip(&pair[1].components.labels))
                    .filter(|(&a, &b)| a != 0 && b != 0)
                    .map(|(&a, &b)| (a, b))
                    .collect();
                pairs.sort_unstable();
                pairs.chunk_by(|x, y| x == y).map(|run| (run[0], run.len())).collect::<BTreeMap<_, _>>()
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

    /// Whether the candidate holds lattice cell `voxel` (linear index); `None` holds everywhere.
    fn holds(&self, (i, label): (usize, u32), voxel: Option<usize>) -> bool {
        voxel.is_none_or(|v| self.levels[i].components.labels[v] == label)
    }

    /// (level index, label) of the candidate `rule` picks, if any candidate survived. With
    /// `through = Some(cell)` (a localised nodule centre, linear index), only candidates that
    /// hold that cell are considered: find first, then size.
    pub fn choose(
        &self,
        rule: Rule,
        annotated_diameter_mm: Option<f64>,
        through: Option<usize>,
    ) -> Option<(usize, u32)> {
        // Ties go to the first in sweep order (lowest percentile, then scipy label order).
        let first_min = |key: &dyn Fn(&Candidate) -> f64| {
            self.all().filter(|&at| self.holds(at, through)).fold(None, |best: Option<((usize, u32), f64)>, at| {
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
            Rule::BlindPersistent => return self.persistent(through),
        };
        pick.map(|(at, _)| at)
    }

    /// Our blind rule. A nodule is a compact blob inside the lungs: it does not touch the box
    /// faces (the chest wall and mediastinum, cut by the box, do), and it survives a range of
    /// thresholds as one component whose size settles. Candidates touching the lattice border
    /// are set aside; each other is chained to the candidate at the next threshold overlapping
    /// it most, while that one is interior too; the longest chain wins (ties: the larger mean
    /// volume, then sweep order), and within it the level whose volume changes least (relative)
    /// to the next. With `through`, chains run only through candidates holding that cell.
    pub fn persistent(&self, through: Option<usize>) -> Option<(usize, u32)> {
        let eligible = |at: (usize, u32)| self.interior(at) && self.holds(at, through);
        let mut best: Option<(usize, f64, (usize, u32))> = None;
        for start in self.all().filter(|&at| eligible(at)) {
            // A candidate continuing an eligible chain from the level before is not a start.
            if self.previous(start).is_some_and(|p| eligible(p) && self.next(p) == Some(start)) {
                continue;
            }
            let mut chain = vec![start];
            while let Some(next) = self.next(*chain.last().expect("non-empty")).filter(|&n| eligible(n)) {
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
        Selection { rule, candidate, volume_interval_mm3: interval, localization, shadows: None, tile: None }
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
