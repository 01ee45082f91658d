//! Marching cubes: the closed, outward-facing triangle surface where a scalar field on a
//! lattice crosses an iso level, with shared vertices, in patient millimetres (SPEC §3 select,
//! `nodule.obj`).
//!
//! Inside is `value ≥ iso`. Nodes beyond the lattice count as `background` (below `iso`), so the
//! surface is always closed, even where the inside touches the lattice border.
//!
//! Instead of a hand-typed 256-case table, each cube's polygons are derived from its six faces,
//! which is what makes the mesh watertight by construction:
//! - On a face, the crossings of its four edges are joined in pairs by segments that separate
//!   inside corners from outside ones. Walking the face's corners counter-clockwise seen from
//!   outside the cube, every segment runs from a crossing where the walk enters the inside to
//!   one where it leaves, so the two cubes sharing a face draw the same segments in opposite
//!   directions.
//! - A face with inside corners on one diagonal and outside corners on the other is ambiguous.
//!   It is decided from the face's four values alone (the asymptotic decider: the inside corners
//!   are joined when the bilinear interpolant's saddle is ≥ iso), so both cubes decide alike.
//!   For a 0/1 mask the saddle is exactly 0.5: voxels touching along an edge are joined, as
//!   18- and 26-connectivity join them; voxels touching at a corner only stay apart.
//! - Each crossing lies on two faces, once as a segment's start and once as an end, so the
//!   segments form closed loops. Each loop becomes a triangle fan from a vertex whose diagonals
//!   all cross the cube's interior (a diagonal along a face could be drawn by the neighbour
//!   too); when no vertex allows that, a fan around a new vertex at the loop's mean. Every mesh
//!   edge is then used by exactly two triangles in opposite directions: closed and consistently
//!   oriented, with right-hand normals pointing from inside to outside.
//!
//! Vertices are keyed by lattice edge and created once, so neighbouring cubes share them.

use super::mesh::Mesh;
use crate::volume::Geometry;

/// The surface of a binary mask: the 0/1 indicator meshed at 0.5 with 0 outside the lattice.
/// Every vertex lies at the midpoint between an inside and an outside voxel centre.
pub fn mesh_mask(mask: &[bool], geometry: &Geometry) -> Mesh {
    let dims = geometry.dims;
    assert_eq!(mask.len(), geometry.len(), "mask holds {} voxels, dims {dims:?} need {}", mask.len(), geometry.len());
    let Some(bounds) = inside_box(dims, |i| mask[i]) else {
        return Mesh::default();
    };
    let local = Local::new(dims, bounds, -0.5, |i| if mask[i] { 0.5 } else { -0.5 });
    local.mesh(geometry)
}

/// The iso-surface `field = iso` of `field` (x-fastest, on `geometry`, values at voxel
/// centres), with `background` (which must be below `iso`) beyond the lattice.
pub fn marching_cubes(field: &[f32], geometry: &Geometry, iso: f64, background: f64) -> Mesh {
    let dims = geometry.dims;
    assert_eq!(
        field.len(),
        geometry.len(),
        "field holds {} values, dims {dims:?} need {}",
        field.len(),
        geometry.len()
    );
    assert!(background < iso, "the background ({background}) must be outside, below the iso level ({iso})");
    let Some(bounds) = inside_box(dims, |i| f64::from(field[i]) >= iso) else {
        return Mesh::default();
    };
    let local = Local::new(dims, bounds, background - iso, |i| f64::from(field[i]) - iso);
    local.mesh(geometry)
}

/// The lattice around the inside: its box plus one node on every side (nodes beyond the
/// lattice take the background), holding value − iso. Local node (i, j, k) is lattice node
/// `lo + (i, j, k) − 1`.
struct Local {
    lo: [usize; 3],
    dims: [usize; 3],
    a: Vec<f64>,
}

