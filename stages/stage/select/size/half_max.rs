//! Sizing from the image instead of from the annotated diameter (`[select] sizing =
//! "half_max"`). A rule's nodule is the connected region, holding its centre, where the
//! sweep's score (σ's local contrast by default) is at least half its peak at the centre, inside
//! the sweep's region: the blob's full width at half maximum, as PET volumetry sizes a lesion by
//! a fraction of its maximum.
//!
//! The paper's guided rule picks the candidate whose equivalent diameter is closest to the
//! annotated one, and the annotated diameter (the largest in-plane extent) is about 1.4× the
//! equivalent one: at best that returns the sphere baseline's volume. Here the diameter only
//! sets the guided centre's blob scale and bounds the region's size (assistance B), and the
//! volume comes from σ alone.
//!
//! A blob search passes over the blobs whose region cannot be the nodule ([`plausible`]): its
//! size is not a nodule's, or (guided) not that of the annotated diameter.

use super::{Inputs, Sized};
use crate::kernels::components::{component_within, label, Components};
use crate::kernels::eigen3::eigenvalues;
use crate::kernels::localization::GroundTruthOnGrid;
use crate::stage::select::find::{Centre, Centres, RegionShape, Search, Weighed};
use crate::stage::select::params::{HalfMaxParams, Rule};
use crate::stage::select::result::Selection;
use crate::stage::sweep::{centroid_mm, equivalent_diameter_mm, summarize, Candidate, Params as SweepParams, Scored};
use crate::volume::Geometry;

/// How far below and above the fraction the volume interval looks (absolute, in units of the peak).
const INTERVAL_STEP: f64 = 0.1;

/// Where a rule cuts its region: at `fraction` of the peak, and no farther than `reach_mm`
/// from the peak when given (the guided rule: a nodule's voxels lie within its largest extent,
/// the annotated diameter, of any of its points, so what lies farther is attached to it).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Cut {
    pub fraction: f64,
    pub reach_mm: Option<f64>,
}

impl Cut {
    /// At `fraction` of the peak, however far from it.
    pub fn at(fraction: f64) -> Cut {
        Cut { fraction, reach_mm: None }
    }
}

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

/// Whether `search` accepts the blob at `centre`: its region, judged at its full width at half
/// maximum ([`plausible`]), is of a nodule's size.
pub fn weigh(inputs: &Inputs, search: Search, centre: &Centre) -> Weighed {
    let (cut, range) = blob_check(search, &inputs.params.half_max, inputs.annotated_mm);
    match plausible(inputs.scored, inputs.sweep, centre, cut, range) {
        Some(region) => Weighed::Accepted { region: Some(region) },
        None => Weighed::PassedOver,
    }
}

/// Each rule's half-maximum region at its centre: the guided rule's within its reach of the
/// peak, both blind rules' at the blind centre (one region, reported under each name).
pub fn size(inputs: &Inputs, centres: &Centres) -> [Sized; 3] {
    size_then(inputs, centres, |_, _, region| Some(region))
}

/// [`size`], each region then handed to `then` with its centre and cut.
pub fn size_then(
    inputs: &Inputs,
    centres: &Centres,
    then: impl Fn(&Centre, Cut, (Selection, Vec<bool>)) -> Sized + Sync,
) -> [Sized; 3] {
    let half_max = &inputs.params.half_max;
    let guided_cut = Cut { fraction: half_max.fraction, reach_mm: half_max.guided_reach_mm(inputs.annotated_mm) };
    let at = |rule, centre: &Option<Centre>, cut: Cut| {
        let centre = centre.as_ref()?;
        let region = half_max_selection(inputs.scored, inputs.sweep, centre, cut, inputs.gt, rule)?;
        then(centre, cut, region)
    };
    // Independent: side by side, a patient's last sizing does not wait for its first.
    let (guided, blind) = rayon::join(
        || at(Rule::Guided, &centres.guided, guided_cut),
        || at(Rule::BlindLargest, &centres.blind, Cut::at(half_max.fraction)),
    );
    let persistent = blind.clone().map(|(s, m)| (Selection { rule: Rule::BlindPersistent, ..s }, m));
    [guided, blind, persistent]
}

