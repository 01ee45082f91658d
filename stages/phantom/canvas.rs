//! One slice being painted. Owns the per-voxel loop: which voxels of the slice a layer can
//! touch (from its bounding box), their positions in patient and reference millimetres, and
//! the blend `hu ← (1 − o)·hu + o·layer_hu` (the same rule as [`super::shapes::Mix`]).

use super::frame::{Aabb, BodyFrame, IndexMap};
use super::shapes::{Sample, V3};

pub(crate) struct SliceCanvas<'a> {
    /// The slice's HU, `[row][col]`.
    pub hu: &'a mut [f32],
    pub k: usize,
    pub grid: &'a IndexMap,
    pub frame: &'a BodyFrame,
}

/// Inclusive column and row ranges of a slice.
pub(crate) type Rect = ((usize, usize), (usize, usize));

impl SliceCanvas<'_> {
    pub(crate) fn cols(&self) -> usize {
        self.grid.dims[0]
    }

    /// Voxels of this slice whose centres may lie in the patient box `b`.
    pub(crate) fn rect(&self, b: &Aabb) -> Option<Rect> {
        let [ci, cj, ck] = self.grid.index_range(b)?;
        (ck.0 <= self.k && self.k <= ck.1).then_some((ci, cj))
    }

    /// Affine map of this slice's voxel (i, j) to `f(patient mm)`: value at (0, 0) and the
    /// steps along i and j.
    fn affine(&self, f: impl Fn([f64; 3]) -> [f64; 3]) -> (V3, V3, V3) {
        let k = self.k as f64;
        let p0 = f(self.grid.to_patient([0.0, 0.0, k]));
        let pi = f(self.grid.to_patient([1.0, 0.0, k]));
        let pj = f(self.grid.to_patient([0.0, 1.0, k]));
        let f32s = |v: [f64; 3]| v.map(|c| c as f32);
        let d = |a: [f64; 3], b: [f64; 3]| f32s(std::array::from_fn(|c| a[c] - b[c]));
        (f32s(p0), d(pi, p0), d(pj, p0))
    }

    /// Patient-mm position of voxel (0, 0) of this slice and the steps along i and j.
    pub(crate) fn patient_affine(&self) -> (V3, V3, V3) {
        self.affine(|p| p)
    }

    /// Blend `sample(reference-frame position)` into the voxels that may lie in `ref_box`.
    pub(crate) fn paint_ref(&mut self, ref_box: &Aabb, sample: impl Fn(V3) -> Option<Sample>) {
        let Some(((i0, i1), (j0, j1))) = self.rect(&self.frame.box_to_patient(ref_box)) else {
            return;
        };
        let frame = *self.frame;
        let (r0, di, dj) = self.affine(|p| frame.to_ref(p));
        let cols = self.cols();
        for j in j0..=j1 {
            let row = &mut self.hu[j * cols..(j + 1) * cols];
            for (i, v) in row.iter_mut().enumerate().take(i1 + 1).skip(i0) {
                let (fi, fj) = (i as f32, j as f32);
                let r = std::array::from_fn(|c| r0[c] + fi * di[c] + fj * dj[c]);
                if let Some(s) = sample(r) {
                    *v += s.occupancy * (s.hu - *v);
                }
            }
        }
    }
}
