//! A 3-D voxel volume with its placement in patient space (DICOM LPS, millimetres).
//!
//! The memory layout is the SPEC's `[slice][row][col]`: the column index `i` varies fastest,
//! then the row index `j`, then the slice index `k`. Axis 0 steps along `direction[0]`
//! (the DICOM row direction cosine), axis 1 along `direction[1]` (the column direction cosine),
//! axis 2 along `direction[2]` (the slice normal, slices ascending).

use serde::{Deserialize, Serialize};

/// Where a voxel grid sits in patient space.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Geometry {
    /// Voxel counts `[columns, rows, slices]`.
    pub dims: [usize; 3],
    /// Distance between voxel centres along each axis, mm.
    pub spacing_mm: [f64; 3],
    /// Patient-space position of the centre of voxel (0, 0, 0), mm.
    pub origin_mm: [f64; 3],
    /// Unit direction of each index axis in patient space: `direction[a]` is axis `a`.
    pub direction: [[f64; 3]; 3],
}

impl Geometry {
    /// Number of voxels.
    pub fn len(&self) -> usize {
        self.dims.iter().product()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Patient-space position (mm) of the centre of voxel `(i, j, k)`.
    pub fn voxel_to_patient_mm(&self, ijk: [f64; 3]) -> [f64; 3] {
        let mut p = self.origin_mm;
        for (axis, &index) in ijk.iter().enumerate() {
            for (c, pc) in p.iter_mut().enumerate() {
                *pc += self.direction[axis][c] * self.spacing_mm[axis] * index;
            }
        }
        p
    }

    /// The voxel whose centre is nearest to patient point `p_mm` (clamped into the volume;
    /// the direction is orthonormal).
    pub fn nearest_voxel(&self, p_mm: [f64; 3]) -> [usize; 3] {
        std::array::from_fn(|axis| {
            let along: f64 = (0..3).map(|c| (p_mm[c] - self.origin_mm[c]) * self.direction[axis][c]).sum();
            (along / self.spacing_mm[axis]).round().clamp(0.0, (self.dims[axis] - 1) as f64) as usize
        })
    }

    /// One flag per voxel: whether its centre lies within `radius_mm` of patient point `centre_mm`.
    pub fn ball_mask(&self, centre_mm: [f64; 3], radius_mm: f64) -> Vec<bool> {
        (0..self.len())
            .map(|i| {
                let p = self.voxel_to_patient_mm(self.voxel_at(i).map(|v| v as f64));
                (0..3).map(|a| (p[a] - centre_mm[a]).powi(2)).sum::<f64>() <= radius_mm * radius_mm
            })
            .collect()
    }

    /// Voxel `[i, j, k]` at linear index `linear`: the inverse of [`Geometry::index`].
    pub fn voxel_at(&self, linear: usize) -> [usize; 3] {
        let [nx, ny, _] = self.dims;
        [linear % nx, (linear / nx) % ny, linear / (nx * ny)]
    }

    /// Linear index of voxel `(i, j, k)` in the `[slice][row][col]` layout.
    pub fn index(&self, i: usize, j: usize, k: usize) -> usize {
        i + self.dims[0] * (j + self.dims[1] * k)
    }
}

/// Voxel values plus their geometry.
#[derive(Debug, Clone, PartialEq)]
pub struct Volume<T> {
    pub geometry: Geometry,
    pub data: Vec<T>,
}

impl<T: Copy> Volume<T> {
    /// A volume whose values are `f(value)` of this one, on the same geometry.
    pub fn map<U>(&self, f: impl Fn(T) -> U) -> Volume<U> {
        Volume { geometry: self.geometry.clone(), data: self.data.iter().map(|&v| f(v)).collect() }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn voxel_at_inverts_index_and_a_ball_mask_holds_the_voxel_centres_within_its_radius() {
        let identity = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        let g = Geometry {
            dims: [9, 7, 5],
            spacing_mm: [1.0, 2.0, 3.0],
            origin_mm: [-4.0, 10.0, 0.0],
            direction: identity,
        };
        assert!((0..g.len()).all(|i| {
            let [x, y, z] = g.voxel_at(i);
            g.index(x, y, z) == i
        }));
        let centre = g.voxel_to_patient_mm([4.0, 3.0, 2.0]);
        let count = |r: f64| g.ball_mask(centre, r).iter().filter(|&&b| b).count();
        // x² + (2y)² + (3z)² ≤ r² over integer offsets: r = 2 holds x ∈ −2..2 and (0, ±1, 0);
        // r = 3 holds x ∈ −3..3, x ∈ −2..2 at y = ±1, and (0, 0, ±1).
        assert_eq!((count(0.5), count(2.0), count(3.0)), (1, 7, 19));
        // Clipped by the lattice: a ball around a corner keeps only the octant inside.
        assert_eq!(g.ball_mask(g.voxel_to_patient_mm([0.0; 3]), 2.0).iter().filter(|&&b| b).count(), 4);
    }
}
