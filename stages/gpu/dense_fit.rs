//! The dense fit on the device: not yet ported to the matrix-free projector (work in progress
//! on this branch; see the issue note). Until then it says so.
use super::Gpu;
use crate::train::dense_tv::DenseFitted;
use crate::train::fit::{LogRow, Views};
use crate::train::params::TrainParams;
use crate::train::render::Renderer;
use std::sync::Arc;
pub fn fit(
    _gpu: &Arc<Gpu>,
    _params: &TrainParams,
    _views: &Views,
    _renderer: &Renderer,
    _on_log: impl FnMut(&LogRow),
) -> anyhow::Result<DenseFitted> {
    anyhow::bail!(
        "the dense fit on the GPU is being ported to the matrix-free projector: use [train] backend = \"cpu\""
    )
}
