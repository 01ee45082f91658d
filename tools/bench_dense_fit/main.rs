//! Benchmark: the shipped dense fit (`[train] model = "dense_tv"`, `pipeline.toml`'s 128³
//! lattice and 256² views) on the CPU, beside two peers run in the same process: the solver the
//! tool used before its matrix-free projector ([`reference`]), and the same solve as a user
//! would write it in Python (`tools/dense_fit_peer.py`: scipy.sparse `A` of the same rays,
//! numpy FISTA with the same steps and stop, 2 threads; `--python` names the interpreter).
//!
//! `cargo run --release --example bench_dense_fit -- [PATIENT_DIR ...] [--runs 3]`: each
//! PATIENT_DIR holds `cameras.json` and `drr_*.exr` (default: `out/LIDC-IDRI-0001`, `0003` and
//! `0014` of the default pipeline). Prints per patient the median over the runs of the seconds a
//! fit takes (set-up included), the steps taken, the final energy, the projector's throughput
//! beside this machine's memory bandwidth, and each peer's time and ratio.

mod reference;

use aret_pipe::stage::drr::CameraSet;
use aret_pipe::train::dense_tv::{self, DenseProblem};
use aret_pipe::train::fit::{renderer, Views};
use aret_pipe::train::params::{DenseTvParams, TrainParams};
use aret_pipe::train::render::Ray;
use clap::Parser;
use std::path::PathBuf;
use std::time::Instant;

