//! `drr`: Beer–Lambert radiographs of three views of the CT (SPEC §3 drr).
//!
//! Inputs: `hu/ct_unit` (v ∈ [0, 1]), and from `ingest` the ground truth (for
//! `roi_center = "nodule"`) or the HU volume (for `"lungs"`). Outputs: `drr_coronal.exr`,
//! `drr_sagittal.exr`, `drr_axial.exr` (float32 `I/I0`, pose, focal, size and units in the
//! header) with `.png` previews, and `cameras.json`: the scene frame, box and the *nominal*
//! cameras the train stage must use — never recomputed downstream. Degradations (noise,
//! pose error, non-orthogonal views) are off by default; a pose error moves only the cameras
//! the images are rendered with, while `cameras.json` keeps the nominal poses.

use crate::artifacts::{drr_image, drr_preview, CAMERAS, CT_HU, CT_UNIT, GROUND_TRUTH};
use crate::engine::{Context, Output, Stage};
use crate::formats::exr_image::{self, DrrImage};
use crate::formats::png;
use crate::geometry::{fit_focal_px, orbit, Aabb, Camera, SceneFrame, View};
use crate::gpu::{self, Backend};
use crate::kernels::lung_field::{lung_field_centroid_mm, LUNG_THRESHOLD_HU};
use crate::kernels::raymarch::{render, VolumeField};
use crate::stage::ingest::truth::GroundTruth;
use crate::volume::Volume;
use anyhow::bail;
use glam::{DMat4, DVec3};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal, Poisson};
use serde::{Deserialize, Serialize};

pub const VERSION: u32 = 2;

/// `focal_px`: a number of pixels, or `"fit"`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum Focal {
    Px(f64),
    Mode(FocalMode),
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum FocalMode {
    /// The largest focal length whose images cover the box's projection in every view.
    Fit,
}

/// `roi_center`: the scene origin, in patient space.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum RoiCenter {
    /// Explicit `[x, y, z]` in patient mm.
    Mm([f64; 3]),
    Mode(RoiMode),
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum RoiMode {
    /// Centroid of the target nodule's consensus (semi-assisted: the paper's setting).
    Nodule,
    /// Centroid of the lung field found by thresholding the CT (blind).
    Lungs,
    /// Boxes tiling the lungs (blind): `[drr.tiles] counts` boxes on a grid `step_mm` apart, centred on
    /// the lung field's centroid. Each is a replica with its own views, fit and grid; `select`
    /// compares them ([`crate::stage::select`]).
    Tiles,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    pub width_px: usize,
    pub height_px: usize,
    pub focal_px: Focal,
    /// Eye distance from the scene origin, scene units.
    pub distance: f64,
    pub mm_per_unit: f64,
    pub aabb_min: [f64; 3],
    pub aabb_max: [f64; 3],
    pub roi_center: RoiCenter,
    /// Attenuation per scene unit of v = 1: `mu = v · attenuation_scale`.
    pub attenuation_scale: f64,
    /// Poisson quantum noise: photons per pixel of the unattenuated beam (0: off).
    pub photons: f64,
    /// Additive Gaussian detector noise, standard deviation in units of I0 (0: off).
    pub detector_noise: f64,
    /// Pose error of the rendering cameras: rotation (degrees, about a random axis through
    /// the scene origin) and translation (mm, in a random direction). 0: off.
    pub pose_error_deg: f64,
    pub pose_error_mm: f64,
    /// Non-orthogonal views: the coronal and sagittal cameras orbit the superior (z) axis, the
    /// axial camera the x axis, by these angles (degrees). Part of the nominal geometry.
    pub view_angle_offsets_deg: [f64; 3],
    /// Seed of the noise and pose errors.
    pub seed: u64,
    /// Where the rays are marched: "cpu", "gpu" or "auto" (resolved before the cache key).
    pub backend: Backend,
    /// `roi_center = "tiles"`: the grid of boxes.
    pub tiles: TileParams,
}

/// `[drr.tiles]`: the boxes of `roi_center = "tiles"`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TileParams {
    /// How many boxes along x, y and z.
    pub counts: [usize; 3],
    /// The distance between neighbouring boxes' centres (mm).
    pub step_mm: [f64; 3],
}

impl Default for TileParams {
    fn default() -> Self {
        TileParams { counts: [2, 3, 3], step_mm: [132.0, 74.0, 120.0] }
    }
}

