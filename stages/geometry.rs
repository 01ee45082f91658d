//! Scene space, its box, and the cameras that look at it (SPEC §2, §3 drr).
//!
//! Scene space is patient space (DICOM LPS, mm) shifted to the region of interest and scaled:
//! `scene = (patient_mm − roi_center_mm) / mm_per_unit`. The field and the DRRs live in the
//! axis-aligned box `aabb` of scene space. Cameras are pinholes `distance` units from the
//! origin looking at it (OpenGL convention: the camera looks down its −z), described by a
//! camera-to-world matrix whose columns are the camera's x, y, z axes and its eye position.

use glam::{DMat3, DMat4, DVec3, DVec4};
use serde::{Deserialize, Serialize};

/// An axis-aligned box in scene units.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Aabb {
    pub min: [f64; 3],
    pub max: [f64; 3],
}

impl Aabb {
    pub fn new(min: [f64; 3], max: [f64; 3]) -> Aabb {
        Aabb { min, max }
    }

    pub fn min(&self) -> DVec3 {
        DVec3::from(self.min)
    }
    pub fn max(&self) -> DVec3 {
        DVec3::from(self.max)
    }

    /// The eight corners.
    pub fn corners(&self) -> [DVec3; 8] {
        std::array::from_fn(|c| {
            DVec3::new(
                if c & 1 == 0 { self.min[0] } else { self.max[0] },
                if c & 2 == 0 { self.min[1] } else { self.max[1] },
                if c & 4 == 0 { self.min[2] } else { self.max[2] },
            )
        })
    }

    /// The parameter interval `[t0, t1]` (t ≥ 0) where `origin + t·dir` is inside, if any
    /// (slab method; `dir` need not be normalised).
    pub fn intersect(&self, origin: DVec3, dir: DVec3) -> Option<(f64, f64)> {
        let (mut t0, mut t1) = (0.0f64, f64::INFINITY);
        for a in 0..3 {
            let (o, d) = (origin[a], dir[a]);
            if d == 0.0 {
                if o < self.min[a] || o > self.max[a] {
                    return None;
                }
                continue;
            }
            let (mut near, mut far) = ((self.min[a] - o) / d, (self.max[a] - o) / d);
            if near > far {
                std::mem::swap(&mut near, &mut far);
            }
            t0 = t0.max(near);
            t1 = t1.min(far);
        }
        (t0 < t1).then_some((t0, t1))
    }

    /// The overlap of two boxes (possibly empty: then some `min > max`).
    pub fn overlap(&self, other: &Aabb) -> Aabb {
        Aabb {
            min: std::array::from_fn(|a| self.min[a].max(other.min[a])),
            max: std::array::from_fn(|a| self.max[a].min(other.max[a])),
        }
    }
}

/// How patient millimetres map to scene units.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SceneFrame {
    pub roi_center_mm: [f64; 3],
    pub mm_per_unit: f64,
}

impl SceneFrame {
    pub fn to_scene(&self, patient_mm: DVec3) -> DVec3 {
        (patient_mm - DVec3::from(self.roi_center_mm)) / self.mm_per_unit
    }
    pub fn to_patient_mm(&self, scene: DVec3) -> DVec3 {
        scene * self.mm_per_unit + DVec3::from(self.roi_center_mm)
    }
}

/// The three views of the method.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum View {
    Coronal,
    Sagittal,
    Axial,
}

impl View {
    pub const ALL: [View; 3] = [View::Coronal, View::Sagittal, View::Axial];

    pub fn name(self) -> &'static str {
        match self {
            View::Coronal => "coronal",
            View::Sagittal => "sagittal",
            View::Axial => "axial",
        }
    }

    /// The nominal camera-to-world pose at `distance` from the origin (SPEC §3 drr):
    /// coronal eye on +y, sagittal eye on +x (the SPEC's corrected pose), axial eye on +z.
    /// Columns: camera x, camera y, camera z (the camera looks down −z), eye.
    pub fn pose(self, distance: f64) -> DMat4 {
        let (x, y, z) = match self {
            // The paper's C_cor: x → x, y → −z, z → +y.
            View::Coronal => (DVec3::X, DVec3::NEG_Z, DVec3::Y),
            // SPEC-decided C_sag = [[0,0,1,d],[1,0,0,0],[0,1,0,0]]: x → +y, y → +z, z → +x.
            View::Sagittal => (DVec3::Y, DVec3::Z, DVec3::X),
            // The paper's C_ax: the identity rotation, eye at +z.
            View::Axial => (DVec3::X, DVec3::Y, DVec3::Z),
        };
        DMat4::from_cols(x.extend(0.0), y.extend(0.0), z.extend(0.0), (z * distance).extend(1.0))
    }
}

/// A pinhole camera: `width × height` pixels, focal length `focal_px`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Camera {
    pub view: View,
    /// Camera-to-world, row-major (row r = world axis r; last column the eye position).
    pub camera_to_world: [[f64; 4]; 4],
    pub focal_px: f64,
    pub width: usize,
    pub height: usize,
}

impl Camera {
    pub fn new(view: View, pose: DMat4, focal_px: f64, width: usize, height: usize) -> Camera {
        let rows = pose.transpose().to_cols_array_2d();
        Camera { view, camera_to_world: rows, focal_px, width, height }
    }

    pub fn pose(&self) -> DMat4 {
        DMat4::from_cols_array_2d(&self.camera_to_world).transpose()
    }

    pub fn eye(&self) -> DVec3 {
        self.pose().w_axis.truncate()
    }

