//! Inclusive voxel boxes and boolean masks local to a box, in the `(i, j, k)` = (row, column,
//! slice) indices of [`super::annotation`]; painting a box mask into a full volume buffer.

/// Why a ground truth cannot be computed from an XML's annotations.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum GroundTruthError {
    #[error("scan geometry: {0}")]
    Geometry(String),
    #[error(
        "ROI at z = {z_mm} mm matches no slice: the nearest slice is at {nearest_mm} mm, \
         more than {tolerance_mm} mm away"
    )]
    ZOffGrid { z_mm: f64, nearest_mm: f64, tolerance_mm: f64 },
    #[error("ROI point (x = {x}, y = {y}) at z = {z_mm} mm lies outside the {cols}×{rows} image")]
    PointOutsideImage { x: i32, y: i32, z_mm: f64, cols: usize, rows: usize },
    /// Names the read's `noduleID`, or `#n` for the n-th annotation passed to a kernel.
    #[error("annotation {0} has no contour")]
    EmptyAnnotation(String),
    #[error(
        "cannot split the annotations into nodules of at most {max_annotations}: the clustering \
         tolerance fell to {tol} (< min_tol {min_tol}) with a cluster of {largest} (pylidc's \
         ClusterError)"
    )]
    ClusterTolerance { max_annotations: usize, tol: f64, min_tol: f64, largest: usize },
    #[error("clustering parameter {0}")]
    ClusterParams(String),
    #[error("clevel {0} is outside (0, 1]")]
    Clevel(f64),
    #[error("a consensus needs at least one annotation")]
    NoAnnotations,
    #[error("annotation index {index} is out of range ({count} annotations)")]
    AnnotationIndex { index: usize, count: usize },
    #[error("cannot paint a mask with bbox {bbox:?} into a volume of dims {dims:?} ({len} values)")]
    PaintDims { bbox: BBox, dims: [usize; 3], len: usize },
    #[error(
        "the nodules' bounding boxes hold {voxels} voxels together, more than the limit of {limit} \
         (MAX_NODULE_BOX_VOXELS; real LIDC nodules hold under a million): the annotations span \
         far more of the scan than any nodule does"
    )]
    NodulesTooLarge { voxels: usize, limit: usize },
}

/// An inclusive voxel box in `(i, j, k)` = (row, column, slice) indices.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BBox {
    pub min_ijk: [usize; 3],
    pub max_ijk: [usize; 3],
}

impl BBox {
    /// Extent along each axis, in voxels.
    pub fn dims(&self) -> [usize; 3] {
        [0, 1, 2].map(|a| self.max_ijk[a] - self.min_ijk[a] + 1)
    }

    pub fn len(&self) -> usize {
        self.dims().iter().product()
    }

    /// Always false: an inclusive box holds at least one voxel.
    pub fn is_empty(&self) -> bool {
        false
    }

    /// The smallest box holding both.
    pub fn union(&self, other: &BBox) -> BBox {
        BBox {
            min_ijk: [0, 1, 2].map(|a| self.min_ijk[a].min(other.min_ijk[a])),
            max_ijk: [0, 1, 2].map(|a| self.max_ijk[a].max(other.max_ijk[a])),
        }
    }

    /// Index into a `[k][i][j]` box-local array, for a voxel inside the box.
    fn local_index(&self, i: usize, j: usize, k: usize) -> usize {
        let [ni, nj, _] = self.dims();
        ((k - self.min_ijk[2]) * ni + (i - self.min_ijk[0])) * nj + (j - self.min_ijk[1])
    }

    fn contains(&self, i: usize, j: usize, k: usize) -> bool {
        let v = [i, j, k];
        (0..3).all(|a| self.min_ijk[a] <= v[a] && v[a] <= self.max_ijk[a])
    }
}

/// A boolean mask over a box, stored `[k][i][j]` (slice, row, column).
#[derive(Debug, Clone, PartialEq)]
pub struct BoxMask {
    pub bbox: BBox,
    pub data: Vec<bool>,
}

impl BoxMask {
    pub fn empty(bbox: BBox) -> Self {
        Self { bbox, data: vec![false; bbox.len()] }
    }

    /// The value at global voxel `(i, j, k)`; false outside the box.
    pub fn get(&self, i: usize, j: usize, k: usize) -> bool {
        self.bbox.contains(i, j, k) && self.data[self.bbox.local_index(i, j, k)]
    }

    /// Sets global voxel `(i, j, k)`; a voxel outside the box is ignored (the mask only covers
    /// its box, as pylidc's mask covers the bbox it is given).
    pub(crate) fn set(&mut self, i: usize, j: usize, k: usize, on: bool) {
        if self.bbox.contains(i, j, k) {
            let index = self.bbox.local_index(i, j, k);
            self.data[index] = on;
        }
    }

    /// Number of voxels on.
    pub fn count(&self) -> usize {
        self.data.iter().filter(|&&on| on).count()
    }

    /// Voxels on per slice of the box, from `bbox.min_ijk[2]` up.
    pub fn count_per_slice(&self) -> Vec<usize> {
        let [ni, nj, _] = self.bbox.dims();
        self.data.chunks(ni * nj).map(|slice| slice.iter().filter(|&&on| on).count()).collect()
    }

    /// Global `(i, j, k)` of every voxel on, in storage order.
    pub fn voxels_on(&self) -> impl Iterator<Item = [usize; 3]> + '_ {
        let [ni, nj, _] = self.bbox.dims();
        let [i0, j0, k0] = self.bbox.min_ijk;
        self.data
            .iter()
            .enumerate()
            .filter(|(_, &on)| on)
            .map(move |(n, _)| [i0 + (n / nj) % ni, j0 + n % nj, k0 + n / (ni * nj)])
    }

    /// Writes `value` at every voxel on into a full volume buffer laid out like
    /// [`crate::volume::Volume`]: `dims = [cols, rows, slices]`, column fastest. Voxels off are
    /// left as they are.
    pub fn paint(&self, data: &mut [u8], dims: [usize; 3], value: u8) -> Result<(), GroundTruthError> {
        let [cols, rows, slices] = dims;
        let [i_max, j_max, k_max] = self.bbox.max_ijk;
        if data.len() != cols * rows * slices || i_max >= rows || j_max >= cols || k_max >= slices {
            return Err(GroundTruthError::PaintDims { bbox: self.bbox, dims, len: data.len() });
        }
        for [i, j, k] in self.voxels_on() {
            data[j + cols * (i + rows * k)] = value;
        }
        Ok(())
    }
}
