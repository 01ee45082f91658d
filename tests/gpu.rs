//! The GPU backend against the CPU backend, on a Vulkan adapter — in CI, Mesa's
//! lavapipe. DRR pixels within 1e-5 relative; one training step's factor gradients within
//! 1e-4; a 300-iteration fit within 1% in loss, repeated bit for bit; a missing adapter is an error that names the key, `auto` falls back once and
//! records the backend that ran, and the cache key never says `auto`.
//!
//! Without an adapter these tests skip with the reason, except under `CI=true`, where CI has
//! installed lavapipe and a missing adapter is a CI bug: they fail.

mod support;

use aret_pipe::geometry::{Aabb, Camera};
use aret_pipe::gpu::device::{Gpu, GpuOptions};
use aret_pipe::gpu::fit::DeviceFit;
use aret_pipe::gpu::Backend;
use aret_pipe::stage::drr::{render_views, Params as DrrParams, RoiCenter};
use aret_pipe::train::fit::{fit, gradient, ray_pool, renderer, BatchStep, Schedule, Step, StepBuffers, Views};
use aret_pipe::train::params::{DenseTvParams, TrainParams, VmParams};
use aret_pipe::train::regularize::TvNorm;
use aret_pipe::train::render::PhotoLoss;
use std::path::Path;
use std::process::{Command, Output};
use std::sync::Arc;
use support::chest::chest_ct;
use support::dicom_writer::{default_name, series, write_series};

const BIN: &str = env!("CARGO_BIN_EXE_aret-pipe");

/// The process's device (the one the stages use), or `None` with the reason printed.
fn device() -> Option<Arc<Gpu>> {
    match Gpu::shared() {
        Ok(gpu) => {
            eprintln!("GPU tests on {}", gpu.describe());
            Some(gpu)
        }
        Err(e) => skip_or_fail(&e),
    }
}

fn skip_or_fail<T>(reason: &str) -> Option<T> {
    if std::env::var("CI").is_ok_and(|v| v == "true") {
        panic!("CI installs lavapipe (mesa-vulkan-drivers), yet no GPU adapter opened: {reason}");
    }
    eprintln!("skipped: no GPU adapter ({reason}); install mesa-vulkan-drivers for lavapipe");
    None
}

fn drr_params(backend: Backend) -> DrrParams {
    DrrParams { width_px: 48, height_px: 48, roi_center: RoiCenter::Mm([0.0; 3]), backend, ..DrrParams::default() }
}

/// The CPU's three DRRs of [`chest_ct`]: what the training tests fit.
fn views() -> (Vec<Camera>, Vec<Vec<f32>>, Aabb) {
    let (set, images) = render_views(&drr_params(Backend::Cpu), &chest_ct(true), [0.0; 3], "explicit").unwrap();
    (set.cameras, images, set.aabb)
}

/// A small VM fit with `vm`'s keys (rank 6, 1024 rays a batch) on a 24³ lattice.
fn small(vm: VmParams) -> TrainParams {
    TrainParams { grid: 24, log_every: 50, vm: VmParams { rank: 6, batch_rays: 1024, ..vm }, ..TrainParams::tensorf() }
}

/// max |a − b| / max |b|: the error relative to the magnitude of the reference.
fn relative_to_max(a: &[f32], b: &[f32]) -> f64 {
    let scale = b.iter().fold(0f64, |m, &x| m.max(f64::from(x).abs()));
    let err = a.iter().zip(b).fold(0f64, |m, (&x, &y)| m.max((f64::from(x) - f64::from(y)).abs()));
    err / scale
}

#[test]
fn drr_pixels_agree_with_the_cpu_within_1e_5_relative() {
    let Some(_gpu) = device() else { return };
    let ct = chest_ct(true);
    // Oblique views too: rays that cross voxels at every angle.
    for offsets in [[0.0; 3], [17.0, -9.5, 6.0]] {
        let render = |backend| {
            let params = DrrParams { view_angle_offsets_deg: offsets, ..drr_params(backend) };
            render_views(&params, &ct, [0.0; 3], "explicit").unwrap().1
        };
        let (cpu, gpu) = (render(Backend::Cpu), render(Backend::Gpu));
        let mut worst = 0f64;
        for (c, g) in cpu.iter().zip(&gpu) {
            assert_eq!(c.len(), g.len());
            for (&c, &g) in c.iter().zip(g) {
                worst = worst.max((f64::from(g) - f64::from(c)).abs() / f64::from(c));
            }
        }
        let darkest = cpu.iter().flatten().fold(1f32, |m, &x| m.min(x));
        eprintln!(
            "DRR, view offsets {offsets:?}: worst relative pixel difference {worst:.2e} (darkest pixel {darkest:.3})"
        );
        assert!(darkest < 0.2, "the scene attenuates: {darkest}");
        assert!(worst <= 1e-5, "GPU DRR pixels differ from the CPU's by {worst:.2e} relative");
    }
}

