//! Rendering a ray batch through the composed field, its photometric loss, and the scatter of
//! `dL/dF` back onto the lattice (SPEC §3 train, Rendering and Loss).
//!
//! Samples lie at `t0 + offset + k·step` inside the box (`offset` ∈ [0, step): one random
//! offset per ray while training — TensoRF's `sample_ray` — and `step/2` when evaluating),
//! each weighing `δ = step`. `σ = ReLU(F + Δ)` with `F` trilinear between nodes and clamped
//! beyond the outermost ones, and `Î = exp(−s · Σ σ_k δ)`, the DRR's Beer–Lambert model. An
//! alpha mask, when given, silences samples none of whose 8 neighbour nodes is kept.

use super::gemm::{give_spare, take_spare, Scalar};
use super::huge_pages::HugePageBuffer;
use crate::geometry::Aabb;
use crate::kernels::trilinear;
use glam::DVec3;
use num_traits::Float;
use rayon::prelude::*;
use walk::RayWalk;

mod walk;

/// The node lattice: N nodes per axis at the cell centres of the box.
#[derive(Debug, Clone, Copy)]
pub struct Lattice {
    pub n: usize,
    pub aabb: Aabb,
}

impl Lattice {
    /// Continuous node index of the ray point `origin + t·dir` is `a + t·b` (before clamping).
    pub(crate) fn index_line(&self, origin: DVec3, dir: DVec3) -> ([f64; 3], [f64; 3]) {
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

/// Rendering constants: `Δ` (`shift`), `s` (`scale`), the sample spacing, and what the
/// photometric loss compares.
#[derive(Debug, Clone, Copy)]
pub struct Renderer {
    pub lattice: Lattice,
    pub shift: f64,
    pub scale: f64,
    pub step: f64,
    pub loss: PhotoLoss,
}

/// What the photometric loss compares, per ray, as a squared error averaged over the batch.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PhotoLoss {
    /// The intensities `Î` and `I` (SPEC §3: MSE of the rendered against the DRR pixels).
    #[default]
    Intensity,
    /// The optical depths `−ln Î` and `−ln I` (line integrals, as NAF fits them): every path
    /// weighs alike, where intensities weigh the bright, thin ones most.
    Log,
}

/// The smallest measured intensity whose logarithm the log loss takes (a fully blocked ray).
pub const MIN_INTENSITY: f64 = 1e-6;

impl PhotoLoss {
    /// One ray's squared error, predicted `p` against measured `target`.
    pub fn error(self, p: f64, target: f64) -> f64 {
        match self {
            PhotoLoss::Intensity => (p - target).powi(2),
            PhotoLoss::Log => (target.max(MIN_INTENSITY).ln() - p.ln()).powi(2),
        }
    }

