//! Benchmark: the dense model's FISTA (`[train] model = "dense_tv"`) on the GPU beside the CPU
//! in one run, on whatever adapter wgpu opens (`WGPU_BACKEND` picks; lavapipe when no GPU is
//! installed), with the shipped configuration (`pipeline.toml`: 128³, λ = 1e-2) on one
//! patient's DRRs.
//!
//! `cargo run --release --example bench_dense_fit -- [PATIENT_DIR] [STEPS] [RUNS] [GRID]`:
//! PATIENT_DIR holds `cameras.json` and `drr_*.exr` (default `out/LIDC-IDRI-0001` of the default
//! pipeline); GRID is the lattice's nodes per axis (default 128). Where there is no adapter, or
//! the device cannot hold `A` (lavapipe past 128³ under 256² views), it says why and times the
//! CPU alone.
//! Prints the host's set-up (building `A` and `Aᵀ`, the step `1/L`; the same for both backends),
//! then the median over RUNS of the seconds for STEPS steps (default 500, the shipped count) on
//! each backend and their ratio, projected to a whole fit, and how far the GPU's σ lies from
//! the CPU's.

use aret_pipe::gpu::dense_fit::DeviceFista;
use aret_pipe::gpu::Gpu;
use aret_pipe::stage::drr::CameraSet;
use aret_pipe::train::dense_tv::{CpuFista, DenseProblem, FistaSolver};
use aret_pipe::train::fit::{renderer, Views};
use aret_pipe::train::params::{DenseTvParams, TrainParams};
use aret_pipe::train::render::Ray;
use std::path::PathBuf;
use std::time::Instant;

fn main() -> anyhow::Result<()> {
    let mut args = std::env::args().skip(1);
    let dir = PathBuf::from(args.next().unwrap_or_else(|| "out/LIDC-IDRI-0001".into()));
    let steps: usize = args.next().map(|s| s.parse()).transpose()?.unwrap_or(500);
    let runs: usize = args.next().map(|s| s.parse()).transpose()?.unwrap_or(3);
    let grid: usize = args.next().map(|s| s.parse()).transpose()?.unwrap_or(128);
    let gpu = match Gpu::shared() {
        Ok(gpu) => {
            println!("adapter: {}; CPU threads: {}", gpu.describe(), rayon::current_num_threads());
            Some(gpu)
        }
        Err(e) => {
            println!("no GPU adapter ({e}); timing the CPU alone on {} threads", rayon::current_num_threads());
            None
        }
    };
    let (set, images) = CameraSet::read_published(&dir)?;
    let views = Views { cameras: &set.cameras, images: &images, aabb: set.aabb };
    let dense_tv = DenseTvParams { iterations: steps, ..DenseTvParams::default() };
    let params = TrainParams { dense_tv, grid, ..TrainParams::default() };
    let rays: Vec<Ray> = views.rays().into_iter().flatten().collect();
    let t = Instant::now();
    let problem = DenseProblem::new(&params, &rays, &renderer(&params, views.aabb));
    let setup_s = t.elapsed().as_secs_f64();
    let entries = problem.projector.rows.index.len();
    println!(
        "{}³ lattice, {} rays ({} meet the box), A holds {entries} entries; host set-up {setup_s:.2} s",
        problem.n,
        rays.len(),
        problem.rays_seen
    );
    let none = |_: usize| false;
    let solve = |solver: &mut dyn FistaSolver| -> anyhow::Result<(f64, Vec<f64>)> {
        let mut sigma = vec![0.0; problem.nodes()];
        let t = Instant::now();
        solver.solve(&problem, &mut sigma, &problem.measured, steps, &none, &mut |_, _| {})?;
        Ok((t.elapsed().as_secs_f64(), sigma))
    };
    let t = Instant::now();
    let mut device = match gpu.map(|gpu| DeviceFista::new(gpu, &problem)) {
        Some(Ok(device)) => {
            println!("GPU upload of A and Aᵀ: {:.2} s", t.elapsed().as_secs_f64());
            Some(device)
        }
        Some(Err(e)) => {
            println!("GPU: {e:#}; timing the CPU alone");
            None
        }
        None => None,
    };
    let mut cpu = CpuFista::new(&problem);
    let (mut on_gpu, mut on_cpu) = (Vec::new(), Vec::new());
    let (mut sigma_gpu, mut sigma_cpu) = (Vec::new(), Vec::new());
    for run in 0..runs {
        if let Some(device) = device.as_mut() {
            let (s, sigma) = solve(device)?;
            on_gpu.push(s);
            if run > 0 && sigma != sigma_gpu {
                println!("run {run}: the GPU's σ differs from run 0's");
            }
            sigma_gpu = sigma;
        }
        let (s, sigma) = solve(&mut cpu)?;
        on_cpu.push(s);
        sigma_cpu = sigma;
        let gpu_s = on_gpu.get(run).map_or("–".into(), |s| format!("{s:.2} s"));
        println!("run {run}: GPU {gpu_s}, CPU {:.2} s for {steps} steps", on_cpu[run]);
    }
    let c = median(&mut on_cpu);
    println!("a whole fit on the CPU (set-up + steps): {:.2} s per patient", setup_s + c);
    if on_gpu.is_empty() {
        return Ok(());
    }
    let g = median(&mut on_gpu);
    println!("median of {runs}: GPU {g:.3} s, CPU {c:.3} s for {steps} steps (CPU / GPU = {:.2})", c / g);
    println!("a whole fit on the GPU (set-up + steps): {:.2} s per patient", setup_s + g);
    let peak = sigma_cpu.iter().fold(0f64, |m, x| m.max(x.abs()));
    let gap = sigma_gpu.iter().zip(&sigma_cpu).fold(0f64, |m, (a, b)| m.max((a - b).abs()));
    println!("σ: max |GPU − CPU| = {:.1e} of the CPU's peak {peak:.4}", gap / peak);
    Ok(())
}

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}