/// Both backends' gradients of one step of `params` at its initial field, on the first batch
/// of its schedule; with `mask_percentile`, after an alpha mask keeping about that share of σ.
fn compare_step(gpu: &Gpu, params: &TrainParams, mask_percentile: Option<f64>) -> (Step, Step) {
    let (cameras, images, aabb) = views();
    let views = Views { cameras: &cameras, images: &images, aabb };
    let renderer = renderer(params, aabb);
    let per_view = views.rays();
    let pool = ray_pool(&per_view, &aabb);
    let (field, mut schedule) = Schedule::start(params, pool.len());
    let drawn = schedule.next_batch(params.vm.batch_rays, renderer.step).to_vec();
    let batch: Vec<_> = drawn.iter().map(|&(i, _)| pool[i]).collect();
    let offsets: Vec<f64> = drawn.iter().map(|&(_, o)| o).collect();
    let mut device = DeviceFit::new(gpu, params, &renderer, &field, batch.len(), &per_view).unwrap();
    let mut mask = None;
    if let Some(p) = mask_percentile {
        // A threshold near the p-th percentile of the nodes' σ (a mask with some bite), in the
        // widest gap between neighbouring values there: no node sits within rounding of it.
        let mut sigma: Vec<f64> = field.compose().iter().map(|&f| f64::from(f).max(0.0)).collect();
        sigma.sort_by(f64::total_cmp);
        let at = (p * sigma.len() as f64) as usize;
        let widest =
            (at - 20..at + 20).max_by(|&a, &b| (sigma[a + 1] - sigma[a]).total_cmp(&(sigma[b + 1] - sigma[b])));
        let k = widest.expect("a window");
        let s = 0.5 * (sigma[k] + sigma[k + 1]);
        let threshold = 1.0 - (-s * renderer.step * renderer.scale).exp();
        let masked = TrainParams { vm: VmParams { alpha_threshold: threshold, ..params.vm.clone() }, ..params.clone() };
        device = DeviceFit::new(gpu, &masked, &renderer, &field, batch.len(), &per_view).unwrap();
        device.remask().unwrap();
        let cpu_mask = renderer.alpha_mask(&field.compose(), threshold);
        let gpu_mask = device.mask().unwrap().expect("a mask after remask");
        let kept = cpu_mask.nodes.iter().filter(|&&k| k).count();
        assert!(kept > cpu_mask.nodes.len() / 10 && kept < cpu_mask.nodes.len() * 9 / 10, "kept {kept}");
        assert_eq!(gpu_mask.nodes, cpu_mask.nodes, "alpha masks differ");
        mask = Some(cpu_mask);
    }
    let mut buffers = StepBuffers::new(field.n, field.rank);
    let step = BatchStep {
        renderer: &renderer,
        field: &field,
        mask: mask.as_ref(),
        rays: &batch,
        offsets: &offsets,
        logged: true,
    };
    let terms = gradient(params, step, &mut buffers);
    let cpu = Step { grad: buffers.grad, terms };
    let gpu = device.gradient(&batch, &offsets).unwrap();
    (cpu, gpu)
}

