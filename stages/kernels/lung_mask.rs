//! The lung field found in a reconstruction itself (find first, then size), and
//! the strongest bright blob inside it. No annotation and no CT are used: only σ.
//!
//! The density box of the paper cuts through the chest, so the lungs touch its faces and
//! cannot be told from the air outside by "enclosed by the body". They are told apart by
//! level instead: after a 3 mm smoothing, tissue lies above Otsu's threshold `t` of the
//! non-air values, outside air near zero (below `AIR_FRACTION · t`: σ is a ReLU), and lung
//! parenchyma between. The large components of that middle band (after an opening that cuts
//! thin bridges) are the lungs; each is closed on its own and its holes are filled slice by
//! slice along x, y and z, so that the nodules inside it belong to the field.

use super::components::{label, Connectivity};
use super::filters::{fill_holes_per_slice, gaussian_mm, hessian_blob_response, otsu_threshold};
use super::morphology;
use rayon::prelude::*;

/// Smoothing before the levels are classified, mm.
const SMOOTHING_MM: f64 = 3.0;
/// Values below this fraction of the tissue threshold are outside air.
const AIR_FRACTION: f32 = 0.2;
/// Smoothed values at or below this are empty space (σ = 0 blurred), left out of Otsu's threshold.
const EMPTY: f32 = 0.01;
/// A lung component holds at least this fraction of the box.
const MIN_LUNG_FRACTION: f64 = 0.02;
/// Radius of the closing that takes in nodules bulging from a lung's wall, as a fraction of the
/// lattice's nodes per axis, so that it spans the same millimetres at any resolution: 3 nodes
/// at 64³, 6 at 128³ (11 × 6 × 7 mm in the paper's box). At 128³ three nodes left juxtapleural
/// nodules and the ends of the lung outside the field and cost the sizing (lab/log.md).
const CLOSING_FRACTION: f64 = 3.0 / 64.0;

/// The lungs of a reconstruction.
#[derive(Debug, Clone)]
pub struct LungField {
    /// The parenchyma band's large components.
    pub lungs: Vec<bool>,
    /// `lungs` closed and hole-filled: the field, nodules included.
    pub field: Vec<bool>,
    /// Otsu's threshold between parenchyma and tissue (smoothed σ).
    pub tissue_threshold: f32,
}

/// The lung field of `density` (x-fastest, `dims`, `spacing_mm`), or `None` when the density
/// has no two levels to separate.
pub fn lung_field(density: &[f32], dims: [usize; 3], spacing_mm: [f64; 3]) -> Option<LungField> {
    let smooth = gaussian_mm(density, dims, spacing_mm, SMOOTHING_MM);
    let occupied: Vec<f32> = smooth.iter().copied().filter(|&v| v > EMPTY).collect();
    let tissue_threshold = otsu_threshold(&occupied)?;
    let band: Vec<bool> =
        smooth.iter().map(|&v| v < tissue_threshold && v >= AIR_FRACTION * tissue_threshold).collect();
    let opened = morphology::dilate(&morphology::erode(&band, dims, 1), dims, 1);
    let components = label(&opened, dims, Connectivity::Six);
    let min_voxels = (MIN_LUNG_FRACTION * density.len() as f64).ceil() as usize;
    let closing_radius = ((CLOSING_FRACTION * dims.into_iter().max().unwrap_or(0) as f64).round() as usize).max(1);
    let mut lungs = vec![false; density.len()];
    let mut field = vec![false; density.len()];
    for l in (1..=components.count() as u32).filter(|&l| components.size(l) >= min_voxels) {
        let lung = components.mask_of(l);
        // One lung at a time: closing both at once would bridge the mediastinum.
        let closed = morphology::close(&lung, dims, closing_radius);
        for i in 0..density.len() {
            lungs[i] |= lung[i];
            field[i] |= closed[i];
        }
    }
    let filled: Vec<Vec<bool>> = (0..3).map(|axis| fill_holes_per_slice(&field, dims, axis)).collect();
    let field = (0..density.len()).map(|i| filled.iter().any(|f| f[i])).collect();
    Some(LungField { lungs, field, tissue_threshold })
}

