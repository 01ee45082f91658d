//! Connected components of a boolean volume (SPEC §3 sweep): labels numbered exactly as
//! `scipy.ndimage.label` numbers them, the voxel count of each, and dropping the small ones.
//!
//! Volumes are x-fastest (`x + nx·(y + ny·z)`, dims `[nx, ny, nz]`), so our linear order is C
//! order of the `(nz, ny, nx)` array scipy sees. scipy numbers components by their first voxel
//! in that order; a union-find whose root is always the smallest index of its set gives the
//! same numbering in one relabelling pass.

use serde::{Deserialize, Serialize};

/// Which neighbours touch: sharing a face (6), a face or an edge (18), or any corner (26) —
/// scipy's `generate_binary_structure(3, 1 | 2 | 3)`. Written as the number in configuration.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(try_from = "u32", into = "u32")]
pub enum Connectivity {
    Six,
    Eighteen,
    TwentySix,
}

#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("connectivity must be 6, 18 or 26 (neighbours sharing a face, an edge or a corner), got {0}")]
pub struct ConnectivityError(pub u32);

impl TryFrom<u32> for Connectivity {
    type Error = ConnectivityError;
    fn try_from(n: u32) -> Result<Self, Self::Error> {
        match n {
            6 => Ok(Self::Six),
            18 => Ok(Self::Eighteen),
            26 => Ok(Self::TwentySix),
            _ => Err(ConnectivityError(n)),
        }
    }
}

impl From<Connectivity> for u32 {
    fn from(c: Connectivity) -> u32 {
        match c {
            Connectivity::Six => 6,
            Connectivity::Eighteen => 18,
            Connectivity::TwentySix => 26,
        }
    }
}

/// 26, the SPEC's (§3 sweep).
impl Default for Connectivity {
    fn default() -> Self {
        Self::TwentySix
    }
}

impl std::fmt::Display for Connectivity {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}", u32::from(*self))
    }
}

impl Connectivity {
    /// Whether offset `d` (each component in −1..=1, not all 0) is a neighbour.
    fn touches(self, d: [i64; 3]) -> bool {
        let nonzero = d.iter().filter(|&&c| c != 0).count();
        match self {
            Self::Six => nonzero == 1,
            Self::Eighteen => nonzero <= 2,
            Self::TwentySix => nonzero <= 3,
        }
    }
}

/// A labelling: `labels[i]` is 0 for background, else the component's number `1..=count`;
/// `sizes[l - 1]` is the voxel count of component `l`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Components {
    pub dims: [usize; 3],
    pub labels: Vec<u32>,
    pub sizes: Vec<usize>,
}

impl Components {
    /// Number of components.
    pub fn count(&self) -> usize {
        self.sizes.len()
    }

    /// Voxel count of component `label` (1-based).
    pub fn size(&self, label: u32) -> usize {
        self.sizes[label as usize - 1]
    }

    /// The voxels of every component.
    pub fn mask(&self) -> Vec<bool> {
        self.labels.iter().map(|&l| l != 0).collect()
    }

    /// The voxels of component `label`.
    pub fn mask_of(&self, label: u32) -> Vec<bool> {
        self.labels.iter().map(|&l| l == label).collect()
    }

    /// The components with at least `min_voxels` voxels, renumbered `1..` in their old order.
    /// Dropping whole components changes no other, so this equals labelling the kept voxels
    /// again (with the same connectivity), without a second union-find.
    pub fn without_small(&self, min_voxels: usize) -> Components {
        let mut renumber = vec![0u32; self.sizes.len() + 1];
        let mut sizes = Vec::new();
        for (old, &size) in self.sizes.iter().enumerate() {
            if size >= min_voxels {
                sizes.push(size);
                renumber[old + 1] = sizes.len() as u32;
            }
        }
        let labels = self.labels.iter().map(|&l| renumber[l as usize]).collect();
        Components { dims: self.dims, labels, sizes }
    }

    /// Only the components listed in `keep` (ascending labels), renumbered `1..` in that order.
    pub fn keep(&self, keep: &[u32]) -> Components {
        let mut renumber = vec![0u32; self.sizes.len() + 1];
        for (new, &old) in keep.iter().enumerate() {
            renumber[old as usize] = new as u32 + 1;
        }
        let labels = self.labels.iter().map(|&l| renumber[l as usize]).collect();
        Components { dims: self.dims, labels, sizes: keep.iter().map(|&l| self.size(l)).collect() }
    }
}

