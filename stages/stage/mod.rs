//! The pipeline's stages, one module each (their graph is declared in [`crate::pipeline`]).
//!
//! Each module reads like the SPEC: its `Params`, its inputs and outputs, a `VERSION`, and one
//! pure `run`. Stages know nothing about caching.

pub mod drr;
pub mod grid;
pub mod hu;
pub mod ingest;
pub mod metrics;
pub mod phantom;
pub mod select;
pub mod sweep;
pub mod train;

/// Every stage name, in pipeline order (`phantom` only for phantom datasets).
pub const STAGE_NAMES: &[&str] = &["phantom", "ingest", "hu", "drr", "train", "grid", "sweep", "select", "metrics"];

/// Serialises a stage's parameters for its cache key.
pub(crate) fn params_json<P: serde::Serialize>(params: &P) -> serde_json::Value {
    serde_json::to_value(params).expect("stage parameters serialise to JSON")
}

/// The MetaImage volume `<name>.mhd` + `<name>.raw` that input stage `stage` produced.
pub(crate) fn read_volume<T: crate::formats::mhd::MetaElement>(
    ctx: &crate::engine::Context,
    stage: &str,
    name: &str,
) -> anyhow::Result<crate::volume::Volume<T>> {
    use anyhow::Context as _;
    let header = String::from_utf8(ctx.read(stage, &format!("{name}.mhd"))?)
        .with_context(|| format!("{stage}/{name}.mhd is not text"))?;
    Ok(crate::formats::mhd::decode(&header, &ctx.read(stage, &format!("{name}.raw"))?)?)
}
