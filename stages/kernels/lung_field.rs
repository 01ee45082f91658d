//! The lung field of a CT found by thresholding alone (no annotation): SPEC §2
//! `roi_center = "lungs"`. On each axial slice, voxels below `threshold_hu` that are not
//! connected (4-neighbourhood, within the slice) to the slice border are inside the body:
//! lungs and airways. Air around the body and under the table touches the border; the
//! trachea leaving the scanned range does not matter because the fill stays within a slice.

use crate::volume::Volume;
use std::collections::VecDeque;

/// Centroid (patient mm) of the low-density voxels enclosed by the body, if there are any.
pub fn lung_field_centroid_mm(ct_hu: &Volume<i16>, threshold_hu: i16) -> Option<[f64; 3]> {
    let [nx, ny, nz] = ct_hu.geometry.dims;
    let (mut sum, mut count) = ([0f64; 3], 0u64);
    for k in 0..nz {
        let slice = &ct_hu.data[k * nx * ny..(k + 1) * nx * ny];
        let outside = border_connected(slice, nx, ny, threshold_hu);
        for j in 0..ny {
            for i in 0..nx {
                let n = i + nx * j;
                if slice[n] < threshold_hu && !outside[n] {
                    sum[0] += i as f64;
                    sum[1] += j as f64;
                    sum[2] += k as f64;
                    count += 1;
                }
            }
        }
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
}