fn assert_gradients_agree(label: &str, cpu: &Step, gpu: &Step) {
    let names = ["plane XY", "plane XZ", "plane YZ", "line Z", "line Y", "line X"];
    for ((name, c), g) in names.iter().zip(cpu.grad.params()).zip(gpu.grad.params()) {
        let err = relative_to_max(g, c);
        eprintln!("{label}: {name} gradient, max |Δ| / max |g_cpu| = {err:.2e}");
        assert!(c.iter().any(|&x| x != 0.0), "{label}: {name}: the CPU gradient is zero");
        assert!(err <= 1e-4, "{label}: {name} gradients differ by {err:.2e} of their largest entry");
    }
    let (c, g) = (cpu.terms, gpu.terms);
    for (term, c, g) in [("mse", c.photo, g.photo), ("l1", c.l1, g.l1), ("tv", c.tv, g.tv), ("tv3d", c.tv3d, g.tv3d)] {
        let err = (g - c).abs() / c.abs();
        eprintln!("{label}: {term} {c:.6e} (cpu) vs {g:.6e} (gpu): {err:.1e}");
        assert!(err <= 1e-5, "{label}: {term} differs by {err:.1e} relative");
    }
}

#[test]
fn one_step_factor_gradients_agree_within_1e_4() {
    let Some(gpu) = device() else { return };
    // The defaults (3-D TV 1e-4) and the paper's loss (no 3-D TV); then heavy regularisers
    // with squared TV, so their gradients matter.
    let defaults = small(VmParams::default());
    let paper = small(VmParams { lambda_tv3d: 0.0, ..VmParams::default() });
    let heavy = small(VmParams {
        lambda_l1: 0.05,
        lambda_tv: 0.05,
        tv_norm: TvNorm::L2,
        lambda_tv3d: 0.05,
        ..VmParams::default()
    });
    let (cpu, g) = compare_step(&gpu, &defaults, None);
    assert_gradients_agree("defaults", &cpu, &g);
    let (cpu, g) = compare_step(&gpu, &paper, None);
    assert_gradients_agree("paper (no 3-D TV)", &cpu, &g);
    let (cpu, g) = compare_step(&gpu, &heavy, None);
    assert_gradients_agree("heavy regularisers, l2 TV, 3-D TV", &cpu, &g);
    let (cpu, g) = compare_step(&gpu, &defaults, Some(0.97));
    assert_gradients_agree("alpha mask", &cpu, &g);
    let log_loss = small(VmParams { loss: PhotoLoss::Log, ..VmParams::default() });
    let (cpu, g) = compare_step(&gpu, &log_loss, None);
    assert_gradients_agree("log loss", &cpu, &g);
}

/// The fit against the CPU's, and against itself: the scatter sums in fixed point, so a second
/// run on the device gives the same bits (float atomics did not, on lavapipe or an H100).
#[test]
fn a_300_iteration_fit_reaches_the_cpu_loss_within_1_percent_and_repeats_itself() {
    let Some(gpu) = device() else { return };
    let (cameras, images, aabb) = views();
    let views = Views { cameras: &cameras, images: &images, aabb };
    let params = small(VmParams { iterations: 300, alpha_mask_iterations: vec![150, 250], ..VmParams::default() });
    let started = std::time::Instant::now();
    let cpu = fit(&params, &views, |_| {});
    let cpu_s = started.elapsed().as_secs_f64();
    let started = std::time::Instant::now();
    let on_gpu = aret_pipe::gpu::fit::fit(&gpu, &params, &views, |_| {}).unwrap();
    let gpu_s = started.elapsed().as_secs_f64();
    eprintln!("300 iterations: CPU {cpu_s:.2} s, GPU {gpu_s:.2} s ({})", gpu.describe());
    assert_eq!(cpu.log.len(), on_gpu.log.len());
    for (c, g) in cpu.log.iter().zip(&on_gpu.log) {
        assert_eq!((c.iteration, c.lr), (g.iteration, g.lr), "the same schedule");
        let err = (g.loss - c.loss).abs() / c.loss;
        eprintln!(
            "iteration {:3}: loss {:.5e} (cpu) {:.5e} (gpu) Δ {:.2e}; PSNR {:.2?} vs {:.2?} dB",
            c.iteration, c.loss, g.loss, err, c.psnr_db, g.psnr_db
        );
    }
    let (c, g) = (cpu.log.last().unwrap(), on_gpu.log.last().unwrap());
    assert!(c.loss * 10.0 < cpu.log[0].loss, "the fit makes progress: {} → {}", cpu.log[0].loss, c.loss);
    assert!((g.loss - c.loss).abs() <= 0.01 * c.loss, "final loss {} (gpu) vs {} (cpu)", g.loss, c.loss);
    for (pc, pg) in c.psnr_db.iter().zip(&g.psnr_db) {
        assert!((pc - pg).abs() < 0.5, "final PSNR {pg} dB (gpu) vs {pc} dB (cpu)");
    }
    let (cm, gm) = (cpu.mask.expect("masked at 150"), on_gpu.mask.expect("masked at 150"));
    let differ = cm.nodes.iter().zip(&gm.nodes).filter(|(a, b)| a != b).count();
    assert!(differ * 100 <= cm.nodes.len(), "{differ} of {} mask nodes differ", cm.nodes.len());
    let field_err =
        on_gpu.field.params().zip(cpu.field.params()).map(|(g, c)| relative_to_max(g, c)).fold(0.0, f64::max);
    eprintln!("final factors: max |Δ| / max |cpu| = {field_err:.2e}; mask nodes differing: {differ}");
    let again = aret_pipe::gpu::fit::fit(&gpu, &params, &views, |_| {}).unwrap();
    let bits =
        |f: &aret_pipe::train::field::VmField<f32>| f.params().flatten().map(|x| x.to_bits()).collect::<Vec<_>>();
    assert!(bits(&again.field) == bits(&on_gpu.field), "a second run on the device changed the factors");
    assert_eq!(again.mask.map(|m| m.nodes), Some(gm.nodes), "a second run on the device changed the mask");
}

