//! Grouping annotations into nodules exactly as pylidc 0.2.3's `Scan.cluster_annotations()`
//! (metric `'min'`); see [`cluster_annotations`] for the rule.

use super::annotation::{check_not_empty, Annotation};
use super::mask::BBox;
use super::mask::GroundTruthError;
use std::cmp::Ordering;
use std::collections::HashMap;

/// Parameters of [`cluster_annotations`], pylidc's defaults by [`Default`].
#[derive(Debug, Clone, PartialEq)]
pub struct ClusterParams {
    /// Starting link distance in index units; `None`: the scan's slice thickness (pylidc).
    pub tol: Option<f64>,
    /// Multiplies `tol` while a cluster is too large; in (0, 1).
    pub factor: f64,
    /// Below this `tol` clustering gives up.
    pub min_tol: f64,
    /// Largest cluster accepted (four LIDC readers).
    pub max_annotations: usize,
}

impl Default for ClusterParams {
    fn default() -> Self {
        Self { tol: None, factor: 0.9, min_tol: 0.1, max_annotations: 4 }
    }
}

/// Annotations grouped into nodules.
#[derive(Debug, Clone, PartialEq)]
pub struct Clustering {
    /// Indices into the annotation list, one `Vec` per nodule; see [`cluster_annotations`] for
    /// the order.
    pub clusters: Vec<Vec<usize>>,
    pub tol_initial: f64,
    /// The tolerance that produced `clusters`.
    pub tol_final: f64,
}

/// pylidc's `Scan.cluster_annotations(metric='min')`.
///
/// The rule: the distance between two annotations is the smallest Euclidean distance between a
/// contour point of one and a contour point of the other, measured in `(i, j, k)` **index**
/// units (not mm), all contours (inclusion and exclusion) counted. Two annotations are linked
/// when that distance is `<= tol`; nodules are the connected components of the links (so
/// linking is transitive). Any two annotations may join, **including two by the same
/// radiologist**: pylidc does not look at who drew them. `tol` starts at `params.tol` or else
/// `slice_thickness_mm`; while any component has more than `params.max_annotations` members,
/// `tol *= factor` and the components are recomputed; if `tol` drops below `min_tol` clustering
/// fails ([`GroundTruthError::ClusterTolerance`], pylidc raises `ClusterError`).
///
/// Order: members in ascending annotation index; components first in order of their smallest
/// member (scipy's labelling), then stably sorted by the mean over members of
/// [`Annotation::centroid_ijk`]`[2]` (the slice index), as pylidc does.
pub fn cluster_annotations(
    annotations: &[Annotation],
    slice_thickness_mm: f64,
    params: &ClusterParams,
) -> Result<Clustering, GroundTruthError> {
    check_cluster_params(params)?;
    check_not_empty(annotations)?;
    let tol_initial = params.tol.unwrap_or(slice_thickness_mm);
    if !(tol_initial.is_finite() && tol_initial >= 0.0) {
        return Err(GroundTruthError::ClusterParams(format!("tol {tol_initial} must be a finite number >= 0")));
    }
    let distances = distance_matrix(annotations, tol_initial);
    let mut tol = tol_initial;
    let mut labels = components(&distances, tol);
    // pylidc returns N <= 1 without looking at sizes; with max_annotations >= 1 that is the same.
    while let Some(largest) = oversized(&labels, params.max_annotations) {
        tol *= params.factor;
        if tol < params.min_tol {
            return Err(GroundTruthError::ClusterTolerance {
                max_annotations: params.max_annotations,
                tol,
                min_tol: params.min_tol,
                largest,
            });
        }
        labels = components(&distances, tol);
    }
    let mut clusters = group_by_label(&labels);
    let centroid_k: Vec<f64> = annotations.iter().map(|a| a.centroid_ijk()[2]).collect();
    let mean_k = |c: &Vec<usize>| c.iter().map(|&a| centroid_k[a]).sum::<f64>() / c.len() as f64;
    clusters.sort_by(|a, b| mean_k(a).total_cmp(&mean_k(b)));
    Ok(Clustering { clusters, tol_initial, tol_final: tol })
}

