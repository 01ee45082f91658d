//! Where the phantom sits in a scan. Owns the two maps every layer needs: voxel index ↔
//! patient millimetres (the scan's [`Geometry`]) and patient millimetres ↔ the *reference
//! frame* the anatomy is drawn in.
//!
//! The reference frame is one adult thorax in millimetres: X toward the patient's left, Y
//! posterior, Z superior, X = Y = 0 on the scanner axis, Z = 0 at the bottom of the scanned
//! range and Z = [`REF_HEIGHT_MM`] at its top. A scan maps onto it by scaling x/y with its
//! field of view (a technologist picks the FOV to fit the body, so the FOV tells the body's
//! size) and z with its scanned range (a chest CT covers the lungs with a small margin).

use crate::volume::Geometry;

/// Height of the reference frame: the scanned range of a typical chest CT, mm.
pub(crate) const REF_HEIGHT_MM: f64 = 330.0;
/// Field of view (the wider of the x and y extents) in which the reference body is drawn at
/// its own size (340 mm wide): a larger FOV means a proportionally larger patient.
pub(crate) const REF_FOV_MM: f64 = 360.0;

/// Boxes in patient or reference millimetres: the scene's box type.
pub(crate) use crate::geometry::Aabb;

/// Voxel index `(i, j, k)` (column, row, slice) ↔ patient mm, for any orientation.
#[derive(Debug, Clone)]
pub(crate) struct IndexMap {
    pub dims: [usize; 3],
    origin: [f64; 3],
    /// `step[a]`: patient-space displacement of one voxel along index axis `a`, mm.
    step: [[f64; 3]; 3],
    /// Rows of the inverse of the matrix whose columns are `step`: `index_a = Σ_c inverse[a][c]·d_c`.
    inverse: [[f64; 3]; 3],
}

impl IndexMap {
    pub(crate) fn new(geometry: &Geometry) -> IndexMap {
        let step: [[f64; 3]; 3] = std::array::from_fn(|a| geometry.direction[a].map(|c| c * geometry.spacing_mm[a]));
        let inverse = glam::DMat3::from_cols_array_2d(&step).inverse().transpose().to_cols_array_2d();
        IndexMap { dims: geometry.dims, origin: geometry.origin_mm, step, inverse }
    }

    pub(crate) fn to_patient(&self, ijk: [f64; 3]) -> [f64; 3] {
        std::array::from_fn(|c| self.origin[c] + (0..3).map(|a| self.step[a][c] * ijk[a]).sum::<f64>())
    }

    pub(crate) fn to_index(&self, p: [f64; 3]) -> [f64; 3] {
        let d: [f64; 3] = std::array::from_fn(|c| p[c] - self.origin[c]);
        std::array::from_fn(|a| (0..3).map(|c| self.inverse[a][c] * d[c]).sum())
    }

    /// Patient-space unit normal of the slices and the slice spacing, mm.
    pub(crate) fn slice_step(&self) -> ([f64; 3], f64) {
        let s = self.step[2];
        let len = (s[0] * s[0] + s[1] * s[1] + s[2] * s[2]).sqrt();
        (s.map(|c| c / len), len)
    }

