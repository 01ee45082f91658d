//! `train`: fits the VM attenuation field to the three DRRs (SPEC §3 train).
//!
//! Inputs: `drr/cameras.json` (the nominal cameras: poses are read, never recomputed) and
//! `drr/drr_<view>.exr`; with `model = "truth"` (a ceiling, no fit) also `hu/ct_unit`, which it
//! puts on the lattice, the images then only scoring it. Outputs: `model.safetensors` (factors,
//! alpha mask, metadata), `train_log.csv` (iteration, loss, photo, L1, TV, PSNR per view, lr)
//! and `loss.svg`. No output holds a wall time, so whoever fits a key writes the same bytes; the
//! fit's time is the run's (`run_report.json`).

use crate::artifacts::{is_drr_image, CAMERAS, CT_UNIT, LOSS_PLOT, MODEL, TRAIN_LOG};
use crate::engine::{Context, Output, Stage};
use crate::formats::model::{self, ModelMeta, PatientSpace};
use crate::formats::svg;
use crate::geometry::{Aabb, SceneFrame};
use crate::gpu;
use crate::kernels::raymarch::VolumeField;
use crate::stage::drr::CameraSet;
use crate::stage::grid::lattice_geometry;
use crate::train::dense_tv::{self, DenseFitted};
use crate::train::fit::{fit, renderer, Fitted, LogRow, Views};
use crate::train::params::FieldModel;
use crate::train::render::Renderer;
use crate::train::truth;
use crate::volume::Volume;
use std::fmt::Write as _;

pub const VERSION: u32 = 9;

/// `[train]` is the fit's own parameter table.
pub use crate::train::params::{Backend, TrainParams as Params};

pub struct Train {
    pub params: Params,
}

impl Train {
    /// Where this stage runs: `auto` resolved to `cpu` or `gpu` (for the key and the run alike).
    fn backend(&self) -> Backend {
        gpu::resolve(self.params.backend, "[train]")
    }

    /// Runs `work` on `[train] threads` workers (0: rayon's global pool, all cores).
    fn in_pool<R: Send>(&self, work: impl FnOnce() -> R + Send) -> anyhow::Result<R> {
        if self.params.threads == 0 {
            return Ok(work());
        }
        Ok(rayon::ThreadPoolBuilder::new().num_threads(self.params.threads).build()?.install(work))
    }
}

impl Stage for Train {
    fn name(&self) -> &'static str {
        "train"
    }
    fn version(&self) -> u32 {
        VERSION
    }
    fn inputs(&self) -> &'static [&'static str] {
        &["drr", "hu"]
    }
    fn params(&self) -> serde_json::Value {
        Params { backend: self.backend(), ..self.params.clone() }.key()
    }
    fn reads(&self, stage: &str, output: &str) -> bool {
        match stage {
            // Only the ceiling reads the CT, so the fits' keys do not depend on it.
            "hu" => self.params.model == FieldModel::Truth && CT_UNIT.holds(output),
            _ => output == CAMERAS.file || is_drr_image(output),
        }
    }
    fn run(&self, ctx: &Context) -> anyhow::Result<Vec<Output>> {
        let backend = self.backend();
        // Before reading anything: a missing adapter or an option the shaders lack fails fast.
        let device = match backend {
            Backend::Gpu if self.params.model != FieldModel::Truth => {
                gpu::fit::check_supported(&self.params)?;
                Some(gpu::require("[train]")?)
            }
            _ => None,
        };
        let set: CameraSet = super::read_json(ctx, CAMERAS)?;
        let images: Vec<Vec<f32>> =
            set.read_images(|name| ctx.read(CAMERAS.stage, name))?.into_iter().map(|image| image.pixels).collect();
        let views = Views { cameras: &set.cameras, images: &images, aabb: set.aabb };
        let placed = Placed { frame: &set.frame, aabb: &set.aabb };
        let (model_bytes, log) = match (self.params.model, device) {
            (FieldModel::Truth, _) => self.truth(ctx, &set, &views)?,
            (FieldModel::DenseTv, Some(device)) => self.fit_dense(&views, placed, |params, views, renderer| {
                gpu::dense_fit::fit(&device, params, views, renderer, |_| {})
            })?,
            (FieldModel::DenseTv, None) => self.fit_dense(&views, placed, |params, views, renderer| {
                Ok(dense_tv::fit(params, views, renderer, |_| {}))
            })?,
            (FieldModel::Vm, Some(device)) => {
                self.fit_vm(&views, placed, |params, views| gpu::fit::fit(&device, params, views, |_| {}))?
            }
            (FieldModel::Vm, None) => {
                self.fit_vm(&views, placed, |params, views| self.in_pool(|| fit(params, views, |_| {})))?
            }
        };
        let views_named: Vec<&str> = set.cameras.iter().map(|c| c.view.name()).collect();
        Ok(vec![
            Output::new(MODEL.file, model_bytes),
            Output::new(TRAIN_LOG.file, log_csv(&log, &views_named)),
            Output::new(LOSS_PLOT.file, loss_svg(&log)),
        ])
    }
}

