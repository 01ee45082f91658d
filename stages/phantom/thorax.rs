//! The anatomy of the synthetic thorax. Owns every organ's shape, position and HU, drawn in
//! the reference frame of `super::frame` (X patient-left, Y posterior, Z superior, mm;
//! Z = 0…330 is the scanned range) and painted slice by slice, back to front, each layer
//! replacing the fraction of a voxel it covers:
//!
//! table → body wall (skin, subcutaneous fat, muscle) → ribs, costal cartilages and
//! scapulae → lungs (textured parenchyma) → pulmonary vessel trees → upper abdomen under the
//! diaphragm (liver, stomach with an air–fluid level, spleen) → mediastinal fat → heart →
//! great vessels in their fat → oesophagus → airways (walls, then air) → sternum →
//! clavicles and rib necks → spine (discs, vertebral bodies, arches, processes, canal).
//!
//! Sizes follow an average adult chest CT: body ≈ 344 × 262 mm at mid-chest, lungs from the
//! apices (10 mm below the top of the scan) to the posterior costophrenic recesses (12 mm
//! above its bottom), the right diaphragm dome higher than the left, the heart left-anterior
//! on the diaphragm, the carina at ≈ 64 % of the height.

use super::canvas::SliceCanvas;
use super::frame::{Aabb, BodyFrame, IndexMap};
use super::noise;
use super::shapes::{capsule_sd, ellipsoid_sd, interval_sd, occupancy, oval_sd, Mix, Profile, Sample, V3};
use super::tubes::{capsules_from_polylines, Capsule, Polyline, TubeSet};
use super::vessels::{grow_tree, TreeSpec};
use super::{PhantomParams, Tissue};
use crate::volume::{Geometry, Volume};
use glam::Vec3;
use rayon::prelude::*;
use std::f32::consts::PI;

/// Attenuation of each material, HU (unenhanced CT).
mod hu {
    pub const AIR: f32 = -1000.0;
    pub const SKIN: f32 = 30.0;
    pub const FAT: f32 = -100.0;
    pub const MUSCLE: f32 = 45.0;
    pub const BLOOD: f32 = 40.0;
    pub const CORTICAL_BONE: f32 = 700.0;
    pub const CANCELLOUS_BONE: f32 = 230.0;
    /// Thin bone (processes, scapular blade, clavicle): cortex and marrow within a voxel.
    pub const THIN_BONE: f32 = 450.0;
    pub const CARTILAGE: f32 = 120.0;
    pub const DISC: f32 = 90.0;
    pub const SPINAL_CANAL: f32 = 25.0;
    pub const LIVER: f32 = 60.0;
    pub const SPLEEN: f32 = 50.0;
    pub const STOMACH_FLUID: f32 = 15.0;
    pub const ABDOMEN: f32 = 20.0;
    pub const AIRWAY_WALL: f32 = 60.0;
    pub const TABLE_SHELL: f32 = 200.0;
    pub const TABLE_CORE: f32 = -600.0;
}

// ---- Body wall --------------------------------------------------------------------------

const BODY_CENTRE_Y: f32 = 12.0;
const BODY_HALF_WIDTH: Profile =
    Profile(&[(0.0, 162.0), (60.0, 167.0), (150.0, 172.0), (230.0, 170.0), (285.0, 158.0), (330.0, 142.0)]);
const BODY_HALF_DEPTH_ANTERIOR: Profile =
    Profile(&[(0.0, 126.0), (80.0, 130.0), (180.0, 130.0), (260.0, 122.0), (330.0, 106.0)]);
/// The back lies flat on the table: constant depth, squarer outline.
const BODY_HALF_DEPTH_POSTERIOR: f32 = 132.0;
const SKIN_MM: f32 = 1.5;
const SUBCUTANEOUS_FAT_MM: Profile = Profile(&[(0.0, 18.0), (120.0, 11.0), (330.0, 9.0)]);

fn body_sd(r: V3) -> f32 {
    let [x, y, z] = r;
    let dy = y - BODY_CENTRE_Y;
    let (depth, squareness) =
        if dy < 0.0 { (BODY_HALF_DEPTH_ANTERIOR.at(z), 0.25) } else { (BODY_HALF_DEPTH_POSTERIOR, 0.6) };
    oval_sd(x, dy, BODY_HALF_WIDTH.at(z), depth, squareness)
}

// ---- Thoracic cavity, lungs, diaphragm ---------------------------------------------------

/// The inner surface of the chest wall (parietal pleura), before the mediastinum, spine,
/// diaphragm and apices carve the lungs out of it.
const CAVITY_CENTRE_Y: f32 = 8.0;
const CAVITY_HALF_WIDTH: Profile = Profile(&[
    (0.0, 140.0),
    (90.0, 147.0),
    (170.0, 148.0),
    (230.0, 140.0),
    (275.0, 121.0),
    (310.0, 98.0),
    (330.0, 84.0),
]);
const CAVITY_HALF_DEPTH_ANTERIOR: Profile =
    Profile(&[(0.0, 98.0), (120.0, 102.0), (200.0, 99.0), (260.0, 90.0), (330.0, 64.0)]);
const CAVITY_HALF_DEPTH_POSTERIOR: Profile = Profile(&[(0.0, 108.0), (160.0, 108.0), (260.0, 102.0), (330.0, 88.0)]);
const CAVITY_SQUARENESS: f32 = 0.5;

fn cavity_sd(r: V3) -> f32 {
    let [x, y, z] = r;
    let dy = y - CAVITY_CENTRE_Y;
    let depth = if dy < 0.0 { CAVITY_HALF_DEPTH_ANTERIOR.at(z) } else { CAVITY_HALF_DEPTH_POSTERIOR.at(z) };
    oval_sd(x, dy, CAVITY_HALF_WIDTH.at(z), depth, CAVITY_SQUARENESS)
}

