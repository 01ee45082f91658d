//! `model.safetensors`: the six VM factor tensors of a trained field plus JSON metadata, in the
//! safetensors format (readable with Python's `safetensors` + numpy).
//!
//! Tensors (float32, row-major): `plane_xy`, `plane_xz`, `plane_yz` of shape `[R, N, N]`
//! (index `[r, v, u]`: u = the plane's first axis, fastest), `line_z`, `line_y`, `line_x` of shape
//! `[R, N]`, and optionally `alpha_mask` (uint8 `[N, N, N]`, index `[z, y, x]`). The metadata has
//! one key, `aret_pipe`, whose value is the JSON of [`ModelMeta`] (one key keeps the bytes
//! deterministic).

use crate::geometry::Aabb;
use crate::train::field::VmField;
use crate::train::render::{Lattice, PhotoLoss, Renderer};
use safetensors::tensor::{Dtype, SafeTensors, TensorView};
use serde::{Deserialize, Serialize};
use std::collections::HashMap;

/// Everything needed to evaluate the field besides its factors.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ModelMeta {
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

pub fn encode(field: &VmField<f32>, mask: Option<&[bool]>, meta: &ModelMeta) -> anyhow::Result<Vec<u8>> {
    let (n, r) = (field.n, field.rank);
    let mut owned: Vec<(String, Dtype, Vec<usize>, Vec<u8>)> = Vec::new();
    for p in 0..3 {
        owned.push((PLANES[p].into(), Dtype::F32, vec![r, n, n], bytes(&field.planes[p])));
        owned.push((LINES[p].into(), Dtype::F32, vec![r, n], bytes(&field.lines[p])));
    }
    if let Some(mask) = mask {
        owned.push(("alpha_mask".into(), Dtype::U8, vec![n, n, n], mask.iter().map(|&k| u8::from(k)).collect()));
    }
    let views = owned
        .iter()
        .map(|(name, dtype, shape, data)| Ok((name.clone(), TensorView::new(*dtype, shape.clone(), data)?)))
        .collect::<Result<Vec<_>, safetensors::SafeTensorError>>()?;
    let metadata = HashMap::from([("aret_pipe".to_string(), serde_json::to_string(meta)?)]);
    Ok(safetensors::serialize(views, &Some(metadata))?)
}

/// The factors, the mask (if stored) and the metadata of a model file.
pub fn decode(data: &[u8]) -> anyhow::Result<(VmField<f32>, Option<Vec<bool>>, ModelMeta)> {
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
    let mut field = VmField::zeros(n, r);
    for p in 0..3 {
        field.planes[p] = floats(PLANES[p], r * n * n)?;
        field.lines[p] = floats(LINES[p], r * n)?;
    }
    let mask = tensors.tensor("alpha_mask").ok().map(|t| t.data().iter().map(|&b| b != 0).collect());
    Ok((field, mask, meta))
}