/// A batch larger than the scatter's integer sums hold exactly is refused, naming the key.
#[test]
fn a_batch_past_the_exact_scatter_limit_is_an_error_naming_the_key() {
    let Some(gpu) = device() else { return };
    let wide = DrrParams { width_px: 96, height_px: 96, ..drr_params(Backend::Cpu) };
    let (set, images) = render_views(&wide, &chest_ct(true), [0.0; 3], "explicit").unwrap();
    let (cameras, aabb) = (set.cameras, set.aabb);
    let views = Views { cameras: &cameras, images: &images, aabb };
    let vm = VmParams { rank: 6, batch_rays: 1_000_000, iterations: 1, ..VmParams::default() };
    let params = TrainParams { grid: 24, vm, ..TrainParams::tensorf() };
    let most = aret_pipe::gpu::grad_from_fixed::max_batch_rays(&renderer(&params, aabb));
    assert!(ray_pool(&views.rays(), &aabb).len() > most, "the views hold more rays than one batch may");
    let e = aret_pipe::gpu::fit::fit(&gpu, &params, &views, |_| {}).err().expect("refused");
    let message = format!("{e:#}");
    assert!(message.contains("[train.vm] batch_rays") && message.contains(&most.to_string()), "{message}");
}

/// The dense model's FISTA on the device against the CPU's (both in f32, the stop's tolerance
/// off so both take every step): the same steps give the same log within 1e-5 and σ within
/// 1e-4 of its peak; the device repeats itself bit for bit.
#[test]
fn the_dense_fit_on_the_device_follows_the_cpu_and_repeats_itself() {
    use aret_pipe::train::dense_tv;
    let Some(gpu) = device() else { return };
    let (cameras, images, aabb) = views();
    let views = Views { cameras: &cameras, images: &images, aabb };
    let dense_tv = DenseTvParams { iterations: 150, tolerance: 0.0, ..DenseTvParams::default() };
    let params = TrainParams { grid: 20, log_every: 50, dense_tv, ..TrainParams::default() };
    let r = renderer(&params, aabb);
    let started = std::time::Instant::now();
    let cpu = dense_tv::fit(&params, &views, &r, |_| {});
    let cpu_s = started.elapsed().as_secs_f64();
    let started = std::time::Instant::now();
    let on_gpu = aret_pipe::gpu::dense_fit::fit(&gpu, &params, &views, &r, |_| {}).unwrap();
    let gpu_s = started.elapsed().as_secs_f64();
    eprintln!("150 dense steps on 20³: CPU {cpu_s:.2} s, GPU {gpu_s:.2} s ({})", gpu.describe());
    let iterations: Vec<usize> = on_gpu.log.iter().map(|row| row.iteration).collect();
    assert_eq!(iterations, [0, 50, 100, 150]);
    for (c, g) in cpu.log.iter().zip(&on_gpu.log) {
        let err = (g.loss - c.loss).abs() / c.loss;
        eprintln!("step {:3}: loss {:.6e} (cpu) {:.6e} (gpu) Δ {err:.1e}", c.iteration, c.loss, g.loss);
        assert_eq!(c.lr, g.lr, "the same steps");
        assert!(err < 1e-5, "step {}: loss {} (gpu) against {} (cpu)", c.iteration, g.loss, c.loss);
    }
    let (first, last) = (cpu.log[0].loss, cpu.log.last().unwrap().loss);
    assert!(last * 10.0 < first, "the fit makes progress: {first} → {last}");
    let sigma_err = relative_to_max(&on_gpu.sigma, &cpu.sigma);
    eprintln!("σ: max |Δ| / max |cpu| = {sigma_err:.1e}");
    assert!(sigma_err < 1e-4, "σ differs by {sigma_err:.1e} of its peak");
    let again = aret_pipe::gpu::dense_fit::fit(&gpu, &params, &views, &r, |_| {}).unwrap();
    assert_eq!(again.sigma, on_gpu.sigma, "the device repeats its own fit bit for bit");
}

