//! `model.safetensors`: the six VM factor tensors of a trained field plus JSON metadata, in the
//! safetensors format (readable with Python's `safetensors` + numpy).
//!
//! Tensors (float32, row-major): `plane_xy`, `plane_xz`, `plane_yz` of shape `[R, N, N]`
//! (index `[r, v, u]`: u = the plane's first axis, fastest), `line_z`, `line_y`, `line_x` of shape
//! `[R, N]`, and optionally `alpha_mask` (uint8 `[N, N, N]`, index `[z, y, x]`). A dense model
//! (`"model": "dense_tv"` or `"truth"` in the metadata) holds one tensor instead, `density` (float32
//! `[N, N, N]`, index `[z, y, x]`): σ at the lattice nodes. The metadata has
//! one key, `aret_pipe`, whose value is the JSON of [`ModelMeta`] (one key keeps the bytes
//! deterministic); its `patient_space` places the lattice's nodes in the patient's coordinates
//! ([`PatientSpace`]), as `density.mhd` does, without `cameras.json`.

use crate::geometry::Aabb;
use crate::train::field::VmField;
use crate::train::params::FieldModel;
use crate::train::render::{Lattice, PhotoLoss, Renderer};
use safetensors::tensor::{Dtype, SafeTensors, TensorView};
use serde::{Deserialize, Serialize};
use std::collections::HashMap;

/// Everything needed to evaluate the field besides its factors.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ModelMeta {
    /// What the tensors hold.
    pub model: FieldModel,
    pub grid: usize,
    pub rank: usize,
    pub aabb: Aabb,
    /// Δ and s of σ = ReLU(f + Δ), Î = exp(−s Σ σ δ).
    pub shift: f64,
    pub scale: f64,
    pub step: f64,
    pub seed: u64,
    pub iterations: usize,
    pub backend: String,
    pub parameters: usize,
    /// Where the nodes lie in the patient; absent in files written before it was recorded.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub patient_space: Option<PatientSpace>,
}

/// Where a model's lattice nodes lie, in the DICOM patient coordinates (LPS, mm) of its CT: the
/// node of tensor index `[z, y, x]` (`density`, `alpha_mask`; the factors' `u`, `v` likewise)
/// lies at `origin_mm + Σ_a index_a · spacing_mm[a] · direction[a]`, with index_0 = x.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PatientSpace {
    /// The node `[0, 0, 0]`, mm.
    pub origin_mm: [f64; 3],
    /// The distance between neighbouring nodes along x, y and z, mm.
    pub spacing_mm: [f64; 3],
    /// The patient-space direction of the x, y and z index axes.
    pub direction: [[f64; 3]; 3],
    /// The tensors' index order, slowest first.
    pub index_order: [String; 3],
}

impl PatientSpace {
    /// The lattice at `origin_mm` with `spacing_mm` along the patient axes, indexed `[z, y, x]`.
    pub fn axis_aligned(origin_mm: [f64; 3], spacing_mm: [f64; 3]) -> PatientSpace {
        PatientSpace {
            origin_mm,
            spacing_mm,
            direction: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            index_order: ["z", "y", "x"].map(String::from),
        }
    }
}

impl ModelMeta {
    /// The renderer the field was trained with (lattice, Δ, s, step), for rendering σ: the
    /// loss it was trained on does not matter there.
    pub fn renderer(&self) -> Renderer {
        Renderer {
            lattice: Lattice { n: self.grid, aabb: self.aabb },
            shift: self.shift,
            scale: self.scale,
            step: self.step,
            loss: PhotoLoss::default(),
        }
    }
}

const PLANES: [&str; 3] = ["plane_xy", "plane_xz", "plane_yz"];
const LINES: [&str; 3] = ["line_z", "line_y", "line_x"];