/// Whether the half-maximum region at `centre` can be the nodule: the score has a positive
/// peak there, and the region ([`half_max_selection`]'s) has an equivalent diameter within the
/// sweep's `diameter_mm` and within `diameter_range_mm` when given. If it can, the region's
/// shape. Grows only the region, and stops past the largest nodule, so a search can weigh many
/// centres.
pub fn plausible(
    scored: &Scored,
    sweep: &SweepParams,
    centre: &Centre,
    cut: Cut,
    diameter_range_mm: Option<[f64; 2]>,
) -> Option<RegionShape> {
    let (seed, peak) = peak_near(scored, centre.voxel)?;
    let geometry = &scored.score.geometry;
    let voxel_mm3: f64 = geometry.spacing_mm.iter().product();
    let largest_voxels = (std::f64::consts::PI / 6.0 * sweep.diameter_mm[1].powi(3) / voxel_mm3).floor() as usize;
    let inside = member(scored, seed, cut.fraction * f64::from(peak), cut.reach_mm);
    // None: larger than any nodule.
    let voxels = component_within(inside, geometry.dims, sweep.connectivity, seed, largest_voxels)?;
    let diameter_mm = equivalent_diameter_mm(voxels.len() as f64 * voxel_mm3);
    let fits =
        within(diameter_mm, sweep.diameter_mm) && diameter_range_mm.is_none_or(|range| within(diameter_mm, range));
    fits.then(|| RegionShape { roundness: roundness(&voxels, geometry), diameter_mm, peak_score: peak })
}

/// How round a region is: √(λ₃/λ₁) of the covariance of its voxels' positions (mm), 1 for a
/// ball, towards 0 for a rod or a plate. Nodules are compact; the blobs that rival them —
/// vessel junctions, the hilum, a nodule's own strand — are drawn out.
pub fn roundness(voxels: &[usize], geometry: &Geometry) -> f64 {
    let n = voxels.len() as f64;
    // Lattice offsets in mm: the covariance needs no origin, and the axes are orthonormal.
    let position = |i: usize| {
        let ijk = geometry.voxel_at(i);
        std::array::from_fn::<f64, 3, _>(|a| ijk[a] as f64 * geometry.spacing_mm[a])
    };
    let mut mean = [0.0; 3];
    for &i in voxels {
        let p = position(i);
        (0..3).for_each(|a| mean[a] += p[a] / n);
    }
    // Second moments: xx, yy, zz, then xy, xz, yz.
    let mut m = [0.0; 6];
    for &i in voxels {
        let p = position(i);
        let d = [p[0] - mean[0], p[1] - mean[1], p[2] - mean[2]];
        for (k, (a, b)) in [(0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)].into_iter().enumerate() {
            m[k] += d[a] * d[b] / n;
        }
    }
    let [largest, _, smallest] = eigenvalues([m[0], m[1], m[2]], [m[3], m[4], m[5]]);
    if largest > 0.0 {
        (smallest.max(0.0) / largest).sqrt()
    } else {
        1.0 // a single voxel
    }
}

/// Whether `diameter_mm` lies in `[lo, hi]`.
fn within(diameter_mm: f64, [lo, hi]: [f64; 2]) -> bool {
    lo <= diameter_mm && diameter_mm <= hi
}