/// Whether `r` lies inside the ellipse with the cavity's half-axes, less `margin_mm`: a
/// cheap (no square root) sufficient test for being inside the cavity, since the oval is
/// at least as full as that ellipse.
fn inside_cavity_ellipse(r: V3, margin_mm: f32) -> bool {
    let [x, y, z] = r;
    let dy = y - CAVITY_CENTRE_Y;
    let depth = if dy < 0.0 { CAVITY_HALF_DEPTH_ANTERIOR.at(z) } else { CAVITY_HALF_DEPTH_POSTERIOR.at(z) };
    let (u, v) = (x / (CAVITY_HALF_WIDTH.at(z) - margin_mm), dy / (depth - margin_mm));
    u * u + v * v < 1.0
}

/// Angle around the cavity centre from the posterior midline (0) to the anterior one (π),
/// the same on both sides.
fn wall_angle(x: f32, y: f32) -> f32 {
    x.abs().atan2(y - CAVITY_CENTRE_Y)
}

/// Diaphragm domes `(x, y, top z)`: right higher (liver below), left lower (heart above).
const DOMES: [(f32, f32, f32); 2] = [(-55.0, -5.0, 88.0), (55.0, 0.0, 75.0)];
const DOME_RADIUS_X: f32 = 100.0;
/// The domes fall faster toward the back: the posterior recesses are the lowest lung.
const DOME_RADIUS_ANTERIOR: f32 = 100.0;
const DOME_RADIUS_POSTERIOR: f32 = 70.0;
/// Lowest point of the costophrenic recesses.
const RECESS_Z: f32 = 12.0;

/// Height of the diaphragm's upper surface above (x, y).
fn diaphragm_z(x: f32, y: f32) -> f32 {
    DOMES
        .iter()
        .map(|&(cx, cy, top)| {
            let (dx, dy) = (x - cx, y - cy);
            let ry = if dy > 0.0 { DOME_RADIUS_POSTERIOR } else { DOME_RADIUS_ANTERIOR };
            top - dx * dx / (2.0 * DOME_RADIUS_X) - dy * dy / (2.0 * ry)
        })
        .fold(RECESS_Z, f32::max)
}

/// Lung apices: paraboloid caps over (±x, y), top at z. The caps fall slowly toward the
/// front (the upper lobes reach the clavicles anteriorly) and faster sideways and backward.
const APEX: (f32, f32, f32) = (48.0, 28.0, 320.0);
const APEX_RADIUS_X: f32 = 60.0;
const APEX_RADIUS_ANTERIOR: f32 = 100.0;
const APEX_RADIUS_POSTERIOR: f32 = 50.0;

fn apex_z(x: f32, y: f32) -> f32 {
    let (dx, dy) = (x.abs() - APEX.0, y - APEX.1);
    let ry = if dy < 0.0 { APEX_RADIUS_ANTERIOR } else { APEX_RADIUS_POSTERIOR };
    APEX.2 - dx * dx / (2.0 * APEX_RADIUS_X) - dy * dy / (2.0 * ry)
}

/// Beyond this (mm outside a surface) a voxel's occupancy is 0 at any pixel size used here,
/// so signed distances may stop being refined.
const CLEARLY_OUTSIDE_MM: f32 = 5.0;
/// Structures farther than this cannot change any decision taken on signed distances (the
/// deepest threshold is a vessel's radius plus 1 mm).
const FAR_MM: f32 = 25.0;

/// Lung parenchyma: denser toward the back (gravity), HU per mm of y.
const LUNG_GRAVITY_HU_PER_MM: f32 = 0.25;
/// Size of the largest texture features (lobules, small vessels below the tree's reach), mm.
const LUNG_TEXTURE_PERIOD_MM: f32 = 6.0;

// ---- Mediastinum, heart ------------------------------------------------------------------

const MEDIASTINUM_X: f32 = 2.0;
/// Half-width of the fat band between the lungs at its widest: narrow at the top (trachea,
/// oesophagus), wider at the great vessels, narrow again behind the heart (which is painted
/// on its own). The vessels' fat rims round it out.
const MEDIASTINUM_HALF_WIDTH: Profile =
    Profile(&[(0.0, 22.0), (70.0, 18.0), (185.0, 16.0), (200.0, 24.0), (240.0, 24.0), (262.0, 15.0), (330.0, 13.0)]);

/// Fraction of that half-width by depth (y): the lungs nearly meet behind the sternum
/// (anterior junction) and the band narrows again toward the spine.
const MEDIASTINUM_DEPTH_PROFILE: Profile =
    Profile(&[(-90.0, 0.3), (-60.0, 0.55), (-35.0, 1.0), (15.0, 1.0), (40.0, 0.75)]);

fn mediastinum_half_width(y: f32, z: f32) -> f32 {
    MEDIASTINUM_HALF_WIDTH.at(z) * MEDIASTINUM_DEPTH_PROFILE.at(y)
}

const HEART_CENTRE: V3 = [16.0, -24.0, 120.0];
/// Half-axes along the long axis (toward the apex), across it, and vertically.
const HEART_SEMI_AXES: V3 = [60.0, 46.0, 54.0];
/// The long axis turns this far from +x toward anterior.
const HEART_AXIS_ANGLE: f32 = 40.0 * PI / 180.0;
const PERICARDIAL_FAT_MM: f32 = 3.0;
/// The heart varies less between patients than the body does: its size in patient mm
/// grows only as (body scale)^¼, so in the reference frame it is scaled by (body scale)^−¾,
/// within these bounds (a large FOV means more fat and a wider chest, not a proportionally
/// larger heart).
const HEART_SCALE_RANGE: (f64, f64) = (0.8, 1.2);

fn heart_scale(body_scale: f64) -> f32 {
    body_scale.powf(-0.75).clamp(HEART_SCALE_RANGE.0, HEART_SCALE_RANGE.1) as f32
}

// ---- Spine ------------------------------------------------------------------------------

const VERTEBRA_Y: f32 = 48.0;
const VERTEBRA_PITCH_MM: f32 = 25.0;
/// Centre of the highest vertebral body in the scan.
const VERTEBRA_TOP_Z: f32 = 318.0;
const VERTEBRAL_BODY_HALF_HEIGHT: f32 = 10.0;
const CANAL_RADIUS_MM: f32 = 8.0;
const VERTEBRAL_CORTEX_MM: f32 = 1.6;