impl Train {
    /// The VM factors fitted by `fit_on` (the CPU or the GPU loop): the model file and the log.
    fn fit_vm(
        &self,
        views: &Views,
        placed: Placed,
        fit_on: impl FnOnce(&Params, &Views) -> anyhow::Result<Fitted>,
    ) -> anyhow::Result<(Vec<u8>, Vec<LogRow>)> {
        let params = &self.params;
        let fitted = fit_on(params, views)?;
        let meta = ModelMeta {
            model: FieldModel::Vm,
            grid: params.grid,
            rank: params.vm.rank,
            aabb: views.aabb,
            shift: params.vm.shift,
            scale: params.scale,
            step: fitted.renderer.step,
            seed: params.vm.seed,
            iterations: params.vm.iterations,
            backend: self.backend().name().into(),
            parameters: fitted.field.len(),
            patient_space: Some(placed.patient_space(params.grid)),
        };
        let mask = fitted.mask.as_ref().map(|m| m.nodes.as_slice());
        Ok((model::encode(&fitted.field, mask, &meta)?, fitted.log))
    }

    /// The dense lattice (`model = "dense_tv"`) fitted by `fit_on` (FISTA on the CPU or the
    /// GPU; `A` is built on the CPU either way): the model file and the log.
    fn fit_dense(
        &self,
        views: &Views,
        placed: Placed,
        fit_on: impl FnOnce(&Params, &Views, &Renderer) -> anyhow::Result<DenseFitted> + Send,
    ) -> anyhow::Result<(Vec<u8>, Vec<LogRow>)> {
        let params = &self.params;
        let renderer = renderer(params, views.aabb);
        let fitted = self.in_pool(|| fit_on(params, views, &renderer))??;
        let meta =
            self.lattice_meta(FieldModel::DenseTv, &renderer, params.dense_tv.iterations, self.backend(), placed);
        Ok((model::encode_dense(&fitted.sigma, &meta)?, fitted.log))
    }

    /// The metadata of σ held at the lattice's nodes (a dense fit or the ceiling).
    fn lattice_meta(
        &self,
        model: FieldModel,
        renderer: &Renderer,
        iterations: usize,
        backend: Backend,
        placed: Placed,
    ) -> ModelMeta {
        let n = self.params.grid;
        ModelMeta {
            model,
            grid: n,
            rank: 0,
            aabb: renderer.lattice.aabb,
            shift: 0.0,
            scale: self.params.scale,
            step: renderer.step,
            seed: 0,
            iterations,
            backend: backend.name().into(),
            parameters: n * n * n,
            patient_space: Some(placed.patient_space(n)),
        }
    }

    /// The ceiling, `model = "truth"`: the CT averaged over each lattice cell (no fit), scored
    /// against the views as a fit's log row is. The model file is a dense one.
    fn truth(&self, ctx: &Context, set: &CameraSet, views: &Views) -> anyhow::Result<(Vec<u8>, Vec<LogRow>)> {
        let params = &self.params;
        let ct_unit: Volume<f32> = super::read_volume(ctx, CT_UNIT)?;
        let renderer = renderer(params, views.aabb);
        let ct = VolumeField::new(&ct_unit, &set.frame);
        let ct_voxel =
            ct_unit.geometry.spacing_mm.iter().copied().fold(f64::INFINITY, f64::min) / set.frame.mm_per_unit;
        let sigma_per_value = set.attenuation_scale / params.scale;
        let sigma = self.in_pool(|| truth::cell_means(&ct, ct_voxel, &renderer.lattice, sigma_per_value))?;
        let row = self.in_pool(|| dense_tv::evaluate_views(params, views, &renderer, &sigma))?;
        let placed = Placed { frame: &set.frame, aabb: &set.aabb };
        let meta = self.lattice_meta(FieldModel::Truth, &renderer, 0, Backend::Cpu, placed);
        Ok((model::encode_dense(&sigma, &meta)?, vec![row]))
    }
}

/// The scene a fit's lattice spans: its box and how the box sits in the patient.
#[derive(Clone, Copy)]
struct Placed<'a> {
    frame: &'a SceneFrame,
    aabb: &'a Aabb,
}

impl Placed<'_> {
    /// Where an `n³` lattice's nodes lie in the patient, as the grid stage places them.
    fn patient_space(self, n: usize) -> PatientSpace {
        let g = lattice_geometry(n, self.aabb, self.frame);
        PatientSpace::axis_aligned(g.origin_mm, g.spacing_mm)
    }
}

fn log_csv(log: &[LogRow], views: &[&str]) -> String {
    let mut s = String::from("iteration,loss,photo,l1,tv,tv3d");
    for v in views {
        let _ = write!(s, ",psnr_{v}_db");
    }
    s.push_str(",lr\n");
    for r in log {
        let _ = write!(s, "{},{:e},{:e},{:e},{:e},{:e}", r.iteration, r.loss, r.photo, r.l1, r.tv, r.tv3d);
        for p in &r.psnr_db {
            let _ = write!(s, ",{p:.4}");
        }
        let _ = writeln!(s, ",{:e}", r.lr);
    }
    s
}

fn loss_svg(log: &[LogRow]) -> String {
    let series = |name, colour, f: fn(&LogRow) -> f64| svg::Series {
        name,
        colour,
        points: log.iter().map(|r| (r.iteration as f64, f(r))).collect(),
    };
    svg::log_plot(
        "Training loss",
        "iteration",
        &[
            series("total loss", "#1f77b4", |r| r.loss),
            series("photometric (MSE)", "#d62728", |r| r.photo),
            series("L1 (before λ1)", "#2ca02c", |r| r.l1),
            series("TV (before λ2)", "#9467bd", |r| r.tv),
            series("3-D TV (before λ3)", "#8c564b", |r| r.tv3d),
        ],
    )
}
