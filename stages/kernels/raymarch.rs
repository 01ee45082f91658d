//! Line integrals of a field along camera rays: the Beer–Lambert forward model of the DRR
//! stage (SPEC §3 drr). The CT enters as a [`VolumeField`]: trilinear interpolation of its
//! values at the voxel centres, clamped to the edge voxels out to the CT's outer faces, zero
//! beyond. Integration is the midpoint rule over the ray's overlap with the scene box and the
//! field's support, with steps that advance at most half a voxel along every axis.

use crate::geometry::{Aabb, SceneFrame};
use crate::volume::Volume;
use glam::{DMat3, DVec3};

/// Something a ray can be marched through.
pub trait Field: Sync {
    /// A ray `origin + t·dir` in whatever form the field samples fastest.
    type Ray;
    fn prepare(&self, origin: DVec3, dir: DVec3) -> Self::Ray;
    /// Where the ray (t ≥ 0) can meet non-zero values, if anywhere.
    fn support(&self, ray: &Self::Ray) -> Option<(f64, f64)>;
    /// The largest step along the (unit) ray that advances at most half a voxel on every axis.
    fn max_step(&self, ray: &Self::Ray) -> f64;
    /// The value at parameter `t`.
    fn sample(&self, ray: &Self::Ray, t: f64) -> f64;
}

/// A volume seen from scene space.
pub struct VolumeField<'a> {
    dims: [usize; 3],
    data: &'a [f32],
    /// Continuous voxel index (voxel centres at integers) of scene point p: `to_index · p + offset`.
    to_index: DMat3,
    offset: DVec3,
}

impl<'a> VolumeField<'a> {
    pub fn new(volume: &'a Volume<f32>, frame: &SceneFrame) -> VolumeField<'a> {
        let g = &volume.geometry;
        // patient = origin + Σ_a direction[a]·spacing[a]·index[a]; scene = (patient − c)/s.
        let axes = DMat3::from_cols_array_2d(&g.direction);
        let index_to_scene = axes * DMat3::from_diagonal(DVec3::from(g.spacing_mm)) / frame.mm_per_unit;
        let to_index = index_to_scene.inverse();
        let origin_scene = frame.to_scene(DVec3::from(g.origin_mm));
        VolumeField { dims: g.dims, data: &volume.data, to_index, offset: -(to_index * origin_scene) }
    }

    /// Voxels per axis (x fastest).
    pub fn dims(&self) -> [usize; 3] {
        self.dims
    }

    /// The values at the voxel centres, index `x + nx·(y + ny·z)`.
    pub fn data(&self) -> &[f32] {
        self.data
    }

    /// The value at scene point `p` (trilinear), and 0 (air) outside the volume's faces, where
    /// the ray march's [support](Field::support) ends too.
    pub fn value_at(&self, p: DVec3) -> f64 {
        let q = self.to_index * p + self.offset;
        let inside = (0..3).all(|a| (-0.5..=self.dims[a] as f64 - 0.5).contains(&q[a]));
        if inside {
            trilinear(self.data, self.dims, q)
        } else {
            0.0
        }
    }
}

impl Field for VolumeField<'_> {
    /// The ray in continuous index space: (origin, direction per scene unit).
    type Ray = (DVec3, DVec3);

    fn prepare(&self, origin: DVec3, dir: DVec3) -> (DVec3, DVec3) {
        (self.to_index * origin + self.offset, self.to_index * dir)
    }

    fn support(&self, &(o, d): &(DVec3, DVec3)) -> Option<(f64, f64)> {
        let faces = Aabb { min: [-0.5; 3], max: self.dims.map(|n| n as f64 - 0.5) };
        faces.intersect(o, d)
    }

    fn max_step(&self, &(_, d): &(DVec3, DVec3)) -> f64 {
        0.5 / d.abs().max_element()
    }

    fn sample(&self, &(o, d): &(DVec3, DVec3), t: f64) -> f64 {
        trilinear(self.data, self.dims, o + d * t)
    }
}

/// Trilinear interpolation at continuous index `p`, clamped to the edge voxels.
pub fn trilinear(data: &[f32], dims: [usize; 3], p: DVec3) -> f64 {
    super::trilinear::sample(data, dims, p.to_array())
}

/// Where a ray is integrated: `count` midpoint samples at `t0 + (s + ½)·delta`, s < count.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Segment {
    pub t0: f64,
    pub delta: f64,
    pub count: usize,
}