/// Half-width and half-depth of the vertebral bodies: larger lower down.
fn vertebral_body_axes(z: f32) -> (f32, f32) {
    let below_top = (330.0 - z).max(0.0);
    (16.0 + 0.022 * below_top, 13.0 + 0.014 * below_top)
}

fn canal_centre_y(z: f32) -> f32 {
    VERTEBRA_Y + vertebral_body_axes(z).1 + 9.0
}

/// The spine and its processes with a margin: the lungs wrap around it.
fn spine_envelope_sd(r: V3) -> f32 {
    let [x, y, z] = r;
    let (a, b) = vertebral_body_axes(z);
    let body = oval_sd(x, y - VERTEBRA_Y, a + 5.0, b + 5.0, 0.3);
    let arch = oval_sd(x, y - canal_centre_y(z) - 6.0, 38.0, 22.0, 0.3);
    body.min(arch)
}

// ---- Ribs, sternum, scapulae -------------------------------------------------------------

const RIB_PAIRS: usize = 12;
/// Height of the first rib's posterior end; the next ones follow every `RIB_PITCH_MM`.
const RIB1_Z: f32 = 300.0;
const RIB_PITCH_MM: f32 = 23.5;
/// Wall angle at which a rib leaves its neck (posterior) and starts following the wall.
const RIB_START_ANGLE: f32 = 0.38;
/// Distance of the rib's axis outside the pleura.
const RIB_OFFSET_MM: f32 = 7.0;
const RIB_CORTEX_MM: f32 = 1.2;

struct RibShape {
    /// Wall angle where bone turns into costal cartilage, and where the cartilage ends.
    bone_end: f32,
    cartilage_end: f32,
    /// How far the rib falls from its neck to its lowest point (front of the side wall),
    /// and how far its costal cartilage then climbs toward the sternum.
    drop_mm: f32,
    rise_mm: f32,
    half_thickness_mm: f32,
    half_height_mm: f32,
}

fn rib_shape(n: usize) -> RibShape {
    const BONE_END: [f32; RIB_PAIRS] = [2.2, 2.35, 2.35, 2.35, 2.35, 2.35, 2.3, 2.25, 2.15, 2.05, 1.65, 1.25];
    let bone_end = BONE_END[n];
    let drop_mm = match n {
        0 => 45.0,
        1 => 55.0,
        _ => 80.0,
    };
    // Ribs 1–7 reach the sternum (their cartilages land on it top to bottom), 8–10 the
    // costal margin, 11–12 float.
    let (cartilage_end, rise_mm) = match n {
        0..=6 => {
            let lowest = RIB1_Z - n as f32 * RIB_PITCH_MM - drop_mm;
            (2.98, 272.0 - 26.0 * n as f32 - lowest)
        }
        7..=9 => (2.6, 30.0),
        _ => (bone_end, 0.0),
    };
    RibShape {
        bone_end,
        cartilage_end,
        drop_mm,
        rise_mm,
        half_thickness_mm: if n == 0 { 4.5 } else { 3.3 },
        half_height_mm: if n == 0 { 8.0 } else { 6.0 },
    }
}

fn smoothstep(lo: f32, hi: f32, x: f32) -> f32 {
    let s = ((x - lo) / (hi - lo)).clamp(0.0, 1.0);
    s * s * (3.0 - 2.0 * s)
}

/// Height of rib `n`'s axis at wall angle `angle`: sloping gently down from the neck,
/// falling steeply along the side wall, its cartilage climbing back toward the front.
fn rib_axis_z(n: usize, angle: f32) -> f32 {
    let shape = rib_shape(n);
    let t = (angle - RIB_START_ANGLE) / (PI - RIB_START_ANGLE);
    let fall = 0.3 * (t / 0.72).clamp(0.0, 1.0) + 0.7 * smoothstep(0.1, 0.72, t);
    RIB1_Z - n as f32 * RIB_PITCH_MM - shape.drop_mm * fall + shape.rise_mm * smoothstep(0.72, 1.0, t)
}

const STERNUM_Z: (f32, f32) = (95.0, 292.0);
const STERNUM_HALF_WIDTH: Profile = Profile(&[(95.0, 9.0), (120.0, 12.0), (250.0, 14.0), (262.0, 24.0), (292.0, 26.0)]);
const STERNUM_HALF_DEPTH: f32 = 6.5;
/// Depth of the sternum's centre below the anterior skin.
const STERNUM_DEPTH_MM: f32 = 19.0;

const SCAPULA_Z: (f32, f32) = (165.0, 305.0);
/// Blade distance outside the pleura and half-thickness.
const SCAPULA_OFFSET_MM: f32 = 17.0;
const SCAPULA_HALF_THICKNESS_MM: f32 = 2.5;

// ---- Abdomen -----------------------------------------------------------------------------

const STOMACH_CENTRE: V3 = [58.0, -18.0, 38.0];
const STOMACH_SEMI_AXES: V3 = [40.0, 36.0, 40.0];
/// Supine: gas floats anterior of this y, fluid lies behind it.
const STOMACH_GAS_LEVEL_Y: f32 = -32.0;
const SPLEEN_CENTRE: V3 = [80.0, 62.0, 45.0];
const SPLEEN_SEMI_AXES: V3 = [26.0, 40.0, 36.0];
const DIAPHRAGM_MM: f32 = 5.0;

// ---- Table -------------------------------------------------------------------------------

const TABLE_TOP_Y: f32 = 147.0;
/// The tabletop curves up at the sides.
const TABLE_CURVE_RADIUS_MM: f32 = 900.0;
const TABLE_THICKNESS_MM: f32 = 40.0;
const TABLE_HALF_WIDTH_MM: f32 = 235.0;
const TABLE_SHELL_MM: f32 = 2.5;

// ---- Tubes (reference frame: centre, radius) ----------------------------------------------