/// The half-maximum region around `centre`, cut as `cut` says, reported as `rule`'s selection
/// with its mask, or `None` when the score has no positive peak at the centre or the region's
/// equivalent diameter lies outside the sweep's `diameter_mm` (it leaked into the
/// surroundings, or is a speck). The volume interval holds the regions at `fraction ± 0.1`.
pub fn half_max_selection(
    scored: &Scored,
    sweep: &SweepParams,
    centre: &Centre,
    cut: Cut,
    gt: Option<&GroundTruthOnGrid>,
    rule: Rule,
) -> Option<(Selection, Vec<bool>)> {
    let geometry = &scored.score.geometry;
    let (seed, peak) = peak_near(scored, centre.voxel)?;
    let peak = f64::from(peak);
    let at = |fraction: f64| region_at(scored, sweep, seed, fraction * peak, cut.reach_mm);
    let fraction = cut.fraction;
    let threshold = fraction * peak;
    let (components, own) = at(fraction);
    let voxel_mm3: f64 = geometry.spacing_mm.iter().product();
    let volume_mm3 = components.size(own) as f64 * voxel_mm3;
    let diameter_mm = equivalent_diameter_mm(volume_mm3);
    if !within(diameter_mm, sweep.diameter_mm) {
        return None;
    }
    let candidate = Candidate {
        percentile: percentile_of(scored, threshold),
        threshold,
        label: own,
        voxels: components.size(own),
        volume_mm3,
        diameter_mm,
        centroid_mm: summarize(&components, geometry)[own as usize - 1],
    };
    let mut interval = [volume_mm3; 2];
    for neighbour in [fraction - INTERVAL_STEP, fraction + INTERVAL_STEP].into_iter().filter(|f| *f > 0.0 && *f <= 1.0)
    {
        let v = seed_region(scored, sweep, seed, neighbour * peak, cut.reach_mm).len() as f64 * voxel_mm3;
        interval = [interval[0].min(v), interval[1].max(v)];
    }
    let localization =
        gt.map(|gt| gt.compare_labels(&components.labels, components.count(), geometry)[own as usize - 1]);
    let selection =
        Selection { rule, candidate, volume_interval_mm3: interval, localization, shadows: None, tile: None };
    Some((selection, components.mask_of(own)))
}

/// The region around `centre` (cut as [`half_max_selection`] cuts it, within `reach_mm` of the
/// peak) whose volume is closest to `volume_mm3`, with its centroid (patient mm): the score's
/// own shape at the size something else measured. The fraction of the peak is found by
/// bisection, as the region shrinks when it rises. `None` when the score has no positive peak
/// at the centre.
pub fn region_of_volume(
    scored: &Scored,
    sweep: &SweepParams,
    centre: &Centre,
    reach_mm: Option<f64>,
    volume_mm3: f64,
) -> Option<(Vec<bool>, [f64; 3])> {
    let geometry = &scored.score.geometry;
    let voxel_mm3: f64 = geometry.spacing_mm.iter().product();
    let (seed, peak) = peak_near(scored, centre.voxel)?;
    let at = |fraction: f64| seed_region(scored, sweep, seed, fraction * f64::from(peak), reach_mm);
    let (mut lo, mut hi) = (0.0, 1.0);
    let mut best: Option<(f64, Vec<usize>)> = None;
    for _ in 0..BISECTION_STEPS {
        let fraction = 0.5 * (lo + hi);
        let voxels = at(fraction);
        let volume = voxels.len() as f64 * voxel_mm3;
        let miss = (volume - volume_mm3).abs();
        if volume > volume_mm3 {
            lo = fraction;
        } else {
            hi = fraction;
        }
        if best.as_ref().is_none_or(|(m, _)| miss < *m) {
            best = Some((miss, voxels));
        }
    }
    let (_, voxels) = best?;
    let mut mask = vec![false; geometry.len()];
    voxels.iter().for_each(|&i| mask[i] = true);
    Some((mask, centroid_mm(&voxels, geometry)))
}

/// Steps of [`region_of_volume`]'s bisection: the fraction to 1/4096 of the peak.
const BISECTION_STEPS: usize = 12;

/// The largest score in the region among `voxel` and its 26 neighbours (the blob centre is a
/// filtered maximum, the score's own may sit a node away), and where it is; `None` when it is
/// not positive.
fn peak_near(scored: &Scored, voxel: [usize; 3]) -> Option<(usize, f32)> {
    let dims = scored.score.geometry.dims;
    let range = |a: usize| voxel[a].saturating_sub(1)..=(voxel[a] + 1).min(dims[a] - 1);
    let mut best: Option<(usize, f32)> = None;
    for z in range(2) {
        for y in range(1) {
            for x in range(0) {
                let i = x + dims[0] * (y + dims[1] * z);
                let v = scored.score.data[i];
                let inside = scored.region.as_ref().is_none_or(|r| r[i]);
                if inside && best.is_none_or(|(_, b)| v > b) {
                    best = Some((i, v));
                }
            }
        }
    }
    best.filter(|&(_, v)| v > 0.0)
}