/// A bright blob's centre.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct BlobPeak {
    /// Lattice index `[x, y, z]`.
    pub voxel: [usize; 3],
    /// The scale-normalised response there (max over the scales).
    pub response: f32,
    /// The scale (mm) that gave it.
    pub scale_mm: f64,
}

/// The voxels more than `inside_mm` inside `region` and inside the lattice, where a blob centre
/// may lie: edges of the region respond too, and a nodule is a blob surrounded by lung. The
/// lattice's faces count as edges: σ ends there (the views see only the box), so a filter
/// there sees half a neighbourhood, and the lungs the box cuts through touch them.
/// `depth_mm` is each node's distance inside the region ([`super::filters::distance_inside_mm`] of it).
pub fn blob_sites(depth_mm: &[f64], dims: [usize; 3], spacing_mm: [f64; 3], inside_mm: f64) -> Vec<bool> {
    // The distance to the nearest node outside the lattice along `axis`, as the EDT measures
    // the distance to the nearest unset node.
    let to_face = |axis: usize, i: usize| (i + 1).min(dims[axis] - i) as f64 * spacing_mm[axis];
    let far_from_faces = |i: usize| {
        let (x, y, z) = (i % dims[0], (i / dims[0]) % dims[1], i / (dims[0] * dims[1]));
        to_face(0, x).min(to_face(1, y)).min(to_face(2, z)) > inside_mm
    };
    depth_mm.iter().enumerate().map(|(i, &d)| d > inside_mm && far_from_faces(i)).collect()
}

/// Every blob the search could answer with, strongest first: the `sites` whose response
/// (the max over `scales_mm`, each node keeping its first strongest scale) is positive and at
/// least that of every neighbouring site (26-connected). The first is the strongest response
/// at any site; ties keep linear order. Empty when no site has a positive response.
pub fn ranked_blobs(
    density: &[f32],
    dims: [usize; 3],
    spacing_mm: [f64; 3],
    scales_mm: &[f64],
    sites: &[bool],
) -> Vec<BlobPeak> {
    let responses: Vec<Vec<f32>> =
        scales_mm.par_iter().map(|&scale_mm| hessian_blob_response(density, dims, spacing_mm, scale_mm)).collect();
    // The strongest response at each node, and the index of its first scale.
    let mut best: Vec<(f32, usize)> = vec![(f32::NEG_INFINITY, 0); density.len()];
    for (k, response) in responses.iter().enumerate() {
        for (b, &r) in best.iter_mut().zip(response) {
            if r > b.0 {
                *b = (r, k);
            }
        }
    }
    let [nx, ny, nz] = dims;
    let voxel = |i: usize| [i % nx, (i / nx) % ny, i / (nx * ny)];
    let is_peak = |i: usize| {
        let r = best[i].0;
        if !(sites[i] && r > 0.0) {
            return false;
        }
        let [x, y, z] = voxel(i);
        let range = |v: usize, n: usize| v.saturating_sub(1)..=(v + 1).min(n - 1);
        range(z, nz).all(|zz| {
            range(y, ny).all(|yy| {
                range(x, nx).all(|xx| {
                    let j = xx + nx * (yy + ny * zz);
                    !sites[j] || best[j].0 <= r
                })
            })
        })
    };
    let mut peaks: Vec<usize> = (0..density.len()).into_par_iter().filter(|&i| is_peak(i)).collect();
    // Stable: equal responses keep linear order.
    peaks.sort_by(|&a, &b| best[b].0.total_cmp(&best[a].0));
    peaks
        .into_iter()
        .map(|i| BlobPeak { voxel: voxel(i), response: best[i].0, scale_mm: scales_mm[best[i].1] })
        .collect()
}

/// `density − G(density, background_mm)`: each value above its local background.
pub fn local_contrast(density: &[f32], dims: [usize; 3], spacing_mm: [f64; 3], background_mm: f64) -> Vec<f32> {
    let background = gaussian_mm(density, dims, spacing_mm, background_mm);
    density.iter().zip(background).map(|(&v, b)| v - b).collect()
}