impl Default for Params {
    fn default() -> Self {
        Params {
            width_px: 256,
            height_px: 256,
            focal_px: Focal::Mode(FocalMode::Fit),
            distance: 50.0,
            mm_per_unit: 40.0,
            aabb_min: [-2.5, -1.5, -2.0],
            aabb_max: [3.5, 1.5, 1.5],
            roi_center: RoiCenter::Mode(RoiMode::Nodule),
            attenuation_scale: 1.0,
            photons: 0.0,
            detector_noise: 0.0,
            pose_error_deg: 0.0,
            pose_error_mm: 0.0,
            view_angle_offsets_deg: [0.0; 3],
            seed: 0,
            backend: Backend::Cpu,
            tiles: TileParams::default(),
        }
    }
}

impl Params {
    pub fn check(&self) -> anyhow::Result<()> {
        let positive = [
            ("width_px", self.width_px as f64),
            ("height_px", self.height_px as f64),
            ("distance", self.distance),
            ("mm_per_unit", self.mm_per_unit),
        ];
        for (key, v) in positive {
            if !(v.is_finite() && v > 0.0) {
                bail!("[drr] {key} must be positive (got {v})");
            }
        }
        if let Focal::Px(f) = self.focal_px {
            if !(f.is_finite() && f > 0.0) {
                bail!("[drr] focal_px must be \"fit\" or a positive number of pixels (got {f})");
            }
        }
        if (0..3).any(|a| self.aabb_min[a] >= self.aabb_max[a]) {
            bail!("[drr] aabb_min must be below aabb_max on every axis");
        }
        let non_negative = [
            ("attenuation_scale", self.attenuation_scale),
            ("photons", self.photons),
            ("detector_noise", self.detector_noise),
            ("pose_error_deg", self.pose_error_deg),
            ("pose_error_mm", self.pose_error_mm),
        ];
        for (key, v) in non_negative {
            if !(v.is_finite() && v >= 0.0) {
                bail!("[drr] {key} must be ≥ 0 (got {v})");
            }
        }
        if self.tiles.counts.contains(&0) {
            bail!("[drr.tiles] counts must be at least 1 along every axis (got {:?})", self.tiles.counts);
        }
        if self.tiles.step_mm.iter().any(|s| !(s.is_finite() && *s > 0.0)) {
            bail!("[drr.tiles] step_mm must be positive on every axis (got {:?})", self.tiles.step_mm);
        }
        if self.aabb_min.iter().chain(&self.aabb_max).any(|&c| c.abs() >= self.distance) {
            bail!("[drr] the cameras (distance {}) must stay outside the box", self.distance);
        }
        Ok(())
    }

    pub fn aabb(&self) -> Aabb {
        Aabb { min: self.aabb_min, max: self.aabb_max }
    }

    fn tiling(&self) -> bool {
        self.roi_center == RoiCenter::Mode(RoiMode::Tiles)
    }

    /// How many boxes tile the lungs (`roi_center = "tiles"`), x slowest, z fastest.
    pub fn tile_count(&self) -> usize {
        self.tiles.counts.iter().product()
    }

    /// The scene origin of box `tile` whose grid is centred on `lungs_mm`: the box's own
    /// centre lies `(i − (n − 1)/2) · step_mm` from it on each axis.
    pub fn tile_origin_mm(&self, lungs_mm: [f64; 3], tile: usize) -> [f64; 3] {
        let TileParams { counts, step_mm } = self.tiles;
        let [_, ny, nz] = counts;
        let index = [tile / (ny * nz), (tile / nz) % ny, tile % nz];
        std::array::from_fn(|a| {
            let box_centre = (self.aabb_min[a] + self.aabb_max[a]) / 2.0 * self.mm_per_unit;
            let offset = (index[a] as f64 - (counts[a] as f64 - 1.0) / 2.0) * step_mm[a];
            lungs_mm[a] + offset - box_centre
        })
    }
}

/// What `cameras.json` holds: everything the train stage needs to cast the same rays.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct CameraSet {
    pub frame: SceneFrame,
    /// How `frame.roi_center_mm` was chosen: "nodule", "lungs", "explicit" or "tileNN" (the box
    /// of a tiling).
    pub roi_center_mode: String,
    pub aabb: Aabb,
    /// The nominal cameras, in the order coronal, sagittal, axial.
    pub cameras: Vec<Camera>,
    /// The cameras the images were actually rendered with, when a pose error was applied.
    pub rendered_with: Option<Vec<Camera>>,
    pub attenuation_scale: f64,
}

