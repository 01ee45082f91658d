//! The projector's path for rays at any angle to the lattice: each ray on its own, grouped by
//! the axis it steps along. `A` reads a tile of rays plane by plane (a tile's reads of a plane
//! share cache lines); `Aᵀ` spreads each ray's bilinear weights over a slab of planes per task.

use super::{others, slab_planes, Line, SharedOut};
use rayon::prelude::*;

/// Rays a forward task reads plane by plane together.
const TILE: usize = 16;

/// Rays that step along one lattice axis.
#[derive(Debug, Clone)]
pub struct Group {
    /// The axis the rays step along: 0 (x), 1 (y) or 2 (z).
    pub axis: usize,
    pub lines: Vec<Line>,
}

impl Group {
    /// Node-index strides of the axis and of the two others (in axis order).
    pub fn strides(&self, n: usize) -> (usize, [usize; 2]) {
        let stride = |a: usize| n.pow(a as u32);
        let [u, v] = others(self.axis);
        (stride(self.axis), [stride(u), stride(v)])
    }

    /// The group's rays' depths through `sigma`, into `depths` (by row of `A`).
    pub fn project(&self, sigma: &[f32], n: usize, depths: &mut [f64]) {
        let (stride, others) = self.strides(n);
        let sums: Vec<[f64; TILE]> =
            self.lines.par_chunks(TILE).map(|tile| project_tile(tile, sigma, n, stride, others)).collect();
        for (tile, sums) in self.lines.chunks(TILE).zip(&sums) {
            for (line, sum) in tile.iter().zip(sums) {
                depths[line.row as usize] = *sum;
            }
        }
    }

    /// Adds the group's `Aᵀ r` to `out`.
    pub fn back_project(&self, r: &[f64], n: usize, out: &mut [f32]) {
        let (stride, others) = self.strides(n);
        let planes = slab_planes(stride) as u32;
        let out = SharedOut(out.as_mut_ptr());
        (0..(n as u32).div_ceil(planes)).into_par_iter().for_each(|slab| {
            let (lo, hi) = (slab * planes, ((slab + 1) * planes).min(n as u32));
            for line in &self.lines {
                let residual = r[line.row as usize] as f32;
                for k in line.first.max(lo)..line.end.min(hi) {
                    let (base, w) = line.corners(k, n, others);
                    let i = base + k as usize * stride;
                    for (offset, w) in [0, others[0], others[1], others[0] + others[1]].into_iter().zip(w) {
                        // SAFETY: node `i + offset` lies on plane `k` of this slab, which no
                        // other task writes, and inside `out` (`corners` keeps it there).
                        unsafe { *out.at(i + offset) += residual * w };
                    }
                }
            }
        });
    }
}

/// The depths of a tile of lines (in order), read plane by plane.
fn project_tile(tile: &[Line], sigma: &[f32], n: usize, stride: usize, others: [usize; 2]) -> [f64; TILE] {
    let mut sums = [0.0f64; TILE];
    let first = tile.iter().map(|l| l.first).min().unwrap_or(0);
    let end = tile.iter().map(|l| l.end).max().unwrap_or(0);
    let corners = [0, others[0], others[1], others[0] + others[1]];
    for k in first..end {
        let plane = &sigma[k as usize * stride..];
        for (line, sum) in tile.iter().zip(&mut sums) {
            if k >= line.first && k < line.end {
                let (base, w) = line.corners(k, n, others);
                let value = corners.iter().zip(w).map(|(&c, w)| w * plane[base + c]).sum::<f32>();
                *sum += f64::from(value);
            }
        }
    }
    sums
}
