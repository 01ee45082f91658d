//! The dense field's projector pair without a matrix: `A σ` (each ray's optical depth through
//! the lattice of σ) and its exact adjoint `Aᵀ r`, in f32 with each ray's sum in f64.
//!
//! Joseph's discretisation: a ray steps along its dominant lattice axis (the one it crosses
//! fastest, in lattice steps), and at each lattice plane perpendicular to that axis the field
//! is read bilinearly at the ray's crossing (clamped to the outermost nodes, as the renderer
//! clamps), weighing `s ×` the ray's length between two planes. A plane counts while the
//! crossing lies inside the box. Both directions compute each weight by one function
//! ([`Line::corners`]), so `Aᵀ` is `A`'s transpose to rounding.
//!
//! The views look along the lattice's axes, so a view's rays share their axis and each plane
//! maps to the detector by one scaled affine map: [`sheet`] reads each plane once per pixel row.
//! Views at an angle to the lattice take [`general`], rays grouped by their own axis and read
//! a tile at a time ([`Projector::path`] says which ran). Either `Aᵀ` splits the lattice into
//! slabs of planes, one task each: every node is written by one task, in ray order, so the
//! result is the same whatever the thread count.

mod general;
pub mod sheet;

use super::render::{Lattice, Ray};
use crate::geometry::Aabb;
pub use general::Group;
use glam::DVec3;
use sheet::Sheet;

/// One ray's crossings of the planes along `axis`: at plane `k` the crossing lies at the
/// continuous node index `u0 + k·du` and `v0 + k·dv` along the two other axes (in axis order).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Line {
    pub u0: f32,
    pub du: f32,
    pub v0: f32,
    pub dv: f32,
    /// `s ×` the ray's length from one plane to the next.
    pub weight: f32,
    /// The planes `first..end` whose crossings lie inside the box.
    pub first: u32,
    pub end: u32,
    /// The ray's index in the projector's rays (its row of `A`).
    pub row: u32,
}

impl Line {
    /// The lower corner's node index (without the plane's offset) and the four bilinear
    /// weights (times the line's weight) of the crossing at plane `k`, corners in the order
    /// (u, v), (u+1, v), (u, v+1), (u+1, v+1).
    #[inline(always)]
    pub fn corners(&self, k: u32, n: usize, strides: [usize; 2]) -> (usize, [f32; 4]) {
        let (iu, fu) = cell(self.u0 + k as f32 * self.du, n);
        let (iv, fv) = cell(self.v0 + k as f32 * self.dv, n);
        let (gu, gv) = (1.0 - fu, 1.0 - fv);
        let w = self.weight;
        (iu * strides[0] + iv * strides[1], [w * gu * gv, w * fu * gv, w * gu * fv, w * fu * fv])
    }
}

/// The lower node and the weight of the upper one for a continuous node index `x`, clamped to
/// the lattice as the renderer clamps (constant beyond the outermost nodes).
#[inline(always)]
pub fn cell(x: f32, n: usize) -> (usize, f32) {
    let x = x.clamp(0.0, (n - 1) as f32);
    let i = (x as usize).min(n - 2);
    (i, x - i as f32)
}

/// The two axes other than `axis`, in order.
pub fn others(axis: usize) -> [usize; 2] {
    match axis {
        0 => [1, 2],
        1 => [0, 2],
        _ => [0, 1],
    }
}

/// Planes an adjoint task writes, planes being `stride` apart: along x a slab's planes share
/// cache lines, so it takes a cache line's width of them.
fn slab_planes(stride: usize) -> usize {
    if stride == 1 {
        16
    } else {
        2
    }
}

/// `A` and `Aᵀ` for a list of rays through an `n³` lattice (index `x + n·(y + n·z)`).
#[derive(Debug, Clone)]
pub struct Projector {
    pub n: usize,
    /// Rows of `A`: every ray given, including those that miss the box (their depth is 0).
    pub rays: usize,
    /// The views that look along a lattice axis.
    pub sheets: Vec<Sheet>,
    /// The other views' rays, by the axis each steps along.
    pub groups: Vec<Group>,
}