/// Whether node `i` may belong to `seed`'s region: its score is at least `threshold`, it lies
/// in the sweep's region, and within `reach_mm` of the seed when given.
fn member(scored: &Scored, seed: usize, threshold: f64, reach_mm: Option<f64>) -> impl Fn(usize) -> bool + '_ {
    let geometry = &scored.score.geometry;
    let at = |i: usize| geometry.voxel_at(i);
    let from = at(seed);
    let reach_sq = reach_mm.map(|r| r * r);
    move |i: usize| {
        // Checked last: most nodes fail the threshold first.
        let near = || {
            let to = at(i);
            let d2: f64 = (0..3).map(|a| ((to[a] as f64 - from[a] as f64) * geometry.spacing_mm[a]).powi(2)).sum();
            reach_sq.is_none_or(|r2| d2 <= r2)
        };
        f64::from(scored.score.data[i]) >= threshold && scored.region.as_ref().is_none_or(|r| r[i]) && near()
    }
}

/// The nodes of `seed`'s component of [`member`]'s (the one [`region_at`] labels `seed`'s),
/// ascending: grown from the seed, it costs what it holds.
fn seed_region(scored: &Scored, sweep: &SweepParams, seed: usize, threshold: f64, reach_mm: Option<f64>) -> Vec<usize> {
    let is_member = member(scored, seed, threshold, reach_mm);
    let dims = scored.score.geometry.dims;
    component_within(is_member, dims, sweep.connectivity, seed, usize::MAX).expect("the seed's score is the peak")
}

/// The components of the nodes that may belong to `seed`'s region ([`member`]), and the label
/// of the one holding `seed` (whose score is the peak, so it is always in one).
fn region_at(
    scored: &Scored,
    sweep: &SweepParams,
    seed: usize,
    threshold: f64,
    reach_mm: Option<f64>,
) -> (Components, u32) {
    let is_member = member(scored, seed, threshold, reach_mm);
    let mask: Vec<bool> = (0..scored.score.data.len()).map(is_member).collect();
    let components = label(&mask, scored.score.geometry.dims, sweep.connectivity);
    let own = components.labels[seed];
    (components, own)
}