const AORTA: &Polyline = &[
    ([-2.0, -22.0, 160.0], 14.0),
    ([-4.0, -22.0, 222.0], 15.0),
    ([4.0, -12.0, 238.0], 13.0),
    ([18.0, 6.0, 238.0], 12.0),
    ([27.0, 24.0, 226.0], 12.0),
    ([25.0, 30.0, 200.0], 12.0),
    ([23.0, 32.0, 120.0], 11.5),
    ([14.0, 34.0, 40.0], 11.0),
    ([8.0, 34.0, -20.0], 10.0),
];
const PULMONARY_TRUNK: &Polyline = &[([20.0, -36.0, 165.0], 14.0), ([12.0, -16.0, 190.0], 13.0)];
const LEFT_PULMONARY_ARTERY: &Polyline =
    &[([12.0, -16.0, 190.0], 11.0), ([30.0, -4.0, 196.0], 10.0), ([46.0, 4.0, 194.0], 9.0)];
const RIGHT_PULMONARY_ARTERY: &Polyline =
    &[([12.0, -16.0, 190.0], 11.0), ([-14.0, -6.0, 192.0], 10.0), ([-44.0, 0.0, 189.0], 9.0)];
const SUPERIOR_VENA_CAVA: &Polyline = &[([-30.0, -12.0, 255.0], 9.0), ([-28.0, -10.0, 172.0], 10.0)];
const INFERIOR_VENA_CAVA: &Polyline = &[([-22.0, 8.0, -20.0], 11.0), ([-20.0, 2.0, 78.0], 12.0)];
const BRACHIOCEPHALIC_ARTERY: &Polyline = &[([-2.0, -16.0, 236.0], 7.0), ([-12.0, -10.0, 345.0], 6.0)];
const LEFT_CAROTID: &Polyline = &[([8.0, -10.0, 238.0], 4.5), ([10.0, -4.0, 345.0], 4.0)];
const LEFT_SUBCLAVIAN: &Polyline = &[([16.0, 2.0, 236.0], 5.0), ([18.0, 14.0, 300.0], 5.0), ([40.0, 16.0, 345.0], 5.0)];
const LEFT_BRACHIOCEPHALIC_VEIN: &Polyline =
    &[([40.0, -22.0, 300.0], 6.0), ([10.0, -26.0, 270.0], 6.5), ([-30.0, -12.0, 255.0], 8.0)];
const RIGHT_BRACHIOCEPHALIC_VEIN: &Polyline = &[([-40.0, -20.0, 310.0], 6.0), ([-30.0, -12.0, 255.0], 8.0)];
/// Fat around the great vessels, beyond their walls.
const VESSEL_FAT_MM: f32 = 3.0;

const OESOPHAGUS: &Polyline = &[
    ([2.0, 20.0, 345.0], 7.0),
    ([4.0, 20.0, 240.0], 7.0),
    ([8.0, 18.0, 180.0], 7.0),
    ([14.0, 12.0, 110.0], 7.5),
    ([28.0, 0.0, 70.0], 8.0),
    ([42.0, -12.0, 55.0], 8.0),
];

/// Airways as outer-wall polylines; the lumen is the wall radius less the wall thickness.
const TRACHEA: &Polyline = &[([0.0, 2.0, 345.0], 10.5), ([0.0, 4.0, 260.0], 10.5), ([0.0, 8.0, 212.0], 10.5)];
const RIGHT_MAIN_BRONCHUS: &Polyline =
    &[([0.0, 8.0, 212.0], 8.0), ([-22.0, 8.0, 202.0], 7.5), ([-40.0, 6.0, 192.0], 7.0)];
const LEFT_MAIN_BRONCHUS: &Polyline =
    &[([0.0, 8.0, 212.0], 7.5), ([24.0, 10.0, 204.0], 7.0), ([44.0, 12.0, 190.0], 6.5)];
const LOBAR_BRONCHI: [&Polyline; 4] = [
    &[([-30.0, 7.0, 198.0], 5.5), ([-50.0, 8.0, 214.0], 4.5)],
    &[([-40.0, 6.0, 192.0], 6.0), ([-47.0, 8.0, 168.0], 5.0)],
    &[([40.0, 11.0, 192.0], 5.0), ([54.0, 4.0, 208.0], 4.0)],
    &[([44.0, 12.0, 190.0], 5.0), ([52.0, 20.0, 166.0], 4.5)],
];
const AIRWAY_WALL_MM: f32 = 1.8;

const CLAVICLE: &Polyline = &[([16.0, -86.0, 292.0], 7.0), ([70.0, -84.0, 300.0], 6.5), ([125.0, -62.0, 308.0], 6.0)];
const RIB_NECK_RADIUS_MM: f32 = 3.5;

/// Pulmonary vessel trees: arteries enter each lung at its hilum, veins leave it toward the
/// left atrium, lower down. `(hilum, trunk direction, side: −1 right, +1 left, name)`.
const VESSEL_TREES: [(V3, V3, f32, &str); 4] = [
    ([-44.0, 0.0, 189.0], [-1.0, 0.2, -0.3], -1.0, "right pulmonary arteries"),
    ([46.0, 4.0, 194.0], [1.0, 0.5, -0.3], 1.0, "left pulmonary arteries"),
    ([-38.0, 10.0, 150.0], [-1.0, 0.1, 0.0], -1.0, "right pulmonary veins"),
    ([44.0, 12.0, 152.0], [1.0, 0.1, 0.0], 1.0, "left pulmonary veins"),
];
/// Attraction points per tree: about its number of twigs.
const VESSEL_TWIGS_PER_TREE: usize = 2500;

/// Painting order, back to front.
#[derive(Debug, Clone, Copy)]
enum Layer {
    Table,
    Body,
    ChestWallBones,
    Lungs,
    Abdomen,
    Mediastinum,
    Heart,
    Sternum,
    Spine,
    Tubes(usize),
}

/// The anatomy's analytic part and the parameters it reads.
struct Anatomy {
    texture_seed: u64,
    /// Size of the heart relative to the reference frame ([`heart_scale`]).
    heart_scale: f32,
    lung_hu: f32,
    lung_texture_hu: f32,
    /// Partial-volume ramp width (one pixel) in reference mm.
    edge: f32,
}