impl Local {
    fn new(dims: [usize; 3], (lo, hi): ([usize; 3], [usize; 3]), outside: f64, value: impl Fn(usize) -> f64) -> Self {
        let ld = [0, 1, 2].map(|ax| hi[ax] - lo[ax] + 3);
        let mut a = vec![outside; ld[0] * ld[1] * ld[2]];
        for z in lo[2]..=hi[2] {
            for y in lo[1]..=hi[1] {
                let row = lo[0] + dims[0] * (y + dims[1] * z);
                let local = 1 + ld[0] * ((y - lo[1] + 1) + ld[1] * (z - lo[2] + 1));
                for x in 0..=hi[0] - lo[0] {
                    a[local + x] = value(row + x);
                }
            }
        }
        Self { lo, dims: ld, a }
    }

    fn mesh(&self, geometry: &Geometry) -> Mesh {
        let (ld, a) = (self.dims, &self.a);
        let plane = ld[0] * ld[1];
        let corner_offset: [usize; 8] =
            std::array::from_fn(|c| (c & 1) + ld[0] * ((c >> 1 & 1) + ld[1] * (c >> 2 & 1)));
        let axis_step = [1, ld[0], plane];
        let inside: Vec<u8> = a.iter().map(|&v| u8::from(v >= 0.0)).collect();
        // A left-handed index frame mirrors space: keep the normals outward by reversing triangles.
        let mirrored = determinant(&geometry.direction) < 0.0;
        let mut mesh = Mesh::default();
        // Vertex ids of the lattice edges starting at each node of the cube layer's two planes
        // (z = k and k + 1), per axis; a layer done, its upper plane becomes the next one's lower.
        let mut slabs = [vec![[u32::MAX; 3]; plane], vec![[u32::MAX; 3]; plane]];
        for k in 0..ld[2] - 1 {
            for j in 0..ld[1] - 1 {
                let row = ld[0] * (j + ld[1] * k);
                // The four nodes at one x of a cube's corners, as the bits of its x = 0 corners
                // (0, 2, 4, 6); the right-hand four of cube i are the left-hand four of i + 1.
                let column = |n: usize| {
                    inside[n] | inside[n + ld[0]] << 2 | inside[n + plane] << 4 | inside[n + ld[0] + plane] << 6
                };
                let mut left = column(row);
                for i in 0..ld[0] - 1 {
                    let base = row + i;
                    let right = column(base + 1);
                    let case = left | right << 1;
                    left = right;
                    if case == 0 || case == 255 {
                        continue;
                    }
                    let loops = match &unambiguous_cases()[case as usize] {
                        Some(loops) => *loops,
                        None => cube_loops(&std::array::from_fn(|c| a[base + corner_offset[c]])),
                    };
                    for polygon in loops.iter() {
                        let mut ids = [0u32; 12];
                        for (id, &e) in ids.iter_mut().zip(polygon) {
                            let (corner, axis) = EDGES[e as usize];
                            let node = base + corner_offset[corner as usize];
                            let slot = &mut slabs[usize::from(corner >> 2)][node % plane][axis as usize];
                            if *slot == u32::MAX {
                                *slot = mesh.vertices.len() as u32;
                                mesh.vertices.push(self.crossing(node, axis as usize, axis_step, geometry));
                            }
                            *id = *slot;
                        }
                        let ids = &ids[..polygon.len()];
                        let n = ids.len();
                        let mut push = |t: [u32; 3]| mesh.triangles.push(if mirrored { [t[0], t[2], t[1]] } else { t });
                        match fan_start(polygon) {
                            Some(s) => {
                                for w in 1..n - 1 {
                                    push([ids[s], ids[(s + w) % n], ids[(s + w + 1) % n]]);
                                }
                            }
                            None => {
                                let centre = mesh.vertices.len() as u32;
                                let mean = ids.iter().fold([0.0; 3], |acc, &id| {
                                    let v = mesh.vertices[id as usize];
                                    [0, 1, 2].map(|ax| acc[ax] + v[ax] / n as f64)
                                });
                                mesh.vertices.push(mean);
                                for w in 0..n {
                                    push([centre, ids[w], ids[(w + 1) % n]]);
                                }
                            }
                        }
                    }
                }
            }
            slabs.swap(0, 1);
            slabs[1].fill([u32::MAX; 3]);
        }
        mesh
    }

