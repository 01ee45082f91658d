//! The lung field of a CT found by thresholding alone (no annotation). On each axial slice,
//! voxels below `threshold_hu` that are not connected (4-neighbourhood, within the slice) to
//! the slice border are inside the body: lungs and airways. Air around the body and under the
//! table touches the border; the trachea leaving the scanned range does not matter because the
//! fill stays within a slice. Its centroid places the blind box (SPEC §2 `roi_center =
//! "lungs"`); filled, it tells a nodule the lung encloses from one against its wall.

use super::filters::fill_holes_per_slice;
use crate::volume::Volume;
use rayon::prelude::*;
use std::collections::VecDeque;

/// Between parenchyma (≈ −850 HU) and soft tissue: the lung field's threshold.
pub const LUNG_THRESHOLD_HU: i16 = -400;

/// Voxels below `threshold_hu` enclosed by the body on their axial slice (x fastest).
pub fn enclosed_air(ct_hu: &Volume<i16>, threshold_hu: i16) -> Vec<bool> {
    let [nx, ny, _] = ct_hu.geometry.dims;
    if nx * ny == 0 {
        return Vec::new();
    }
    ct_hu
        .data
        .par_chunks(nx * ny)
        .flat_map_iter(|slice| {
            let outside = border_connected(slice, nx, ny, threshold_hu);
            slice.iter().zip(outside).map(move |(&hu, out)| hu < threshold_hu && !out).collect::<Vec<_>>()
        })
        .collect()
}

/// [`enclosed_air`] with its holes filled slice by slice across z, then y, then x: the lungs
/// with the vessels and nodules they enclose. A nodule against the chest wall or the
/// mediastinum stays partly outside, since its slices open onto tissue on that side.
pub fn filled_lung_field(ct_hu: &Volume<i16>, threshold_hu: i16) -> Vec<bool> {
    let dims = ct_hu.geometry.dims;
    [2, 1, 0]
        .into_iter()
        .fold(enclosed_air(ct_hu, threshold_hu), |field, axis| fill_holes_per_slice(&field, dims, axis))
}

/// Centroid (patient mm) of the low-density voxels enclosed by the body, if there are any.
pub fn lung_field_centroid_mm(ct_hu: &Volume<i16>, threshold_hu: i16) -> Option<[f64; 3]> {
    let [nx, ny, _] = ct_hu.geometry.dims;
    let (mut sum, mut count) = ([0f64; 3], 0u64);
    for (n, _) in enclosed_air(ct_hu, threshold_hu).iter().enumerate().filter(|(_, &inside)| inside) {
        sum[0] += (n % nx) as f64;
        sum[1] += (n / nx % ny) as f64;
        sum[2] += (n / (nx * ny)) as f64;
        count += 1;
    }
    (count > 0).then(|| ct_hu.geometry.voxel_to_patient_mm(sum.map(|s| s / count as f64)))
}

/// Low-density pixels reachable from the image border through low-density pixels.
fn border_connected(slice: &[i16], nx: usize, ny: usize, threshold_hu: i16) -> Vec<bool> {
    let mut seen = vec![false; nx * ny];
    let mut queue = VecDeque::new();
    let push = |i: usize, j: usize, seen: &mut Vec<bool>, queue: &mut VecDeque<(usize, usize)>| {
        let n = i + nx * j;
        if !seen[n] && slice[n] < threshold_hu {
            seen[n] = true;
            queue.push_back((i, j));
        }
    };
    for i in 0..nx {
        push(i, 0, &mut seen, &mut queue);
        push(i, ny - 1, &mut seen, &mut queue);
    }
    for j in 0..ny {
        push(0, j, &mut seen, &mut queue);
        push(nx - 1, j, &mut seen, &mut queue);
    }
    while let Some((i, j)) = queue.pop_front() {
        if i > 0 {
            push(i - 1, j, &mut seen, &mut queue);
        }
        if i + 1 < nx {
            push(i + 1, j, &mut seen, &mut queue);
        }
        if j > 0 {
            push(i, j - 1, &mut seen, &mut queue);
        }
        if j + 1 < ny {
            push(i, j + 1, &mut seen, &mut queue);
        }
    }
    seen
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::volume::Geometry;

    #[test]
    fn enclosed_air_is_found_and_outside_air_is_not() {
        // 9×9×2: air everywhere, a body ring of soft tissue, an air pocket at (5..7, 3..5) inside.
        let (nx, ny, nz) = (9, 9, 2);
        let mut data = vec![-1000i16; nx * ny * nz];
        for k in 0..nz {
            for j in 1..8 {
                for i in 1..8 {
                    let pocket = (5..7).contains(&i) && (3..5).contains(&j);
                    data[i + nx * (j + ny * k)] = if pocket { -850 } else { 40 };
                }
            }
        }
        let geometry = Geometry {
            dims: [nx, ny, nz],
            spacing_mm: [1.0, 2.0, 3.0],
            origin_mm: [10.0, 20.0, 30.0],
            direction: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        };
        let c = lung_field_centroid_mm(&Volume { geometry, data }, -400).unwrap();
        assert_eq!(c, [10.0 + 5.5, 20.0 + 2.0 * 3.5, 30.0 + 3.0 * 0.5]);
    }

    #[test]
    fn the_filled_field_encloses_a_free_nodule_and_not_one_on_the_wall() {
        // 24×24×12: outside air, a tissue body (2..22 in x and y), a lung (5..19 in x and y,
        // slices 2..10) holding a free nodule (9..12, 9..12, 5..8) and one on its wall
        // (16..20, 10..13, 5..8: it reaches into the body).
        let dims = [24, 24, 12];
        let mut data = vec![-1000i16; dims.iter().product()];
        let inside = |i: usize, j: usize, lo: usize, hi: usize| (lo..hi).contains(&i) && (lo..hi).contains(&j);
        let free = |i: usize, j: usize, k: usize| (9..12).contains(&i) && (9..12).contains(&j) && (5..8).contains(&k);
        let wall = |i: usize, j: usize, k: usize| (16..20).contains(&i) && (10..13).contains(&j) && (5..8).contains(&k);
        for k in 0..dims[2] {
            for j in 0..dims[1] {
                for i in 0..dims[0] {
                    let lung = inside(i, j, 5, 19) && (2..10).contains(&k);
                    data[i + dims[0] * (j + dims[1] * k)] = match () {
                        _ if free(i, j, k) || wall(i, j, k) => 30,
                        _ if lung => -850,
                        _ if inside(i, j, 2, 22) => 40,
                        _ => -1000,
                    };
                }
            }
        }
        let geometry = Geometry {
            dims,
            spacing_mm: [1.0; 3],
            origin_mm: [0.0; 3],
            direction: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        };
        let ct = Volume { geometry, data };
        let field = filled_lung_field(&ct, -400);
        let at = |i: usize, j: usize, k: usize| field[i + dims[0] * (j + dims[1] * k)];
        assert!(at(10, 10, 6), "the free nodule is enclosed");
        assert!(at(6, 6, 3), "the lung is in the field");
        assert!(!at(19, 11, 6), "the part of the wall nodule in the body is not");
        assert!(!at(3, 3, 6) && !at(0, 0, 6), "neither is the body nor the air around it");
        assert_eq!(enclosed_air(&ct, -400).iter().filter(|&&a| a).count(), 14 * 14 * 8 - 27 - 3 * 3 * 3);
    }
}
