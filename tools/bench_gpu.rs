//! Benchmark: the GPU backend beside the CPU backend in one run, on whatever adapter wgpu opens
//! (`WGPU_BACKEND` picks; lavapipe when no GPU is installed) — the paper configuration (64³,
//! rank 16, 2048 rays per batch) trained on one patient's DRRs, and that patient's DRRs.
//!
//! `cargo run --release --example bench_gpu -- [PATIENT_DIR] [ITERATIONS] [RUNS] [PNG]`:
//! PATIENT_DIR holds `cameras.json` and `drr_*.exr` (default `out/LIDC-IDRI-0001` of the
//! default pipeline), and for the DRR comparison `ct_unit.mhd` + `.raw` (left out if absent).
//! Prints the median over RUNS of seconds per patient (projected to the paper's 3000
//! iterations from ITERATIONS, default 300) for each backend and their ratio, the DRR stage's
//! rendering time on each, and how far the GPU's DRR pixels are from the CPU's. With PNG, writes
//! the coronal DRR as GPU | CPU | 1000× |difference| there, to look at.

use aret_pipe::formats::{mhd, png};
use aret_pipe::gpu::fit::DeviceFit;
use aret_pipe::gpu::{Backend, Gpu};
use aret_pipe::stage::drr::{render_views, CameraSet, Focal, Params as DrrParams, RoiCenter};
use aret_pipe::train::fit::{fit, ray_pool, renderer, Schedule, Views};
use aret_pipe::train::params::{TrainParams, VmParams};
use aret_pipe::volume::Volume;
use std::path::{Path, PathBuf};
use std::time::Instant;

fn main() -> anyhow::Result<()> {
    let mut args = std::env::args().skip(1);
    let dir = PathBuf::from(args.next().unwrap_or_else(|| "out/LIDC-IDRI-0001".into()));
    let iterations: usize = args.next().map(|s| s.parse()).transpose()?.unwrap_or(300);
    let runs: usize = args.next().map(|s| s.parse()).transpose()?.unwrap_or(3);
    let png_path = args.next().map(PathBuf::from);
    let gpu = Gpu::shared().map_err(|e| anyhow::anyhow!("no GPU adapter: {e}"))?;
    println!("adapter: {}", gpu.describe());
    let (set, images) = CameraSet::read_published(&dir)?;
    let views = Views { cameras: &set.cameras, images: &images, aabb: set.aabb };
    // The paper's configuration: the defaults without the 3-D TV of the composed field.
    let vm = VmParams { iterations, lambda_tv3d: 0.0, ..VmParams::default() };
    let params = TrainParams { log_every: iterations, vm, ..TrainParams::tensorf() };
    let (mut on_gpu, mut on_cpu) = (Vec::new(), Vec::new());
    let mut first_gpu_field = None;
    for run in 0..runs {
        let t = Instant::now();
        let g = aret_pipe::gpu::fit::fit(&gpu, &params, &views, |_| {})?;
        on_gpu.push(t.elapsed().as_secs_f64());
        // Float atomics add in whatever order the device runs the rays: say whether that
        // showed in the bits.
        match &first_gpu_field {
            None => first_gpu_field = Some(g.field.clone()),
            Some(first) => {
                let a: Vec<f32> = first.params().flatten().copied().collect();
                let b: Vec<f32> = g.field.params().flatten().copied().collect();
                let differ = a.iter().zip(&b).filter(|(x, y)| x != y).count();
                let largest = a.iter().fold(0f32, |m, x| m.max(x.abs()));
                let gap = a.iter().zip(&b).fold(0f32, |m, (x, y)| m.max((x - y).abs()));
                println!(
                    "run {run}: GPU factors {} run 0's: {differ} of {} differ, by at most {:.1e} of the largest",
                    if differ == 0 { "bit-identical to" } else { "differ from" },
                    g.field.len(),
                    gap / largest
                );
            }
        }
        let t = Instant::now();
        let c = fit(&params, &views, |_| {});
        on_cpu.push(t.elapsed().as_secs_f64());
        let (gl, cl) = (g.log.last().expect("a row"), c.log.last().expect("a row"));
        println!(
            "run {run}: {iterations} iterations: GPU {:.2} s (loss {:.4e}, PSNR {:.1?} dB), CPU {:.2} s (loss {:.4e}, PSNR {:.1?} dB)",
            on_gpu[run], gl.loss, gl.psnr_db, on_cpu[run], cl.loss, cl.psnr_db
        );
    }
    let per_patient = |s: &mut Vec<f64>| median(s) / iterations as f64 * 3000.0;
    let (g, c) = (per_patient(&mut on_gpu), per_patient(&mut on_cpu));
    println!(
        "train, paper configuration (3000 iterations, projected from {iterations}, with the two full-view \
         evaluations of a {iterations}-iteration log; median of {runs}): GPU {g:.1} s per patient \
         ({:.1} ms per iteration), CPU ({} threads) {c:.1} s per patient ({:.1} ms): CPU / GPU = {:.3}",
        g / 3.0,
        rayon::current_num_threads(),
        c / 3.0,
        c / g
    );
    profile_kernels(&gpu, &params, &views)?;
    if dir.join("ct_unit.mhd").exists() {
        bench_drr(&dir, &set, runs, png_path.as_deref())?;
    }
    Ok(())
}