    /// Where value = iso on the lattice edge from local `node` along `axis`, in patient mm.
    fn crossing(&self, node: usize, axis: usize, axis_step: [usize; 3], geometry: &Geometry) -> [f64; 3] {
        let ld = self.dims;
        let (a0, a1) = (self.a[node], self.a[node + axis_step[axis]]);
        // Clamped off the nodes so that a value exactly at iso cannot put several vertices on
        // one point (which mesh tools would weld into non-manifold edges).
        let t = (a0 / (a0 - a1)).clamp(1e-3, 1.0 - 1e-3);
        let mut q = [node % ld[0], node / ld[0] % ld[1], node / (ld[0] * ld[1])].map(|v| v as f64);
        q[axis] += t;
        geometry.voxel_to_patient_mm([0, 1, 2].map(|ax| q[ax] + self.lo[ax] as f64 - 1.0))
    }
}

/// Cube corner `c` sits at offset `(c & 1, c >> 1 & 1, c >> 2 & 1)`. Edge `e` runs along axis
/// `e / 4` from corner `EDGES[e].0`; the other two axes' offsets are the bits of `e % 4`.
const EDGES: [(u8, u8); 12] =
    [(0, 0), (2, 0), (4, 0), (6, 0), (0, 1), (1, 1), (4, 1), (5, 1), (0, 2), (1, 2), (2, 2), (3, 2)];

/// Each face's corners, counter-clockwise seen from outside the cube (right-handed about the
/// outward normal): −z, +z, −y, +y, −x, +x.
const FACES: [[u8; 4]; 6] = [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]];

/// The edge joining corners `p` and `q` (which differ along one axis).
const fn edge_between(p: u8, q: u8) -> u8 {
    let low = if p < q { p } else { q };
    let axis = (p ^ q).trailing_zeros() as u8;
    // The two other axes' bits of the lower corner, in axis order, make `e % 4`.
    let others = match axis {
        0 => (low >> 1 & 1) | (low >> 2 & 1) << 1,
        1 => (low & 1) | (low >> 2 & 1) << 1,
        _ => (low & 1) | (low >> 1 & 1) << 1,
    };
    axis * 4 + others
}

/// The polygons of one cube, as loops of edge numbers, from `values` = value − iso at its eight
/// corners (inside: ≥ 0). See the module comment for the rules.
fn cube_loops(values: &[f64; 8]) -> Loops {
    let inside = values.map(|v| v >= 0.0);
    let mut next = [u8::MAX; 12];
    for face in &FACES {
        // The crossings met walking the face's edges counter-clockwise: (edge, entering?).
        let mut crossings = [(0u8, false); 4];
        let mut m = 0;
        for k in 0..4 {
            let (p, q) = (face[k], face[(k + 1) % 4]);
            if inside[p as usize] != inside[q as usize] {
                crossings[m] = (edge_between(p, q), inside[q as usize]);
                m += 1;
            }
        }
        // Two crossings: one segment. Four: inside corners on one diagonal; joined when the
        // bilinear saddle is inside, i.e. when (its value − iso) ≥ 0, which has the sign of
        // a·a' − b·b' (a, a' the inside diagonal's values, b, b' the outside's, iso subtracted).
        // The neighbouring cube computes the same products, maybe subtracted the other way
        // round, which negates the difference exactly: both cubes decide alike.
        let joined = m == 4 && {
            let v = face.map(|c| values[c as usize]);
            let d = v[0] * v[2] - v[1] * v[3];
            (if inside[face[0] as usize] { d } else { -d }) >= 0.0
        };
        for k in 0..m {
            let (edge, entering) = crossings[k];
            if entering {
                // Separate: leave by the crossing right after (around the inside corner
                // passed); joined: by the one right before (around the outside corner).
                let partner = if joined { (k + m - 1) % m } else { (k + 1) % m };
                next[edge as usize] = crossings[partner].0;
            }
        }
    }
    let mut loops = Loops { edges: [0; 12], ends: [0; 4], count: 0 };
    let mut len = 0;
    let mut used = [false; 12];
    for start in 0..12 {
        if next[start] == u8::MAX || used[start] {
            continue;
        }
        let mut e = start;
        while !used[e] {
            used[e] = true;
            loops.edges[len] = e as u8;
            len += 1;
            e = next[e] as usize;
        }
        debug_assert_eq!(e, start, "face segments always close into loops");
        loops.ends[loops.count] = len as u8;
        loops.count += 1;
    }
    loops
}