impl Projector {
    /// The projector of `rays` (each a row, in order) through `lattice`, `scale` being `s`.
    /// `views` gives the rays of each view as consecutive runs of `(rays, pixels a row)`.
    pub fn new(lattice: &Lattice, scale: f64, rays: &[Ray], views: &[(usize, usize)]) -> Projector {
        let n = lattice.n;
        assert!(n >= 2, "a lattice of at least 2 nodes a side");
        assert_eq!(views.iter().map(|v| v.0).sum::<usize>(), rays.len(), "the views' rays are the rays");
        let mut sheets = Vec::new();
        let mut by_axis: [Vec<Line>; 3] = Default::default();
        let mut start = 0;
        for &(len, width) in views {
            let view = &rays[start..start + len];
            let pinhole: Vec<(DVec3, DVec3)> = view.iter().map(|r| (r.origin, r.dir)).collect();
            match Sheet::of_view(&lattice.aabb, n, scale, &pinhole, width, start) {
                Some(sheet) => sheets.push(sheet),
                None => {
                    for (row, ray) in (start..).zip(view) {
                        if let Some((axis, line)) = line_of(lattice, scale, ray, row as u32) {
                            by_axis[axis].push(line);
                        }
                    }
                }
            }
            start += len;
        }
        let groups = by_axis
            .into_iter()
            .enumerate()
            .filter(|(_, lines)| !lines.is_empty())
            .map(|(axis, lines)| Group { axis, lines })
            .collect();
        Projector { n, rays: rays.len(), sheets, groups }
    }

    pub fn nodes(&self) -> usize {
        self.n * self.n * self.n
    }

    /// Whether every view took the sheet path.
    pub fn aligned(&self) -> bool {
        self.groups.is_empty()
    }

    /// Which path the views take, for logs and benchmarks.
    pub fn path(&self) -> &'static str {
        match (self.sheets.is_empty(), self.groups.is_empty()) {
            (_, true) => "views along the lattice's axes (plane by plane per pixel row)",
            (true, false) => "views at an angle to the lattice (ray by ray)",
            (false, false) => "some views along the lattice's axes, some at an angle",
        }
    }

    /// The row of every ray that meets the box, whichever path holds it, in no set order.
    pub fn lines(&self) -> impl Iterator<Item = u32> + '_ {
        let on_sheets = self
            .sheets
            .iter()
            .flat_map(|s| (0..s.weights.len()).filter(|&p| s.meets(p)).map(move |p| (s.first_ray + p) as u32));
        on_sheets.chain(self.groups.iter().flat_map(|g| g.lines.iter().map(|l| l.row)))
    }

    /// `A σ` into `depths` (one per ray; 0 where a ray misses the box).
    pub fn project(&self, sigma: &[f32], depths: &mut [f64]) {
        assert_eq!((sigma.len(), depths.len()), (self.nodes(), self.rays));
        depths.fill(0.0);
        for sheet in &self.sheets {
            sheet.project(sigma, self.n, depths);
        }
        for group in &self.groups {
            group.project(sigma, self.n, depths);
        }
    }

    /// `Aᵀ r` into `out` (one value per node), `r` one residual per ray.
    pub fn back_project(&self, r: &[f64], out: &mut [f32]) {
        assert_eq!((r.len(), out.len()), (self.rays, self.nodes()));
        out.fill(0.0);
        for sheet in &self.sheets {
            sheet.back_project(r, self.n, out);
        }
        for group in &self.groups {
            group.back_project(r, self.n, out);
        }
    }
}

/// `out`'s pointer, shared by slab tasks that write disjoint planes.
#[derive(Clone, Copy)]
struct SharedOut(*mut f32);
// SAFETY: the tasks that share it write disjoint nodes (see the adjoints' slabs).
unsafe impl Send for SharedOut {}
unsafe impl Sync for SharedOut {}

impl SharedOut {
    /// SAFETY: the caller owns node `i` for the duration of the write, and `i` is in bounds.
    #[inline(always)]
    unsafe fn at(self, i: usize) -> *mut f32 {
        unsafe { self.0.add(i) }
    }