fn check_cluster_params(params: &ClusterParams) -> Result<(), GroundTruthError> {
    if !(params.factor > 0.0 && params.factor < 1.0) {
        return Err(GroundTruthError::ClusterParams(format!("factor {} must lie in (0, 1)", params.factor)));
    }
    if params.min_tol.partial_cmp(&0.0) != Some(Ordering::Greater) || params.max_annotations == 0 {
        return Err(GroundTruthError::ClusterParams(format!(
            "min_tol {} must be > 0 and max_annotations {} >= 1",
            params.min_tol, params.max_annotations
        )));
    }
    Ok(())
}

/// Symmetric matrix of annotation distances (index units), `+inf` beyond `cutoff`: `tol` only
/// shrinks from `cutoff`, so such pairs can never link. Pairs whose bounding boxes are farther
/// apart than `cutoff` skip the point-by-point search.
fn distance_matrix(annotations: &[Annotation], cutoff: f64) -> Vec<Vec<f64>> {
    let n = annotations.len();
    let points: Vec<Vec<[i64; 3]>> = annotations.iter().map(|a| a.points_ijk().collect()).collect();
    let boxes: Vec<BBox> = annotations.iter().map(Annotation::bbox).collect();
    let mut d = vec![vec![0.0; n]; n];
    for a in 0..n {
        for b in a + 1..n {
            let dist = if bbox_distance(&boxes[a], &boxes[b]) > cutoff {
                f64::INFINITY
            } else {
                min_point_distance(&points[a], &points[b], cutoff)
            };
            d[a][b] = dist;
            d[b][a] = dist;
        }
    }
    d
}

/// Euclidean gap between two boxes (0 when they overlap): a lower bound on point distances.
fn bbox_distance(a: &BBox, b: &BBox) -> f64 {
    let gap = |axis: usize| {
        let (lo_a, hi_a) = (a.min_ijk[axis] as f64, a.max_ijk[axis] as f64);
        let (lo_b, hi_b) = (b.min_ijk[axis] as f64, b.max_ijk[axis] as f64);
        (lo_b - hi_a).max(lo_a - hi_b).max(0.0)
    };
    (0..3).map(|axis| gap(axis).powi(2)).sum::<f64>().sqrt()
}

/// `cdist(...).min()` when it is at most `cutoff`, else `+inf`: clustering never links a pair
/// farther apart than its starting tolerance, so the exact value beyond it does not matter.
///
/// The points of `b` are bucketed in cubes of side ⌈cutoff⌉ (at least 1), and each point of `a`
/// meets only the points in its own and the 26 neighbouring cubes, where any pair within
/// `cutoff` lies. The work grows with the points, not with their product (two annotations of
/// 40,000 points each once cost 1.6 × 10⁹ comparisons). The squared distances are exact integers
/// and `sqrt` is monotone and correctly rounded, so `sqrt(min d²)` equals scipy's minimum of
/// square roots bit for bit.
fn min_point_distance(a: &[[i64; 3]], b: &[[i64; 3]], cutoff: f64) -> f64 {
    let side = (cutoff.ceil() as i64).max(1);
    let cube_of = |p: &[i64; 3]| p.map(|v| v.div_euclid(side));
    let mut cubes: HashMap<[i64; 3], Vec<[i64; 3]>> = HashMap::new();
    for q in b {
        cubes.entry(cube_of(q)).or_default().push(*q);
    }
    for points in cubes.values_mut() {
        points.sort_unstable();
        points.dedup();
    }
    let mut a = a.to_vec();
    a.sort_unstable();
    a.dedup();
    let mut best = i64::MAX;
    for p in &a {
        let c = cube_of(p);
        for d in NEIGHBOURS {
            let Some(points) = cubes.get(&[c[0] + d[0], c[1] + d[1], c[2] + d[2]]) else { continue };
            for q in points {
                best = best.min((0..3).map(|c| (p[c] - q[c]).pow(2)).sum::<i64>());
            }
        }
    }
    let distance = (best as f64).sqrt();
    if best == i64::MAX || distance > cutoff {
        f64::INFINITY
    } else {
        distance
    }
}

/// A cube's offsets to itself and its 26 neighbours.
const NEIGHBOURS: [[i64; 3]; 27] = {
    let mut out = [[0; 3]; 27];
    let mut n = 0;
    while n < 27 {
        out[n] = [(n % 3) as i64 - 1, (n / 3 % 3) as i64 - 1, (n / 9) as i64 - 1];
        n += 1;
    }
    out
};