/// A cube's loops, one after another in `edges`; loop k ends before `ends[k]`. Twelve edges
/// make at most four loops of three.
#[derive(Clone, Copy)]
struct Loops {
    edges: [u8; 12],
    ends: [u8; 4],
    count: usize,
}

impl Loops {
    fn iter(&self) -> impl Iterator<Item = &[u8]> {
        (0..self.count).map(|k| {
            let start = if k == 0 { 0 } else { self.ends[k - 1] as usize };
            &self.edges[start..self.ends[k] as usize]
        })
    }
}

/// [`cube_loops`] of every case without an ambiguous face (whose loops depend on the inside
/// pattern alone), computed once; `None` for the cases that must look at the values.
fn unambiguous_cases() -> &'static [Option<Loops>; 256] {
    static TABLE: std::sync::OnceLock<[Option<Loops>; 256]> = std::sync::OnceLock::new();
    TABLE.get_or_init(|| {
        std::array::from_fn(|case| {
            let inside = |c: u8| case >> c & 1 == 1;
            let ambiguous = FACES
                .iter()
                .any(|f| inside(f[0]) == inside(f[2]) && inside(f[1]) == inside(f[3]) && inside(f[0]) != inside(f[1]));
            (!ambiguous).then(|| cube_loops(&std::array::from_fn(|c| if inside(c as u8) { 0.5 } else { -0.5 })))
        })
    })
}

/// The faces (bits of [`FACES`] indices) each edge lies on.
const EDGE_FACES: [u8; 12] = {
    let mut out = [0u8; 12];
    let mut f = 0;
    while f < 6 {
        let mut k = 0;
        while k < 4 {
            out[edge_between(FACES[f][k], FACES[f][(k + 1) % 4]) as usize] |= 1 << f;
            k += 1;
        }
        f += 1;
    }
    out
};

/// Where to start a triangle fan over `polygon` (a loop of edge numbers) so that no diagonal
/// joins two vertices on a common cube face; `None` if no start avoids that. Such a diagonal
/// could be drawn again by the cube beyond that face (as a segment or its own diagonal), and an
/// edge of three or four triangles is not a surface. Other diagonals lie inside this cube only.
fn fan_start(polygon: &[u8]) -> Option<usize> {
    let n = polygon.len();
    (0..n)
        .find(|&s| (2..n - 1).all(|k| EDGE_FACES[polygon[s] as usize] & EDGE_FACES[polygon[(s + k) % n] as usize] == 0))
}

fn determinant(m: &[[f64; 3]; 3]) -> f64 {
    m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1]) - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
        + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
}