/// With its stop on, the device's solve settles where the CPU's does: the same steps taken (its
/// sums are in f32 in another order, so within two), the last row logged at that step.
#[test]
fn the_dense_fit_on_the_device_stops_where_the_cpu_stops() {
    use aret_pipe::train::dense_tv;
    let Some(gpu) = device() else { return };
    let (cameras, images, aabb) = views();
    let views = Views { cameras: &cameras, images: &images, aabb };
    let dense_tv = DenseTvParams { iterations: 400, tolerance: 1e-3, ..DenseTvParams::default() };
    let params = TrainParams { grid: 20, log_every: 50, dense_tv, ..TrainParams::default() };
    let r = renderer(&params, aabb);
    let cpu = dense_tv::fit(&params, &views, &r, |_| {});
    let on_gpu = aret_pipe::gpu::dense_fit::fit(&gpu, &params, &views, &r, |_| {}).unwrap();
    let (c, g) = (cpu.steps[1], on_gpu.steps[1]);
    eprintln!("settled after {c} steps on the CPU, {g} on the GPU");
    assert!(c < 400 && g < 400, "both settle before the ceiling: {c}, {g}");
    assert!(c.abs_diff(g) <= 2, "{c} against {g}");
    assert_eq!(on_gpu.log.last().unwrap().iteration, g);
}

#[test]
fn no_adapter_is_an_error_not_a_panic() {
    let nothing = GpuOptions { backends: wgpu::Backends::empty() };
    let e = Gpu::open(nothing).err().expect("with no backend there is no adapter");
    assert!(e.contains("backends tried"), "the error says what was looked for: {e}");
}

// ---- The stages through the command line ----

/// A dataset of one or two tiny CT series and a configuration with `extra` appended.
fn project(patients: &[&str], extra: &str) -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    for id in patients {
        let series_dir = dir.path().join(format!("data/{id}/series"));
        std::fs::create_dir_all(&series_dir).unwrap();
        write_series(&series_dir, &series(3), default_name);
    }
    write_config(dir.path(), extra);
    dir
}

/// A tiny VM fit with `extra` in its `[train]` table; `extra` may pick another model instead.
fn write_config(dir: &Path, extra: &str) {
    let model = if extra.contains("model =") { "" } else { "model = \"vm\"\n" };
    let vm = if model.is_empty() { "" } else { "[train.vm]\niterations = 3\nrank = 2\nbatch_rays = 64\n" };
    let text = format!(
        "[pipeline]\nname = \"gpu\"\nworkers = 2\n[dataset]\nkind = \"dicom\"\nroot = \"data\"\n\
         [drr]\nroi_center = [0.0, 0.0, 0.0]\nwidth_px = 32\nheight_px = 32\n\
         [train]\n{model}grid = 8\nlog_every = 1\n{extra}{vm}"
    );
    std::fs::write(dir.join("pipeline.toml"), text).unwrap();
}

/// `aret-pipe run` up to the train stage; `no_adapter` hides every adapter (this build speaks
/// Vulkan only, so asking wgpu for OpenGL finds none).
fn run(dir: &Path, no_adapter: bool) -> Output {
    let mut cmd = Command::new(BIN);
    cmd.args(["run", "pipeline.toml", "--until", "train"]).current_dir(dir).env("CI", "true");
    if no_adapter {
        cmd.env("WGPU_BACKEND", "gl");
    }
    cmd.output().unwrap()
}

