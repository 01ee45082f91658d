//! Pure numeric kernels: no I/O, no pipeline knowledge.
//!
//! [`consensus`] turns radiologist contours into pylidc-exact nodule ground truth (its public
//! API, re-exporting what it needs from [`annotation`], [`cluster`] and [`mask`]); [`polygon`]
//! is the matplotlib-exact point-in-polygon the annotation masks use.
pub mod annotation;
pub mod cluster;
pub mod components;
pub mod consensus;
pub mod localization;
pub mod lung_field;
pub mod marching_cubes;
pub mod mask;
pub mod mesh;
pub mod morphology;
pub mod polygon;
pub mod raymarch;
pub mod stats;
pub mod trilinear;