/// The inclusive index box of the nodes where `inside` holds, if any.
fn inside_box(dims: [usize; 3], inside: impl Fn(usize) -> bool) -> Option<([usize; 3], [usize; 3])> {
    let mut lo = [usize::MAX; 3];
    let mut hi = [0; 3];
    for z in 0..dims[2] {
        for y in 0..dims[1] {
            let row = dims[0] * (y + dims[1] * z);
            let Some(first) = (0..dims[0]).find(|&x| inside(row + x)) else {
                continue;
            };
            let last = (first..dims[0]).rev().find(|&x| inside(row + x)).expect("the first is inside");
            for (ax, (l, h)) in [(first, last), (y, y), (z, z)].into_iter().enumerate() {
                lo[ax] = lo[ax].min(l);
                hi[ax] = hi[ax].max(h);
            }
        }
    }
    (lo[0] != usize::MAX).then_some((lo, hi))
}

#[cfg(test)]
mod tests {
    use super::super::mesh::{check_edges, enclosed_volume_mm3};
    use super::*;
    use rand::{Rng, SeedableRng};

    fn geometry(dims: [usize; 3], spacing_mm: [f64; 3]) -> Geometry {
        Geometry {
            dims,
            spacing_mm,
            origin_mm: [-120.0, 35.5, -310.25],
            direction: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        }
    }

    fn ball(dims: [usize; 3], centre: [f64; 3], radius: f64) -> Vec<bool> {
        let mut m = Vec::new();
        for z in 0..dims[2] {
            for y in 0..dims[1] {
                for x in 0..dims[0] {
                    let d = [x as f64 - centre[0], y as f64 - centre[1], z as f64 - centre[2]];
                    m.push(d.iter().map(|c| c * c).sum::<f64>() <= radius * radius);
                }
            }
        }
        m
    }

    #[test]
    fn the_face_and_edge_tables_describe_a_cube() {
        for (e, &(corner, axis)) in EDGES.iter().enumerate() {
            assert_eq!(edge_between(corner, corner | 1 << axis), e as u8);
            assert_eq!(corner >> axis & 1, 0);
        }
        // Every edge is on two faces, walked in opposite directions.
        let mut walked = std::collections::HashMap::new();
        for face in &FACES {
            for k in 0..4 {
                *walked.entry((face[k], face[(k + 1) % 4])).or_insert(0) += 1;
            }
        }
        assert_eq!(walked.len(), 24);
        assert!(walked.keys().all(|&(p, q)| walked.get(&(q, p)) == Some(&1)));
    }

    #[test]
    fn all_256_cases_close_into_oriented_loops() {
        // Every case, both ways of deciding its ambiguous faces (a 0/1 saddle at exactly 0.5,
        // and a value field where outside wins): one closed, oriented surface in each cube.
        for case in 1..255u16 {
            for inside_value in [0.5, 0.2] {
                let values: [f64; 8] = std::array::from_fn(|c| if case >> c & 1 == 1 { inside_value } else { -0.5 });
                let loops = cube_loops(&values);
                let polygons: Vec<&[u8]> = loops.iter().collect();
                let mut crossing_edges: Vec<u8> = polygons.concat();
                crossing_edges.sort();
                let expected: Vec<u8> = (0..12u8)
                    .filter(|&e| {
                        let (c, ax) = EDGES[e as usize];
                        (values[c as usize] >= 0.0) != (values[(c | 1 << ax) as usize] >= 0.0)
                    })
                    .collect();
                assert_eq!(crossing_edges, expected, "case {case:08b}");
                assert!(polygons.iter().all(|p| p.len() >= 3));
            }
        }
    }

    #[test]
    fn one_voxel_is_an_outward_octahedron() {
        let dims = [3, 3, 3];
        let mut mask = vec![false; 27];
        mask[13] = true;
        let g = geometry(dims, [2.0, 1.0, 3.0]);
        let mesh = mesh_mask(&mask, &g);
        assert_eq!((mesh.vertices.len(), mesh.triangles.len()), (6, 8));
        assert!(check_edges(&mesh).is_closed_and_oriented());
        // Vertices half a voxel from the centre along each axis: (4/3)·(1·0.5·1.5) mm³.
        let expected = 4.0 / 3.0 * 1.0 * 0.5 * 1.5;
        assert!((enclosed_volume_mm3(&mesh) - expected).abs() < 1e-9);
    }