    /// In-plane pixel size (the smaller of the two), mm.
    pub(crate) fn pixel_mm(&self) -> f64 {
        let len = |v: [f64; 3]| (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        len(self.step[0]).min(len(self.step[1]))
    }

    /// Patient-space box holding every voxel centre.
    pub(crate) fn patient_bounds(&self) -> Aabb {
        let last = self.dims.map(|n| n.saturating_sub(1) as f64);
        bounds_of(Aabb::new([0.0; 3], last).corners().into_iter().map(|c| self.to_patient(c.to_array())))
    }

    /// Inclusive index ranges `[lo, hi]` per axis of the voxels whose centres may lie in the
    /// patient box `b`, clipped to the grid; `None` if none can.
    pub(crate) fn index_range(&self, b: &Aabb) -> Option<[(usize, usize); 3]> {
        let ib = bounds_of(b.corners().into_iter().map(|c| self.to_index(c.to_array())));
        let mut out = [(0, 0); 3];
        for (a, range) in out.iter_mut().enumerate() {
            let lo = ib.min[a].ceil().max(0.0);
            let hi = ib.max[a].floor().min(self.dims[a] as f64 - 1.0);
            if lo > hi {
                return None;
            }
            *range = (lo as usize, hi as usize);
        }
        Some(out)
    }
}

fn bounds_of(points: impl Iterator<Item = [f64; 3]>) -> Aabb {
    let mut b = Aabb::new([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
    for p in points {
        for (a, v) in p.into_iter().enumerate() {
            b.min[a] = b.min[a].min(v);
            b.max[a] = b.max[a].max(v);
        }
    }
    b
}

/// Patient mm ↔ reference-frame mm (see the module doc).
#[derive(Debug, Clone, Copy)]
pub(crate) struct BodyFrame {
    centre_xy_mm: [f64; 2],
    /// Patient mm per reference mm, in-plane.
    pub scale_xy: f64,
    z_lo_mm: f64,
    /// Patient mm per reference mm, along z.
    pub scale_z: f64,
}

impl BodyFrame {
    /// Fit the reference body to a scan: the FOV's centre is the scanner axis, its larger
    /// extent sets the body size, and the scanned z range (slab edges) maps onto
    /// `0..REF_HEIGHT_MM`.
    pub(crate) fn fit(grid: &IndexMap) -> BodyFrame {
        let b = grid.patient_bounds();
        let (normal, spacing) = grid.slice_step();
        let pixel = grid.pixel_mm();
        // Voxel centres span the FOV less one voxel; the FOV itself is one voxel wider.
        let fov = (b.max[0] - b.min[0]).max(b.max[1] - b.min[1]) + pixel;
        let slab = spacing * normal[2].abs();
        let z_range = (b.max[2] - b.min[2] + slab).max(1.0);
        BodyFrame {
            centre_xy_mm: [(b.min[0] + b.max[0]) / 2.0, (b.min[1] + b.max[1]) / 2.0],
            scale_xy: (fov / REF_FOV_MM).max(1e-3),
            z_lo_mm: b.min[2] - slab / 2.0,
            scale_z: z_range / REF_HEIGHT_MM,
        }
    }

    pub(crate) fn to_ref(self, p: [f64; 3]) -> [f64; 3] {
        [
            (p[0] - self.centre_xy_mm[0]) / self.scale_xy,
            (p[1] - self.centre_xy_mm[1]) / self.scale_xy,
            (p[2] - self.z_lo_mm) / self.scale_z,
        ]
    }

    pub(crate) fn to_patient(self, r: [f64; 3]) -> [f64; 3] {
        [
            r[0] * self.scale_xy + self.centre_xy_mm[0],
            r[1] * self.scale_xy + self.centre_xy_mm[1],
            r[2] * self.scale_z + self.z_lo_mm,
        ]
    }

    /// A reference-frame box in patient mm (the map is an axis-aligned scaling).
    pub(crate) fn box_to_patient(self, b: &Aabb) -> Aabb {
        Aabb::new(self.to_patient(b.min), self.to_patient(b.max))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn oblique() -> Geometry {
        let (c, s) = (0.8, 0.6);
        Geometry {
            dims: [10, 8, 5],
            spacing_mm: [0.7, 0.9, 2.5],
            origin_mm: [-100.0, 50.0, 10.0],
            direction: [[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]],
        }
    }

    #[test]
    fn index_map_round_trips_and_matches_geometry() {
        let g = oblique();
        let m = IndexMap::new(&g);
        let ijk = [3.0, 5.5, 2.0];
        let p = m.to_patient(ijk);
        let want = g.voxel_to_patient_mm(ijk);
        assert!((0..3).all(|a| (p[a] - want[a]).abs() < 1e-9), "{p:?} vs {want:?}");
        let back = m.to_index(p);
        for a in 0..3 {
            assert!((back[a] - ijk[a]).abs() < 1e-9, "{back:?}");
        }
    }

    #[test]
    fn body_frame_maps_the_scan_onto_the_reference_height() {
        let g = Geometry {
            dims: [512, 512, 133],
            spacing_mm: [0.703125, 0.703125, 2.5],
            origin_mm: [-180.0, -180.0, -340.0],
            direction: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        };
        let f = BodyFrame::fit(&IndexMap::new(&g));
        assert!((f.scale_xy - 1.0).abs() < 1e-9);
        let bottom = f.to_ref([0.0, 0.0, -340.0 - 1.25]);
        let top = f.to_ref([0.0, 0.0, -10.0 + 1.25]);
        assert!(bottom[2].abs() < 1e-9 && (top[2] - REF_HEIGHT_MM).abs() < 1e-9);
        let p = [12.0, -30.0, -100.0];
        let q = f.to_patient(f.to_ref(p));
        assert!((0..3).all(|a| (p[a] - q[a]).abs() < 1e-9));
    }
}