#[derive(Parser)]
struct Args {
    /// Patient folders of a pipeline's `out_dir`.
    patients: Vec<PathBuf>,
    /// Runs per patient; medians are quoted.
    #[arg(long, default_value_t = 3)]
    runs: usize,
    /// The most FISTA steps (the shipped ceiling by default).
    #[arg(long)]
    steps: Option<usize>,
    /// The stop's tolerance (the shipped one by default).
    #[arg(long)]
    tolerance: Option<f64>,
    /// Nodes a side of the lattice.
    #[arg(long, default_value_t = 128)]
    grid: usize,
    /// Skip the old CSR solver.
    #[arg(long)]
    no_reference: bool,
    /// Skip the Python peer (`tools/dense_fit_peer.py`).
    #[arg(long)]
    no_peer: bool,
    /// The Python that runs the peer (with numpy and scipy).
    #[arg(long, default_value = ".venv/bin/python")]
    python: PathBuf,
    /// Time the GPU fit too when only a software adapter (lavapipe) opens (slow: for checking).
    #[arg(long)]
    software_gpu: bool,
    /// Print every step's energy of the new solver.
    #[arg(long)]
    trace: bool,
    /// Run the reference this many steps (σ compared at 500 and at the end).
    #[arg(long, default_value_t = 500)]
    reference_steps: usize,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let patients = if args.patients.is_empty() {
        ["0001", "0003", "0014"].map(|p| PathBuf::from(format!("out/LIDC-IDRI-{p}"))).to_vec()
    } else {
        args.patients.clone()
    };
    let defaults = DenseTvParams::default();
    let dense_tv = DenseTvParams {
        iterations: args.steps.unwrap_or(defaults.iterations),
        tolerance: args.tolerance.unwrap_or(defaults.tolerance),
        ..defaults
    };
    let log_every = if args.trace { 1 } else { TrainParams::default().log_every };
    let params = TrainParams { dense_tv, grid: args.grid, log_every, ..TrainParams::default() };
    println!("CPU threads: {}", rayon::current_num_threads());
    let bandwidth = memory_bandwidth();
    println!("memory bandwidth (a parallel copy of 256 MiB, read + write, median of 7): {:.1} GB/s", bandwidth / 1e9);
    let gpu = match aret_pipe::gpu::Gpu::shared() {
        Ok(gpu) if !gpu.is_software() || args.software_gpu => {
            println!("GPU: {}", gpu.describe());
            Some(gpu)
        }
        Ok(gpu) => {
            println!("GPU: only {} (software; --software-gpu times it anyway)", gpu.describe());
            None
        }
        Err(e) => {
            println!("GPU: none ({e})");
            None
        }
    };
    for dir in &patients {
        let (set, images) = CameraSet::read_published(dir)?;
        let views = Views { cameras: &set.cameras, images: &images, aabb: set.aabb };
        let r = renderer(&params, views.aabb);
        let mut times = Vec::new();
        let mut fitted = None;
        for _ in 0..args.runs {
            let t = Instant::now();
            let fit = dense_tv::fit(&params, &views, &r, |row| {
                if args.trace && (row.iteration % 25 == 0 || row.iteration < 10) {
                    println!(
                        "  step {:4} E {:.9e} data {:.6e} tv {:.6e} {:.2}s",
                        row.iteration, row.loss, row.photo, row.tv3d, row.seconds
                    );
                }
            });
            times.push(t.elapsed().as_secs_f64());
            fitted = Some(fit);
        }
        let fitted = fitted.expect("at least one run");
        let last = fitted.log.last().expect("a final row");
        println!(
            "{}: new solver {:.2} s (median of {}: {:?}), steps {} coarse + {} fine, E {:.9e}",
            dir.display(),
            median(&mut times),
            args.runs,
            times.iter().map(|t| (t * 100.0).round() / 100.0).collect::<Vec<_>>(),
            fitted.steps[0],
            fitted.steps[1],
            last.loss
        );
        if let Some(gpu) = &gpu {
            let mut on_gpu = Vec::new();
            let mut fitted_gpu = None;
            for _ in 0..args.runs {
                let t = Instant::now();
                fitted_gpu = Some(aret_pipe::gpu::dense_fit::fit(gpu, &params, &views, &r, |_| {})?);
                on_gpu.push(t.elapsed().as_secs_f64());
            }
            let g = fitted_gpu.expect("at least one run");
            let peak = fitted.sigma.iter().fold(0f32, |m, &v| m.max(v.abs()));
            let gap = g.sigma.iter().zip(&fitted.sigma).fold(0f32, |m, (a, b)| m.max((a - b).abs()));
            println!(
                "  GPU: {:.3} s a patient, set-up included (median of {}), steps {} + {}, E {:.9e}; CPU / GPU = {:.1}; max |σ_gpu − σ_cpu| = {:.1e} of the peak",
                median(&mut on_gpu),
                args.runs,
                g.steps[0],
                g.steps[1],
                g.log.last().expect("a final row").loss,
                median(&mut times) / median(&mut on_gpu),
                gap / peak
            );
        }
        let rays: Vec<Ray> = views.rays().into_iter().flatten().collect();
        let spans: Vec<(usize, usize)> = set.cameras.iter().map(|c| (c.width * c.height, c.width)).collect();
        let (lambda, epsilon) = (params.dense_tv.lambda, params.dense_tv.epsilon);
        let problem = DenseProblem::new(&r.lattice, r.scale, lambda, epsilon, &rays, &spans);
        println!("  projector: {}", problem.projector.path());
        let sigma = &fitted.sigma;
        let mut depths = vec![0.0; problem.projector.rays];
        let mut back = vec![0.0f32; problem.nodes()];
        let (mut fwd, mut bwd) = (Vec::new(), Vec::new());
        for _ in 0..7 {
            let t = Instant::now();
            problem.projector.project(sigma, &mut depths);
            fwd.push(t.elapsed().as_secs_f64());
            let t = Instant::now();
            problem.projector.back_project(&depths, &mut back);
            bwd.push(t.elapsed().as_secs_f64());
        }
        let updates = (set.cameras.len() * problem.nodes()) as f64;
        let (f, b) = (median(&mut fwd), median(&mut bwd));
        // Each view reads (or writes) σ once in f32: what either direction moves at the least.
        let floor = updates * 4.0 / bandwidth;
        println!(
            "  projection {:.2} ms, back-projection {:.2} ms: {:.2} and {:.2} G voxel updates/s; moving σ once per view at the measured bandwidth takes {:.2} ms",
            f * 1e3,
            b * 1e3,
            updates / f / 1e9,
            updates / b / 1e9,
            floor * 1e3
        );
        if !args.no_peer {
            let peer = python_peer(&args.python, &rays, &r, &params)?;
            println!(
                "  Python peer (scipy.sparse A, numpy FISTA, 2 threads): build A {:.2} s ({} entries) + solve {:.2} s, {} steps, E {:.9e}; peer / ours = {:.1}",
                peer.build_s,
                peer.entries,
                peer.solve_s,
                peer.steps,
                peer.energy,
                (peer.build_s + peer.solve_s) / median(&mut times)
            );
        }
        if !args.no_reference {
            let t = Instant::now();
            let old = reference::CsrProblem::new(&r, &rays, lambda, epsilon);
            let setup = t.elapsed().as_secs_f64();
            let t = Instant::now();
            let mut at_500 = Vec::new();
            let sigma = old.solve(args.reference_steps, |k, s| {
                if args.trace && (k % 25 == 0 || k < 10) {
                    println!("  old step {k:4} E {:.9e}", old.energy(s));
                }
                if k == 500 {
                    at_500 = s.to_vec();
                }
            });
            let gap = |a: &[f64], b: &[f64]| {
                let d: f64 = a.iter().zip(b).map(|(x, y)| (x - y).powi(2)).sum();
                (d / b.iter().map(|y| y * y).sum::<f64>()).sqrt()
            };
            let ours: Vec<f64> = fitted.sigma.iter().map(|&v| f64::from(v)).collect();
            println!(
                "  |σ_new − σ_old500| / |σ_old500| = {:.4}; |σ_old{} − σ_old500| / |σ_old500| = {:.4}; E_old(σ_old{}) {:.9e}",
                gap(&ours, &at_500),
                args.reference_steps,
                gap(&sigma, &at_500),
                args.reference_steps,
                old.energy(&sigma)
            );
            let sigma = at_500;
            let solve = t.elapsed().as_secs_f64();
            let ours: Vec<f64> = fitted.sigma.iter().map(|&v| f64::from(v)).collect();
            let old_f32: Vec<f32> = sigma.iter().map(|&v| v as f32).collect();
            println!(
                "  reference: set-up {setup:.2} s + 500 steps {solve:.2} s; E_old(σ_old) {:.9e}, E_old(σ_new) {:.9e}, E_new(σ_old) {:.9e}",
                old.energy(&sigma),
                old.energy(&ours),
                problem.evaluate(&old_f32).energy(lambda)
            );
        }
    }
    Ok(())
}