impl CameraSet {
    /// Each camera's DRR (`drr_<view>.exr`), in camera order, read by `read` and checked against
    /// its camera's size.
    pub fn read_images(&self, mut read: impl FnMut(&str) -> anyhow::Result<Vec<u8>>) -> anyhow::Result<Vec<DrrImage>> {
        use anyhow::Context as _;
        self.cameras
            .iter()
            .map(|camera| {
                let name = drr_image(camera.view.name());
                let image = exr_image::decode(&read(&name)?).with_context(|| format!("decoding {name}"))?;
                if (image.width, image.height) != (camera.width, camera.height) {
                    anyhow::bail!(
                        "{name} is {} × {} pixels, its camera in {} {} × {}: rerun with --force drr",
                        image.width,
                        image.height,
                        CAMERAS.file,
                        camera.width,
                        camera.height
                    );
                }
                Ok(image)
            })
            .collect()
    }

    /// A published view set: `dir`'s `cameras.json` and its `drr_<view>.exr` pixels in camera
    /// order (how the benchmarks read a patient's folder of `out_dir`).
    pub fn read_published(dir: &std::path::Path) -> anyhow::Result<(CameraSet, Vec<Vec<f32>>)> {
        use anyhow::Context as _;
        let read =
            |name: &str| std::fs::read(dir.join(name)).with_context(|| format!("reading {}", dir.join(name).display()));
        let set: CameraSet = serde_json::from_slice(&read(CAMERAS.file)?)
            .with_context(|| format!("parsing {}", dir.join(CAMERAS.file).display()))?;
        let images = set.read_images(read)?.into_iter().map(|image| image.pixels).collect();
        Ok((set, images))
    }
}

pub struct Drr {
    pub params: Params,
}

impl Stage for Drr {
    fn name(&self) -> &'static str {
        "drr"
    }
    fn version(&self) -> u32 {
        VERSION
    }
    fn inputs(&self) -> &'static [&'static str] {
        &["ingest", "hu"]
    }
    fn params(&self) -> serde_json::Value {
        let backend = gpu::resolve(self.params.backend, "[drr]");
        let mut json = super::params_json(&Params { backend, ..self.params.clone() });
        // The boxes' grid is read only by a tiling.
        if !self.params.tiling() {
            json.as_object_mut().expect("params are a table").remove("tiles");
        }
        json
    }
    /// `roi_center = "tiles"` fans each patient out into its boxes.
    fn replica_names(&self) -> Vec<String> {
        if !self.params.tiling() {
            return vec![];
        }
        (0..self.params.tile_count()).map(|t| format!("tile{t:02}")).collect()
    }
    /// The normalised CT, and from ingest only what the ROI centre needs.
    fn reads(&self, stage: &str, output: &str) -> bool {
        match (stage, self.params.roi_center) {
            ("hu", _) => CT_UNIT.holds(output),
            (_, RoiCenter::Mode(RoiMode::Nodule)) => output == GROUND_TRUTH.file,
            (_, RoiCenter::Mode(RoiMode::Lungs | RoiMode::Tiles)) => CT_HU.holds(output),
            (_, RoiCenter::Mm(_)) => false,
        }
    }
    fn run(&self, ctx: &Context) -> anyhow::Result<Vec<Output>> {
        let ct_unit: Volume<f32> = super::read_volume(ctx, CT_UNIT)?;
        let (roi_center_mm, mode) = self.roi_center(ctx)?;
        let (set, images) = render_views(&self.params, &ct_unit, roi_center_mm, &mode)?;
        let mut outputs = vec![Output::new(CAMERAS.file, serde_json::to_vec_pretty(&set)?)];
        for (camera, pixels) in set.cameras.iter().zip(images) {
            let view = camera.view.name();
            let image = DrrImage {
                width: camera.width,
                height: camera.height,
                pixels,
                camera_to_world: camera.camera_to_world.map(|r| r.map(|x| x as f32)),
                focal_px: camera.focal_px as f32,
                units: format!("I/I0 (Beer-Lambert); scene units of {} mm", set.frame.mm_per_unit),
                view: view.to_string(),
            };
            outputs.push(Output::new(drr_preview(view), preview(&image)));
            outputs.push(Output::new(drr_image(view), exr_image::encode(&image)?));
        }
        Ok(outputs)
    }
}

