//! Tubes: airways, great vessels, the pulmonary vessel trees, clavicles. Owns the rasterising
//! of many tapered capsules with one HU into slices, fast: each slice keeps the list of
//! capsules whose bounding boxes reach it, and each capsule is evaluated only over its own
//! box. Capsules are stored in patient millimetres so tubes stay round whatever the body
//! scaling. A voxel is covered by the union of the set (the largest capsule occupancy), and
//! its occupancy is averaged over three depths across the slice, so a thin vessel lying in
//! the slice plane is partial-volumed by the slice thickness as on a real CT.

use super::canvas::SliceCanvas;
use super::frame::{Aabb, BodyFrame, IndexMap};
use super::shapes::{capsule_sd, occupancy, Sample, V3};
use super::Tissue;

/// One tapering tube segment, patient mm.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Capsule {
    pub a: V3,
    pub b: V3,
    pub radius_a_mm: f32,
    pub radius_b_mm: f32,
}

impl Capsule {
    fn sd(&self, p: V3) -> f32 {
        capsule_sd(p, self.a, self.b, self.radius_a_mm, self.radius_b_mm)
    }

    fn bounds(&self, margin: f64) -> Aabb {
        let r = f64::from(self.radius_a_mm.max(self.radius_b_mm)) + margin;
        let lo = std::array::from_fn(|c| f64::from(self.a[c].min(self.b[c])) - r);
        let hi = std::array::from_fn(|c| f64::from(self.a[c].max(self.b[c])) + r);
        Aabb::new(lo, hi)
    }
}

/// A polyline of tube control points in the reference frame: (position, radius), mm.
pub(crate) type Polyline = [(V3, f32)];

impl Capsule {
    /// This reference-frame capsule in patient mm (radii scale with the body's width).
    pub(crate) fn to_patient(self, frame: &BodyFrame) -> Capsule {
        let point = |p: V3| frame.to_patient(p.map(f64::from)).map(|c| c as f32);
        let radius = |r: f32| r * frame.scale_xy as f32;
        Capsule {
            a: point(self.a),
            b: point(self.b),
            radius_a_mm: radius(self.radius_a_mm),
            radius_b_mm: radius(self.radius_b_mm),
        }
    }
}

/// Capsules joining consecutive control points of reference-frame polylines, in patient mm.
pub(crate) fn capsules_from_polylines(frame: &BodyFrame, lines: &[&Polyline]) -> Vec<Capsule> {
    lines
        .iter()
        .flat_map(|line| line.windows(2))
        .map(|w| Capsule { a: w[0].0, b: w[1].0, radius_a_mm: w[0].1, radius_b_mm: w[1].1 }.to_patient(frame))
        .collect()
}

/// Capsules of one material, indexed by slice.
pub(crate) struct TubeSet {
    capsules: Vec<Capsule>,
    hu: f32,
    tissue: Tissue,
    /// Capsules (indices) whose box reaches slice k.
    by_slice: Vec<Vec<u32>>,
    /// Slice normal and the three depths across a slice at which occupancy is averaged.
    normal: V3,
    depths_mm: [f32; 3],
    /// Width of the partial-volume ramp at a tube wall, mm.
    edge_mm: f32,
}

impl TubeSet {
    pub(crate) fn new(capsules: Vec<Capsule>, hu: f32, tissue: Tissue, grid: &IndexMap) -> Self {
        let (normal, spacing) = grid.slice_step();
        let edge_mm = grid.pixel_mm();
        let margin = spacing / 2.0 + edge_mm;
        let mut by_slice = vec![Vec::new(); grid.dims[2]];
        for (n, c) in capsules.iter().enumerate() {
            if let Some([_, _, (k0, k1)]) = grid.index_range(&c.bounds(margin)) {
                for list in &mut by_slice[k0..=k1] {
                    list.push(n as u32);
                }
            }
        }
        let third = (spacing / 3.0) as f32;
        TubeSet {
            capsules,
            hu,
            tissue,
            by_slice,
            normal: normal.map(|c| c as f32),
            depths_mm: [-third, 0.0, third],
            edge_mm: edge_mm as f32,
        }
    }

    pub(crate) fn len(&self) -> usize {
        self.capsules.len()
    }

    /// Occupancy of the voxel centred at `p` (patient mm) by capsule `c`.
    fn occupancy_of(&self, c: &Capsule, p: V3) -> f32 {
        let mut sum = 0.0;
        for d in self.depths_mm {
            let q = std::array::from_fn(|a| p[a] + d * self.normal[a]);
            sum += occupancy(c.sd(q), self.edge_mm);
        }
        sum / 3.0
    }

    /// What the set contributes at patient position `p`, a point query. `slice`: the slice
    /// `p` lies in, if it is inside the grid (then only that slice's capsules can reach it).
    pub(crate) fn sample(&self, p: V3, slice: Option<usize>) -> Option<Sample> {
        let occupancy = |c: &Capsule| self.occupancy_of(c, p);
        let o = match slice {
            Some(k) => self.by_slice[k].iter().map(|&n| occupancy(&self.capsules[n as usize])).fold(0.0f32, f32::max),
            None => self.capsules.iter().map(occupancy).fold(0.0f32, f32::max),
        };
        (o > 0.0).then_some(Sample { occupancy: o, hu: self.hu, tissue: self.tissue })
    }

    pub(crate) fn paint(&self, canvas: &mut SliceCanvas) {
        let list = &self.by_slice[canvas.k];
        if list.is_empty() {
            return;
        }
        let margin = f64::from(self.edge_mm);
        let rects: Vec<_> = list
            .iter()
            .filter_map(|&n| {
                let c = &self.capsules[n as usize];
                canvas.rect(&c.bounds(margin)).map(|r| (c, r))
            })
            .collect();
        let Some(((i0, i1), (j0, j1))) = rects
            .iter()
            .map(|&(_, r)| r)
            .reduce(|a, b| ((a.0 .0.min(b.0 .0), a.0 .1.max(b.0 .1)), (a.1 .0.min(b.1 .0), a.1 .1.max(b.1 .1))))
        else {
            return;
        };
        // Union of the set: the largest occupancy over capsules, then one blend.
        let w = i1 - i0 + 1;
        let mut occ = vec![0.0f32; w * (j1 - j0 + 1)];
        let (p0, di, dj) = canvas.patient_affine();
        for (c, ((ci0, ci1), (cj0, cj1))) in rects {
            for j in cj0..=cj1 {
                for i in ci0..=ci1 {
                    let (fi, fj) = (i as f32, j as f32);
                    let p = std::array::from_fn(|a| p0[a] + fi * di[a] + fj * dj[a]);
                    let o = self.occupancy_of(c, p);
                    let slot = &mut occ[(j - j0) * w + (i - i0)];
                    *slot = slot.max(o);
                }
            }
        }
        let cols = canvas.cols();
        for j in j0..=j1 {
            for i in i0..=i1 {
                let o = occ[(j - j0) * w + (i - i0)];
                if o > 0.0 {
                    let v = &mut canvas.hu[j * cols + i];
                    *v += o * (self.hu - *v);
                }
            }
        }
    }
}
