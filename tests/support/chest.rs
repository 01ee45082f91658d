//! A small chest-like CT for the training tests: body, two lungs, a 30 mm "nodule", and
//! optionally a denser spine, as the `hu` stage's [0, 1] values (48 × 32 × 32 voxels of
//! 5 × 4 × 4.5 mm, centred on the origin).
#![allow(dead_code)] // shared by several test crates; each uses a subset

use aret_pipe::volume::{Geometry, Volume};

pub fn chest_ct(with_spine: bool) -> Volume<f32> {
    let geometry = Geometry {
        dims: [48, 32, 32],
        spacing_mm: [5.0, 4.0, 4.5],
        origin_mm: [-117.5, -62.0, -69.75],
        direction: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
    };
    let mut data = Vec::with_capacity(geometry.len());
    for k in 0..32 {
        for j in 0..32 {
            for i in 0..48 {
                let [x, y, z] = geometry.voxel_to_patient_mm([i as f64, j as f64, k as f64]);
                let body = (x / 110.0).powi(2) + (y / 55.0).powi(2) < 1.0;
                let lung = ((x.abs() - 45.0) / 35.0).powi(2) + (y / 40.0).powi(2) + (z / 60.0).powi(2) < 1.0;
                let nodule = (x - 40.0).powi(2) + y.powi(2) + (z - 10.0).powi(2) < 15.0f64.powi(2);
                let spine = with_spine && x.abs() < 12.0 && (y - 35.0).abs() < 12.0;
                data.push(if nodule || spine {
                    0.74 + 0.2 * f32::from(spine)
                } else if lung && body {
                    0.1
                } else if body {
                    0.74
                } else {
                    0.0
                });
            }
        }
    }
    Volume { geometry, data }
}