/// A synthetic thorax fitted to one scan geometry: ask it for its HU volume or for the
/// tissue at any point.
pub struct Thorax {
    geometry: Geometry,
    grid: IndexMap,
    frame: BodyFrame,
    anatomy: Anatomy,
    tubes: Vec<TubeSet>,
    order: Vec<Layer>,
}

impl Thorax {
    /// Lay out the anatomy for `geometry` (grows the vessel trees; a fraction of a second).
    pub fn new(geometry: &Geometry, params: &PhantomParams) -> Thorax {
        let grid = IndexMap::new(geometry);
        let frame = BodyFrame::fit(&grid);
        let anatomy = Anatomy {
            texture_seed: noise::stream_seed(params.seed, "lung texture", 0),
            heart_scale: heart_scale(frame.scale_xy),
            lung_hu: params.lung_hu,
            lung_texture_hu: params.lung_texture_hu,
            edge: (grid.pixel_mm() / frame.scale_xy) as f32,
        };
        let mut thorax =
            Thorax { geometry: geometry.clone(), grid, frame, anatomy, tubes: Vec::new(), order: Vec::new() };
        thorax.lay_out(params);
        thorax
    }

    fn lay_out(&mut self, params: &PhantomParams) {
        use Layer::*;
        self.order = vec![Table, Body, ChestWallBones, Lungs];
        let trees = self.pulmonary_vessels(params);
        self.push_tubes(trees, hu::BLOOD, Tissue::PulmonaryVessel);
        self.order.extend([Abdomen, Mediastinum, Heart]);

        let great_vessels: Vec<&Polyline> = vec![
            AORTA,
            PULMONARY_TRUNK,
            LEFT_PULMONARY_ARTERY,
            RIGHT_PULMONARY_ARTERY,
            SUPERIOR_VENA_CAVA,
            BRACHIOCEPHALIC_ARTERY,
            LEFT_CAROTID,
            LEFT_SUBCLAVIAN,
            LEFT_BRACHIOCEPHALIC_VEIN,
            RIGHT_BRACHIOCEPHALIC_VEIN,
        ];
        let mut vessels = capsules_from_polylines(&self.frame, &great_vessels);
        let fat_margin = VESSEL_FAT_MM * self.frame.scale_xy as f32;
        let rims = vessels.iter().map(|c| widened(c, fat_margin)).collect();
        self.push_tubes(rims, hu::FAT, Tissue::Mediastinum);
        // The inferior vena cava runs through the liver: no fat around it.
        vessels.extend(capsules_from_polylines(&self.frame, &[INFERIOR_VENA_CAVA]));
        self.push_tubes(vessels, hu::BLOOD, Tissue::GreatVessel);
        let oesophagus = capsules_from_polylines(&self.frame, &[OESOPHAGUS]);
        self.push_tubes(oesophagus, hu::MUSCLE, Tissue::Oesophagus);

        let mut airways = vec![TRACHEA, RIGHT_MAIN_BRONCHUS, LEFT_MAIN_BRONCHUS];
        airways.extend(LOBAR_BRONCHI);
        let walls = capsules_from_polylines(&self.frame, &airways);
        let wall_mm = AIRWAY_WALL_MM * self.frame.scale_xy as f32;
        let lumens = walls.iter().map(|c| widened(c, -wall_mm)).collect();
        self.push_tubes(walls, hu::AIRWAY_WALL, Tissue::AirwayWall);
        self.push_tubes(lumens, hu::AIR, Tissue::Airway);

        self.order.push(Sternum);
        let mirrored: Vec<(V3, f32)> = CLAVICLE.iter().map(|&([x, y, z], r)| ([-x, y, z], r)).collect();
        let mut bones = capsules_from_polylines(&self.frame, &[CLAVICLE, &mirrored]);
        bones.extend(self.rib_necks());
        self.push_tubes(bones, hu::THIN_BONE, Tissue::Bone);
        self.order.push(Spine);
    }

    fn push_tubes(&mut self, capsules: Vec<Capsule>, hu: f32, tissue: Tissue) {
        self.tubes.push(TubeSet::new(capsules, hu, tissue, &self.grid));
        self.order.push(Layer::Tubes(self.tubes.len() - 1));
    }

    /// The four pulmonary vessel trees (arteries and veins of each lung), patient mm.
    fn pulmonary_vessels(&self, params: &PhantomParams) -> Vec<Capsule> {
        let lung = |r: V3| self.anatomy.lung_sd(r);
        VESSEL_TREES
            .iter()
            .enumerate()
            .flat_map(|(n, &(hilum, trunk_dir, side, name))| {
                let (x0, x1) = if side < 0.0 { (-150.0, 0.0) } else { (0.0, 150.0) };
                let spec = TreeSpec {
                    hilum,
                    trunk_dir,
                    lung_box: Aabb::new([x0, -100.0, 0.0], [x1, 125.0, 325.0]),
                    points: VESSEL_TWIGS_PER_TREE,
                    min_radius_mm: params.min_vessel_radius_mm,
                };
                let mut rng = noise::stream(params.seed, name, n as u64);
                grow_tree(&spec, &lung, &mut rng)
            })
            .map(|c| c.to_patient(&self.frame))
            .collect()
    }

    /// Necks joining each rib's posterior end to the side of its vertebra.
    fn rib_necks(&self) -> Vec<Capsule> {
        let mut necks = Vec::new();
        for n in 0..RIB_PAIRS {
            let z = rib_axis_z(n, RIB_START_ANGLE);
            let (sin, cos) = RIB_START_ANGLE.sin_cos();
            // Walk out along the start angle to the pleura, then to the rib's axis.
            let mut t = 80.0;
            for _ in 0..8 {
                t -= cavity_sd([t * sin, CAVITY_CENTRE_Y + t * cos, z]);
            }
            t += RIB_OFFSET_MM;
            for side in [-1.0f32, 1.0] {
                let head = [side * 14.0, canal_centre_y(z) - 6.0, z + 4.0];
                let start = [side * t * sin, CAVITY_CENTRE_Y + t * cos, z];
                let r = RIB_NECK_RADIUS_MM;
                necks.push(Capsule { a: head, b: start, radius_a_mm: r, radius_b_mm: r }.to_patient(&self.frame));
            }
        }
        necks
    }