    /// `dL/dσ_k` of a ray's active sample, `L` the mean error over a batch of `batch_len` and
    /// `depth_scale` = s·δ (so `dτ̂/dσ_k = depth_scale`, with `τ̂ = −ln p`).
    fn d_sigma(self, p: f64, target: f64, batch_len: usize, depth_scale: f64) -> f64 {
        let b = batch_len as f64;
        match self {
            // dL/dÎ = 2(Î − I)/B;  dÎ/dσ_k = −s·δ·Î.
            PhotoLoss::Intensity => 2.0 * (p - target) / b * (-depth_scale * p),
            // dL/dτ̂ = 2(τ̂ − τ)/B.
            PhotoLoss::Log => 2.0 * (target.max(MIN_INTENSITY).ln() - p.ln()) / b * depth_scale,
        }
    }
}

/// A batch's predictions, their intensity MSE (for PSNR), and the loss the renderer trains on
/// (equal to `mse` for [`PhotoLoss::Intensity`]).
pub struct BatchResult<T> {
    pub predicted: Vec<T>,
    pub mse: f64,
    pub loss: f64,
}

/// The alpha mask: kept lattice nodes, and the cells with at least one kept corner (the
/// samples that still contribute).
#[derive(Debug, Clone, PartialEq)]
pub struct AlphaMask {
    pub nodes: Vec<bool>,
    /// Per cell, all ones (a vector lane mask) when a corner is kept, else zero.
    cells: Vec<u32>,
}

impl AlphaMask {
    /// The mask of the kept `nodes` on an `n³` lattice.
    pub fn from_nodes(nodes: Vec<bool>, n: usize) -> AlphaMask {
        let dims = [n; 3];
        let mut cells = vec![0; nodes.len()];
        for z in 0..n.saturating_sub(1) {
            for y in 0..n - 1 {
                for x in 0..n - 1 {
                    let origin = x + n * (y + n * z);
                    let kept = trilinear::corners(origin, [0.0; 3], dims).iter().any(|&(i, _)| nodes[i]);
                    cells[origin] = if kept { u32::MAX } else { 0 };
                }
            }
        }
        AlphaMask { nodes, cells }
    }
}

/// The largest lattice `batch` takes (cell indices are packed in 32 bits).
pub const MAX_GRID: usize = 512;

/// Rays' gradient footprints, one record per cell a ray's active samples passed through: the
/// cell's lower corner node `x + N·(y + N·z)` and the 8 corner weights of those samples,
/// summed (consecutive samples of a ray often share a cell). The weights are unscaled; the
/// scatter multiplies them by the ray's `dL/dσ`. Two columns: finding a ray's run on a slab
/// reads the cells alone, and each record's weights fill one aligned half cache line.
///
/// A batch's records share one arena on huge pages, each tracing task writing its rays' in its
/// own region: in per-task buffers of 4 KiB pages the scatter, which reads runs of every
/// task, met a new page at nearly every run.
#[derive(Default)]
struct Records<T: Copy> {
    cells: HugePageBuffer<u32>,
    weights: HugePageBuffer<CornerWeights<T>>,
}

impl<T: Scalar> Records<T> {
    /// Room for at least `len` records; what the records held is not kept.
    fn make_room(&mut self, len: usize) {
        if self.cells.len() < len {
            *self = Records {
                cells: HugePageBuffer::filled(len, u32::MAX),
                weights: HugePageBuffer::filled(len, CornerWeights([T::zero(); 8])),
            };
        }
    }

    /// The records cut into regions of `len`, in order.
    fn regions(&mut self, len: usize) -> impl Iterator<Item = RecordsMut<'_, T>> {
        let weights = self.weights.chunks_mut(len);
        self.cells.chunks_mut(len).zip(weights).map(|(cells, weights)| RecordsMut { cells, weights })
    }
}

/// Records to write: a region of [`Records`], or what is left of it.
struct RecordsMut<'a, T> {
    cells: &'a mut [u32],
    weights: &'a mut [CornerWeights<T>],
}

impl<T> RecordsMut<'_, T> {
    /// The records from `first` on.
    fn from(&mut self, first: usize) -> RecordsMut<'_, T> {
        RecordsMut { cells: &mut self.cells[first..], weights: &mut self.weights[first..] }
    }
}

/// A record's trilinear weights, corners in the order x fastest, then y, then z (the first
/// four on the cell's lower plane, the last four on its upper one).
#[derive(Debug, Clone, Copy)]
#[repr(C, align(32))]
struct CornerWeights<T>([T; 8]);

impl<T: Scalar> CornerWeights<T> {
    /// `weights` as f32 weights, when that is their type: the way into f32-only vector
    /// kernels.
    #[cfg(target_arch = "x86_64")]
    fn as_f32_mut(weights: &mut [Self]) -> Option<&mut [CornerWeights<f32>]> {
        (std::any::TypeId::of::<T>() == std::any::TypeId::of::<f32>()).then(|| {
            // SAFETY: `T` is f32 (checked), so the two slice types are one.
            unsafe { &mut *(weights as *mut [Self] as *mut [CornerWeights<f32>]) }
        })
    }
}

/// Rays per tracing task; fixed, so the work split never depends on the thread count.
const RAYS_PER_TASK: usize = 32;
/// Lattice z-planes per scatter task. A slab also reads the records on the plane below it
/// (their upper faces), so thinner slabs read more records twice: at 64³, 2 planes a slab took
/// 4.5 % more per iteration than 4, 8 took ≈ 1 % less than 4, 16 ≈ 1.3 % less than 8, and 32
/// (two tasks for two threads) ≈ 1 % more than 16.
const PLANES_PER_SLAB: usize = 16;

