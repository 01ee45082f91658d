//! `[train]`: which field is fitted, and each field's own keys (`[train.dense_tv]`,
//! `[train.vm]`). The defaults are the shipped method: the dense 128³ lattice under a smoothed
//! 3-D TV. The cache key holds the keys of the model in use and nothing else ([`TrainParams::key`]).

use super::adam::AdamParams;
use super::regularize::TvNorm;
use super::render::{PhotoLoss, MAX_GRID};
use anyhow::bail;
use serde::{Deserialize, Serialize};

pub use crate::backend::Backend;

/// What `train` fits.
/// A fit's arrays a lattice node: the dense model's σ, look-ahead, back-projection, gradient,
/// curvature and TV directions (about twelve f32s); the VM model's field, gradient and masks hold
/// fewer.
pub const PEAK_BYTES_A_NODE: u64 = 48;
/// A fit's bytes a ray: its origin and direction, the measured and rendered depth and the
/// residual (f64s), and the projector's weights.
pub const PEAK_BYTES_A_RAY: u64 = 96;

#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FieldModel {
    /// σ itself on the N³ lattice, fitted to the optical depths under a smoothed 3-D TV by a
    /// convex solver ([`super::dense_tv`]; its steps on the CPU or the GPU).
    #[default]
    DenseTv,
    /// TensoRF's vector–matrix factors (SPEC §3 train).
    Vm,
    /// No fit: the true CT averaged over each lattice cell ([`super::truth`]), the field a
    /// perfect fit would reach on that lattice. A lab instrument for measuring `select`.
    Truth,
}

impl FieldModel {
    pub fn is_vm(&self) -> bool {
        *self == FieldModel::Vm
    }

    /// The model's name in `[train] model`.
    pub fn name(self) -> &'static str {
        match self {
            FieldModel::DenseTv => "dense_tv",
            FieldModel::Vm => "vm",
            FieldModel::Truth => "truth",
        }
    }
}

/// `[train]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TrainParams {
    /// What is fitted.
    pub model: FieldModel,
    /// Lattice nodes per axis (N).
    pub grid: usize,
    /// s in Î = exp(−s · Σ σ δ).
    pub scale: f64,
    /// Evaluate and log every this many steps (and at the last).
    pub log_every: usize,
    /// Where the fit runs (part of the cache key: backends differ in rounding).
    pub backend: Backend,
    /// Worker threads (0: all cores). Results do not depend on it: not part of the cache key.
    pub threads: usize,
    /// `model = "dense_tv"`.
    pub dense_tv: DenseTvParams,
    /// `model = "vm"`.
    pub vm: VmParams,
}

/// `[train.dense_tv]`: σ on the lattice under a smoothed 3-D TV, by FISTA.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct DenseTvParams {
    /// The most FISTA steps, each a projection and back-projection of every ray.
    pub iterations: usize,
    /// The fit stops once a step changes σ by at most this fraction of its norm.
    pub tolerance: f64,
    /// λ of the smoothed TV, per node, against the data term per ray.
    pub lambda: f64,
    /// ε of the smoothed TV `√(|∇σ|² + ε²)`, in σ per lattice step.
    pub epsilon: f64,
}

/// `[train.vm]`: TensoRF's vector–matrix factors, by Adam on ray batches (SPEC §3).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct VmParams {
    /// Components per plane/line pair (R).
    pub rank: usize,
    /// Δ in σ = ReLU(f + Δ).
    pub shift: f64,
    /// Adam iterations.
    pub iterations: usize,
    pub batch_rays: usize,
    pub lr: f64,
    /// Learning rate at the end over at the start (exponential decay).
    pub lr_decay_ratio: f64,
    pub lambda_l1: f64,
    pub lambda_tv: f64,
    pub tv_norm: TvNorm,
    /// Weight of the 3-D TV of the composed field F (0: off, as in the paper).
    pub lambda_tv3d: f64,
    /// What the photometric term compares: intensities (the paper) or optical depths.
    pub loss: PhotoLoss,
    /// Factors start as `init_scale · N(0, 1)`.
    pub init_scale: f64,
    /// Iterations after which the alpha mask is (re)computed.
    pub alpha_mask_iterations: Vec<usize>,
    pub alpha_threshold: f64,
    /// Seed of the initial factors, the batches and the ray jitter.
    pub seed: u64,
}

impl Default for TrainParams {
    fn default() -> Self {
        TrainParams {
            model: FieldModel::DenseTv,
            grid: 128,
            scale: 1.0,
            log_every: 100,
            backend: Backend::Cpu,
            threads: 0,
            dense_tv: DenseTvParams::default(),
            vm: VmParams::default(),
        }
    }
}

impl Default for DenseTvParams {
    fn default() -> Self {
        DenseTvParams { iterations: 500, tolerance: 1e-4, lambda: 1e-2, epsilon: 1e-3 }
    }
}