/// Connected components of `mask` (x-fastest on `dims`) under `connectivity`, numbered as
/// `scipy.ndimage.label(mask_zyx, generate_binary_structure(3, k))` numbers them.
///
/// Works on runs (maximal stretches of set voxels along x) rather than voxels: a run touches
/// the runs of the four earlier neighbouring rows it overlaps, found by one merge of two sorted
/// lists, and the union-find holds one node per run. Runs are numbered in linear order, so the
/// smallest run of a set holds the component's first voxel.
pub fn label(mask: &[bool], dims: [usize; 3], connectivity: Connectivity) -> Components {
    let [nx, ny, nz] = dims;
    let n = nx * ny * nz;
    assert_eq!(mask.len(), n, "mask holds {} voxels, dims {dims:?} need {n}", mask.len());
    assert!(n < u32::MAX as usize, "volumes of 2³² voxels or more are not supported");
    let rows = ny * nz;
    // runs[row_start[r]..row_start[r + 1]] are row r's runs, as inclusive [x0, x1].
    let mut runs: Vec<[u32; 2]> = Vec::new();
    let mut row_start = Vec::with_capacity(rows + 1);
    row_start.push(0);
    if nx > 0 {
        for row in mask.chunks_exact(nx) {
            let mut x = 0;
            while x < nx {
                if row[x] {
                    let x0 = x;
                    while x < nx && row[x] {
                        x += 1;
                    }
                    runs.push([x0 as u32, x as u32 - 1]);
                } else {
                    x += 1;
                }
            }
            row_start.push(runs.len());
        }
    } else {
        row_start.resize(rows + 1, 0);
    }
    // The earlier rows a row touches, and how far along x a contact may reach (1 when a
    // diagonal step in x is still a neighbour at that (dy, dz), 0 when only straight across is).
    let earlier: Vec<(i64, i64, u32)> = [(-1, 0), (-1, -1), (0, -1), (1, -1)]
        .into_iter()
        .filter_map(|(dy, dz)| {
            if connectivity.touches([1, dy, dz]) {
                Some((dy, dz, 1))
            } else {
                connectivity.touches([0, dy, dz]).then_some((dy, dz, 0))
            }
        })
        .collect();
    let mut parent: Vec<u32> = (0..runs.len() as u32).collect();
    for z in 0..nz {
        for y in 0..ny {
            let r = y + ny * z;
            let (here, here_end) = (row_start[r], row_start[r + 1]);
            if here == here_end {
                continue;
            }
            for &(dy, dz, reach) in &earlier {
                let (yy, zz) = (y as i64 + dy, z as i64 + dz);
                if yy < 0 || yy >= ny as i64 || zz < 0 {
                    continue;
                }
                let other = yy as usize + ny * zz as usize;
                let (mut i, mut j, j_end) = (here, row_start[other], row_start[other + 1]);
                // Two pointers over sorted runs: run a touches run b when [a0, a1] meets
                // [b0 − reach, b1 + reach]; step past whichever ends first (b on a tie, as the
                // next b may still reach a).
                while i < here_end && j < j_end {
                    let ([a0, a1], [b0, b1]) = (runs[i], runs[j]);
                    if a0 <= b1 + reach && b0 <= a1 + reach {
                        union(&mut parent, i as u32, j as u32);
                    }
                    if a1 < b1 + reach {
                        i += 1;
                    } else {
                        j += 1;
                    }
                }
            }
        }
    }
    let mut labels = vec![0u32; n];
    let mut sizes: Vec<usize> = Vec::new();
    let mut run_label = vec![0u32; runs.len()];
    for r in 0..rows {
        for k in row_start[r]..row_start[r + 1] {
            let root = find(&mut parent, k as u32) as usize;
            let l = if root == k {
                sizes.push(0);
                sizes.len() as u32
            } else {
                run_label[root] // the root comes first, so it is labelled already
            };
            run_label[k] = l;
            let [x0, x1] = runs[k].map(|x| x as usize);
            labels[r * nx + x0..=r * nx + x1].fill(l);
            sizes[l as usize - 1] += x1 - x0 + 1;
        }
    }
    Components { dims, labels, sizes }
}

/// The voxels of `seed`'s component of `inside` (the one [`label`] would give it), ascending,
/// grown outward from the seed: a few thousand voxels cost what they hold, not the volume.
/// `None` when the component holds more than `max_voxels` (the fill stops there), or when
/// `seed` itself is not inside.
pub fn component_within(
    inside: impl Fn(usize) -> bool,
    dims: [usize; 3],
    connectivity: Connectivity,
    seed: usize,
    max_voxels: usize,
) -> Option<Vec<usize>> {
    if !inside(seed) || max_voxels == 0 {
        return None;
    }
    let offsets: Vec<[i64; 3]> = (-1..=1)
        .flat_map(|dz| (-1..=1).flat_map(move |dy| (-1..=1).map(move |dx| [dx, dy, dz])))
        .filter(|&d| d != [0, 0, 0] && connectivity.touches(d))
        .collect();
    let mut seen = vec![false; dims.iter().product()];
    seen[seed] = true;
    let mut voxels = vec![seed];
    let mut stack = vec![seed];
    while let Some(i) = stack.pop() {
        let at = [i % dims[0], (i / dims[0]) % dims[1], i / (dims[0] * dims[1])].map(|v| v as i64);
        for d in &offsets {
            let n = [at[0] + d[0], at[1] + d[1], at[2] + d[2]];
            if (0..3).any(|a| n[a] < 0 || n[a] >= dims[a] as i64) {
                continue;
            }
            let j = n[0] as usize + dims[0] * (n[1] as usize + dims[1] * n[2] as usize);
            if !seen[j] && inside(j) {
                seen[j] = true;
                voxels.push(j);
                if voxels.len() > max_voxels {
                    return None;
                }
                stack.push(j);
            }
        }
    }
    // Callers sum over the voxels: in index order, as a scan of the labels would.
    voxels.sort_unstable();
    Some(voxels)
}

