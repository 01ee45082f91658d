//! Triangle meshes with shared vertices, and what is measured on them: the volume they enclose
//! (divergence theorem), whether they are closed and consistently oriented, vertex normals.

use glam::DVec3;
use std::collections::HashMap;

/// Vertices (patient mm) and triangles indexing them, counter-clockwise seen from outside
/// (right-hand normals point out of the enclosed volume).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Mesh {
    pub vertices: Vec<[f64; 3]>,
    pub triangles: Vec<[u32; 3]>,
}

/// The volume enclosed by a closed, outward-oriented mesh, in the cube of its vertex unit:
/// the sum of the signed tetrahedra each triangle spans with a fixed point (the divergence
/// theorem). Negative when the triangles face inwards; meaningless for an open mesh.
pub fn enclosed_volume_mm3(mesh: &Mesh) -> f64 {
    // The tetrahedra's apex is the vertices' mean rather than the origin: patient coordinates
    // are hundreds of mm away from a nodule a few mm wide, and the terms would cancel badly.
    let n = mesh.vertices.len().max(1) as f64;
    let apex = mesh.vertices.iter().fold(DVec3::ZERO, |s, &v| s + DVec3::from(v) / n);
    let sum: f64 = mesh
        .triangles
        .iter()
        .map(|t| {
            let [a, b, c] = t.map(|i| DVec3::from(mesh.vertices[i as usize]) - apex);
            a.dot(b.cross(c))
        })
        .sum();
    sum / 6.0
}

/// How far a mesh is from a closed, consistently oriented surface. Every count is 0 for a
/// watertight mesh whose triangles all face the same way ([`EdgeReport::is_closed_and_oriented`]).
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct EdgeReport {
    /// Undirected edges used by one triangle only (holes).
    pub boundary: usize,
    /// Undirected edges used by three or more triangles.
    pub non_manifold: usize,
    /// Edges used twice in the same direction (neighbouring triangles facing opposite ways).
    pub misoriented: usize,
    /// Triangles naming a vertex twice or a vertex that does not exist.
    pub degenerate: usize,
}

impl EdgeReport {
    pub fn is_closed_and_oriented(&self) -> bool {
        *self == EdgeReport::default()
    }
}

/// Counts, over all undirected edges, how many triangles use each and in which direction.
pub fn check_edges(mesh: &Mesh) -> EdgeReport {
    let mut report = EdgeReport::default();
    // (low, high) → (uses low→high, uses high→low)
    let mut edges: HashMap<(u32, u32), (u32, u32)> = HashMap::with_capacity(mesh.triangles.len() * 3 / 2);
    for t in &mesh.triangles {
        if t[0] == t[1] || t[1] == t[2] || t[0] == t[2] || t.iter().any(|&i| i as usize >= mesh.vertices.len()) {
            report.degenerate += 1;
            continue;
        }
        for k in 0..3 {
            let (a, b) = (t[k], t[(k + 1) % 3]);
            let entry = edges.entry((a.min(b), a.max(b))).or_default();
            if a < b {
                entry.0 += 1;
            } else {
                entry.1 += 1;
            }
        }
    }
    for &(forward, backward) in edges.values() {
        match forward + backward {
            1 => report.boundary += 1,
            2 if forward != 1 => report.misoriented += 1,
            2 => {}
            _ => report.non_manifold += 1,
        }
    }
    report
}

/// Unit normal per vertex: the area-weighted mean of its triangles' normals (outward for an
/// outward mesh); zero for a vertex no triangle uses.
pub fn vertex_normals(mesh: &Mesh) -> Vec<[f64; 3]> {
    let mut normals = vec![DVec3::ZERO; mesh.vertices.len()];
    for t in &mesh.triangles {
        let [a, b, c] = t.map(|i| DVec3::from(mesh.vertices[i as usize]));
        // |(b − a) × (c − a)| is twice the area: the weight comes with the direction.
        let n = (b - a).cross(c - a);
        for &i in t {
            normals[i as usize] += n;
        }
    }
    normals
        .into_iter()
        .map(|n| {
            let len = n.length();
            if len > 0.0 { n / len } else { n }.to_array()
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A unit cube's 12 triangles, outward, moved by `offset`.
    pub(crate) fn cube(offset: [f64; 3]) -> Mesh {
        let vertices = (0..8)
            .map(|c| [(c & 1) as f64 + offset[0], (c >> 1 & 1) as f64 + offset[1], (c >> 2 & 1) as f64 + offset[2]])
            .collect();
        // Each face as two triangles, counter-clockwise seen from outside.
        let quads = [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]];
        let triangles = quads.iter().flat_map(|q: &[u32; 4]| [[q[0], q[1], q[2]], [q[0], q[2], q[3]]]).collect();
        Mesh { vertices, triangles }
    }

    #[test]
    fn a_cube_far_from_the_origin_encloses_its_volume() {
        let mesh = cube([-312.5, 140.25, 1000.0]);
        assert!((enclosed_volume_mm3(&mesh) - 1.0).abs() < 1e-12);
        assert!(check_edges(&mesh).is_closed_and_oriented());
        let normals = vertex_normals(&mesh);
        let s = 1.0 / 3f64.sqrt();
        assert!(normals[0].iter().all(|c| (c + s).abs() < 1e-12));
        assert!(normals[7].iter().all(|c| (c - s).abs() < 1e-12));
    }

    #[test]
    fn defects_are_counted() {
        let mut flipped = cube([0.0; 3]);
        flipped.triangles[0].swap(1, 2);
        flipped.triangles[1].swap(1, 2);
        let r = check_edges(&flipped);
        assert_eq!((r.misoriented, r.boundary, r.non_manifold), (4, 0, 0));
        let mut open = cube([0.0; 3]);
        open.triangles.pop();
        let r = check_edges(&open);
        assert_eq!(r.boundary, 3);
        let mut inward = cube([0.0; 3]);
        inward.triangles.iter_mut().for_each(|t| t.swap(1, 2));
        assert!(check_edges(&inward).is_closed_and_oriented());
        assert!((enclosed_volume_mm3(&inward) + 1.0).abs() < 1e-12);
        let mut doubled = cube([0.0; 3]);
        doubled.triangles.push([0, 2, 3]);
        doubled.triangles.push([0, 0, 1]);
        let r = check_edges(&doubled);
        assert_eq!((r.non_manifold, r.degenerate), (3, 1));
        assert_eq!(enclosed_volume_mm3(&Mesh::default()), 0.0);
    }
}
