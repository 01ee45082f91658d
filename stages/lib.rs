//! aret-pipe: measure lung nodules in 3D from only three X-rays.
//!
//! A streaming pipeline of cached stages (SPEC §3): DICOM CT ingest → HU normalisation → DRRs →
//! attenuation-field fit → density grid → threshold sweep → nodule selection → cohort metrics (DRRs and
//! fit on the CPU, or on a GPU through wgpu: [`gpu`]). The [`engine`] runs any graph of pure
//! [`engine::Stage`]s with content-hashed caching and knows nothing about CT; [`stage`] holds
//! the stages; [`formats`] the file formats; [`config`] the `pipeline.toml` schema;
//! [`commands`] what the CLI calls.

pub mod artifacts;
pub mod backend;
pub mod commands;
pub mod config;
pub mod dataset;
pub use aret_pipe_engine as engine;
pub mod formats;
pub mod geometry;
pub mod gpu;
pub mod kernel_command;
pub mod kernels;
pub mod phantom;
pub mod pipeline;
pub mod resources;
pub mod shard;
pub mod stage;
pub mod submit;
pub mod train;
pub mod volume;

pub use stage::STAGE_NAMES;
