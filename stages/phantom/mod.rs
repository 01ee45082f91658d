//! Synthetic thorax CT phantoms. Owns the whole phantom: an anatomy a radiologist recognises
//! on axial slices and on projections ([`Thorax`]: body wall, ribs, sternum, scapulae,
//! spine, textured lungs with branching vessel trees, heart, mediastinum, airways, diaphragm
//! and upper abdomen, patient table), real nodules inserted from radiologists' masks with
//! partial volume ([`nodule`]), and CT noise.
//!
//! The body is fitted to the scan it is generated for: its size follows the field of view
//! (340 mm wide in a 360-mm FOV), its centre is the scanner axis (the image centre) and its
//! lungs span the scanned z range, so a real scan's geometry (e.g. an LIDC-IDRI series)
//! yields a thorax whose lung fields hold that patient's nodule positions. Anatomy is never
//! moved to fit nodules.
//!
//! Everything is a deterministic function of (geometry, [`PhantomParams`]): the same seed
//! gives a bit-identical volume whatever the number of threads (random streams are keyed by
//! seed and slice or object, never by scheduling).
//!
//! Entry points: [`phantom_ct`] (anatomy + nodules + noise, in that order so nodules carry the
//! same noise as their surroundings), or the steps [`thorax_hu`], [`insert_nodule`],
//! [`add_scanner_noise`].

mod canvas;
mod frame;
pub mod nodule;
mod noise;
pub mod patient;
mod shapes;
mod thorax;
mod tubes;
mod vessels;

pub use nodule::{
    ellipsoid_mask, insert_nodule, nodule_hu_for_texture, occupancy_from_fraction, occupancy_from_mask,
    solid_share_for_texture, textured_nodule, BoxGrid, NoduleInsert,
};
pub use thorax::Thorax;

use crate::volume::{Geometry, Volume};
use serde::{Deserialize, Serialize};

/// What the phantom generator can be asked to vary.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PhantomParams {
    /// Seed of every random choice (vessel trees, lung texture, scanner noise). The same
    /// seed and geometry give a bit-identical volume.
    pub seed: u64,
    /// Standard deviation of the CT noise added to every voxel, HU (0: none). Typical
    /// chest CT at 2.5 mm: 15–20 HU.
    pub noise_hu: f32,
    /// Mean attenuation of lung parenchyma at mid-depth, HU (the back is ≈ 25 HU denser,
    /// the front ≈ 25 HU lighter, as in a supine patient).
    pub lung_hu: f32,
    /// Standard deviation of the parenchyma's spatially correlated texture (features of
    /// ≈ 3–6 mm), HU.
    pub lung_texture_hu: f32,
    /// Radius at which the pulmonary vessel trees stop branching, mm of a 340-mm-wide body
    /// (scaled with it).
    pub min_vessel_radius_mm: f32,
    /// How far each nodule's tissue reaches.
    pub nodule_extent: NoduleExtent,
}

/// How a nodule's readers' contours become its tissue.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum NoduleExtent {
    /// Every voxel any reader drew, at the nodule's full attenuation: the object is the union
    /// of the contours, larger than the 50 % consensus the metrics measure against (1.0–1.8×,
    /// median 1.24× on the paper's 19 targets).
    Union,
    /// Each voxel filled by the fraction of readers who drew it: where they disagree the edge
    /// is graded, and the object's half-attenuation surface is the 50 % consensus.
    #[default]
    Readers,
    /// The 50 % consensus itself (pylidc's default `clevel`, the metrics' default), at full
    /// attenuation: the object is the ground truth the metrics score against, with the same
    /// partial-volume edge as the union.
    Consensus,
}

impl Default for PhantomParams {
    fn default() -> Self {
        PhantomParams {
            seed: 1,
            noise_hu: 18.0,
            lung_hu: -850.0,
            lung_texture_hu: 25.0,
            min_vessel_radius_mm: 0.3,
            nodule_extent: NoduleExtent::Readers,
        }
    }
}

/// What a voxel of the phantom is made of (the label of [`Thorax::tissue_at_mm`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Tissue {
    Air,
    Table,
    Skin,
    Fat,
    Muscle,
    Bone,
    Cartilage,
    Disc,
    SpinalCanal,
    Lung,
    PulmonaryVessel,
    Airway,
    AirwayWall,
    Heart,
    GreatVessel,
    /// Mediastinal and pericardial fat.
    Mediastinum,
    Oesophagus,
    Diaphragm,
    Liver,
    Stomach,
    Spleen,
    /// Other upper-abdominal contents.
    Abdomen,
}

impl Tissue {
    /// Inside a lung: parenchyma or the vessels running through it.
    pub fn is_lung_field(self) -> bool {
        matches!(self, Tissue::Lung | Tissue::PulmonaryVessel)
    }
}

/// HU of the anatomy alone: no nodule, no noise.
pub fn thorax_hu(geometry: &Geometry, params: &PhantomParams) -> Volume<f32> {
    Thorax::new(geometry, params).hu()
}

/// Add the scanner noise of `params` (`noise_hu`, seeded by `params.seed`) to `ct`.
pub fn add_scanner_noise(ct: &mut Volume<f32>, params: &PhantomParams) {
    noise::add_scanner_noise(ct, noise::stream_seed(params.seed, "scanner", 0), params.noise_hu);
}

/// A complete phantom CT: anatomy, then `nodules` blended in, then noise over everything.
pub fn phantom_ct(geometry: &Geometry, params: &PhantomParams, nodules: &[NoduleInsert]) -> Volume<f32> {
    let mut ct = thorax_hu(geometry, params);
    for n in nodules {
        insert_nodule(&mut ct, n);
    }
    add_scanner_noise(&mut ct, params);
    ct
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn params_default_missing_fields_and_refuse_unknown_ones() {
        let p: PhantomParams = toml::from_str("seed = 7\nnoise_hu = 0.0").unwrap();
        assert_eq!(p, PhantomParams { seed: 7, noise_hu: 0.0, ..PhantomParams::default() });
        let err = toml::from_str::<PhantomParams>("sede = 7").unwrap_err();
        assert!(err.to_string().contains("sede"), "{err}");
        let err = toml::from_str::<PhantomParams>("nodule_extent = \"consensos\"").unwrap_err();
        for accepted in ["union", "readers", "consensus"] {
            assert!(err.to_string().contains(accepted), "{err}");
        }
    }

    #[test]
    fn the_extent_is_part_of_the_cache_key() {
        let default = serde_json::to_value(PhantomParams::default()).unwrap();
        assert_eq!(default["nodule_extent"], "readers", "{default}");
        let consensus = PhantomParams { nodule_extent: NoduleExtent::Consensus, ..PhantomParams::default() };
        assert_eq!(serde_json::to_value(consensus).unwrap()["nodule_extent"], "consensus");
    }
}
