//! Host of `shaders/grad_from_fixed.wgsl` (+ `fixed_point.wgsl`): the render's integer sums
//! of `dL/dF` into the f32 lattice the 3-D TV and the contractions use, one invocation per
//! node; and the limit those sums put on a batch.

use super::kernel::{groups, whole, Binding, Bound, Kernel, WORKGROUP};
use super::Gpu;
use crate::train::render::Renderer;
use bytemuck::{Pod, Zeroable};

const SOURCE: &str = include_str!("../../shaders/grad_from_fixed.wgsl");

/// `shaders/fixed_point.wgsl`: the integer format, appended to this kernel and to `render.wgsl`.
pub const FIXED_POINT: &str = include_str!("../../shaders/fixed_point.wgsl");

/// Bytes of the integer sums for `nodes` lattice nodes (eight u32 words each).
pub fn fixed_bytes(nodes: usize) -> u64 {
    32 * nodes as u64
}

/// Chunks one word takes before it could wrap (each chunk is below 2^16).
const CHUNKS_PER_WORD: usize = 1 << 16;

/// The most rays a batch may hold so that no node's word can wrap: a node takes addends from
/// the samples in its 2 × 2 × 2 cells (3 × 3 × 3 where the walk clamps at the box's faces), and
/// one ray leaves at most `diagonal / step + 1` samples in such a block.
pub fn max_batch_rays(renderer: &Renderer) -> usize {
    let lattice = &renderer.lattice;
    let block_diagonal = (0..3)
        .map(|k| (3.0 * (lattice.aabb.max[k] - lattice.aabb.min[k]) / lattice.n as f64).powi(2))
        .sum::<f64>()
        .sqrt();
    let per_ray = (block_diagonal / renderer.step).ceil() as usize + 1;
    CHUNKS_PER_WORD / per_ray
}

/// `struct Shape` of the shader.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct Shape {
    pub nodes: u32,
    pub _pad: [u32; 3],
}

pub struct GradFromFixed(Kernel);

impl GradFromFixed {
    pub fn new(gpu: &Gpu) -> anyhow::Result<GradFromFixed> {
        let bindings = [Binding::Uniform, Binding::Storage { read_only: true }, Binding::Storage { read_only: false }];
        Ok(GradFromFixed(Kernel::new(gpu, "grad_from_fixed", &[SOURCE, FIXED_POINT].concat(), &bindings)?))
    }

    /// Reads `fixed` (the render's sums), writes `dense_grad`, over `nodes` nodes.
    pub fn bind(
        &self,
        gpu: &Gpu,
        shape: &wgpu::Buffer,
        fixed: &wgpu::Buffer,
        dense_grad: &wgpu::Buffer,
        nodes: usize,
    ) -> anyhow::Result<Bound> {
        let group = self.0.bind(gpu, &[whole(shape), whole(fixed), whole(dense_grad)]);
        Ok(Bound { group, groups: groups(gpu, nodes as u64, WORKGROUP)? })
    }

    pub fn record(&self, encoder: &mut wgpu::CommandEncoder, bound: &Bound) {
        self.0.record(encoder, bound);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::Aabb;
    use crate::train::fit::renderer;
    use crate::train::params::TrainParams;
    use crate::train::render::Ray;
    use glam::DVec3;
    use rand::{Rng, SeedableRng};
    use std::collections::HashMap;

    /// The addends one ray leaves on each node, counted as the shader places its samples (the
    /// cell's lower node clamped to N − 2, positions clamped to the outer nodes).
    fn addends_per_node(renderer: &Renderer, ray: &Ray) -> HashMap<[usize; 3], usize> {
        let n = renderer.lattice.n;
        let (q0, dq, count) = renderer.samples(ray, 0.5 * renderer.step);
        let mut per_node = HashMap::new();
        for k in 0..count {
            let base: [usize; 3] = std::array::from_fn(|a| {
                let q = (q0[a] + k as f64 * dq[a]).clamp(0.0, (n - 1) as f64);
                (q as usize).min(n - 2)
            });
            for corner in 0..8 {
                let node = std::array::from_fn(|a| base[a] + (corner >> a & 1));
                *per_node.entry(node).or_insert(0) += 1;
            }
        }
        per_node
    }

    #[test]
    fn no_ray_leaves_more_addends_on_a_node_than_the_bound_allows() {
        let aabb = Aabb::new([-1.0, -0.7, -1.2], [1.0, 0.7, 1.2]);
        let params = TrainParams { grid: 16, ..TrainParams::default() };
        let walk = renderer(&params, aabb);
        let most = max_batch_rays(&walk);
        let per_ray = CHUNKS_PER_WORD / most;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let mut seen = 0;
        for _ in 0..20_000 {
            // Rays from a sphere around the box through points inside it, many nearly along an
            // axis or a face (where the clamped walk piles samples onto the outer cells).
            let target = DVec3::from_array(std::array::from_fn(|a| rng.gen_range(aabb.min[a]..aabb.max[a])));
            let mut dir = DVec3::new(rng.gen_range(-1.0..1.0), rng.gen_range(-1.0..1.0), rng.gen_range(-1.0..1.0));
            if rng.gen_bool(0.5) {
                let mut squash = DVec3::splat(1e-3);
                squash[rng.gen_range(0..3)] = 1.0;
                dir *= squash;
            }
            let dir = dir.normalize();
            let ray = Ray { origin: target - 5.0 * dir, dir, target: 1.0 };
            seen = seen.max(addends_per_node(&walk, &ray).into_values().max().unwrap_or(0));
        }
        assert!(seen <= per_ray, "a ray left {seen} addends on one node; the bound says {per_ray}");
        assert!(seen * 2 > per_ray, "the bound ({per_ray}) is not needlessly loose: {seen} seen");
        // The paper's configuration (cubic cells, half-cell steps, 2048 rays) fits with room.
        let cubic = renderer(&TrainParams::default(), Aabb::new([-1.0; 3], [1.0; 3]));
        assert_eq!(max_batch_rays(&cubic), CHUNKS_PER_WORD / 12);
        assert!(TrainParams::default().vm.batch_rays <= max_batch_rays(&cubic));
    }
}
