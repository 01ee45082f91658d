//! `[train] model = "truth"`: no fit. Each lattice node's σ is the true CT's attenuation
//! averaged over the node's cell, in the units the fits use (`Î = exp(−s Σ σ δ)`). This is the
//! field a perfect fit would reach on that lattice, so the stages after `train` can be measured
//! with the reconstruction taken out of the question (docs/experiments.md, "A perfect field").
//! It reads the CT, which no method may: a ceiling, never a configuration to report as a result.

use crate::kernels::raymarch::VolumeField;
use crate::train::render::Lattice;
use glam::DVec3;
use rayon::prelude::*;

/// Samples per cell and axis for the cell mean (midpoints of a 4 × 4 × 4 split): finer than
/// the CT's voxels on the shipped 128³ lattice, whose cells are 0.9–1.9 mm.
pub const SAMPLES_PER_AXIS: usize = 4;

/// σ at every node of `lattice` (index `x + N·(y + N·z)`): the mean of `ct` over the node's
/// cell times `sigma_per_value`, the σ of v = 1 (the views' attenuation scale over the
/// renderer's `s`). Outside the CT the value is air, 0.
pub fn cell_means(ct: &VolumeField, lattice: &Lattice, sigma_per_value: f64) -> Vec<f32> {
    let n = lattice.n;
    let min = DVec3::from(lattice.aabb.min);
    let cell = (DVec3::from(lattice.aabb.max) - min) / n as f64;
    let k = SAMPLES_PER_AXIS;
    let offsets: Vec<DVec3> = (0..k * k * k)
        .map(|s| {
            let at = |i: usize| (i as f64 + 0.5) / k as f64;
            DVec3::new(at(s % k), at(s / k % k), at(s / (k * k))) * cell
        })
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