fn text(b: &[u8]) -> String {
    String::from_utf8_lossy(b).into_owned()
}

fn model_backend(dir: &Path, patient: &str) -> String {
    let bytes = std::fs::read(dir.join(format!("out/{patient}/model.safetensors"))).unwrap();
    aret_pipe::formats::model::decode(&bytes).unwrap().2.backend
}

fn train_outcomes(dir: &Path) -> Vec<String> {
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join("out/run_report.json")).unwrap()).unwrap();
    let records = report["records"].as_array().unwrap();
    records.iter().filter(|r| r["stage"] == "train").map(|r| r["outcome"].as_str().unwrap().to_string()).collect()
}

#[test]
fn gpu_without_an_adapter_fails_the_stage_with_the_key_named() {
    let dir = project(&["P1"], "backend = \"gpu\"\n");
    let out = run(dir.path(), true);
    let (stdout, stderr) = (text(&out.stdout), text(&out.stderr));
    assert_eq!(out.status.code(), Some(1), "{stdout}\n{stderr}");
    assert!(stdout.contains("[train] backend = \"gpu\", but no GPU adapter"), "{stdout}\n{stderr}");
    assert!(stdout.contains("backend = \"cpu\""), "the message says what to do: {stdout}");
    assert!(!stderr.contains("panicked"), "{stderr}");
}

#[test]
fn auto_without_an_adapter_says_so_once_runs_on_the_cpu_and_keys_as_cpu() {
    let dir = project(&["P1", "P2"], "backend = \"auto\"\n");
    std::fs::write(
        dir.path().join("pipeline.toml"),
        std::fs::read_to_string(dir.path().join("pipeline.toml"))
            .unwrap()
            .replace("[train]", "backend = \"auto\"\n[train]"),
    )
    .unwrap();
    let out = run(dir.path(), true);
    let stderr = text(&out.stderr);
    assert!(out.status.success(), "{}\n{stderr}", text(&out.stdout));
    for table in ["[drr]", "[train]"] {
        let said = format!("{table} backend = \"auto\" runs on the CPU");
        assert_eq!(stderr.matches(&said).count(), 1, "said once for two patients: {stderr}");
    }
    assert_eq!(model_backend(dir.path(), "P1"), "cpu");
    // The key holds the resolved backend: asking for "cpu" outright finds everything cached.
    write_config(dir.path(), "backend = \"cpu\"\n");
    let out = run(dir.path(), true);
    assert!(out.status.success(), "{}", text(&out.stderr));
    assert_eq!(train_outcomes(dir.path()), ["cached", "cached"]);
}

#[test]
fn the_model_records_the_backend_that_ran() {
    let Some(gpu) = device() else { return };
    let dir = project(&["P1"], "backend = \"gpu\"\n");
    let out = run(dir.path(), false);
    assert!(out.status.success(), "{}\n{}", text(&out.stdout), text(&out.stderr));
    assert_eq!(model_backend(dir.path(), "P1"), "gpu");
    // "auto" takes a hardware GPU, never a software renderer such as lavapipe.
    let expected = if gpu.is_software() { "cpu" } else { "gpu" };
    write_config(dir.path(), "backend = \"auto\"\n");
    let out = run(dir.path(), false);
    assert!(out.status.success(), "{}", text(&out.stderr));
    assert_eq!(model_backend(dir.path(), "P1"), expected, "auto on {}", gpu.describe());
    // Same key as the explicit backend it resolved to: cached when that one ran before.
    let outcome = if expected == "gpu" { "cached" } else { "computed" };
    assert_eq!(train_outcomes(dir.path()), [outcome]);
    // The dense model runs there too.
    write_config(dir.path(), "backend = \"gpu\"\nmodel = \"dense_tv\"\n[train.dense_tv]\niterations = 5\n");
    let out = run(dir.path(), false);
    assert!(out.status.success(), "{}\n{}", text(&out.stdout), text(&out.stderr));
    assert_eq!(model_backend(dir.path(), "P1"), "gpu");
}