/// Median time of each GPU kernel of one iteration, at the initial field of the paper
/// configuration, on its first batch.
fn profile_kernels(gpu: &Gpu, params: &TrainParams, views: &Views) -> anyhow::Result<()> {
    let renderer = renderer(params, views.aabb);
    let per_view = views.rays();
    let pool = ray_pool(&per_view, &views.aabb);
    let (field, mut schedule) = Schedule::start(params, pool.len());
    let drawn = schedule.next_batch(params.vm.batch_rays, renderer.step).to_vec();
    let batch: Vec<_> = drawn.iter().map(|&(i, _)| pool[i]).collect();
    let offsets: Vec<f64> = drawn.iter().map(|&(_, o)| o).collect();
    let mut device = DeviceFit::new(gpu, params, &renderer, &field, batch.len(), &per_view)?;
    println!("GPU kernel medians (ms, 5 repeats, each submitted and waited for alone):");
    for (name, ms) in device.profile(&batch, &offsets, 5)? {
        println!("  {name:<18} {ms:9.3}");
    }
    Ok(())
}

fn median(seconds: &mut [f64]) -> f64 {
    seconds.sort_by(f64::total_cmp);
    seconds[seconds.len() / 2]
}

/// The DRR stage's three views of the patient's CT on both backends, timed and compared.
fn bench_drr(dir: &Path, set: &CameraSet, runs: usize, png_path: Option<&Path>) -> anyhow::Result<()> {
    let header = std::fs::read_to_string(dir.join("ct_unit.mhd"))?;
    let ct: Volume<f32> = mhd::decode(&header, &std::fs::read(dir.join("ct_unit.raw"))?)?;
    let cam = &set.cameras[0];
    let params = |backend| DrrParams {
        width_px: cam.width,
        height_px: cam.height,
        focal_px: Focal::Px(cam.focal_px),
        mm_per_unit: set.frame.mm_per_unit,
        aabb_min: set.aabb.min,
        aabb_max: set.aabb.max,
        roi_center: RoiCenter::Mm(set.frame.roi_center_mm),
        attenuation_scale: set.attenuation_scale,
        backend,
        ..DrrParams::default()
    };
    let centre = set.frame.roi_center_mm;
    let time = |backend| -> anyhow::Result<(f64, Vec<Vec<f32>>)> {
        let mut seconds = Vec::new();
        let mut images = Vec::new();
        for _ in 0..runs {
            let t = Instant::now();
            images = render_views(&params(backend), &ct, centre, "explicit")?.1;
            seconds.push(t.elapsed().as_secs_f64());
        }
        Ok((median(&mut seconds), images))
    };
    let (g, gpu) = time(Backend::Gpu)?;
    let (c, cpu) = time(Backend::Cpu)?;
    let worst = gpu
        .iter()
        .flatten()
        .zip(cpu.iter().flatten())
        .map(|(&g, &c)| (f64::from(g) - f64::from(c)).abs() / f64::from(c))
        .fold(0.0, f64::max);
    let [nx, ny, nz] = ct.geometry.dims;
    println!(
        "drr: three {}² views of a {nx}×{ny}×{nz} CT, median of {runs}: GPU {g:.3} s, CPU {c:.3} s (CPU / GPU = {:.2}); \
         largest relative pixel difference {worst:.2e}",
        cam.width,
        c / g
    );
    if let Some(path) = png_path {
        std::fs::write(path, side_by_side(&gpu[0], &cpu[0], cam.width, cam.height))?;
        println!("wrote {} (coronal: GPU | CPU | 1000 × |GPU − CPU|, as −ln I)", path.display());
    }
    Ok(())
}

/// GPU | CPU | difference, as attenuation −ln I (dense = white), one window for the two DRRs.
fn side_by_side(gpu: &[f32], cpu: &[f32], w: usize, h: usize) -> Vec<u8> {
    let gap = 4;
    let width = 3 * w + 2 * gap;
    let att = |i: f32| -(i.max(1e-6)).ln();
    let hi = cpu.iter().map(|&i| att(i)).fold(0f32, f32::max);
    let mut pixels = vec![255u8; width * h];
    for j in 0..h {
        for i in 0..w {
            let k = i + w * j;
            let grey = |v: f32| (255.0 * (v / hi).clamp(0.0, 1.0)) as u8;
            pixels[i + width * j] = grey(att(gpu[k]));
            pixels[w + gap + i + width * j] = grey(att(cpu[k]));
            pixels[2 * (w + gap) + i + width * j] = grey(1000.0 * (att(gpu[k]) - att(cpu[k])).abs());
        }
    }
    png::encode_gray8(width, h, &pixels)
}