/// Where `threshold` lies among the region's scores, in percent (the fraction below it).
fn percentile_of(scored: &Scored, threshold: f64) -> f64 {
    let region = scored.region.as_deref();
    let (mut below, mut count) = (0usize, 0usize);
    for (i, &v) in scored.score.data.iter().enumerate() {
        if region.is_none_or(|r| r[i]) {
            count += 1;
            below += usize::from(f64::from(v) < threshold);
        }
    }
    if count == 0 {
        0.0
    } else {
        100.0 * below as f64 / count as f64
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::volume::{Geometry, Volume};

    fn geometry(dims: [usize; 3]) -> Geometry {
        Geometry {
            dims,
            spacing_mm: [1.0, 1.0, 1.0],
            origin_mm: [0.0; 3],
            direction: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        }
    }

    /// A Gaussian bump of width `w` (nodes) at `c`, peak 1, on a 32³ lattice.
    fn bump(c: [f64; 3], w: f64) -> Scored {
        let dims = [32, 32, 32];
        let mut data = vec![0f32; 32 * 32 * 32];
        for z in 0..32 {
            for y in 0..32 {
                for x in 0..32 {
                    let r2 = (x as f64 - c[0]).powi(2) + (y as f64 - c[1]).powi(2) + (z as f64 - c[2]).powi(2);
                    data[x + 32 * (y + 32 * z)] = (-r2 / (2.0 * w * w)).exp() as f32;
                }
            }
        }
        Scored { score: Volume { geometry: geometry(dims), data }, region: None }
    }

    fn centre(voxel: [usize; 3]) -> Centre {
        Centre::at(voxel, voxel.map(|v| v as f64))
    }

    #[test]
    fn the_half_maximum_region_of_a_gaussian_is_its_fwhm_ball() {
        let w = 4.0;
        let scored = bump([16.0, 16.0, 16.0], w);
        let sweep = SweepParams { diameter_mm: [1.0, 80.0], ..SweepParams::default() };
        // The centre a node off the peak: the peak is found beside it.
        let (selection, mask) =
            half_max_selection(&scored, &sweep, &centre([15, 16, 16]), Cut::at(0.5), None, Rule::Guided).unwrap();
        // Nodes within the half-maximum radius w·√(2 ln 2) of the peak, counted directly.
        let r = w * (2.0 * 2f64.ln()).sqrt();
        let expected = (0..32usize.pow(3))
            .filter(|&i| {
                let (x, y, z) = (i % 32, (i / 32) % 32, i / 1024);
                let d2 = [x, y, z].iter().map(|&v| (v as f64 - 16.0).powi(2)).sum::<f64>();
                d2 <= r * r
            })
            .count();
        assert_eq!(selection.candidate.voxels, expected);
        assert_eq!(mask.iter().filter(|&&b| b).count(), expected);
        assert_eq!(selection.candidate.centroid_mm, [16.0, 16.0, 16.0]);
        assert!((selection.candidate.threshold - 0.5).abs() < 1e-9);
        // The interval holds the regions at 0.4 and 0.6 of the peak: larger and smaller.
        let [lo, hi] = selection.volume_interval_mm3;
        assert!(lo < selection.candidate.volume_mm3 && selection.candidate.volume_mm3 < hi);
    }

    #[test]
    fn a_region_outside_the_diameter_range_or_no_peak_selects_nothing() {
        let scored = bump([16.0, 16.0, 16.0], 4.0);
        let small = SweepParams { diameter_mm: [1.0, 5.0], ..SweepParams::default() };
        assert!(half_max_selection(&scored, &small, &centre([16, 16, 16]), Cut::at(0.5), None, Rule::Guided).is_none());
        let flat =
            Scored { score: Volume { geometry: geometry([32; 3]), data: vec![0.0; 32 * 32 * 32] }, region: None };
        let any = SweepParams::default();
        assert!(half_max_selection(&flat, &any, &centre([16, 16, 16]), Cut::at(0.5), None, Rule::Guided).is_none());
    }

    #[test]
    fn the_region_stays_inside_the_sweeps_region() {
        let mut scored = bump([16.0, 16.0, 16.0], 4.0);
        // Only the half-space x ≤ 16 is region.
        scored.region = Some((0..32usize.pow(3)).map(|i| i % 32 <= 16).collect());
        let sweep = SweepParams { diameter_mm: [1.0, 80.0], ..SweepParams::default() };
        let (_, mask) =
            half_max_selection(&scored, &sweep, &centre([16, 16, 16]), Cut::at(0.5), None, Rule::Guided).unwrap();
        assert!(mask.iter().enumerate().all(|(i, &b)| !b || i % 32 <= 16));
        assert!(mask[15 + 32 * (16 + 32 * 16)]);
    }

    #[test]
    fn a_region_is_plausible_when_its_size_fits() {
        let mut scored = bump([16.0, 16.0, 16.0], 4.0);
        let sweep = SweepParams { diameter_mm: [1.0, 80.0], ..SweepParams::default() };
        let at = centre([16, 16, 16]);
        // The FWHM ball's equivalent diameter is ≈ 2 · 4 · √(2 ln 2) ≈ 9.4 nodes.
        assert!(plausible(&scored, &sweep, &at, Cut::at(0.5), None).is_some());
        assert!(plausible(&scored, &sweep, &at, Cut::at(0.5), Some([8.0, 11.0])).is_some());
        assert!(plausible(&scored, &sweep, &at, Cut::at(0.5), Some([11.0, 30.0])).is_none(), "smaller than the range");
        assert!(plausible(&scored, &sweep, &at, Cut::at(0.5), Some([2.0, 8.0])).is_none(), "larger than the range");
        let narrow = SweepParams { diameter_mm: [1.0, 8.0], ..SweepParams::default() };
        assert!(plausible(&scored, &narrow, &at, Cut::at(0.5), None).is_none(), "larger than any nodule");
        // Only the part inside the sweep's region counts: a cap of the ball (x ≤ 13) is small.
        scored.region = Some((0..32usize.pow(3)).map(|i| i % 32 <= 13).collect());
        assert!(plausible(&scored, &sweep, &centre([13, 16, 16]), Cut::at(0.5), Some([8.0, 11.0])).is_none());
        assert!(plausible(&scored, &sweep, &centre([13, 16, 16]), Cut::at(0.5), Some([3.0, 8.0])).is_some());
        // No positive peak: nothing to size.
        let flat =
            Scored { score: Volume { geometry: geometry([32; 3]), data: vec![0.0; 32 * 32 * 32] }, region: None };
        assert!(plausible(&flat, &sweep, &at, Cut::at(0.5), None).is_none());
    }

    #[test]
    fn a_reach_cuts_off_a_strand_beyond_it() {
        // A bump with a strand at its full height along +x from the peak to the lattice's edge.
        let mut scored = bump([10.0, 16.0, 16.0], 3.0);
        for x in 10..32 {
            scored.score.data[x + 32 * (16 + 32 * 16)] = 1.0;
        }
        let sweep = SweepParams { diameter_mm: [1.0, 80.0], ..SweepParams::default() };
        let at = centre([10, 16, 16]);
        let strand_tip = 31 + 32 * (16 + 32 * 16);
        let (free, free_mask) = half_max_selection(&scored, &sweep, &at, Cut::at(0.5), None, Rule::Guided).unwrap();
        assert!(free_mask[strand_tip], "without a reach the region follows the strand");
        let cut = Cut { fraction: 0.5, reach_mm: Some(8.0) };
        let (held, mask) = half_max_selection(&scored, &sweep, &at, cut, None, Rule::Guided).unwrap();
        assert!(!mask[strand_tip] && mask[18 + 32 * (16 + 32 * 16)] && !mask[19 + 32 * (16 + 32 * 16)]);
        assert_eq!(free.candidate.voxels - held.candidate.voxels, 13, "the strand's nodes x = 19..31 go");
        // The search's check measures the same region.
        let d = held.candidate.diameter_mm;
        assert!(plausible(&scored, &sweep, &at, cut, Some([d - 1e-9, d + 1e-9])).is_some());
        assert!(plausible(&scored, &sweep, &at, Cut::at(0.5), Some([d - 1e-9, d + 1e-9])).is_none());
    }

    #[test]
    fn roundness_is_one_for_a_ball_and_the_axis_ratio_for_an_ellipsoid() {
        // Solid ellipsoids on 0.5 mm cells: their covariance is diag(a², b², c²)/5, so the
        // roundness is the smallest semi-axis over the largest.
        let g = Geometry { spacing_mm: [0.5; 3], ..geometry([64; 3]) };
        let solid = |axes_mm: [f64; 3]| -> Vec<usize> {
            (0..g.len())
                .filter(|&i| {
                    let ijk = g.voxel_at(i);
                    (0..3).map(|a| ((ijk[a] as f64 - 32.0) * 0.5 / axes_mm[a]).powi(2)).sum::<f64>() <= 1.0
                })
                .collect()
        };
        assert!((roundness(&solid([10.0; 3]), &g) - 1.0).abs() < 0.01);
        for (axes, expected) in [([12.0, 6.0, 4.0], 4.0 / 12.0), ([5.0, 10.0, 8.0], 0.5)] {
            let got = roundness(&solid(axes), &g);
            assert!((got - expected).abs() < 0.02 * expected, "{axes:?}: {got} against {expected}");
        }
        // A rod of voxels has no spread across it; a single voxel counts as round.
        let rod: Vec<usize> = (10..40).map(|x| x + 64 * (32 + 64 * 32)).collect();
        assert!(roundness(&rod, &g) < 1e-6);
        assert_eq!(roundness(&[5], &g), 1.0);
    }

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
}