impl Drr {
    /// The scene origin in patient mm, and how it was chosen.
    fn roi_center(&self, ctx: &Context) -> anyhow::Result<([f64; 3], String)> {
        match self.params.roi_center {
            RoiCenter::Mm(c) => Ok((c, "explicit".into())),
            RoiCenter::Mode(RoiMode::Nodule) => {
                let truth: GroundTruth = super::read_json(ctx, GROUND_TRUTH)?;
                let centre = truth.target.and_then(|t| truth.nodules[t].centroid_mm);
                match centre {
                    Some(c) => Ok((c, "nodule".into())),
                    None => bail!(
                        "[drr] roi_center = \"nodule\" needs a target nodule, and patient {} has no annotated \
                         nodule: use roi_center = \"lungs\" or an explicit [x, y, z] in mm",
                        ctx.patient()
                    ),
                }
            }
            RoiCenter::Mode(mode @ (RoiMode::Lungs | RoiMode::Tiles)) => {
                let ct_hu: Volume<i16> = super::read_volume(ctx, CT_HU)?;
                let Some(lungs) = lung_field_centroid_mm(&ct_hu, LUNG_THRESHOLD_HU) else {
                    let name = if mode == RoiMode::Lungs { "lungs" } else { "tiles" };
                    bail!("[drr] roi_center = \"{name}\": no air enclosed by the body below {LUNG_THRESHOLD_HU} HU")
                };
                match (mode, ctx.replica()) {
                    (RoiMode::Tiles, Some(tile)) => {
                        Ok((self.params.tile_origin_mm(lungs, tile), format!("tile{tile:02}")))
                    }
                    (RoiMode::Tiles, None) => {
                        bail!("[drr] roi_center = \"tiles\" runs once per box, and no box was given")
                    }
                    _ => Ok((lungs, "lungs".into())),
                }
            }
        }
    }
}

/// The whole stage as a pure function: cameras and the three images (coronal, sagittal, axial).
pub fn render_views(
    params: &Params,
    ct_unit: &Volume<f32>,
    roi_center_mm: [f64; 3],
    roi_center_mode: &str,
) -> anyhow::Result<(CameraSet, Vec<Vec<f32>>)> {
    let frame = SceneFrame { roi_center_mm, mm_per_unit: params.mm_per_unit };
    let aabb = params.aabb();
    let poses: Vec<DMat4> = View::ALL.iter().map(|&v| nominal_pose(params, v)).collect();
    let focal = match params.focal_px {
        Focal::Px(f) => f,
        Focal::Mode(FocalMode::Fit) => fit_focal_px(&poses, &aabb, params.width_px, params.height_px),
    };
    let camera = |view: View, pose: DMat4| Camera::new(view, pose, focal, params.width_px, params.height_px);
    let cameras: Vec<Camera> = View::ALL.iter().zip(&poses).map(|(&v, &p)| camera(v, p)).collect();
    let perturbed = params.pose_error_deg > 0.0 || params.pose_error_mm > 0.0;
    let rendered: Vec<Camera> = if perturbed {
        View::ALL.iter().zip(&poses).map(|(&v, &p)| camera(v, pose_error(params, v, p))).collect()
    } else {
        cameras.clone()
    };
    let field = VolumeField::new(ct_unit, &frame);
    let mut images: Vec<Vec<f32>> = match gpu::resolve(params.backend, "[drr]") {
        Backend::Gpu => {
            let device = gpu::require("[drr]")?;
            gpu::drr_march::render(&device, &field, &aabb, &rendered, params.attenuation_scale)?
        }
        _ => rendered.iter().map(|cam| render(&field, &aabb, cam, f64::INFINITY, params.attenuation_scale)).collect(),
    };
    for (cam, pixels) in rendered.iter().zip(&mut images) {
        degrade(params, cam.view, pixels);
    }
    let set = CameraSet {
        frame,
        roi_center_mode: roi_center_mode.to_string(),
        aabb,
        cameras,
        rendered_with: perturbed.then_some(rendered),
        attenuation_scale: params.attenuation_scale,
    };
    Ok((set, images))
}