    /// Number of pulmonary vessel segments (for reports).
    pub fn vessel_segments(&self) -> usize {
        self.tubes.first().map_or(0, TubeSet::len)
    }

    /// The noiseless HU volume: slices painted in parallel, each independently.
    pub fn hu(&self) -> Volume<f32> {
        let [cols, rows, slices] = self.grid.dims;
        let mut data = vec![hu::AIR; cols * rows * slices];
        if cols * rows > 0 {
            data.par_chunks_mut(cols * rows).enumerate().for_each(|(k, slice)| {
                let mut canvas = SliceCanvas { hu: slice, k, grid: &self.grid, frame: &self.frame };
                for &layer in &self.order {
                    self.paint(layer, &mut canvas);
                }
            });
        }
        Volume { geometry: self.geometry.clone(), data }
    }

    fn paint(&self, layer: Layer, canvas: &mut SliceCanvas) {
        let a = &self.anatomy;
        let b = match layer {
            Layer::Tubes(n) => return self.tubes[n].paint(canvas),
            _ => layer_bounds(layer),
        };
        match layer {
            Layer::Table => canvas.paint_ref(&b, |r| a.table(r)),
            Layer::Body => canvas.paint_ref(&b, |r| a.body(r)),
            Layer::ChestWallBones => canvas.paint_ref(&b, |r| a.chest_wall_bones(r)),
            Layer::Lungs => canvas.paint_ref(&b, |r| a.lungs(r)),
            Layer::Abdomen => canvas.paint_ref(&b, |r| a.abdomen(r)),
            Layer::Mediastinum => canvas.paint_ref(&b, |r| a.mediastinum(r)),
            Layer::Heart => canvas.paint_ref(&b, |r| a.heart(r)),
            Layer::Sternum => canvas.paint_ref(&b, |r| a.sternum(r)),
            Layer::Spine => canvas.paint_ref(&b, |r| a.spine(r)),
            Layer::Tubes(_) => {}
        }
    }

    /// What a voxel centred at patient position `p_mm` would be labelled: the last layer
    /// covering at least half of it (air where nothing does).
    pub fn tissue_at_mm(&self, p_mm: [f64; 3]) -> Tissue {
        let r = self.frame.to_ref(p_mm).map(|c| c as f32);
        let p = p_mm.map(|c| c as f32);
        let ijk = self.grid.to_index(p_mm);
        let inside = (0..3).all(|a| ijk[a] > -0.5 && ijk[a] < self.grid.dims[a] as f64 - 0.5);
        let slice = inside.then(|| ijk[2].round() as usize);
        let a = &self.anatomy;
        let mut mix = Mix::new();
        for &layer in &self.order {
            let s = match layer {
                Layer::Table => a.table(r),
                Layer::Body => a.body(r),
                Layer::ChestWallBones => a.chest_wall_bones(r),
                Layer::Lungs => a.lungs(r),
                Layer::Abdomen => a.abdomen(r),
                Layer::Mediastinum => a.mediastinum(r),
                Layer::Heart => a.heart(r),
                Layer::Sternum => a.sternum(r),
                Layer::Spine => a.spine(r),
                Layer::Tubes(n) => self.tubes[n].sample(p, slice),
            };
            mix.paint_sample(s);
        }
        mix.tissue().unwrap_or(Tissue::Air)
    }
}

/// A capsule with both radii changed by `delta_mm`.
fn widened(c: &Capsule, delta_mm: f32) -> Capsule {
    Capsule { radius_a_mm: (c.radius_a_mm + delta_mm).max(0.0), radius_b_mm: (c.radius_b_mm + delta_mm).max(0.0), ..*c }
}

/// Reference-frame box each analytic layer lives in (whole height where it spans it).
fn layer_bounds(layer: Layer) -> Aabb {
    let all_z = (-50.0, 400.0);
    let (x, y, z): ((f64, f64), (f64, f64), (f64, f64)) = match layer {
        Layer::Table => ((-240.0, 240.0), (100.0, 200.0), all_z),
        Layer::Body | Layer::ChestWallBones => ((-175.0, 175.0), (-125.0, 150.0), all_z),
        Layer::Lungs => ((-150.0, 150.0), (-95.0, 120.0), (0.0, 325.0)),
        Layer::Abdomen => ((-150.0, 150.0), (-95.0, 120.0), (-50.0, 100.0)),
        Layer::Mediastinum => ((-30.0, 35.0), (-95.0, 120.0), (40.0, 400.0)),
        Layer::Heart => {
            let m = HEART_SCALE_RANGE.1 * f64::from(HEART_SEMI_AXES[0]) + 5.0;
            let c = HEART_CENTRE.map(f64::from);
            ((c[0] - m, c[0] + m), (c[1] - m, c[1] + m), (c[2] - m, c[2] + m))
        }
        Layer::Sternum => ((-32.0, 32.0), (-125.0, -60.0), (90.0, 297.0)),
        Layer::Spine => ((-65.0, 65.0), (15.0, 140.0), all_z),
        Layer::Tubes(_) => unreachable!("tube sets have their own slice lists"),
    };
    Aabb::new([x.0, y.0, z.0], [x.1, y.1, z.1])
}

impl Anatomy {
    fn heart_sd(&self, r: V3) -> f32 {
        let d = (Vec3::from(r) - Vec3::from(HEART_CENTRE)).to_array();
        let (s, c) = HEART_AXIS_ANGLE.sin_cos();
        let along = d[0] * c - d[1] * s;
        let across = d[0] * s + d[1] * c;
        ellipsoid_sd([along, across, d[2]], HEART_SEMI_AXES.map(|a| a * self.heart_scale))
    }

