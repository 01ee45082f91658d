//! `[train] model = "truth"`: no fit. Each lattice node's σ is the true CT's attenuation
//! averaged over the node's cell, in the units the fits use (`Î = exp(−s Σ σ δ)`). This is the
//! field a perfect fit would reach on that lattice, so the stages after `train` can be measured
//! with the reconstruction taken out of the question (lab/log.md, "A perfect field").
//! It reads the CT, which no method may: a ceiling, never a configuration to report as a result.

use crate::kernels::raymarch::VolumeField;
use crate::train::render::Lattice;
use glam::DVec3;
use rayon::prelude::*;

/// The fewest samples per cell and axis for the cell mean (midpoints of an even split): on
/// the shipped 128³ lattice, whose cells are 0.9–1.9 mm, finer than every CT of the cohort.
pub const MIN_SAMPLES_PER_AXIS: usize = 4;

/// σ at every node of `lattice` (index `x + N·(y + N·z)`): the mean of `ct` over the node's
/// cell times `sigma_per_value`, the σ of v = 1 (the views' attenuation scale over the
/// renderer's `s`). Outside the CT the value is air, 0. Each cell is sampled at least once per
/// `ct_voxel` (the CT's finest voxel side, scene units) along each axis, so that no voxel of
/// the CT falls between samples.
pub fn cell_means(ct: &VolumeField, ct_voxel: f64, lattice: &Lattice, sigma_per_value: f64) -> Vec<f32> {
    let n = lattice.n;
    let min = DVec3::from(lattice.aabb.min);
    let cell = (DVec3::from(lattice.aabb.max) - min) / n as f64;
    let k: [usize; 3] = std::array::from_fn(|a| ((cell[a] / ct_voxel).ceil() as usize).max(MIN_SAMPLES_PER_AXIS));
    let at = |i: usize, a: usize| (i as f64 + 0.5) / k[a] as f64 * cell[a];
    let offsets: Vec<DVec3> = (0..k[0] * k[1] * k[2])
        .map(|s| DVec3::new(at(s % k[0], 0), at(s / k[0] % k[1], 1), at(s / (k[0] * k[1]), 2)))
        .collect();
    (0..n * n * n)
        .into_par_iter()
        .map(|node| {
            let corner = min + DVec3::new((node % n) as f64, (node / n % n) as f64, (node / (n * n)) as f64) * cell;
            let sum: f64 = offsets.iter().map(|&o| ct.value_at(corner + o)).sum();
            (sum / offsets.len() as f64 * sigma_per_value) as f32
        })
        .collect()
}