    #[test]
    fn empty_full_and_border_masks() {
        let g = geometry([4, 3, 2], [1.0; 3]);
        assert_eq!(mesh_mask(&[false; 24], &g), Mesh::default());
        // A full lattice is closed by the background beyond it: a box with chamfered edges.
        let full = mesh_mask(&[true; 24], &g);
        assert!(check_edges(&full).is_closed_and_oriented());
        let v = enclosed_volume_mm3(&full);
        assert!(v > 0.0 && v < 24.0, "{v}");
        // A voxel in a corner of the lattice.
        let mut corner = vec![false; 24];
        corner[23] = true;
        let m = mesh_mask(&corner, &g);
        assert!(check_edges(&m).is_closed_and_oriented());
        assert!((enclosed_volume_mm3(&m) - 1.0 / 6.0).abs() < 1e-12);
    }

    #[test]
    fn diagonal_contacts_and_checkerboards_stay_watertight() {
        let g = geometry([6, 6, 6], [1.0; 3]);
        let checker: Vec<bool> = (0..216).map(|i| (i % 6 + i / 6 % 6 + i / 36) % 2 == 0).collect();
        let m = mesh_mask(&checker, &g);
        assert!(check_edges(&m).is_closed_and_oriented());
        assert!(enclosed_volume_mm3(&m) > 0.0);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        for density in [0.1, 0.3, 0.5, 0.7, 0.9] {
            let mask: Vec<bool> = (0..216).map(|_| rng.gen_bool(density)).collect();
            let m = mesh_mask(&mask, &g);
            assert!(check_edges(&m).is_closed_and_oriented(), "density {density}: {:?}", check_edges(&m));
            assert!(enclosed_volume_mm3(&m) > 0.0);
            // Real-valued fields decide ambiguous faces both ways.
            let field: Vec<f32> = (0..216).map(|_| rng.gen::<f32>()).collect();
            let m = marching_cubes(&field, &g, f64::from(density as f32), -1.0);
            assert!(check_edges(&m).is_closed_and_oriented(), "field at {density}: {:?}", check_edges(&m));
        }
    }

    #[test]
    fn a_mirrored_frame_keeps_normals_outward() {
        let dims = [12, 12, 12];
        let mask = ball(dims, [5.5, 5.5, 5.5], 4.0);
        let mut g = geometry(dims, [1.0, 1.0, 2.0]);
        let v = enclosed_volume_mm3(&mesh_mask(&mask, &g));
        g.direction[2] = [0.0, 0.0, -1.0];
        let m = mesh_mask(&mask, &g);
        assert!(check_edges(&m).is_closed_and_oriented());
        assert!((enclosed_volume_mm3(&m) - v).abs() < 1e-9 * v);
    }

    #[test]
    fn a_voxelised_sphere_encloses_its_voxel_volume() {
        for (radius, spacing) in [(6.0, [1.0, 1.0, 1.0]), (8.0, [0.7, 0.7, 2.5]), (12.0, [3.75, 1.875, 2.1875])] {
            let dims = [2 * radius as usize + 5; 3];
            let c = (dims[0] - 1) as f64 / 2.0 + 0.3;
            let mask = ball(dims, [c, c - 0.1, c + 0.2], radius);
            let g = geometry(dims, spacing);
            let mesh = mesh_mask(&mask, &g);
            let voxel_mm3 = spacing.iter().product::<f64>();
            let voxels = mask.iter().filter(|&&v| v).count() as f64 * voxel_mm3;
            let error = enclosed_volume_mm3(&mesh) / voxels - 1.0;
            assert!(error.abs() < 0.03, "radius {radius}: {:.2}%", 100.0 * error);
        }
    }
}
