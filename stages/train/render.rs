//! Rendering a ray batch through the composed field, its photometric loss, and the scatter of
//! `dL/dF` back onto the lattice (SPEC §3 train, Rendering and Loss).
//!
//! Samples lie at `t0 + offset + k·step` inside the box (`offset` ∈ [0, step): one random
//! offset per ray while training — TensoRF's `sample_ray` — and `step/2` when evaluating),
//! each weighing `δ = step`. `σ = ReLU(F + Δ)` with `F` trilinear between nodes and clamped
//! beyond the outermost ones, and `Î = exp(−s · Σ σ_k δ)`, the DRR's Beer–Lambert model. An
//! alpha mask, when given, silences samples none of whose 8 neighbour nodes is kept.

use super::gemm::Scalar;
use crate::geometry::Aabb;
use crate::kernels::trilinear;
use glam::DVec3;
use num_traits::Float;
use rayon::prelude::*;

/// The node lattice: N nodes per axis at the cell centres of the box.
#[derive(Debug, Clone, Copy)]
pub struct Lattice {
    pub n: usize,
    pub aabb: Aabb,
}

impl Lattice {
    /// Continuous node index of the ray point `origin + t·dir` is `a + t·b` (before clamping).
    fn index_line(&self, origin: DVec3, dir: DVec3) -> ([f64; 3], [f64; 3]) {
        let cell: [f64; 3] = std::array::from_fn(|k| (self.aabb.max[k] - self.aabb.min[k]) / self.n as f64);
        (
            std::array::from_fn(|k| (origin[k] - self.aabb.min[k]) / cell[k] - 0.5),
            std::array::from_fn(|k| dir[k] / cell[k]),
        )
    }
}

/// A training ray: origin, unit direction, and the measured pixel `I/I0`.
#[derive(Debug, Clone, Copy)]
pub struct Ray {
    pub origin: DVec3,
    pub dir: DVec3,
    pub target: f64,
}

/// Rendering constants: `Δ` (`shift`), `s` (`scale`) and the sample spacing.
#[derive(Debug, Clone, Copy)]
pub struct Renderer {
    pub lattice: Lattice,
    pub shift: f64,
    pub scale: f64,
    pub step: f64,
}

/// A batch's predictions and its mean squared error.
pub struct BatchResult<T> {
    pub predicted: Vec<T>,
    pub mse: f64,
}

/// The alpha mask: kept lattice nodes, and the cells with at least one kept corner (the
/// samples that still contribute).
#[derive(Debug, Clone, PartialEq)]
pub struct AlphaMask {
    pub nodes: Vec<bool>,
    cells: Vec<bool>,
}

impl AlphaMask {
    /// The mask of the kept `nodes` on an `n³` lattice.
    pub fn from_nodes(nodes: Vec<bool>, n: usize) -> AlphaMask {
        let dims = [n; 3];
        let mut cells = vec![false; nodes.len()];
        for z in 0..n.saturating_sub(1) {
            for y in 0..n - 1 {
                for x in 0..n - 1 {
                    let origin = x + n * (y + n * z);
                    cells[origin] = trilinear::corners(origin, [0.0; 3], dims).iter().any(|&(i, _)| nodes[i]);
                }
            }
        }
        AlphaMask { nodes, cells }
    }
}

/// A sample with a positive activation (its gradient is non-zero): its cell's lower corner
/// and its ray within the tracing task, packed in 32 bits (16 bytes a sample in f32), and its
/// position in the cell.
#[derive(Debug, Clone, Copy, Default)]
struct Active<T> {
    cell_and_ray: u32,
    frac: [T; 3],
}

/// Bits of `Active::cell_and_ray` for the cell: lattices up to 512³ nodes.
const CELL_BITS: u32 = 27;
/// The largest lattice `batch` takes.
pub const MAX_GRID: usize = 512;

impl<T> Active<T> {
    fn cell(&self) -> usize {
        (self.cell_and_ray & ((1 << CELL_BITS) - 1)) as usize
    }

    fn ray_in_task(&self) -> usize {
        (self.cell_and_ray >> CELL_BITS) as usize
    }
}

/// Rays per tracing task (at most 2^(32 − CELL_BITS)); fixed, so the work split never
/// depends on the thread count.
const RAYS_PER_TASK: usize = 32;
/// Lattice z-planes per scatter task.
const PLANES_PER_SLAB: usize = 4;

/// One task's traced rays: predictions, and its active samples by the z-plane of their cell
/// (`by_plane[z]`, in ray order within a plane).
struct Traced<T> {
    predicted: Vec<f64>,
    by_plane: Vec<Vec<Active<T>>>,
}