/// The root of `i`'s set, halving the path on the way.
fn find(parent: &mut [u32], mut i: u32) -> u32 {
    while parent[i as usize] != i {
        let grand = parent[parent[i as usize] as usize];
        parent[i as usize] = grand;
        i = grand;
    }
    i
}

/// Joins the sets of `a` and `b` under the smaller root.
fn union(parent: &mut [u32], a: u32, b: u32) {
    let (ra, rb) = (find(parent, a), find(parent, b));
    match ra.cmp(&rb) {
        std::cmp::Ordering::Less => parent[rb as usize] = ra,
        std::cmp::Ordering::Greater => parent[ra as usize] = rb,
        std::cmp::Ordering::Equal => {}
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn mask_from(dims: [usize; 3], on: &[[usize; 3]]) -> Vec<bool> {
        let mut m = vec![false; dims.iter().product()];
        for &[x, y, z] in on {
            m[x + dims[0] * (y + dims[1] * z)] = true;
        }
        m
    }

    /// A breadth-first labelling straight from the definition (all 26 offsets, bounds
    /// checked), numbering components as their first voxel appears.
    fn reference(mask: &[bool], dims: [usize; 3], c: Connectivity) -> (Vec<u32>, Vec<usize>) {
        let [nx, ny, _] = dims;
        let mut labels = vec![0u32; mask.len()];
        let mut sizes = Vec::new();
        for start in 0..mask.len() {
            if !mask[start] || labels[start] != 0 {
                continue;
            }
            sizes.push(0);
            let l = sizes.len() as u32;
            labels[start] = l;
            let mut queue = std::collections::VecDeque::from([start]);
            while let Some(i) = queue.pop_front() {
                sizes[l as usize - 1] += 1;
                let p = [i % nx, (i / nx) % ny, i / (nx * ny)].map(|v| v as i64);
                for dz in -1..=1 {
                    for dy in -1..=1 {
                        for dx in -1..=1 {
                            if (dx, dy, dz) == (0, 0, 0) || !c.touches([dx, dy, dz]) {
                                continue;
                            }
                            let q = [p[0] + dx, p[1] + dy, p[2] + dz];
                            if q.iter().zip(dims).any(|(&v, n)| v < 0 || v >= n as i64) {
                                continue;
                            }
                            let j = q[0] as usize + nx * (q[1] as usize + ny * q[2] as usize);
                            if mask[j] && labels[j] == 0 {
                                labels[j] = l;
                                queue.push_back(j);
                            }
                        }
                    }
                }
            }
        }
        (labels, sizes)
    }

    #[test]
    fn connectivity_is_validated() {
        assert_eq!(Connectivity::try_from(26), Ok(Connectivity::TwentySix));
        assert_eq!(u32::from(Connectivity::Eighteen), 18);
        assert_eq!(Connectivity::default(), Connectivity::TwentySix);
        let err = Connectivity::try_from(8).unwrap_err();
        assert_eq!(
            err.to_string(),
            "connectivity must be 6, 18 or 26 (neighbours sharing a face, an edge or a corner), got 8"
        );
        let parsed: Result<Connectivity, _> = serde_json::from_str("4");
        assert!(parsed.unwrap_err().to_string().contains("got 4"));
        assert_eq!(serde_json::to_string(&Connectivity::Six).unwrap(), "6");
    }

    #[test]
    fn diagonal_contacts_join_by_connectivity() {
        let dims = [3, 3, 3];
        // Two voxels touching by a corner only, by an edge only, and by a face.
        let corner = mask_from(dims, &[[0, 0, 0], [1, 1, 1]]);
        let edge = mask_from(dims, &[[0, 0, 0], [1, 1, 0]]);
        let face = mask_from(dims, &[[0, 0, 0], [0, 0, 1]]);
        let count = |m: &[bool], c| label(m, dims, c).count();
        assert_eq!(
            [Connectivity::Six, Connectivity::Eighteen, Connectivity::TwentySix].map(|c| count(&corner, c)),
            [2, 2, 1]
        );
        assert_eq!(
            [Connectivity::Six, Connectivity::Eighteen, Connectivity::TwentySix].map(|c| count(&edge, c)),
            [2, 1, 1]
        );
        assert_eq!(
            [Connectivity::Six, Connectivity::Eighteen, Connectivity::TwentySix].map(|c| count(&face, c)),
            [1, 1, 1]
        );
    }

    #[test]
    fn numbering_follows_first_appearance() {
        // A U shape in one slice: its left arm starts first, but the component that starts at
        // x = 2 in row 0 must keep number 2 even though the U's arms meet only in row 2.
        let dims = [5, 3, 1];
        let m = mask_from(
            dims,
            &[
                [0, 0, 0],
                [2, 0, 0],
                [4, 0, 0],
                [0, 1, 0],
                [4, 1, 0],
                [0, 2, 0],
                [1, 2, 0],
                [2, 2, 0],
                [3, 2, 0],
                [4, 2, 0],
            ],
        );
        let c = label(&m, dims, Connectivity::Six);
        assert_eq!(c.sizes, vec![9, 1]);
        assert_eq!(&c.labels[0..5], &[1, 0, 2, 0, 1]);
    }

    #[test]
    fn empty_full_single_and_border() {
        let dims = [4, 3, 2];
        let empty = label(&[false; 24], dims, Connectivity::TwentySix);
        assert_eq!((empty.count(), empty.labels.iter().all(|&l| l == 0)), (0, true));
        let full = label(&[true; 24], dims, Connectivity::Six);
        assert_eq!((full.sizes.clone(), full.labels.iter().all(|&l| l == 1)), (vec![24], true));
        let single = label(&mask_from(dims, &[[3, 2, 1]]), dims, Connectivity::TwentySix);
        assert_eq!((single.sizes.clone(), single.labels[23]), (vec![1], 1));
        // Voxels on opposite x ends of neighbouring rows must not wrap around into one.
        let wrap = mask_from(dims, &[[3, 0, 0], [0, 1, 0]]);
        assert_eq!(label(&wrap, dims, Connectivity::TwentySix).count(), 2);
        let nothing = label(&[], [0, 0, 0], Connectivity::Six);
        assert_eq!(nothing.count(), 0);
    }

    #[test]
    fn matches_a_breadth_first_reference_on_random_masks() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(6);
        for &density in &[0.05, 0.2, 0.35, 0.5, 0.8] {
            for c in [Connectivity::Six, Connectivity::Eighteen, Connectivity::TwentySix] {
                let dims = [13, 9, 11];
                let m: Vec<bool> = (0..13 * 9 * 11).map(|_| rng.gen_bool(density)).collect();
                let ours = label(&m, dims, c);
                let (labels, sizes) = reference(&m, dims, c);
                assert_eq!(ours.labels, labels, "density {density}, connectivity {c}");
                assert_eq!(ours.sizes, sizes);
            }
        }
    }

    #[test]
    fn without_small_equals_relabelling_the_kept_voxels() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let dims = [16, 12, 10];
        let m: Vec<bool> = (0..16 * 12 * 10).map(|_| rng.gen_bool(0.25)).collect();
        let all = label(&m, dims, Connectivity::Six);
        let kept = all.without_small(3);
        assert!(kept.count() < all.count() && kept.sizes.iter().all(|&s| s >= 3));
        assert_eq!(kept, label(&kept.mask(), dims, Connectivity::Six));
        assert_eq!(all.without_small(0), all);
        assert_eq!(all.mask_of(1).iter().filter(|&&v| v).count(), all.size(1));
    }

    #[test]
    fn component_within_equals_the_labels_component_and_stops_at_the_bound() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(8);
        let dims = [14, 10, 12];
        for c in [Connectivity::Six, Connectivity::Eighteen, Connectivity::TwentySix] {
            let m: Vec<bool> = (0..14 * 10 * 12).map(|_| rng.gen_bool(0.3)).collect();
            let all = label(&m, dims, c);
            for seed in (0..m.len()).step_by(7) {
                let grown = component_within(|i| m[i], dims, c, seed, usize::MAX);
                let own = all.labels[seed];
                let expected =
                    (own != 0).then(|| (0..m.len()).filter(|&i| all.labels[i] == own).collect::<Vec<usize>>());
                assert_eq!(grown, expected, "seed {seed}, connectivity {c}");
                if let Some(voxels) = expected {
                    let size = voxels.len();
                    assert_eq!(component_within(|i| m[i], dims, c, seed, size), Some(voxels));
                    assert_eq!(component_within(|i| m[i], dims, c, seed, size - 1), None);
                }
            }
        }
    }
}
