//! `grid`: the trained field as a dense density volume (SPEC §3 grid).
//!
//! Input: `train/model.safetensors` (factors, alpha mask, Δ, AABB) and `drr/cameras.json` (the
//! scene frame: scene units → patient mm). σ is evaluated at the N³ lattice nodes, which are
//! the cell centres of the AABB (the training lattice itself), with the renderer's alpha-mask
//! rule; a dense model (`[train] model = "dense_tv"`) holds σ at those nodes already.
//! Outputs: `density.mhd/.raw` (f32), `uncertainty.mhd/.raw` (|∇σ| by central
//! differences in mm, scaled to [0, 1]) and `density.vdb` holding both as FloatGrids, all in
//! patient millimetres.

use crate::artifacts::{CAMERAS, DENSITY, DENSITY_VDB, MODEL, UNCERTAINTY};
use crate::engine::{Context, Output, Stage};
use crate::formats::model;
use crate::formats::vdb::{self, FloatGrid, GridClass};
use crate::geometry::{Aabb, SceneFrame};
use crate::stage::drr::CameraSet;
use crate::train::render::AlphaMask;
use crate::volume::{Geometry, Volume};
use glam::DVec3;
use serde::{Deserialize, Serialize};

pub const VERSION: u32 = 2;

/// `[grid]` takes no keys: the lattice is the model's own.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Params {}

pub struct Grid {
    pub params: Params,
}

impl Stage for Grid {
    fn name(&self) -> &'static str {
        "grid"
    }
    fn version(&self) -> u32 {
        VERSION
    }
    fn inputs(&self) -> &'static [&'static str] {
        &["drr", "train"]
    }
    fn params(&self) -> serde_json::Value {
        super::params_json(&self.params)
    }
    fn reads(&self, stage: &str, output: &str) -> bool {
        [CAMERAS, MODEL].iter().any(|a| (a.stage, a.file) == (stage, output))
    }
    fn run(&self, ctx: &Context) -> anyhow::Result<Vec<Output>> {
        let set: CameraSet = super::read_json(ctx, CAMERAS)?;
        let (field, mask, meta) = model::decode(&super::read(ctx, MODEL)?)?;
        let geometry = lattice_geometry(meta.grid, &meta.aabb, &set.frame);
        let density = Volume { geometry: geometry.clone(), data: node_density(field, mask, &meta) };
        let uncertainty = Volume { geometry, data: gradient_magnitude_unit(&density) };
        let vdb_bytes = vdb::encode(&[
            vdb_grid(DENSITY.name, &density, GridClass::FogVolume),
            vdb_grid(UNCERTAINTY.name, &uncertainty, GridClass::Unknown),
        ])?;
        let mut outputs = Vec::from(super::volume_outputs(DENSITY, &density));
        outputs.extend(super::volume_outputs(UNCERTAINTY, &uncertainty));
        outputs.push(Output::new(DENSITY_VDB.file, vdb_bytes));
        Ok(outputs)
    }
}

/// σ at the lattice nodes of a decoded model, index `x + N·(y + N·z)`: the VM field composed and
/// sampled as the renderer samples it (with its alpha mask), or a dense model's own values.
pub fn node_density(field: model::Field, mask: Option<Vec<bool>>, meta: &model::ModelMeta) -> Vec<f32> {
    match field {
        model::Field::Vm(factors) => {
            let mask = mask.map(|nodes| AlphaMask::from_nodes(nodes, meta.grid));
            meta.renderer().node_density(&factors.compose(), mask.as_ref())
        }
        model::Field::Dense(sigma) => sigma,
    }
}

/// `volume` as a VDB float grid named `name`.
fn vdb_grid<'a>(name: &'a str, volume: &'a Volume<f32>, class: GridClass) -> FloatGrid<'a> {
    FloatGrid {
        name,
        dims: volume.geometry.dims,
        values: &volume.data,
        voxel_size_mm: volume.geometry.spacing_mm,
        origin_mm: volume.geometry.origin_mm,
        class,
    }
}

/// The patient-space geometry of an `n³` lattice of cell centres in `aabb` (scene units):
/// the scene axes are the patient axes, scaled by `frame.mm_per_unit`.
pub fn lattice_geometry(n: usize, aabb: &Aabb, frame: &SceneFrame) -> Geometry {
    let cell = DVec3::from(aabb.max) - DVec3::from(aabb.min);
    let cell = cell / n as f64;
    let first_node = frame.to_patient_mm(DVec3::from(aabb.min) + 0.5 * cell);
    Geometry {
        dims: [n; 3],
        spacing_mm: (cell * frame.mm_per_unit).to_array(),
        origin_mm: first_node.to_array(),
        direction: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
    }
}

/// `|∇σ|` (per mm) by central differences — one-sided on the border, as `numpy.gradient` —
/// divided by its maximum so it spans [0, 1] (all zero for a constant volume).
pub fn gradient_magnitude_unit(volume: &Volume<f32>) -> Vec<f32> {
    let [nx, ny, nz] = volume.geometry.dims;
    let dims = [nx, ny, nz];
    let v = |x: usize, y: usize, z: usize| f64::from(volume.data[x + nx * (y + ny * z)]);
    let mut magnitude = vec![0f64; volume.data.len()];
    for z in 0..nz {
        for y in 0..ny {
            for x in 0..nx {
                let at = [x, y, z];
                let mut sum = 0.0;
                for a in 0..3 {
                    if dims[a] < 2 {
                        continue;
                    }
                    let (lo, hi) = (at[a].saturating_sub(1), (at[a] + 1).min(dims[a] - 1));
                    let (mut p, mut q) = (at, at);
                    p[a] = lo;
                    q[a] = hi;
                    let d = (v(q[0], q[1], q[2]) - v(p[0], p[1], p[2]))
                        / ((hi - lo) as f64 * volume.geometry.spacing_mm[a]);
                    sum += d * d;
                }
                magnitude[x + nx * (y + ny * z)] = sum.sqrt();
            }
        }
    }
    let max = magnitude.iter().copied().fold(0.0, f64::max);
    magnitude.iter().map(|&m| if max > 0.0 { (m / max) as f32 } else { 0.0 }).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_gradient_of_a_ramp_is_constant_and_scaled_to_one() {
        let geometry = Geometry {
            dims: [4, 3, 2],
            spacing_mm: [2.0, 1.0, 1.0],
            origin_mm: [0.0; 3],
            direction: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        };
        // σ = 3·x_mm: ∂σ/∂x = 3 per mm everywhere, including the one-sided borders.
        let data = (0..24).map(|i| 3.0 * 2.0 * (i % 4) as f32).collect();
        let g = gradient_magnitude_unit(&Volume { geometry, data });
        assert!(g.iter().all(|&v| (v - 1.0).abs() < 1e-6), "{g:?}");
    }

    #[test]
    fn lattice_nodes_sit_at_cell_centres_in_patient_mm() {
        let aabb = Aabb { min: [-1.0, -2.0, -3.0], max: [1.0, 2.0, 3.0] };
        let frame = SceneFrame { roi_center_mm: [10.0, 20.0, 30.0], mm_per_unit: 40.0 };
        let g = lattice_geometry(4, &aabb, &frame);
        assert_eq!(g.spacing_mm, [20.0, 40.0, 60.0]);
        assert_eq!(g.origin_mm, [10.0 - 40.0 + 10.0, 20.0 - 80.0 + 20.0, 30.0 - 120.0 + 30.0]);
    }
}