    /// Signed distance to either lung: the cavity less the mediastinum, spine, heart, below
    /// the apices and above the diaphragm.
    ///
    /// Speed: the cheap terms go first, and a point clearly outside (> [`CLEARLY_OUTSIDE_MM`])
    /// returns early; the spine and the heart are skipped when they are too far to matter.
    /// Either way, every value at or below `CLEARLY_OUTSIDE_MM`, and every comparison with
    /// a threshold above −[`FAR_MM`], is the same as the full formula's.
    fn lung_sd(&self, r: V3) -> f32 {
        let [x, y, z] = r;
        let band = mediastinum_half_width(y, z) - (x - MEDIASTINUM_X).abs();
        let mut d = (diaphragm_z(x, y) - z).max(z - apex_z(x, y)).max(band.min(VERTEBRA_Y - y));
        if d > CLEARLY_OUTSIDE_MM {
            return d;
        }
        d = d.max(cavity_sd(r));
        if d > CLEARLY_OUTSIDE_MM {
            return d;
        }
        // The spine envelope lies within |x| < 40, 25 < y < 102.
        if x.abs() < 40.0 + FAR_MM && y > 25.0 - FAR_MM && y < 102.0 + FAR_MM {
            d = d.max(-spine_envelope_sd(r));
        }
        let reach = HEART_SCALE_RANGE.1 as f32 * HEART_SEMI_AXES[0] + FAR_MM;
        if (0..3).all(|a| (r[a] - HEART_CENTRE[a]).abs() < reach) {
            d = d.max(PERICARDIAL_FAT_MM - self.heart_sd(r));
        }
        d
    }

    fn occ(&self, sd: f32) -> f32 {
        occupancy(sd, self.edge)
    }

    fn table(&self, r: V3) -> Option<Sample> {
        let [x, y, _] = r;
        let top = TABLE_TOP_Y - x * x / (2.0 * TABLE_CURVE_RADIUS_MM);
        let sd = interval_sd(y, top, top + TABLE_THICKNESS_MM).max(x.abs() - TABLE_HALF_WIDTH_MM);
        let mut m = Mix::new();
        m.paint(self.occ(sd), hu::TABLE_SHELL, Tissue::Table);
        m.paint(self.occ(sd + TABLE_SHELL_MM), hu::TABLE_CORE, Tissue::Table);
        m.sample()
    }

    fn body(&self, r: V3) -> Option<Sample> {
        let muscle = Some(Sample { occupancy: 1.0, hu: hu::MUSCLE, tissue: Tissue::Muscle });
        // Inside the thoracic cavity the body wall is ≥ 20 mm away: all muscle (what the mix
        // below gives there), quickly.
        if inside_cavity_ellipse(r, 0.0) {
            return muscle;
        }
        let d = body_sd(r);
        let o = self.occ(d);
        if o <= 0.0 {
            return None;
        }
        let fat_mm = SUBCUTANEOUS_FAT_MM.at(r[2]);
        if d < -(SKIN_MM + fat_mm + self.edge) {
            return muscle;
        }
        let mut m = Mix::new();
        m.paint(o, hu::SKIN, Tissue::Skin);
        m.paint(self.occ(d + SKIN_MM), hu::FAT, Tissue::Fat);
        m.paint(self.occ(d + SKIN_MM + fat_mm), hu::MUSCLE, Tissue::Muscle);
        m.sample()
    }

    /// Ribs (bone and costal cartilage) and scapulae: bones at set depths outside the
    /// pleura, sharing one evaluation of the cavity's signed distance.
    fn chest_wall_bones(&self, r: V3) -> Option<Sample> {
        let [x, y, _] = r;
        if inside_cavity_ellipse(r, 0.0) {
            return None;
        }
        let outside_pleura = cavity_sd(r);
        if !(RIB_OFFSET_MM - 7.0..=SCAPULA_OFFSET_MM + 6.0).contains(&outside_pleura) {
            return None;
        }
        let angle = wall_angle(x, y);
        let arc_mm = x.hypot(y - CAVITY_CENTRE_Y);
        let mut m = Mix::new();
        self.paint_scapula(&mut m, r, outside_pleura - SCAPULA_OFFSET_MM, angle, arc_mm);
        self.paint_ribs(&mut m, r, outside_pleura - RIB_OFFSET_MM, angle, arc_mm);
        m.sample()
    }

    /// The scapular blade, `radial` mm outside its mid-surface.
    fn paint_scapula(&self, m: &mut Mix, r: V3, radial: f32, angle: f32, arc_mm: f32) {
        let z = r[2];
        if radial.abs() > 6.0 {
            return;
        }
        // The blade narrows toward its inferior angle.
        let low = (1.0 - (z - SCAPULA_Z.0) / 60.0).clamp(0.0, 1.0);
        let (a0, a1) = (0.6 + 0.3 * low, 1.2 - 0.25 * low);
        let sd = (radial.abs() - SCAPULA_HALF_THICKNESS_MM).max(interval_sd(angle, a0, a1) * arc_mm).max(interval_sd(
            z,
            SCAPULA_Z.0,
            SCAPULA_Z.1,
        ));
        m.paint(self.occ(sd), hu::THIN_BONE, Tissue::Bone);
    }

    /// The ribs, `radial` mm outside their axes' surface.
    fn paint_ribs(&self, m: &mut Mix, r: V3, radial: f32, angle: f32, arc_mm: f32) {
        let z = r[2];
        if radial.abs() > 7.0 || angle < RIB_START_ANGLE - 0.05 {
            return;
        }
        for n in 0..RIB_PAIRS {
            let shape = rib_shape(n);
            let dz = z - rib_axis_z(n, angle);
            if dz.abs() > shape.half_height_mm + 3.0 {
                continue;
            }
            let cross = oval_sd(radial, dz, shape.half_thickness_mm, shape.half_height_mm, 0.0);
            let bone = cross.max(interval_sd(angle, RIB_START_ANGLE, shape.bone_end) * arc_mm);
            m.paint(self.occ(bone), hu::CORTICAL_BONE, Tissue::Bone);
            m.paint(self.occ(bone + RIB_CORTEX_MM), hu::CANCELLOUS_BONE, Tissue::Bone);
            if shape.cartilage_end > shape.bone_end {
                let along = interval_sd(angle, shape.bone_end, shape.cartilage_end) * arc_mm;
                m.paint(self.occ(cross.max(along)), hu::CARTILAGE, Tissue::Cartilage);
            }
        }
    }

