//! The sparse tree of a dense volume: its 8³ leaves with an active voxel, in the order OpenVDB
//! serialises them, and what the grid metadata says about them (active count, bounding box).

/// log2 of the node sizes, in voxels per side: leaf 8, lower internal 16 leaves, upper 32.
pub(super) const LEAF_LOG2: u32 = 3;
pub(super) const LOWER_LOG2: u32 = 4;
pub(super) const UPPER_LOG2: u32 = 5;
/// Voxels per side covered by a lower (16³) and an upper (32³) internal node.
pub(super) const LOWER_SPAN_LOG2: u32 = LEAF_LOG2 + LOWER_LOG2; // 128 voxels
pub(super) const UPPER_SPAN_LOG2: u32 = LOWER_SPAN_LOG2 + UPPER_LOG2; // 4096 voxels
pub(super) const LEAF_VOXELS: usize = 1 << (3 * LEAF_LOG2);

/// An 8³ leaf with at least one active voxel.
pub(super) struct Leaf {
    /// Index coordinates of the leaf's first voxel (multiples of 8).
    pub origin: [i32; 3],
    /// Bit `n` set when voxel `n` is active; `n = (x&7)·64 + (y&7)·8 + (z&7)` (z fastest,
    /// OpenVDB's order, the opposite of our arrays').
    pub mask: [u64; LEAF_VOXELS / 64],
    /// Every voxel's value in bit order; inactive ones are 0.
    pub values: [f32; LEAF_VOXELS],
}

impl Leaf {
    pub fn upper_origin(&self) -> [i32; 3] {
        self.origin.map(|c| c & !((1 << UPPER_SPAN_LOG2) - 1))
    }
    pub fn lower_origin(&self) -> [i32; 3] {
        self.origin.map(|c| c & !((1 << LOWER_SPAN_LOG2) - 1))
    }
    pub fn active_count(&self) -> u64 {
        self.mask.iter().map(|w| w.count_ones() as u64).sum()
    }
    /// The active values in bit order: what a node stores under active-mask compression.
    pub fn active_values(&self) -> impl Iterator<Item = f32> + '_ {
        self.values.iter().enumerate().filter(|(n, _)| self.mask[n >> 6] >> (n & 63) & 1 == 1).map(|(_, v)| *v)
    }
}

/// The non-empty leaves of the volume `values` (`dims`, x fastest), in the order OpenVDB
/// serialises them: upper nodes by origin (the root's `std::map<Coord>` order, x then y then z),
/// then lower nodes and leaves by their offset in the parent node (x-major too), i.e. depth
/// first. A voxel is active exactly when its value is not 0 (the background; -0 included).
pub(super) fn leaves(dims: [usize; 3], values: &[f32]) -> Vec<Leaf> {
    let [nx, ny, nz] = dims;
    let step = 1 << LEAF_LOG2;
    let mut leaves = Vec::new();
    for z0 in (0..nz).step_by(step) {
        for y0 in (0..ny).step_by(step) {
            for x0 in (0..nx).step_by(step) {
                let mut leaf =
                    Leaf { origin: [x0 as i32, y0 as i32, z0 as i32], mask: [0; 8], values: [0.0; LEAF_VOXELS] };
                let mut any = false;
                for z in z0..(z0 + step).min(nz) {
                    for y in y0..(y0 + step).min(ny) {
                        let row = nx * (y + ny * z);
                        for x in x0..(x0 + step).min(nx) {
                            let v = values[row + x];
                            // Exactly 0 (and -0) is the background: inactive, not stored.
                            if v != 0.0 {
                                let n = ((x - x0) << 6) | ((y - y0) << 3) | (z - z0);
                                leaf.mask[n >> 6] |= 1 << (n & 63);
                                leaf.values[n] = v;
                                any = true;
                            }
                        }
                    }
                }
                if any {
                    leaves.push(leaf);
                }
            }
        }
    }
    leaves.sort_by_key(|l| (l.upper_origin(), l.lower_origin(), l.origin));
    leaves
}