/// One task's traced rays: predictions and footprints.
#[derive(Default)]
struct Traced<T> {
    predicted: Vec<f64>,
    footprints: Footprints<T>,
}

/// What a recording batch keeps for the next: its records and each task's traced rays (one
/// spare, rather than one a task: handing 64 back and forth cost a lock and a box each).
#[derive(Default)]
struct BatchBuffers<T: Copy> {
    records: Records<T>,
    traced: Vec<Traced<T>>,
}

/// One task's rays' footprints, ray after ray, each ray's in the walk's order (a straight
/// ray's planes are monotone), and for each scatter slab where each ray's run on the slab's
/// planes lies. The walk writes a ray's records straight into the task's region of the
/// batch's [`Records`], past the `used` ones (no copy).
#[derive(Default)]
struct Footprints<T> {
    /// Where the task's region starts in the batch's records.
    start: usize,
    used: usize,
    /// Per scatter slab, each ray's run of footprints on the slab's planes, in ray order.
    slab_runs: Vec<Vec<Run<T>>>,
}

/// A ray's footprints `from..to` (positions in the batch's records) on one scatter slab's
/// planes, read `backwards` when the ray's planes descend (so that they are added in
/// ascending plane order), and the ray's `dL/dσ` that scales their weights.
#[derive(Debug, Clone, Copy)]
struct Run<T> {
    from: u32,
    to: u32,
    backwards: bool,
    d_sigma: T,
}

impl<T: Scalar> Footprints<T> {
    /// No footprints yet, in a region from `start` of the batch's records.
    fn clear(&mut self, start: usize) {
        (self.start, self.used) = (start, 0);
        self.slab_runs.iter_mut().for_each(Vec::clear);
    }

    /// Keeps the `len` records the walk wrote after the used ones of the task's region
    /// `region_cells` (monotone in plane, either way) for a ray whose `dL/dσ` is `d_sigma`,
    /// and notes their run on each scatter slab of a lattice with `plane_nodes` nodes a plane.
    /// A ray whose planes descend keeps its records in walk order, and the scatter reads its
    /// runs backwards (reversing them here cost ≈ 1.5 % of an iteration).
    fn keep_ray(&mut self, region_cells: &[u32], len: usize, d_sigma: T, plane_nodes: usize) {
        let first = self.used;
        self.used = first + len;
        let cells = &region_cells[first..first + len];
        let (Some(&head), Some(&tail)) = (cells.first(), cells.last()) else { return };
        let (head, tail) = (head as usize / plane_nodes, tail as usize / plane_nodes);
        let descending = head > tail;
        let (low, high) = (head.min(tail), head.max(tail));
        // Slab s reads planes sP − 1 ..= (s + 1)P − 1 (P planes a slab): plane p lies on slab
        // p / P, and on the next one too when it is a slab's last.
        let (first_slab, last_slab) = (low / PLANES_PER_SLAB, (high + 1) / PLANES_PER_SLAB);
        if self.slab_runs.len() <= last_slab {
            self.slab_runs.resize_with(last_slab + 1, Vec::new);
        }
        // In ascending plane order, slab s's run is the records from the first on plane
        // sP − 1 or above to the last below (s + 1)P: counted, [below(sP − 1), below((s + 1)P)),
        // a record lying below plane p when its cell is below p's first node.
        let (first, end) = (self.start + first, (self.start + first + len) as u32);
        for chunk in (first_slab..=last_slab).step_by(LIMIT_SLABS) {
            let slabs = chunk..(chunk + LIMIT_SLABS).min(last_slab + 1);
            let mut limits = [0u32; 2 * LIMIT_SLABS];
            for (i, slab) in slabs.clone().enumerate() {
                limits[2 * i] = ((slab * PLANES_PER_SLAB).saturating_sub(1) * plane_nodes) as u32;
                limits[2 * i + 1] = ((slab + 1) * PLANES_PER_SLAB * plane_nodes) as u32;
            }
            let below = count_below(cells, limits);
            for (i, slab) in slabs.enumerate() {
                let (a, b) = (below[2 * i], below[2 * i + 1]);
                // As positions in `records`: counted from the ray's end when it is stored
                // backwards.
                let (from, to) = if descending { (end - b, end - a) } else { (first as u32 + a, first as u32 + b) };
                if from != to {
                    self.slab_runs[slab].push(Run { from, to, backwards: descending, d_sigma });
                }
            }
        }
    }