/// The SPEC pose of `view`, orbited by its configured angle offset.
fn nominal_pose(params: &Params, view: View) -> DMat4 {
    let (axis, offset_deg) = match view {
        View::Coronal => (DVec3::Z, params.view_angle_offsets_deg[0]),
        View::Sagittal => (DVec3::Z, params.view_angle_offsets_deg[1]),
        View::Axial => (DVec3::X, params.view_angle_offsets_deg[2]),
    };
    orbit(view.pose(params.distance), axis, offset_deg.to_radians())
}

/// A random stream per (seed, purpose, view): results never depend on evaluation order.
fn rng(params: &Params, purpose: &str, view: View) -> ChaCha8Rng {
    let hash = blake3::hash(format!("{}/{purpose}/{}", params.seed, view.name()).as_bytes());
    ChaCha8Rng::from_seed(*hash.as_bytes())
}

/// `pose` rotated by `pose_error_deg` about a random axis through the origin, then shifted by
/// `pose_error_mm` in a random direction.
fn pose_error(params: &Params, view: View, pose: DMat4) -> DMat4 {
    let mut rng = rng(params, "pose", view);
    let mut unit = || {
        let normal = Normal::new(0.0, 1.0).expect("unit normal");
        DVec3::new(normal.sample(&mut rng), normal.sample(&mut rng), normal.sample(&mut rng)).normalize()
    };
    let (axis, shift) = (unit(), unit());
    let rotated = orbit(pose, axis, params.pose_error_deg.to_radians());
    DMat4::from_translation(shift * params.pose_error_mm / params.mm_per_unit) * rotated
}

/// Poisson quantum noise (`photons` per unattenuated pixel), then Gaussian detector noise.
fn degrade(params: &Params, view: View, pixels: &mut [f32]) {
    if params.photons > 0.0 {
        let mut rng = rng(params, "quantum", view);
        for p in pixels.iter_mut() {
            let mean = params.photons * f64::from(*p);
            let counts = if mean > 0.0 { Poisson::new(mean).expect("positive mean").sample(&mut rng) } else { 0.0 };
            *p = (counts / params.photons) as f32;
        }
    }
    if params.detector_noise > 0.0 {
        let mut rng = rng(params, "detector", view);
        let normal = Normal::new(0.0, params.detector_noise).expect("positive sd");
        for p in pixels.iter_mut() {
            *p += normal.sample(&mut rng) as f32;
        }
    }
}

/// A radiograph-style preview: attenuation `−ln I` (dense = white), windowed to its range.
fn preview(image: &DrrImage) -> Vec<u8> {
    let data: Vec<f32> = image.pixels.iter().map(|&i| -(i.max(1e-6)).ln()).collect();
    let img = png::Image { width: image.width, height: image.height, pixel_mm: 1.0, data };
    png::image_png(&img, png::Window::spanning(&img))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{Aabb, SceneFrame, View};

    #[test]
    fn a_drr_of_another_size_than_its_camera_is_an_error_naming_the_file() {
        let camera = Camera::new(View::Coronal, glam::DMat4::IDENTITY, 10.0, 3, 2);
        let set = CameraSet {
            frame: SceneFrame { roi_center_mm: [0.0; 3], mm_per_unit: 40.0 },
            roi_center_mode: "nodule".into(),
            aabb: Aabb { min: [-1.0; 3], max: [1.0; 3] },
            cameras: vec![camera],
            rendered_with: None,
            attenuation_scale: 1.0,
        };
        let image = |width: usize, height: usize| DrrImage {
            width,
            height,
            pixels: vec![0.5; width * height],
            camera_to_world: [[0.0; 4]; 4],
            focal_px: 10.0,
            units: String::new(),
            view: "coronal".into(),
        };
        let read_as = |w, h| {
            move |name: &str| {
                assert_eq!(name, "drr_coronal.exr");
                Ok(exr_image::encode(&image(w, h))?)
            }
        };
        let images = set.read_images(read_as(3, 2)).unwrap();
        assert_eq!(images[0].pixels, vec![0.5; 6]);
        let e = set.read_images(read_as(2, 2)).unwrap_err().to_string();
        assert!(e.contains("drr_coronal.exr is 2 × 2") && e.contains("--force drr"), "{e}");
    }
}