fn bytes(v: &[f32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

/// A trained field as the file stores it.
#[derive(Debug, Clone)]
pub enum Field {
    /// VM factors: σ = ReLU(F + Δ) of their composition.
    Vm(VmField<f32>),
    /// σ at the N³ nodes, index `x + N·(y + N·z)`.
    Dense(Vec<f32>),
}

type Tensors = Vec<(String, Dtype, Vec<usize>, Vec<u8>)>;

pub fn encode(field: &VmField<f32>, mask: Option<&[bool]>, meta: &ModelMeta) -> anyhow::Result<Vec<u8>> {
    let (n, r) = (field.n, field.rank);
    let mut owned: Tensors = Vec::new();
    for p in 0..3 {
        owned.push((PLANES[p].into(), Dtype::F32, vec![r, n, n], bytes(&field.planes[p])));
        owned.push((LINES[p].into(), Dtype::F32, vec![r, n], bytes(&field.lines[p])));
    }
    if let Some(mask) = mask {
        owned.push(("alpha_mask".into(), Dtype::U8, vec![n, n, n], mask.iter().map(|&k| u8::from(k)).collect()));
    }
    serialize(&owned, meta)
}

/// A dense model: σ at the `meta.grid³` nodes.
pub fn encode_dense(sigma: &[f32], meta: &ModelMeta) -> anyhow::Result<Vec<u8>> {
    let n = meta.grid;
    anyhow::ensure!(sigma.len() == n * n * n, "a {n}³ dense model needs {} values, not {}", n * n * n, sigma.len());
    serialize(&vec![("density".into(), Dtype::F32, vec![n, n, n], bytes(sigma))], meta)
}

fn serialize(owned: &Tensors, meta: &ModelMeta) -> anyhow::Result<Vec<u8>> {
    let views = owned
        .iter()
        .map(|(name, dtype, shape, data)| Ok((name.clone(), TensorView::new(*dtype, shape.clone(), data)?)))
        .collect::<Result<Vec<_>, safetensors::SafeTensorError>>()?;
    let metadata = HashMap::from([("aret_pipe".to_string(), serde_json::to_string(meta)?)]);
    Ok(safetensors::serialize(views, &Some(metadata))?)
}

/// The field, the mask (if stored) and the metadata of a model file.
pub fn decode(data: &[u8]) -> anyhow::Result<(Field, Option<Vec<bool>>, ModelMeta)> {
    let (_, header) = SafeTensors::read_metadata(data)?;
    let meta_json = header
        .metadata()
        .as_ref()
        .and_then(|m| m.get("aret_pipe"))
        .ok_or_else(|| anyhow::anyhow!("model file has no `aret_pipe` metadata"))?;
    let meta: ModelMeta = serde_json::from_str(meta_json)?;
    let tensors = SafeTensors::deserialize(data)?;
    let floats = |name: &str, len: usize| -> anyhow::Result<Vec<f32>> {
        let t = tensors.tensor(name)?;
        anyhow::ensure!(
            t.dtype() == Dtype::F32 && t.data().len() == 4 * len,
            "tensor `{name}` has the wrong type or size"
        );
        Ok(t.data().chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect())
    };
    let (n, r) = (meta.grid, meta.rank);
    if meta.model != FieldModel::Vm {
        return Ok((Field::Dense(floats("density", n * n * n)?), None, meta));
    }
    let mut field = VmField::zeros(n, r);
    for p in 0..3 {
        field.planes[p] = floats(PLANES[p], r * n * n)?;
        field.lines[p] = floats(LINES[p], r * n)?;
    }
    let mask = tensors.tensor("alpha_mask").ok().map(|t| t.data().iter().map(|&b| b != 0).collect());
    Ok((Field::Vm(field), mask, meta))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn meta(model: FieldModel, grid: usize, rank: usize) -> ModelMeta {
        ModelMeta {
            model,
            grid,
            rank,
            aabb: Aabb { min: [-1.0; 3], max: [1.0; 3] },
            shift: 0.0,
            scale: 1.0,
            step: 0.1,
            seed: 3,
            iterations: 10,
            backend: "cpu".into(),
            parameters: 0,
            patient_space: Some(PatientSpace::axis_aligned([-10.0, 20.0, -300.0], [1.5, 1.5, 2.0])),
        }
    }

    #[test]
    fn a_dense_model_round_trips_and_a_vm_model_keeps_its_metadata() {
        let sigma: Vec<f32> = (0..27).map(|i| i as f32 * 0.5).collect();
        let bytes = encode_dense(&sigma, &meta(FieldModel::DenseTv, 3, 0)).unwrap();
        let (field, mask, decoded) = decode(&bytes).unwrap();
        assert!(matches!(field, Field::Dense(ref s) if *s == sigma) && mask.is_none());
        assert_eq!(decoded, meta(FieldModel::DenseTv, 3, 0));
        assert!(encode_dense(&sigma[..26], &meta(FieldModel::DenseTv, 3, 0)).is_err());
        // A VM model's metadata names its model too.
        let vm = VmField::zeros(3, 2);
        let bytes = encode(&vm, None, &meta(FieldModel::Vm, 3, 2)).unwrap();
        let (_, header) = SafeTensors::read_metadata(&bytes).unwrap();
        assert!(header.metadata().as_ref().unwrap()["aret_pipe"].contains(r#""model":"vm""#));
        assert!(matches!(decode(&bytes).unwrap().0, Field::Vm(ref f) if f.rank == 2));
    }
}