    /// Unit direction (world) of the ray through the centre of pixel (column `i`, row `j`):
    /// camera-space `normalize((i + 0.5 − W/2)/f, −(j + 0.5 − H/2)/f, −1)`.
    pub fn ray_dir(&self, i: usize, j: usize) -> DVec3 {
        let x = (i as f64 + 0.5 - self.width as f64 / 2.0) / self.focal_px;
        let y = -(j as f64 + 0.5 - self.height as f64 / 2.0) / self.focal_px;
        let rotation = DMat3::from_mat4(self.pose());
        (rotation * DVec3::new(x, y, -1.0)).normalize()
    }

    /// Pixel coordinates (column, row; continuous, pixel centres at +0.5) where world point `p`
    /// projects, or `None` behind the camera.
    pub fn project(&self, p: DVec3) -> Option<(f64, f64)> {
        let c = self.pose().inverse() * DVec4::from((p, 1.0));
        if c.z >= 0.0 {
            return None;
        }
        let (x, y) = (c.x / -c.z, c.y / -c.z);
        Some((x * self.focal_px + self.width as f64 / 2.0, -y * self.focal_px + self.height as f64 / 2.0))
    }
}

/// The largest focal length (px) at which every pose's image still covers the whole projection
/// of `aabb` (SPEC `focal_px = "fit"`).
pub fn fit_focal_px(poses: &[DMat4], aabb: &Aabb, width: usize, height: usize) -> f64 {
    let mut focal = f64::INFINITY;
    for pose in poses {
        let to_camera = pose.inverse();
        for corner in aabb.corners() {
            let c = to_camera * DVec4::from((corner, 1.0));
            let depth = -c.z; // positive in front of the camera
            if c.x != 0.0 {
                focal = focal.min(width as f64 / 2.0 * depth / c.x.abs());
            }
            if c.y != 0.0 {
                focal = focal.min(height as f64 / 2.0 * depth / c.y.abs());
            }
        }
    }
    focal
}

/// `pose` turned by `angle_rad` about the world axis `axis` through the origin (the camera
/// keeps looking at the scene it orbits).
pub fn orbit(pose: DMat4, axis: DVec3, angle_rad: f64) -> DMat4 {
    DMat4::from_axis_angle(axis.normalize(), angle_rad) * pose
}

#[cfg(test)]
mod tests {
    use super::*;

    const PAPER_BOX: Aabb = Aabb { min: [-2.5, -1.5, -2.0], max: [3.5, 1.5, 1.5] };

    #[test]
    fn each_view_looks_at_the_origin_from_its_side() {
        for (view, eye) in [(View::Coronal, DVec3::Y), (View::Sagittal, DVec3::X), (View::Axial, DVec3::Z)] {
            let cam = Camera::new(view, view.pose(50.0), 100.0, 128, 128);
            assert!((cam.eye() - eye * 50.0).length() < 1e-12);
            // The central ray (between the four middle pixels) points at the origin.
            let mid = (DMat3::from_mat4(cam.pose()) * DVec3::NEG_Z).normalize();
            assert!((mid + eye).length() < 1e-12, "{view:?}");
            let (u, v) = cam.project(DVec3::ZERO).unwrap();
            assert!((u - 64.0).abs() < 1e-9 && (v - 64.0).abs() < 1e-9);
        }
    }

    #[test]
    fn sagittal_pose_is_the_spec_matrix() {
        let rows = Camera::new(View::Sagittal, View::Sagittal.pose(50.0), 1.0, 1, 1).camera_to_world;
        assert_eq!(rows, [[0.0, 0.0, 1.0, 50.0], [1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]);
        let cor = Camera::new(View::Coronal, View::Coronal.pose(50.0), 1.0, 1, 1).camera_to_world;
        assert_eq!(cor, [[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 50.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]);
    }

    #[test]
    fn rays_and_projection_agree() {
        let cam = Camera::new(View::Coronal, View::Coronal.pose(50.0), 900.0, 128, 128);
        for (i, j) in [(0, 0), (17, 100), (127, 127)] {
            let p = cam.eye() + cam.ray_dir(i, j) * 42.0;
            let (u, v) = cam.project(p).unwrap();
            assert!((u - (i as f64 + 0.5)).abs() < 1e-9 && (v - (j as f64 + 0.5)).abs() < 1e-9);
        }
    }

    #[test]
    fn fitted_focal_just_covers_the_box() {
        let poses: Vec<DMat4> = View::ALL.iter().map(|v| v.pose(50.0)).collect();
        let f = fit_focal_px(&poses, &PAPER_BOX, 128, 128);
        let inside = |f: f64| {
            poses.iter().all(|&p| {
                let cam = Camera::new(View::Axial, p, f, 128, 128);
                PAPER_BOX.corners().iter().all(|&c| {
                    let (u, v) = cam.project(c).unwrap();
                    (-1e-9..=128.0 + 1e-9).contains(&u) && (-1e-9..=128.0 + 1e-9).contains(&v)
                })
            })
        };
        assert!(inside(f) && !inside(f * 1.001), "f = {f}");
        assert!(f < 1280.0, "the paper's f = 1280 does not cover the box (SPEC)");
    }

    #[test]
    fn slab_intersection_gives_chord_length() {
        let b = Aabb { min: [-1.0, -1.0, -1.0], max: [1.0, 2.0, 3.0] };
        let (t0, t1) = b.intersect(DVec3::new(-5.0, 0.0, 0.0), DVec3::X).unwrap();
        assert!((t0 - 4.0).abs() < 1e-12 && (t1 - 6.0).abs() < 1e-12);
        assert!(b.intersect(DVec3::new(-5.0, 5.0, 0.0), DVec3::X).is_none());
    }
}