/// Component label per annotation for links `d <= tol`; labels numbered in order of each
/// component's smallest member, like scipy's `connected_components`.
fn components(distances: &[Vec<f64>], tol: f64) -> Vec<usize> {
    let n = distances.len();
    let mut labels = vec![usize::MAX; n];
    let mut next = 0;
    for start in 0..n {
        if labels[start] != usize::MAX {
            continue;
        }
        labels[start] = next;
        let mut stack = vec![start];
        while let Some(a) = stack.pop() {
            for b in 0..n {
                if labels[b] == usize::MAX && distances[a][b] <= tol {
                    labels[b] = next;
                    stack.push(b);
                }
            }
        }
        next += 1;
    }
    labels
}

/// Size of the largest component if it exceeds `max`.
fn oversized(labels: &[usize], max: usize) -> Option<usize> {
    let mut sizes = vec![0usize; labels.len()];
    for &l in labels {
        sizes[l] += 1;
    }
    sizes.into_iter().max().filter(|&s| s > max)
}

fn group_by_label(labels: &[usize]) -> Vec<Vec<usize>> {
    let count = labels.iter().map(|&l| l + 1).max().unwrap_or(0);
    let mut groups = vec![Vec::new(); count];
    for (a, &l) in labels.iter().enumerate() {
        groups[l].push(a);
    }
    groups
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernels::annotation::tests::square_annotation;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn clustering_links_by_index_distance_and_shrinks_tol() {
        // Five identical squares on slice 1 and one far away: five > 4 forces tol down until
        // the touching five split; identical contours are at distance 0 and never split, so
        // clustering must give up below min_tol.
        let near: Vec<Annotation> = (0..5).map(|_| square_annotation(&[1], 2, 2, 4)).collect();
        let err = cluster_annotations(&near, 2.5, &ClusterParams::default()).unwrap_err();
        assert!(matches!(err, GroundTruthError::ClusterTolerance { largest: 5, .. }));

        // Squares 2 apart in j (index units), one on another slice 1 away in k.
        let anns = vec![
            square_annotation(&[3], 2, 20, 4), // mean k 3
            square_annotation(&[1], 2, 2, 4),  // 0
            square_annotation(&[1], 2, 8, 4),  // 2 from #1 (j 6 → 8)
            square_annotation(&[2], 2, 2, 4),  // 1 from #1 (k)
        ];
        let c = cluster_annotations(&anns, 2.5, &ClusterParams::default()).unwrap();
        assert_eq!(c.clusters, vec![vec![1, 2, 3], vec![0]]);
        assert_eq!((c.tol_initial, c.tol_final), (2.5, 2.5));
        let tight = ClusterParams { tol: Some(1.5), ..ClusterParams::default() };
        let c = cluster_annotations(&anns, 2.5, &tight).unwrap();
        assert_eq!(c.clusters, vec![vec![2], vec![1, 3], vec![0]]);
    }

    /// The cube search finds scipy's minimum whenever it is within the cutoff, bit for bit,
    /// and says `+inf` exactly when it is not.
    #[test]
    fn cube_search_matches_all_pairs_within_the_cutoff() {
        let mut rng = ChaCha8Rng::seed_from_u64(0x0DDB_A11C_AFE5_EED5);
        let mut next = |n: u64| rng.gen_range(0..n) as i64;
        for _ in 0..600 {
            let spread = 1 + next(30) as u64;
            let (len_a, len_b) = (1 + next(25) as usize, 1 + next(25) as usize);
            let mut points = |n: usize| -> Vec<[i64; 3]> {
                (0..n).map(|_| [next(spread) - 5, next(spread), next(spread / 3 + 1)]).collect()
            };
            let (a, b) = (points(len_a), points(len_b));
            let cutoff = next(40) as f64 / 7.0;
            let mut best = i64::MAX;
            for p in &a {
                for q in &b {
                    best = best.min((0..3).map(|c| (p[c] - q[c]).pow(2)).sum::<i64>());
                }
            }
            let all_pairs = (best as f64).sqrt();
            let found = min_point_distance(&a, &b, cutoff);
            if all_pairs <= cutoff {
                assert_eq!(found.to_bits(), all_pairs.to_bits(), "{a:?} {b:?} {cutoff}");
            } else {
                assert_eq!(found, f64::INFINITY, "{a:?} {b:?} {cutoff}");
            }
        }
    }
}