impl Renderer {
    /// The continuous lattice index of the first sample of `ray` (offset `offset` ∈ [0, step)),
    /// its increment per sample, and the number of samples inside the box. (The GPU backend
    /// uploads these per ray, so both backends walk the same samples.)
    pub fn samples(&self, ray: &Ray, offset: f64) -> ([f64; 3], [f64; 3], usize) {
        let Some((t0, t1)) = self.lattice.aabb.intersect(ray.origin, ray.dir) else {
            return ([0.0; 3], [0.0; 3], 0);
        };
        let (a, b) = self.lattice.index_line(ray.origin, ray.dir);
        let first = t0 + offset;
        // Samples at first + k·step for every k ≥ 0 with first + k·step < t1.
        let count = if first < t1 { ((t1 - first) / self.step).ceil() as usize } else { 0 };
        (std::array::from_fn(|k| a[k] + first * b[k]), std::array::from_fn(|k| self.step * b[k]), count)
    }

    /// `Î` of one ray; with `active`, also appends the samples whose σ is positive (their
    /// gradient is non-zero), tagged with the ray's index in its task.
    fn trace<T: Scalar>(
        &self,
        dense: &[T],
        mask: Option<&AlphaMask>,
        ray: &Ray,
        offset: f64,
        mut active: Option<(&mut [Vec<Active<T>>], u32)>,
    ) -> f64 {
        let (q0, dq, count) = self.samples(ray, offset);
        let (q0, dq) = (q0.map(|v| T::from(v).expect("finite")), dq.map(|v| T::from(v).expect("finite")));
        let n = self.lattice.n;
        let (sy, sz) = (n, n * n);
        let (last_node, last_cell) = (T::from(n - 1).expect("small"), n - 2);
        let shift = T::from(self.shift).expect("finite");
        let mut optical_depth = T::zero();
        let mut k = T::zero();
        for _ in 0..count {
            // The cell and position in it, clamped to the outermost nodes (kernels::trilinear's
            // rule, in T).
            let mut base = [0usize; 3];
            let mut frac = [T::zero(); 3];
            for a in 0..3 {
                let x = (q0[a] + k * dq[a]).max(T::zero()).min(last_node);
                base[a] = x.trunc_index().min(last_cell);
                frac[a] = x - T::from(base[a]).expect("small");
            }
            k = k + T::one();
            let cell = base[0] + n * (base[1] + n * base[2]);
            if mask.is_some_and(|m| !m.cells[cell]) {
                continue;
            }
            let [fx, fy, fz] = frac;
            let lerp = |a: T, b: T, t: T| a + (b - a) * t;
            let corners = &dense[cell..=cell + sz + sy + 1]; // one bounds check per sample
            let v = |i: usize| corners[i];
            let f = lerp(
                lerp(lerp(v(0), v(1), fx), lerp(v(sy), v(sy + 1), fx), fy),
                lerp(lerp(v(sz), v(sz + 1), fx), lerp(v(sz + sy), v(sz + sy + 1), fx), fy),
                fz,
            );
            let sigma = f + shift;
            optical_depth = optical_depth + sigma.max(T::zero());
            if let Some((by_plane, ray)) = active.as_mut() {
                // Pushed, then dropped unless active: no branch on the sign of σ, which would
                // mispredict on a field near zero.
                let list = &mut by_plane[base[2]];
                list.push(Active { cell_and_ray: cell as u32 | *ray << CELL_BITS, frac: [fx, fy, fz] });
                list.truncate(list.len() - usize::from(sigma <= T::zero()));
            }
        }
        (-self.scale * self.step * optical_depth.to_f64().expect("finite")).exp()
    }

    /// `Î` of one ray.
    pub fn render_ray<T: Scalar>(&self, dense: &[T], mask: Option<&AlphaMask>, ray: &Ray, offset: f64) -> f64 {
        self.trace(dense, mask, ray, offset, None)
    }

    /// Renders `rays` (with their per-ray `offsets`), returns predictions and MSE, and when
    /// `grad` is given adds `dMSE/dF` to it.
    ///
    /// Rays trace in parallel, in fixed groups that record their active samples bucketed by
    /// z-plane; the scatter then runs in parallel over z-slabs of the lattice, each adding the
    /// groups' samples in group, then plane, then ray order. Every gradient element is summed
    /// in one fixed order: the result is bit-identical whatever the thread count.
    pub fn batch<T: Scalar>(
        &self,
        dense: &[T],
        mask: Option<&AlphaMask>,
        rays: &[Ray],
        offsets: &[f64],
        grad: Option<&mut [T]>,
    ) -> BatchResult<T> {
        let want_grad = grad.is_some();
        let n = self.lattice.n;
        let traced: Vec<Traced<T>> = rays
            .par_chunks(RAYS_PER_TASK)
            .zip(offsets.par_chunks(RAYS_PER_TASK))
            .map(|(rays, offsets)| {
                let mut by_plane = vec![Vec::new(); if want_grad { n } else { 0 }];
                let predicted = rays
                    .iter()
                    .zip(offsets)
                    .enumerate()
                    .map(|(i, (ray, &off))| {
                        self.trace(dense, mask, ray, off, want_grad.then_some((by_plane.as_mut_slice(), i as u32)))
                    })
                    .collect();
                Traced { predicted, by_plane }
            })
            .collect();
        let predicted: Vec<f64> = traced.iter().flat_map(|t| t.predicted.iter().copied()).collect();
        let b = rays.len() as f64;
        let mse = rays.iter().zip(&predicted).map(|(r, p)| (p - r.target).powi(2)).sum::<f64>() / b;
        if let Some(grad) = grad {
            // dL/dÎ = 2(Î − I)/B;  dÎ/dσ_k = −s·δ·Î;  dσ/dF = 1[F + Δ > 0] (the active samples).
            let d_sigma: Vec<T> = rays
                .iter()
                .zip(&predicted)
                .map(|(ray, &p)| T::from(2.0 * (p - ray.target) / b * (-self.scale * self.step * p)).expect("finite"))
                .collect();
            self.scatter(&traced, &d_sigma, grad);
        }
        BatchResult { predicted: predicted.into_iter().map(|p| T::from(p).expect("finite")).collect(), mse }
    }