/// The midpoint-rule samples of the ray `origin + t·dir` (unit `dir`, `ray` its prepared form)
/// inside `aabb` and the field's support, in equal steps no longer than `max_step` (and than
/// the field's half-voxel step); `None` when the ray misses either. The CPU march and the GPU
/// backend's host (which uploads these per pixel) share it, so their sample counts agree.
pub fn segment<F: Field>(
    field: &F,
    aabb: &Aabb,
    ray: &F::Ray,
    origin: DVec3,
    dir: DVec3,
    max_step: f64,
) -> Option<Segment> {
    let (a0, a1) = aabb.intersect(origin, dir)?;
    let (f0, f1) = field.support(ray)?;
    let (t0, t1) = (a0.max(f0), a1.min(f1));
    if t1 <= t0 {
        return None;
    }
    let step = max_step.min(field.max_step(ray));
    // The span is often an exact multiple of the half-voxel step (rays leaving through the CT's
    // faces): forgive rounding noise so the sample count does not hinge on the last ulp.
    let count = ((t1 - t0) / step - 1e-9).ceil().max(1.0) as usize;
    Some(Segment { t0, delta: (t1 - t0) / count as f64, count })
}

/// `∫ field ds` along the ray `origin + t·dir` (unit `dir`) inside `aabb`: midpoint rule with
/// equal steps no longer than `max_step` (and than the field's half-voxel step).
pub fn march_ray<F: Field>(field: &F, aabb: &Aabb, origin: DVec3, dir: DVec3, max_step: f64) -> f64 {
    let ray = field.prepare(origin, dir);
    let Some(Segment { t0, delta, count }) = segment(field, aabb, &ray, origin, dir, max_step) else {
        return 0.0;
    };
    let mut sum = 0.0;
    for s in 0..count {
        sum += field.sample(&ray, t0 + (s as f64 + 0.5) * delta);
    }
    sum * delta
}

/// The transmitted intensity `I/I0 = exp(−scale · ∫ field)` of every pixel of `camera`,
/// row-major from the top row. Pixels are independent: the result does not depend on how
/// rayon schedules the rows.
pub fn render<F: Field>(
    field: &F,
    aabb: &Aabb,
    camera: &crate::geometry::Camera,
    max_step: f64,
    scale: f64,
) -> Vec<f32> {
    use rayon::prelude::*;
    let eye = camera.eye();
    let mut pixels = vec![0f32; camera.width * camera.height];
    pixels.par_chunks_mut(camera.width).enumerate().for_each(|(j, row)| {
        for (i, px) in row.iter_mut().enumerate() {
            let integral = march_ray(field, aabb, eye, camera.ray_dir(i, j), max_step);
            *px = (-scale * integral).exp() as f32;
        }
    });
    pixels
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::volume::Geometry;

    fn uniform(dims: [usize; 3], spacing: [f64; 3], origin: [f64; 3], value: f32) -> Volume<f32> {
        let geometry = Geometry {
            dims,
            spacing_mm: spacing,
            origin_mm: origin,
            direction: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        };
        Volume { data: vec![value; geometry.len()], geometry }
    }

    #[test]
    fn trilinear_reproduces_linear_fields() {
        let dims = [4, 3, 5];
        let data: Vec<f32> =
            (0..60).map(|n| (n % 4) as f32 * 2.0 + ((n / 4) % 3) as f32 * 3.0 - (n / 12) as f32).collect();
        let p = DVec3::new(1.3, 0.6, 2.9);
        assert!((trilinear(&data, dims, p) - (1.3 * 2.0 + 0.6 * 3.0 - 2.9)).abs() < 1e-9);
        // Clamped beyond the last centre.
        assert_eq!(trilinear(&data, dims, DVec3::new(9.0, 9.0, 9.0)), f64::from(data[59]));
    }

    #[test]
    fn uniform_volume_integrates_to_its_chord() {
        let v = uniform([10, 8, 6], [2.0, 3.0, 4.0], [-9.0, -10.5, -10.0], 1.0);
        let frame = SceneFrame { roi_center_mm: [0.0; 3], mm_per_unit: 10.0 };
        let field = VolumeField::new(&v, &frame);
        let big = Aabb { min: [-10.0; 3], max: [10.0; 3] };
        // Faces at x ∈ [-10, 10] mm = [-1, 1] units.
        let chord = march_ray(&field, &big, DVec3::new(-5.0, 0.0, 0.0), DVec3::X, 1.0);
        assert!((chord - 2.0).abs() < 1e-12, "{chord}");
        let dir = DVec3::new(1.0, 0.3, 0.2).normalize();
        let cut = Aabb { min: [-0.5, -0.4, -0.3], max: [0.6, 0.4, 0.3] };
        let (t0, t1) = cut.intersect(DVec3::new(-3.0, -0.6, -0.4), dir).unwrap();
        let got = march_ray(&field, &cut, DVec3::new(-3.0, -0.6, -0.4), dir, 1.0);
        assert!((got - (t1 - t0)).abs() < 1e-12);
    }
}