    /// SAFETY: the caller owns nodes `i..i + len` for the borrow's life, and they are in bounds.
    #[inline(always)]
    #[allow(clippy::mut_from_ref)]
    unsafe fn row<'a>(self, i: usize, len: usize) -> &'a mut [f32] {
        unsafe { std::slice::from_raw_parts_mut(self.0.add(i), len) }
    }
}

/// The continuous node index of the point `origin + t·dir` is `a + t·b` (before clamping).
pub fn index_line(aabb: &Aabb, n: usize, origin: DVec3, dir: DVec3) -> ([f64; 3], [f64; 3]) {
    Lattice { n, aabb: *aabb }.index_line(origin, dir)
}

/// The continuous planes `k` at which `start + k·slope` lies inside the box (−½ to n − ½)
/// and on the lattice (0 to n − 1), or `None` when there are none.
fn plane_range(start: f64, slope: f64, n: usize) -> Option<(f64, f64)> {
    let n = n as f64;
    if slope == 0.0 {
        return (-0.5..=n - 0.5).contains(&start).then_some((0.0, n - 1.0));
    }
    let (p, q) = ((-0.5 - start) / slope, (n - 0.5 - start) / slope);
    Some((p.min(q).max(0.0), p.max(q).min(n - 1.0))).filter(|(lo, hi)| lo <= hi)
}