/// Offset of a child in its parent internal node: x-major, `log2` children per side, each
/// child spanning `2^child_span_log2` voxels.
pub(super) fn child_offset(origin: [i32; 3], log2: u32, child_span_log2: u32) -> usize {
    let side = (1 << log2) - 1;
    let [x, y, z] = origin.map(|c| ((c >> child_span_log2) & side) as usize);
    (x << (2 * log2)) | (y << log2) | z
}

/// Inclusive index bounds of the active voxels. An empty grid gets OpenVDB's empty box
/// (min = i32::MAX, max = i32::MIN on every axis), as OpenVDB itself writes.
pub(super) fn active_bbox(leaves: &[Leaf]) -> ([i32; 3], [i32; 3]) {
    let (mut lo, mut hi) = ([i32::MAX; 3], [i32::MIN; 3]);
    for leaf in leaves {
        for (w, &word) in leaf.mask.iter().enumerate() {
            let mut bits = word;
            while bits != 0 {
                let n = w * 64 + bits.trailing_zeros() as usize;
                bits &= bits - 1;
                let local = [n >> 6, (n >> 3) & 7, n & 7];
                for a in 0..3 {
                    let c = leaf.origin[a] + local[a] as i32;
                    lo[a] = lo[a].min(c);
                    hi[a] = hi[a].max(c);
                }
            }
        }
    }
    (lo, hi)
}

/// The number of distinct origins in a sorted sequence.
pub(super) fn count_distinct(sorted: impl Iterator<Item = [i32; 3]>) -> i64 {
    let mut last = None;
    sorted.filter(|o| last.replace(*o) != Some(*o)).count() as i64
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn leaves_are_sparse_and_in_openvdb_order() {
        // Active voxels in three leaves: (0,0,0), (200,0,0) (second lower node), (8,0,0).
        let mut values = vec![0.0f32; 201];
        values[0] = 1.0;
        values[200] = 2.0;
        values[8] = -0.0; // -0 is the background too
        values[9] = 3.0;
        let leaves = leaves([201, 1, 1], &values);
        let origins: Vec<[i32; 3]> = leaves.iter().map(|l| l.origin).collect();
        assert_eq!(origins, [[0, 0, 0], [8, 0, 0], [200, 0, 0]]);
        assert_eq!(leaves.iter().map(Leaf::active_count).sum::<u64>(), 3);
        // (9,0,0) is local x = 1: bit 64, the first bit of word 1 (z fastest inside a leaf).
        assert_eq!(leaves[1].mask[1], 1);
        assert_eq!(leaves[1].active_values().collect::<Vec<_>>(), [3.0]);
        assert_eq!(active_bbox(&leaves), ([0, 0, 0], [200, 0, 0]));
        assert_eq!(child_offset([200, 0, 0], LOWER_LOG2, LEAF_LOG2), (200 / 8 % 16) << 8);
        assert_eq!(child_offset([200, 0, 0], UPPER_LOG2, LOWER_SPAN_LOG2), 1 << 10);
    }

    #[test]
    fn active_values_follow_the_mask_in_bit_order() {
        // A 2×2×2 block: bit order is z fastest, so (x=0,y=0,z=1) comes before (x=1,y=0,z=0).
        let values = [0.0, 5.0, 0.0, 0.0, 7.0, 0.0, 0.0, 0.0]; // x fastest: (1,0,0) = 5, (0,0,1) = 7
        let leaves = leaves([2, 2, 2], &values);
        assert_eq!(leaves[0].active_values().collect::<Vec<_>>(), [7.0, 5.0]);
    }

    #[test]
    fn all_zero_volume_has_no_leaves_and_openvdbs_empty_box() {
        let leaves = leaves([3, 3, 3], &[0.0f32; 27]);
        assert!(leaves.is_empty());
        assert_eq!(active_bbox(&leaves), ([i32::MAX; 3], [i32::MIN; 3]));
    }
}
