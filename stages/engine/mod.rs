//! The engine: cached, content-hashed, streaming execution of a stage graph.
//!
//! It knows nothing about CT. A [`Stage`] is a pure function of its input artifacts and its
//! own parameters; the engine keys it by a blake3 hash of exactly those (see [`key`]), stores
//! what it returns as content-addressed blobs with a manifest (see [`store`]), and runs many
//! patients through the stages at once (see [`run`]).

pub mod export;
pub mod files;
pub mod key;
pub mod lease;
pub mod leftovers;
pub mod lock;
pub mod plan;
pub mod preview;
pub mod progress;
pub mod remote;
pub mod run;
pub mod source;
pub mod stage;
pub mod store;
pub mod summary;

pub use key::Hash;
pub use stage::{Context, InputFile, Output, OutputRef, Stage, StageGraph, SOURCE};