/// The line of `ray` and the axis it steps along, or `None` when it misses the box.
fn line_of(lattice: &Lattice, scale: f64, ray: &Ray, row: u32) -> Option<(usize, Line)> {
    lattice.aabb.intersect(ray.origin, ray.dir)?;
    let (a, b) = lattice.index_line(ray.origin, ray.dir);
    let axis = (0..3).max_by(|&i, &j| b[i].abs().total_cmp(&b[j].abs())).expect("three axes");
    let [u, v] = others(axis);
    // The crossing of plane k is at t_k = (k − a_axis)/b_axis.
    let (du, dv) = (b[u] / b[axis], b[v] / b[axis]);
    let (u0, v0) = (a[u] - a[axis] * du, a[v] - a[axis] * dv);
    let (u_lo, u_hi) = plane_range(u0, du, lattice.n)?;
    let (v_lo, v_hi) = plane_range(v0, dv, lattice.n)?;
    let (mut lo, mut hi) = (u_lo.max(v_lo), u_hi.min(v_hi));
    // Ahead of the origin: t_k ≥ 0.
    if b[axis] > 0.0 {
        lo = lo.max(a[axis]);
    } else {
        hi = hi.min(a[axis]);
    }
    let (first, end) = (lo.ceil(), hi.floor() + 1.0);
    if first >= end {
        return None;
    }
    let line = Line {
        u0: u0 as f32,
        du: du as f32,
        v0: v0 as f32,
        dv: dv as f32,
        weight: (scale / b[axis].abs()) as f32,
        first: first as u32,
        end: end as u32,
        row,
    };
    Some((axis, line))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::Aabb;
    use glam::DVec3;

    fn lattice(n: usize) -> Lattice {
        Lattice { n, aabb: Aabb { min: [-1.0, -0.8, -0.6], max: [1.0, 0.8, 0.6] } }
    }

    /// A pinhole view along `forward` (a unit axis, or rotated by `angle` about `spin`) of
    /// `side²` pixels from distance 6.
    fn view(forward: DVec3, up: DVec3, side: usize, angle: f64) -> Vec<Ray> {
        let rotation = glam::DQuat::from_axis_angle(up, angle);
        let (forward, right) = (rotation * forward, rotation * forward.cross(up));
        let eye = -6.0 * forward;
        let mut rays = Vec::new();
        for j in 0..side {
            for i in 0..side {
                let (x, y) = ((i as f64 + 0.5) / side as f64 - 0.5, (j as f64 + 0.5) / side as f64 - 0.5);
                let dir = (forward + 0.5 * x * right - 0.5 * y * up).normalize();
                rays.push(Ray { origin: eye, dir, target: 0.5 });
            }
        }
        rays
    }

    fn views(side: usize, angle: f64) -> (Vec<Ray>, Vec<(usize, usize)>) {
        let mut rays = view(DVec3::Y, DVec3::Z, side, angle);
        rays.extend(view(DVec3::X, DVec3::Z, side, angle));
        rays.extend(view(DVec3::Z, DVec3::Y, side, angle));
        (rays, vec![(side * side, side); 3])
    }

    fn random(len: usize, seed: u64) -> Vec<f64> {
        let mut state = seed;
        (0..len)
            .map(|_| {
                state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                (state >> 11) as f64 / (1u64 << 53) as f64
            })
            .collect()
    }

    fn dot_product_gap(angle: f64) -> (bool, f64) {
        let (rays, spans) = views(24, angle);
        let projector = Projector::new(&lattice(11), 1.3, &rays, &spans);
        let x: Vec<f32> = random(projector.nodes(), 1).into_iter().map(|v| v as f32).collect();
        let y = random(rays.len(), 2);
        let (mut ax, mut aty) = (vec![0.0; rays.len()], vec![0.0; projector.nodes()]);
        projector.project(&x, &mut ax);
        projector.back_project(&y, &mut aty);
        let left: f64 = ax.iter().zip(&y).map(|(a, b)| a * b).sum();
        let right: f64 = aty.iter().zip(&x).map(|(&a, &b)| f64::from(a) * f64::from(b)).sum();
        (projector.aligned(), (left - right).abs() / left.abs())
    }

    #[test]
    fn the_back_projection_is_the_adjoint_for_aligned_and_rotated_views() {
        let (aligned, gap) = dot_product_gap(0.0);
        assert!(aligned, "views along the axes take the aligned path");
        assert!(gap < 1e-6, "axis-aligned: ⟨Ax, y⟩ and ⟨x, Aᵀy⟩ differ by {gap:e}");
        let (aligned, gap) = dot_product_gap(0.35);
        assert!(!aligned, "rotated views take the general path");
        assert!(gap < 1e-6, "rotated: ⟨Ax, y⟩ and ⟨x, Aᵀy⟩ differ by {gap:e}");
    }

    #[test]
    fn a_uniform_field_gives_each_ray_its_chord_through_the_box() {
        // σ = 1 everywhere: the depth is s × the chord, to within a plane's length at the ends.
        let lattice = lattice(40);
        let (rays, spans) = views(16, 0.2);
        let projector = Projector::new(&lattice, 1.0, &rays, &spans);
        let mut depths = vec![0.0; rays.len()];
        projector.project(&vec![1.0; projector.nodes()], &mut depths);
        let cell = 2.0 / 40.0 * 1.05;
        let mut met = 0;
        for (ray, depth) in rays.iter().zip(&depths) {
            match lattice.aabb.intersect(ray.origin, ray.dir) {
                Some((t0, t1)) => {
                    met += 1;
                    assert!(
                        (depth - (t1 - t0)).abs() <= 2.0 * cell / ray.dir.abs().max_element(),
                        "{depth} against {}",
                        t1 - t0
                    );
                }
                None => assert_eq!(*depth, 0.0),
            }
        }
        assert!(met > rays.len() / 4, "{met} of {} rays meet the box", rays.len());
    }

    #[test]
    fn the_projection_does_not_depend_on_the_thread_count() {
        let (rays, spans) = views(20, 0.3);
        let projector = Projector::new(&lattice(13), 1.0, &rays, &spans);
        let x: Vec<f32> = random(projector.nodes(), 3).into_iter().map(|v| v as f32).collect();
        let y = random(rays.len(), 4);
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            pool.install(|| {
                let (mut ax, mut aty) = (vec![0.0; rays.len()], vec![0.0; projector.nodes()]);
                projector.project(&x, &mut ax);
                projector.back_project(&y, &mut aty);
                (ax, aty)
            })
        };
        assert!(run(1) == run(3));
    }
}
