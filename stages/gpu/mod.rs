//! The GPU backend: the CPU's algorithms, kernel for kernel, as WGSL compute shaders
//! (`shaders/`, one kernel per file) run through wgpu on Vulkan (lavapipe in CI, NVIDIA's
//! driver on a real GPU). Each shader has one host file here that mirrors it — its bindings,
//! uniform struct and dispatch size — and the table in `docs/gpu.md` pairs each with the CPU
//! function it reproduces.
//!
//! - [`device`]: adapter and device, errors that say what to do.
//! - [`kernel`], [`buffers`]: pipelines and bind groups, buffers and read-back.
//! - [`drr_march`]: the DRR stage's Beer–Lambert march through the CT.
//! - [`compose`], [`render`], [`grad_from_fixed`], [`contract_planes`], [`contract_lines`], [`l1`], [`tv`], [`tv_dense`], [`adam`],
//!   [`alpha_mask`]: one training iteration, and [`fit`], the loop that keeps it on the device.
//! - [`sheet_project`], [`sheet_back`], [`tv_direction`], [`fista_step`], [`fista_state`],
//!   [`fista_restart`]: one step of the dense model's FISTA, and [`dense_fit`], its loop on the
//!   device.

pub mod adam;
pub mod alpha_mask;
pub mod buffers;
pub mod compose;
pub mod contract_lines;
pub mod contract_planes;
pub mod dense_fit;
pub mod device;
pub mod drr_march;
pub mod fista_restart;
pub mod fista_state;
pub mod fista_step;
pub mod fit;
pub mod grad_from_fixed;
pub mod kernel;
pub mod l1;
pub mod render;
pub mod sheet_back;
pub mod sheet_project;
pub mod tv;
pub mod tv_dense;
pub mod tv_direction;

pub use device::Gpu;

use std::collections::BTreeSet;
use std::sync::Mutex;

pub use crate::backend::Backend;

/// The concrete backend for `backend`: `Auto` becomes `Gpu` when a hardware adapter opens, else
/// `Cpu` (said once per `table`, e.g. `"[train]"`, on stderr). Stages resolve before they name
/// their cache key, so a key never says `auto`.
pub fn resolve(backend: Backend, table: &str) -> Backend {
    if backend != Backend::Auto {
        return backend;
    }
    let why_not = match Gpu::shared() {
        Ok(gpu) if !gpu.is_software() => return Backend::Gpu,
        Ok(gpu) => format!("only the software adapter {} was found", gpu.describe()),
        Err(e) => format!("no GPU adapter found ({e})"),
    };
    static SAID: Mutex<BTreeSet<String>> = Mutex::new(BTreeSet::new());
    if SAID.lock().map(|mut said| said.insert(table.to_string())).unwrap_or(false) {
        eprintln!("{why_not}; {table} backend = \"auto\" runs on the CPU");
    }
    Backend::Cpu
}

/// The shared device for a stage whose `table` asked for `backend = "gpu"`, or an error that
/// names the key and says what to do.
pub fn require(table: &str) -> anyhow::Result<std::sync::Arc<Gpu>> {
    Gpu::shared().map_err(|e| {
        anyhow::anyhow!(
            "{table} backend = \"gpu\", but no GPU adapter is usable: {e}. Install a Vulkan driver (Debian: \
             `apt-get install mesa-vulkan-drivers libvulkan1`, which includes the lavapipe software renderer), \
             or set {table} backend = \"cpu\" (or \"auto\": a GPU when there is one, else the CPU)"
        )
    })
}