    /// Adds each active sample's `d_sigma` times its trilinear weights to its cell's corners.
    fn scatter<T: Scalar>(&self, traced: &[Traced<T>], d_sigma: &[T], grad: &mut [T]) {
        let n = self.lattice.n;
        let (sy, sz) = (n, n * n);
        grad.par_chunks_mut(sz * PLANES_PER_SLAB).enumerate().for_each(|(slab, out)| {
            let (z0, z1) = (slab * PLANES_PER_SLAB, ((slab + 1) * PLANES_PER_SLAB).min(n));
            let base = z0 * sz;
            for (t, d_sigma) in traced.iter().zip(d_sigma.chunks(RAYS_PER_TASK)) {
                // Cells on plane z0 − 1 reach into this slab with their upper corners.
                for a in t.by_plane[z0.saturating_sub(1)..z1].iter().flatten() {
                    let g = d_sigma[a.ray_in_task()];
                    if g == T::zero() {
                        continue;
                    }
                    let cell = a.cell();
                    let cz = cell / sz;
                    let [fx, fy, fz] = a.frac;
                    let (gx, gy) = (T::one() - fx, T::one() - fy);
                    let face = [gx * gy, fx * gy, gx * fy, fx * fy];
                    let offsets = [0, 1, sy, sy + 1];
                    let mut splat = |plane_origin: usize, w: T| {
                        let face_nodes = &mut out[plane_origin - base..=plane_origin - base + sy + 1];
                        for (o, f) in offsets.iter().zip(face) {
                            face_nodes[*o] = face_nodes[*o] + w * f;
                        }
                    };
                    if cz >= z0 {
                        splat(cell, g * (T::one() - fz));
                    }
                    if cz + 1 < z1 {
                        splat(cell + sz, g * fz);
                    }
                }
            }
        });
    }

    /// σ at every lattice node as the renderer samples it there (`ReLU(F + Δ)`, zero where the
    /// alpha mask silences the node's cell), index `x + N·(y + N·z)`: the grid stage's density.
    pub fn node_density<T: Scalar>(&self, dense: &[T], mask: Option<&AlphaMask>) -> Vec<f32> {
        let n = self.lattice.n;
        let last_cell = |c: usize| c.min(n - 2);
        (0..n * n * n)
            .map(|i| {
                let (x, y, z) = (i % n, (i / n) % n, i / (n * n));
                let cell = last_cell(x) + n * (last_cell(y) + n * last_cell(z));
                if mask.is_some_and(|m| !m.cells[cell]) {
                    return 0.0;
                }
                (dense[i].to_f64().expect("finite") + self.shift).max(0.0) as f32
            })
            .collect()
    }

    /// The alpha mask on the lattice: `alpha = 1 − exp(−σ·step·s)` at each node, dilated by a
    /// 3×3×3 max, kept where above `threshold`.
    pub fn alpha_mask<T: Float>(&self, dense: &[T], threshold: f64) -> AlphaMask {
        let n = self.lattice.n;
        let alpha: Vec<f64> = dense
            .iter()
            .map(|&f| 1.0 - (-(f.to_f64().expect("finite") + self.shift).max(0.0) * self.step * self.scale).exp())
            .collect();
        let mut keep = vec![false; alpha.len()];
        for z in 0..n {
            for y in 0..n {
                for x in 0..n {
                    let range = |c: usize| c.saturating_sub(1)..=(c + 1).min(n - 1);
                    let max = range(z)
                        .flat_map(|zz| range(y).flat_map(move |yy| range(x).map(move |xx| xx + n * (yy + n * zz))))
                        .map(|i| alpha[i])
                        .fold(0.0, f64::max);
                    keep[x + n * (y + n * z)] = max > threshold;
                }
            }
        }
        AlphaMask::from_nodes(keep, n)
    }
}
