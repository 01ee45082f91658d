//! Pure numeric kernels: no I/O, no pipeline knowledge.
//!
//! [`consensus`] turns radiologist contours into pylidc-exact nodule ground truth (its public
//! API, re-exporting what it needs from [`annotation`], [`cluster`] and [`mask`]); [`polygon`]
//! is the matplotlib-exact point-in-polygon the annotation masks use. The sweep/select kernels —
//! [`components`], [`morphology`], [`stats`] percentiles, [`marching_cubes`] and [`mesh`] — are
//! described, with what each equals, in `docs/kernels.md`, as are the cohort metrics'
//! [`statistics`] (correlations, Wilcoxon, bootstrap CIs, Bland–Altman, as scipy computes them)
//! and the 3-D image [`filters`] (Gaussian, blob response, distance transform, Otsu, per-slice
//! hole filling, each equal to its scipy / scikit-image counterpart), whose Hessian filter takes
//! its eigenvalues from [`eigen3`]. [`robust_fit`] is the bounded
//! soft-L1 least squares (scipy's `least_squares(loss="soft_l1")`) that sizes a nodule in the views.
pub mod annotation;
pub mod cluster;
pub mod components;
pub mod consensus;
pub mod eigen3;
pub mod filters;
pub mod localization;
pub mod lung_field;
pub mod lung_mask;
pub mod marching_cubes;
pub mod mask;
pub mod mesh;
pub mod morphology;
pub mod polygon;
pub mod raymarch;
pub mod robust_fit;
pub mod statistics;
pub mod stats;
pub mod trilinear;
pub mod wide;