impl Default for VmParams {
    fn default() -> Self {
        VmParams {
            rank: 16,
            shift: 0.0,
            iterations: 3000,
            batch_rays: 2048,
            lr: 0.02,
            lr_decay_ratio: 0.1,
            lambda_l1: 1e-4,
            lambda_tv: 1e-5,
            tv_norm: TvNorm::L1,
            lambda_tv3d: 1e-4,
            loss: PhotoLoss::Intensity,
            init_scale: 0.1,
            alpha_mask_iterations: vec![1500, 2500],
            alpha_threshold: 1e-3,
            seed: 0,
        }
    }
}

impl TrainParams {
    /// SPEC §3's TensoRF field: the VM factors on a 64³ lattice.
    pub fn tensorf() -> TrainParams {
        TrainParams { model: FieldModel::Vm, grid: 64, ..TrainParams::default() }
    }

    pub fn check(&self) -> anyhow::Result<()> {
        if !(2..=MAX_GRID).contains(&self.grid) {
            bail!("[train] grid must be in [2, {MAX_GRID}] (got {})", self.grid);
        }
        if !(self.scale.is_finite() && self.scale > 0.0) {
            bail!("[train] scale must be positive (got {})", self.scale);
        }
        self.dense_tv.check()?;
        self.vm.check()
    }

    /// About how many bytes one patient's fit holds at its peak, with `rays` pixels in its three
    /// views: σ and the solver's arrays a lattice node ([`PEAK_BYTES_A_NODE`]), each ray's geometry,
    /// measurement and residuals ([`PEAK_BYTES_A_RAY`]).
    pub fn peak_bytes_estimate(&self, rays: u64) -> u64 {
        (self.grid as u64).pow(3) * PEAK_BYTES_A_NODE + rays * PEAK_BYTES_A_RAY
    }

    /// The canonical form of what the model in use reads: the stage's cache key. `threads` is
    /// not in it (results do not depend on it), and neither is the other model's table.
    pub fn key(&self) -> serde_json::Value {
        let (grid, scale, model) = (self.grid, self.scale, self.model.name());
        match self.model {
            // The CT on the lattice depends on the lattice and s alone.
            FieldModel::Truth => serde_json::json!({ "model": model, "grid": grid, "scale": scale }),
            FieldModel::DenseTv => serde_json::json!({
                "model": model, "grid": grid, "scale": scale, "log_every": self.log_every,
                "backend": self.backend, "dense_tv": self.dense_tv,
            }),
            FieldModel::Vm => serde_json::json!({
                "model": model, "grid": grid, "scale": scale, "log_every": self.log_every,
                "backend": self.backend, "vm": self.vm,
            }),
        }
    }

    /// Whether the three views are evaluated and a row logged after `done` steps.
    pub fn logs_after(&self, done: usize) -> bool {
        done.is_multiple_of(self.log_every.max(1)) || done == self.steps()
    }

    /// The fit's length: Adam iterations (VM) or FISTA steps (dense).
    pub fn steps(&self) -> usize {
        match self.model {
            FieldModel::Vm => self.vm.iterations,
            FieldModel::DenseTv => self.dense_tv.iterations,
            FieldModel::Truth => 0,
        }
    }
}

impl DenseTvParams {
    fn check(&self) -> anyhow::Result<()> {
        if self.iterations == 0 {
            bail!("[train.dense_tv] iterations must be at least 1");
        }
        if !(self.epsilon.is_finite() && self.epsilon > 0.0) {
            bail!("[train.dense_tv] epsilon must be positive (got {})", self.epsilon);
        }
        if !(0.0..1.0).contains(&self.tolerance) {
            bail!("[train.dense_tv] tolerance must be at least 0 and under 1 (got {})", self.tolerance);
        }
        if !(self.lambda.is_finite() && self.lambda >= 0.0) {
            bail!("[train.dense_tv] lambda must be 0 or more (got {})", self.lambda);
        }
        Ok(())
    }
}

impl VmParams {
    fn check(&self) -> anyhow::Result<()> {
        if self.rank == 0 || self.iterations == 0 || self.batch_rays == 0 {
            bail!("[train.vm] rank, iterations and batch_rays must be at least 1");
        }
        for (key, v) in [("lr", self.lr), ("lr_decay_ratio", self.lr_decay_ratio)] {
            if !(v.is_finite() && v > 0.0) {
                bail!("[train.vm] {key} must be positive (got {v})");
            }
        }
        Ok(())
    }

    /// Whether the alpha mask is (re)computed after `done` iterations.
    pub fn remasks_after(&self, done: usize) -> bool {
        self.alpha_mask_iterations.contains(&done)
    }

    /// The optimiser: TensoRF's Adam with the configured rate and decay.
    pub fn adam(&self) -> AdamParams {
        AdamParams {
            lr: self.lr,
            beta1: 0.9,
            beta2: 0.99,
            eps: 1e-8,
            decay_ratio: self.lr_decay_ratio,
            iterations: self.iterations,
        }
    }
}