    /// The runs of footprints on scatter slab `slab`, ray by ray: cells and weights (in the
    /// batch's `records`), whether to read them backwards, and the ray's `dL/dσ`.
    fn on_slab<'a>(&'a self, slab: usize, records: &'a Records<T>) -> impl Iterator<Item = RunView<'a, T>> {
        self.slab_runs.get(slab).into_iter().flatten().map(|r| {
            let range = r.from as usize..r.to as usize;
            RunView {
                cells: &records.cells[range.clone()],
                weights: &records.weights[range],
                backwards: r.backwards,
                d_sigma: r.d_sigma,
            }
        })
    }
}

/// A [`Run`]'s records.
#[derive(Clone, Copy)]
struct RunView<'a, T> {
    cells: &'a [u32],
    weights: &'a [CornerWeights<T>],
    backwards: bool,
    d_sigma: T,
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

    /// At least as many samples as any of `rays` has: a line's chord through the box is at most
    /// the box's diagonal, which a ray with direction `d` crosses in `diagonal / |d|` of its
    /// parameter.
    fn max_samples(&self, rays: &[Ray]) -> usize {
        let Some(shortest) = rays.iter().map(|r| r.dir.length_squared()).reduce(f64::min) else { return 0 };
        assert!(shortest > 0.0, "batch: a ray without a direction");
        let (min, max) = (self.lattice.aabb.min, self.lattice.aabb.max);
        let diagonal = (0..3).map(|a| (max[a] - min[a]).powi(2)).sum::<f64>().sqrt();
        (diagonal / (shortest.sqrt() * self.step)).ceil() as usize + 1
    }

    /// The walk of `ray`'s samples (offset `offset` ∈ [0, step)) through `dense`.
    fn walk<'a, T: Scalar>(
        &self,
        dense: &'a [T],
        mask: Option<&'a AlphaMask>,
        ray: &Ray,
        offset: f64,
    ) -> RayWalk<'a, T> {
        let (q0, dq, count) = self.samples(ray, offset);
        let value = |v: f64| T::from(v).expect("finite");
        RayWalk {
            dense,
            kept: mask.map(|m| m.cells.as_slice()),
            q0: q0.map(value),
            dq: dq.map(value),
            count,
            n: self.lattice.n,
            shift: value(self.shift),
        }
    }

    /// `Î = exp(−s·δ·Σ σ)` from the optical depth.
    fn transmittance<T: Scalar>(&self, optical_depth: T) -> f64 {
        (-self.scale * self.step * optical_depth.to_f64().expect("finite")).exp()
    }

    /// `Î` of one ray.
    pub fn render_ray<T: Scalar>(&self, dense: &[T], mask: Option<&AlphaMask>, ray: &Ray, offset: f64) -> f64 {
        let no_records = RecordsMut { cells: &mut [], weights: &mut [] };
        self.transmittance(walk::march::<T, false>(&self.walk(dense, mask, ray, offset), no_records).0)
    }

    /// Renders `rays` (with their per-ray `offsets`), returns predictions and MSE, and when
    /// `grad` is given writes `dL/dF` into it (overwriting it).
    ///
    /// Rays trace in parallel, in fixed groups that record their footprints (already scaled by
    /// the ray's `dL/dσ`) and note each ray's run of them on each z-slab of the lattice; the
    /// scatter then runs in parallel over those slabs, each adding the footprints on its planes
    /// in group, then ray, then plane order. Every gradient element is summed in one fixed
    /// order: the result is bit-identical whatever the thread count.
    pub fn batch<T: Scalar>(
        &self,
        dense: &[T],
        mask: Option<&AlphaMask>,
        rays: &[Ray],
        offsets: &[f64],
        grad: Option<&mut [T]>,
    ) -> BatchResult<T> {
        let groups = rays.par_chunks(RAYS_PER_TASK).zip(offsets.par_chunks(RAYS_PER_TASK));
        let mut buffers: BatchBuffers<T> = if grad.is_some() { take_spare() } else { BatchBuffers::default() };
        let BatchBuffers { records, traced } = &mut buffers;
        if grad.is_some() {
            // Each task's region holds every sample of its rays.
            let region = RAYS_PER_TASK * self.max_samples(rays);
            let tasks = rays.len().div_ceil(RAYS_PER_TASK);
            assert!(tasks * region <= u32::MAX as usize, "batch: footprints beyond 32-bit positions");
            records.make_room(tasks * region);
            traced.resize_with(tasks, Traced::default);
            let regions = records.regions(region).collect::<Vec<_>>();
            traced.par_iter_mut().zip(groups).zip(regions).enumerate().for_each(|(i, ((t, group), records))| {
                self.trace_recording(t, dense, mask, group, rays.len(), (records, i * region))
            });
        } else {
            let render = |(group, offsets): (&[Ray], &[f64])| {
                let predicted =
                    group.iter().zip(offsets).map(|(ray, &off)| self.render_ray(dense, mask, ray, off)).collect();
                Traced { predicted, ..Traced::default() }
            };
            *traced = groups.map(render).collect();
        }
        let predicted: Vec<f64> = traced.iter().flat_map(|t| t.predicted.iter().copied()).collect();
        let b = rays.len() as f64;
        let mse = rays.iter().zip(&predicted).map(|(r, p)| (p - r.target).powi(2)).sum::<f64>() / b;
        let loss = match self.loss {
            PhotoLoss::Intensity => mse,
            kind => rays.iter().zip(&predicted).map(|(r, &p)| kind.error(p, r.target)).sum::<f64>() / b,
        };
        if let Some(grad) = grad {
            self.scatter(traced, records, grad);
            give_spare(buffers);
        }
        BatchResult { predicted: predicted.into_iter().map(|p| T::from(p).expect("finite")).collect(), mse, loss }
    }

    /// Traces one group of rays (with their offsets) of a batch of `batch_len` into `t`,
    /// recording each ray's footprints into `records`, the group's region of the batch's
    /// records, which starts at `start` of them and has room for every sample.
    fn trace_recording<T: Scalar>(
        &self,
        t: &mut Traced<T>,
        dense: &[T],
        mask: Option<&AlphaMask>,
        (group, offsets): (&[Ray], &[f64]),
        batch_len: usize,
        (mut records, start): (RecordsMut<T>, usize),
    ) {
        assert!(group.len() <= RAYS_PER_TASK, "trace: at most {RAYS_PER_TASK} rays a task");
        let walks: [Option<RayWalk<T>>; RAYS_PER_TASK] =
            std::array::from_fn(|i| Some(self.walk(dense, mask, group.get(i)?, offsets[i])));
        t.footprints.clear(start);
        t.predicted.clear();
        for (ray, walk) in group.iter().zip(walks.iter().flatten()) {
            let (depth, len) = walk::march::<T, true>(walk, records.from(t.footprints.used));
            let p = self.transmittance(depth);
            // dσ/dF = 1[F + Δ > 0]: the ray's active samples share its dL/dσ.
            let d_sigma = self.loss.d_sigma(p, ray.target, batch_len, self.scale * self.step);
            let d_sigma = T::from(d_sigma).expect("finite");
            if d_sigma != T::zero() {
                t.footprints.keep_ray(records.cells, len, d_sigma, self.lattice.n * self.lattice.n);
            }
            t.predicted.push(p);
        }
    }

    /// Writes the gradient: every footprint, scaled by its ray's `dL/dσ`, added to the
    /// corners of its cell, each slab of `grad` zeroed first (in the same pass, while it is in
    /// cache).
    fn scatter<T: Scalar>(&self, traced: &[Traced<T>], records: &Records<T>, grad: &mut [T]) {
        let n = self.lattice.n;
        let (sy, sz) = (n, n * n);
        grad.par_chunks_mut(sz * PLANES_PER_SLAB).enumerate().for_each(move |(slab, out)| {
            let (z0, z1) = (slab * PLANES_PER_SLAB, ((slab + 1) * PLANES_PER_SLAB).min(n));
            // Node i is out[i − split]; cells on plane z0 − 1 reach into this slab with their
            // upper corners, and cells on plane z1 − 1 into the next one.
            let (split, upper_end) = (z0 * sz, (z1 - 1) * sz);
            out.fill(T::zero());
            // Each ray's run of footprints on these planes, in ray order: short runs far apart
            // in memory, so the runs a few rays ahead are prefetched.
            let runs: Vec<RunView<T>> = traced.iter().flat_map(|t| t.footprints.on_slab(slab, records)).collect();
            let add = |out: &mut [T], cell: u32, weights: &CornerWeights<T>, d_sigma: T| {
                let cell = cell as usize;
                let [l0, l1, l2, l3, u0, u1, u2, u3] = weights.0.map(|w| w * d_sigma);
                // The record's faces on this slab's planes; their last node (the face's
                // origin + sy + 1) must lie in `out`, checked once per face.
                if cell >= split {
                    add_face(out, cell - split, sy, [l0, l1, l2, l3]);
                }
                if cell < upper_end {
                    add_face(out, cell + sz - split, sy, [u0, u1, u2, u3]);
                }
            };
            for (i, run) in runs.iter().enumerate() {
                if let Some(ahead) = runs.get(i + PREFETCH_AHEAD) {
                    prefetch(ahead.cells, ahead.backwards);
                    prefetch(ahead.weights, ahead.backwards);
                }
                let records = run.cells.iter().zip(run.weights);
                if run.backwards {
                    records.rev().for_each(|(&cell, weights)| add(out, cell, weights, run.d_sigma));
                } else {
                    records.for_each(|(&cell, weights)| add(out, cell, weights, run.d_sigma));
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
                if mask.is_some_and(|m| m.cells[cell] == 0) {
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

/// Slabs whose runs one pass of [`count_below`] finds (two limits each: eight lanes).
const LIMIT_SLABS: usize = 4;

/// How many of `cells` are below each of `limits` (branch-free, one vector compare a cell).
#[inline(always)]
fn count_below(cells: &[u32], limits: [u32; 2 * LIMIT_SLABS]) -> [u32; 2 * LIMIT_SLABS] {
    let mut below = [0u32; 2 * LIMIT_SLABS];
    for &cell in cells {
        for (count, &limit) in below.iter_mut().zip(&limits) {
            *count += u32::from(cell < limit);
        }
    }
    below
}

/// Adds the weights `w` of a cell face's 4 corners (x fastest, then y) to `out`, the face's
/// first corner at `origin`: two pairs of x-neighbours, `sy` apart.
///
/// # Panics
/// If the face's last node, `origin + sy + 1`, is outside `out`.
#[inline(always)]
fn add_face<T: Scalar>(out: &mut [T], origin: usize, sy: usize, w: [T; 4]) {
    assert!(origin + sy + 1 < out.len(), "scatter: a footprint's face lies outside its slab");
    // SAFETY: the four nodes origin, origin + 1, origin + sy, origin + sy + 1 are at most
    // origin + sy + 1, inside `out` (checked above).
    unsafe {
        let face = out.as_mut_ptr().add(origin);
        for (node, w) in [(0, w[0]), (1, w[1]), (sy, w[2]), (sy + 1, w[3])] {
            *face.add(node) = *face.add(node) + w;
        }
    }
}

/// Rays ahead whose footprints the scatter asks the cache for (4 measured the same).
const PREFETCH_AHEAD: usize = 8;
/// How much of each column of a ray's run is prefetched: 2 KB (64 records' weights, about a
/// whole run) took ≈ 1.5 % less per iteration than 256 bytes.
const PREFETCH_BYTES: usize = 2048;

/// Asks for the cache lines of `records` (a column of a ray's run on a slab's planes, read
/// `backwards` or not), up to [`PREFETCH_BYTES`] from the end read first: the hardware
/// prefetcher cannot guess the jumps from one ray's run to the next.
#[inline(always)]
fn prefetch<T>(records: &[T], backwards: bool) {
    #[cfg(target_arch = "x86_64")]
    {
        let size = std::mem::size_of_val(records);
        let bytes = size.min(PREFETCH_BYTES);
        let start = records.as_ptr() as *const i8;
        // SAFETY: inside `records`, or one past it when it is empty (not dereferenced).
        let start = if backwards { unsafe { start.add(size - bytes) } } else { start };
        for offset in (0..bytes).step_by(64) {
            // SAFETY: prefetching has no architectural effect; the address lies inside `records`.
            unsafe { std::arch::x86_64::_mm_prefetch::<{ std::arch::x86_64::_MM_HINT_T0 }>(start.add(offset)) };
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (records, backwards);
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn no_ray_has_more_samples_than_the_bound_the_records_are_sized_by() {
        // Rays from every side of a flat box, at every angle, directions of any length: the
        // walk asserts its room, so a bound too small would fail the training tests too, but
        // here it is checked where it is tight (rays along the diagonal).
        let aabb = Aabb { min: [-30.0, -20.0, -5.0], max: [30.0, 25.0, 5.0] };
        let renderer = Renderer {
            lattice: Lattice { n: 16, aabb },
            shift: 0.0,
            scale: 1.0,
            step: 0.37,
            loss: PhotoLoss::Intensity,
        };
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let mut rays: Vec<Ray> = (0..500)
            .map(|_| {
                let dir = DVec3::new(rng.gen_range(-1.0..1.0), rng.gen_range(-1.0..1.0), rng.gen_range(-1.0..1.0));
                let length = rng.gen_range(0.2..3.0);
                Ray { origin: -80.0 * dir.normalize(), dir: length * dir.normalize(), target: 0.5 }
            })
            .collect();
        let corner = DVec3::from(aabb.max) - DVec3::from(aabb.min);
        let diagonal = Ray { origin: DVec3::from(aabb.min) - corner, dir: 0.5 * corner.normalize(), target: 0.5 };
        rays.push(diagonal);
        let bound = renderer.max_samples(&rays);
        let most = rays.iter().map(|ray| renderer.samples(ray, 0.0).2).max().expect("rays");
        assert!(most <= bound, "{most} samples, bound {bound}");
        // Along the diagonal the bound is tight.
        let (count, bound) = (renderer.samples(&diagonal, 0.0).2, renderer.max_samples(&[diagonal]));
        assert!(count <= bound && bound <= count + 2, "the diagonal ray: {count} samples, bound {bound}");
    }

    #[test]
    fn each_slab_gets_the_run_of_records_on_its_planes() {
        // Rays up and down through a lattice of 160 planes (ten slabs, more than one pass of
        // limits), three rays after one another in one task's region (the batch's second),
        // each record's cell anywhere on its plane.
        let (mut rng, plane_nodes) = (ChaCha8Rng::seed_from_u64(11), 160 * 160);
        let mut records = Records::<f32>::default();
        records.make_room(2 * 360);
        let region = records.regions(360).nth(1).expect("two regions");
        let mut footprints = Footprints::<f32>::default();
        footprints.clear(360);
        let mut rays: Vec<Vec<u32>> = Vec::new();
        for ray in 0..3 {
            let (low, high) = (rng.gen_range(0..80u32), rng.gen_range(80..159u32));
            let mut planes: Vec<u32> = (0..120).map(|_| rng.gen_range(low..=high)).collect();
            planes.sort_unstable();
            if ray == 1 {
                planes.reverse();
            }
            for (i, &plane) in planes.iter().enumerate() {
                let cell = plane * plane_nodes as u32 + rng.gen_range(0..plane_nodes as u32);
                region.cells[footprints.used + i] = cell;
            }
            footprints.keep_ray(region.cells, planes.len(), 2.0 + ray as f32, plane_nodes);
            rays.push(planes);
        }
        for slab in 0..10 {
            let (from, to) = ((slab * PLANES_PER_SLAB).saturating_sub(1) as u32, ((slab + 1) * PLANES_PER_SLAB) as u32);
            let expected: Vec<(Vec<u32>, f32)> = rays
                .iter()
                .enumerate()
                .map(|(ray, planes)| {
                    let mut on_slab: Vec<u32> = planes.iter().copied().filter(|p| (from..to).contains(p)).collect();
                    on_slab.sort_unstable();
                    (on_slab, 2.0 + ray as f32)
                })
                .filter(|(on_slab, _)| !on_slab.is_empty())
                .collect();
            let found: Vec<(Vec<u32>, f32)> = footprints
                .on_slab(slab, &records)
                .map(|run| {
                    let planes = run.cells.iter().map(|&c| c / plane_nodes as u32);
                    let planes = if run.backwards { planes.rev().collect() } else { planes.collect() };
                    (planes, run.d_sigma)
                })
                .collect();
            assert_eq!(found, expected, "slab {slab}");
        }
    }
}