    fn lungs(&self, r: V3) -> Option<Sample> {
        let o = self.occ(self.lung_sd(r));
        if o <= 0.0 {
            return None;
        }
        let texture = noise::fbm(self.texture_seed, r, LUNG_TEXTURE_PERIOD_MM, 2);
        let hu = self.lung_hu + LUNG_GRAVITY_HU_PER_MM * (r[1] - 10.0) + self.lung_texture_hu * texture;
        Some(Sample { occupancy: o, hu, tissue: Tissue::Lung })
    }

    fn abdomen(&self, r: V3) -> Option<Sample> {
        let [x, y, z] = r;
        let dome = diaphragm_z(x, y);
        if z - dome > CLEARLY_OUTSIDE_MM {
            return None;
        }
        let o = self.occ(cavity_sd(r).max(z - dome));
        if o <= 0.0 {
            return None;
        }
        let mut m = Mix::new();
        m.paint(o, hu::ABDOMEN, Tissue::Abdomen);
        // The liver fills the right upper quadrant; its left lobe crosses the midline in front.
        let yl = y + 30.0;
        let liver = (x + 0.45 * yl - 0.004 * yl * yl - 18.0) / 1.1;
        m.paint(o * self.occ(liver), hu::LIVER, Tissue::Liver);
        let stomach = ellipsoid_sd((Vec3::from(r) - Vec3::from(STOMACH_CENTRE)).to_array(), STOMACH_SEMI_AXES);
        m.paint(o * self.occ(stomach), hu::MUSCLE, Tissue::Stomach);
        let contents = o * self.occ(stomach + 3.0);
        m.paint(contents, hu::STOMACH_FLUID, Tissue::Stomach);
        let gas = self.occ(y - STOMACH_GAS_LEVEL_Y);
        m.paint(contents * gas, hu::AIR, Tissue::Stomach);
        let spleen = ellipsoid_sd((Vec3::from(r) - Vec3::from(SPLEEN_CENTRE)).to_array(), SPLEEN_SEMI_AXES);
        m.paint(o * self.occ(spleen), hu::SPLEEN, Tissue::Spleen);
        m.paint(o * self.occ(dome - DIAPHRAGM_MM - z), hu::MUSCLE, Tissue::Diaphragm);
        m.sample()
    }

    fn mediastinum(&self, r: V3) -> Option<Sample> {
        let [x, y, z] = r;
        let sd =
            ((x - MEDIASTINUM_X).abs() - mediastinum_half_width(y, z)).max(y - VERTEBRA_Y).max(diaphragm_z(x, y) - z);
        if sd > CLEARLY_OUTSIDE_MM {
            return None;
        }
        let o = self.occ(sd.max(cavity_sd(r)));
        (o > 0.0).then_some(Sample { occupancy: o, hu: hu::FAT, tissue: Tissue::Mediastinum })
    }

    fn heart(&self, r: V3) -> Option<Sample> {
        let d = self.heart_sd(r);
        let mut m = Mix::new();
        m.paint(self.occ(d - PERICARDIAL_FAT_MM), hu::FAT, Tissue::Mediastinum);
        m.paint(self.occ(d), hu::BLOOD, Tissue::Heart);
        m.sample()
    }

    fn sternum(&self, r: V3) -> Option<Sample> {
        let [x, y, z] = r;
        let centre_y = BODY_CENTRE_Y - BODY_HALF_DEPTH_ANTERIOR.at(z) + STERNUM_DEPTH_MM;
        let sd = oval_sd(x, y - centre_y, STERNUM_HALF_WIDTH.at(z), STERNUM_HALF_DEPTH, 0.5).max(interval_sd(
            z,
            STERNUM_Z.0,
            STERNUM_Z.1,
        ));
        let mut m = Mix::new();
        m.paint(self.occ(sd), hu::CORTICAL_BONE, Tissue::Bone);
        m.paint(self.occ(sd + 1.5), hu::CANCELLOUS_BONE, Tissue::Bone);
        m.sample()
    }

    fn spine(&self, r: V3) -> Option<Sample> {
        let [x, y, z] = r;
        let (a, b) = vertebral_body_axes(z);
        let mut m = Mix::new();
        // Discs fill the column; bodies, arches and processes are painted over them.
        let column = oval_sd(x, y - VERTEBRA_Y, a - 1.0, b - 1.0, 0.25);
        m.paint(self.occ(column), hu::DISC, Tissue::Disc);
        let canal_y = canal_centre_y(z);
        let canal = x.hypot(y - canal_y) - CANAL_RADIUS_MM;
        let nearest = (VERTEBRA_TOP_Z - z) / VERTEBRA_PITCH_MM;
        for n in [nearest.floor(), nearest.floor() + 1.0] {
            let zc = VERTEBRA_TOP_Z - n * VERTEBRA_PITCH_MM;
            let dz = z - zc;
            let body = oval_sd(x, y - VERTEBRA_Y, a, b, 0.25).max(dz.abs() - VERTEBRAL_BODY_HALF_HEIGHT);
            m.paint(self.occ(body), hu::CORTICAL_BONE, Tissue::Bone);
            m.paint(self.occ(body + VERTEBRAL_CORTEX_MM), hu::CANCELLOUS_BONE, Tissue::Bone);
            // Pedicles and laminae ring the canal behind the body.
            let arch = (canal - 5.5).max(VERTEBRA_Y + b - 3.0 - y).max((dz + 1.0).abs() - 9.0);
            let spinous = capsule_sd(r, [0.0, canal_y + 10.0, zc - 2.0], [0.0, canal_y + 38.0, zc - 20.0], 5.0, 3.5);
            let transverse =
                capsule_sd([x.abs(), y, z], [8.0, canal_y - 4.0, zc + 3.0], [34.0, canal_y + 10.0, zc + 5.0], 4.5, 4.0);
            let processes = arch.min(spinous).min(transverse);
            m.paint(self.occ(processes), hu::THIN_BONE, Tissue::Bone);
        }
        m.paint(self.occ(canal), hu::SPINAL_CANAL, Tissue::SpinalCanal);
        m.sample()
    }
}