/// What `tools/dense_fit_peer.py` prints.
#[derive(serde::Deserialize)]
struct Peer {
    build_s: f64,
    solve_s: f64,
    steps: usize,
    energy: f64,
    entries: usize,
}

/// Runs the Python peer on the same rays and parameters, 2 threads.
fn python_peer(
    python: &std::path::Path,
    rays: &[Ray],
    r: &aret_pipe::train::render::Renderer,
    params: &TrainParams,
) -> anyhow::Result<Peer> {
    use anyhow::Context as _;
    let dir = tempfile::tempdir()?;
    let bytes: Vec<u8> = rays
        .iter()
        .flat_map(|ray| [ray.origin.x, ray.origin.y, ray.origin.z, ray.dir.x, ray.dir.y, ray.dir.z, ray.target])
        .flat_map(f64::to_le_bytes)
        .collect();
    std::fs::write(dir.path().join("rays.f64"), bytes)?;
    let problem = serde_json::json!({
        "n": r.lattice.n, "aabb_min": r.lattice.aabb.min, "aabb_max": r.lattice.aabb.max, "scale": r.scale,
        "lambda": params.dense_tv.lambda, "epsilon": params.dense_tv.epsilon,
        "tolerance": params.dense_tv.tolerance, "iterations": params.dense_tv.iterations,
    });
    std::fs::write(dir.path().join("problem.json"), problem.to_string())?;
    let out = std::process::Command::new(python)
        .arg(concat!(env!("CARGO_MANIFEST_DIR"), "/tools/dense_fit_peer.py"))
        .arg(dir.path())
        .envs([("OMP_NUM_THREADS", "2"), ("OPENBLAS_NUM_THREADS", "2"), ("MKL_NUM_THREADS", "2")])
        .output()
        .with_context(|| format!("running {} (make it with tools/setup-venv, or pass --python)", python.display()))?;
    anyhow::ensure!(out.status.success(), "the Python peer failed: {}", String::from_utf8_lossy(&out.stderr));
    Ok(serde_json::from_slice(&out.stdout)?)
}

/// Bytes a second that a parallel copy of 256 MiB moves (read and written), median of 7.
fn memory_bandwidth() -> f64 {
    use rayon::prelude::*;
    let len = 64 << 20;
    let from: Vec<f32> = (0..len).map(|i| i as f32).collect();
    let mut to = vec![0.0f32; len];
    let mut times: Vec<f64> = (0..7)
        .map(|_| {
            let t = Instant::now();
            to.par_chunks_mut(1 << 20).zip(from.par_chunks(1 << 20)).for_each(|(t, f)| t.copy_from_slice(f));
            t.elapsed().as_secs_f64()
        })
        .collect();
    assert_eq!(to[len - 1], from[len - 1]);
    2.0 * (len * 4) as f64 / median(&mut times)
}

fn median(v: &mut [f64]) -> f64 {
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    s[s.len() / 2]
}
