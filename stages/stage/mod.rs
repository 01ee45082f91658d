//! The pipeline's stages, one module each (their graph is declared in [`crate::pipeline`]).
//!
//! Each module reads like the SPEC: its `Params`, its inputs and outputs, a `VERSION`, and one
//! pure `run`. Stages know nothing about caching.

pub mod blobs;
pub mod drr;
pub mod grid;
pub mod hu;
pub mod ingest;
pub mod metrics;
pub mod phantom;
pub mod select;
pub mod sweep;
pub mod train;

use crate::artifacts::{Artifact, VolumeArtifact};
use crate::engine::{Context, Output};
use anyhow::Context as _;

/// Every stage name, in pipeline order (`phantom` only for phantom datasets, `blobs` only for
/// `[select] localize = "blob"`).
pub const STAGE_NAMES: &[&str] =
    &["phantom", "ingest", "hu", "drr", "train", "grid", "sweep", "blobs", "select", "metrics"];

/// Serialises a stage's parameters for its cache key.
pub(crate) fn params_json<P: serde::Serialize>(params: &P) -> serde_json::Value {
    serde_json::to_value(params).expect("stage parameters serialise to JSON")
}

/// The bytes of input artifact `a`.
pub(crate) fn read(ctx: &Context, a: Artifact) -> anyhow::Result<Vec<u8>> {
    ctx.read(a.stage, a.file)
}

/// Input artifact `a`, a JSON document.
pub(crate) fn read_json<T: serde::de::DeserializeOwned>(ctx: &Context, a: Artifact) -> anyhow::Result<T> {
    serde_json::from_slice(&read(ctx, a)?).with_context(|| format!("{}/{}", a.stage, a.file))
}

/// Input volume `v`, its header and its data.
pub(crate) fn read_volume<T: crate::formats::mhd::MetaElement>(
    ctx: &Context,
    v: VolumeArtifact,
) -> anyhow::Result<crate::volume::Volume<T>> {
    let header = String::from_utf8(ctx.read(v.stage, v.header)?)
        .with_context(|| format!("{}/{} is not text", v.stage, v.header))?;
    Ok(crate::formats::mhd::decode(&header, &ctx.read(v.stage, v.raw)?)?)
}

/// Volume `v` as this stage's two outputs, header and data.
pub(crate) fn volume_outputs<T: crate::formats::mhd::MetaElement>(
    v: VolumeArtifact,
    volume: &crate::volume::Volume<T>,
) -> [Output; 2] {
    let (header, raw) = crate::formats::mhd::encode(volume, v.raw);
    [Output::new(v.header, header), Output::new(v.raw, raw)]
}
