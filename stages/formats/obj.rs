//! Wavefront OBJ: a triangle mesh as text, read by ParaView, 3D Slicer, MeshLab, Blender,
//! trimesh and every mesh tool. `v x y z` per vertex, `vn` per vertex normal when given, and
//! `f a b c` per triangle with 1-based indices (`f a//a b//b c//c` with normals).
//!
//! The bytes depend only on the mesh: numbers are written as the shortest decimal that reads
//! back as the same f64, so a reader recovers our vertices exactly.

use std::fmt::Write as _;

/// The comment block every file starts with: where the numbers live.
const HEADER: &str = "# aret-pipe triangle mesh\n\
                      # units: mm, patient LPS (x towards the patient's left, y posterior, z superior)\n\
                      # faces: counter-clockwise seen from outside (right-hand normals point outwards)\n";

/// The OBJ text of the triangles `triangles` (0-based indices into `vertices`), with per-vertex
/// `normals` if given and extra `comments` (one line each, after the header).
pub fn encode(
    vertices: &[[f64; 3]],
    normals: Option<&[[f64; 3]]>,
    triangles: &[[u32; 3]],
    comments: &[&str],
) -> String {
    if let Some(n) = normals {
        assert_eq!(n.len(), vertices.len(), "one normal per vertex");
    }
    assert!(
        triangles.iter().flatten().all(|&i| (i as usize) < vertices.len()),
        "a triangle names a vertex that does not exist"
    );
    let mut s = String::with_capacity(40 * vertices.len() + 24 * triangles.len() + 256);
    s.push_str(HEADER);
    for line in comments {
        for part in line.lines() {
            let _ = writeln!(s, "# {part}");
        }
    }
    let _ = writeln!(s, "# {} vertices, {} triangles", vertices.len(), triangles.len());
    for v in vertices {
        let _ = writeln!(s, "v {} {} {}", num(v[0]), num(v[1]), num(v[2]));
    }
    for n in normals.unwrap_or(&[]) {
        let _ = writeln!(s, "vn {} {} {}", num(n[0]), num(n[1]), num(n[2]));
    }
    for t in triangles {
        let [a, b, c] = t.map(|i| i as u64 + 1);
        if normals.is_some() {
            let _ = writeln!(s, "f {a}//{a} {b}//{b} {c}//{c}");
        } else {
            let _ = writeln!(s, "f {a} {b} {c}");
        }
    }
    s
}

/// Shortest text that parses back to the same f64 (Rust's `Display`, never an exponent), with
/// −0 written as 0.
fn num(x: f64) -> String {
    if x == 0.0 {
        "0".into()
    } else {
        format!("{x}")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A tetrahedron in patient mm, outward.
    fn tetrahedron() -> (Vec<[f64; 3]>, Vec<[u32; 3]>) {
        let v =
            vec![[-120.5, 33.125, -310.0], [-110.5, 33.125, -310.0], [-120.5, 43.1, -310.0], [-120.5, 33.125, -0.3e-7]];
        let t = vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]];
        (v, t)
    }

    #[test]
    fn text_is_as_documented() {
        let (v, t) = tetrahedron();
        let text = encode(&v, None, &t, &["enclosed volume 1 mm³"]);
        assert!(text.starts_with(HEADER));
        assert!(text.contains("\n# enclosed volume 1 mm³\n# 4 vertices, 4 triangles\nv -120.5 33.125 -310\n"));
        assert!(text.contains("\nv -120.5 33.125 -0.00000003\n"));
        assert!(text.ends_with("f 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"));
        assert_eq!(text, encode(&v, None, &t, &["enclosed volume 1 mm³"]));
        assert_eq!(num(-0.0), "0");
    }

    #[test]
    fn tobj_reads_back_the_same_mesh() {
        let (v, t) = tetrahedron();
        let normals: Vec<[f64; 3]> = (0..4).map(|i| [i as f64 * 0.25, -0.5, 0.75]).collect();
        for with_normals in [false, true] {
            let text = encode(&v, with_normals.then_some(&normals[..]), &t, &[]);
            let options = tobj::LoadOptions { single_index: false, triangulate: false, ..Default::default() };
            let (models, _) =
                tobj::load_obj_buf(&mut text.as_bytes(), &options, |_| unreachable!("no materials")).unwrap();
            assert_eq!(models.len(), 1);
            let m = &models[0].mesh;
            // tobj renumbers vertices in the order the faces first use them: compare each
            // triangle's corners, and that the vertices stay shared (4, not 12).
            assert_eq!(m.positions.len(), 3 * v.len());
            assert!(m.face_arities.is_empty()); // all triangles
            let at = |data: &[f64], i: u32| [0, 1, 2].map(|k| data[3 * i as usize + k]);
            let corners: Vec<[f64; 3]> = m.indices.iter().map(|&i| at(&m.positions, i)).collect();
            assert_eq!(corners, t.iter().flatten().map(|&i| v[i as usize]).collect::<Vec<_>>());
            if with_normals {
                let read: Vec<[f64; 3]> = m.normal_indices.iter().map(|&i| at(&m.normals, i)).collect();
                assert_eq!(read, t.iter().flatten().map(|&i| normals[i as usize]).collect::<Vec<_>>());
            } else {
                assert!(m.normals.is_empty());
            }
        }
    }
}
