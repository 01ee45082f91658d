//! Benchmark: training on the CPU with the paper's configuration (64³, rank 16, 2048 rays per
//! batch, 3000 iterations) on one patient's DRRs — seconds per iteration and per patient.
//!
//! `cargo run --release --example bench_train -- [DRR_DIR] [ITERATIONS] [RUNS]`: DRR_DIR holds
//! `cameras.json` and `drr_*.exr` (default `out/LIDC-IDRI-0001` of the default pipeline).
//! Prints the median over RUNS of the time per iteration, and the projected time for 3000; the
//! loop's time per iteration without the setup; and the median of the iterations' own times
//! after 10 of warm-up ("per step": what the references print and
//! `tools/bench_train_vs_reference` compares). It runs inside a rayon pool, as the train stage does.
//! The fit logs as the pipeline does (`log_every` = 100: a full three-view evaluation every
//! 100 iterations), so the time is what a patient costs.

use aret_pipe::stage::drr::CameraSet;
use aret_pipe::train::adam::{Adam, AdamParams};
use aret_pipe::train::field::VmField;
use aret_pipe::train::fit::{fit, renderer, view_mse, Views};
use aret_pipe::train::params::{TrainParams, VmParams};
use aret_pipe::train::regularize;
use rand::SeedableRng;
use std::time::Instant;

/// Iterations left out of the per-step median, as the references' `--warmup` default.
const WARM_UP: usize = 10;

fn main() -> anyhow::Result<()> {
    // Inside a pool, as the train stage runs `fit`: parallel calls from outside one would hand
    // every kernel to the pool and wait on a lock, a context switch per call on each side.
    rayon::ThreadPoolBuilder::new().build()?.install(bench)
}

fn bench() -> anyhow::Result<()> {
    let mut args = std::env::args().skip(1);
    let dir = std::path::PathBuf::from(args.next().unwrap_or_else(|| "out/LIDC-IDRI-0001".into()));
    let iterations: usize = args.next().map(|s| s.parse()).transpose()?.unwrap_or(300);
    let runs: usize = args.next().map(|s| s.parse()).transpose()?.unwrap_or(3);
    let (set, images) = CameraSet::read_published(&dir)?;
    let views = Views { cameras: &set.cameras, images: &images, aabb: set.aabb };
    // The paper's configuration: the defaults without the 3-D TV of the composed field.
    let params =
        TrainParams { vm: VmParams { iterations, lambda_tv3d: 0.0, ..VmParams::default() }, ..TrainParams::tensorf() };
    let (mut per_iteration, mut in_loop, mut steps) = (Vec::new(), Vec::new(), Vec::new());
    let mut last_field = None;
    for run in 0..runs {
        let t = Instant::now();
        let fitted = fit(&params, &views, |_| {});
        let s = t.elapsed().as_secs_f64();
        let (first, last) = (fitted.log.first().expect("a log row"), fitted.log.last().expect("a log row"));
        println!("run {run}: {iterations} iterations in {s:.2} s; PSNR {:?} dB", last.psnr_db);
        per_iteration.push(s / iterations as f64);
        // The loop alone: from the initial row (rays, pool and the initial evaluation done)
        // to the last, logging included.
        in_loop.push((last.seconds - first.seconds) / iterations as f64);
        // As the references time theirs: each iteration's step, the first 10 left out.
        steps.extend(fitted.step_seconds.iter().skip(WARM_UP));
        last_field = Some(fitted.field);
    }
    let median = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let (whole, in_loop, step) = (median(&mut per_iteration), median(&mut in_loop), median(&mut steps));
    println!(
        "median {:.2} ms per iteration on {} threads → {:.1} s per patient at 3000 iterations (target ≤ 10 s)",
        whole * 1e3,
        rayon::current_num_threads(),
        whole * 3000.0
    );
    // What to set beside a reference's per-iteration time (its setup is not in it either).
    println!("training loop alone: median {:.2} ms per iteration", in_loop * 1e3);
    println!(
        "per step: median {:.2} ms over {} iterations' steps (evaluations excluded, as the references time theirs)",
        step * 1e3,
        steps.len()
    );
    profile_kernels(&params, &views, &last_field.expect("at least one run"));
    Ok(())
}

/// Median time of each kernel of one iteration, on the trained field (realistic activity).
fn profile_kernels(params: &TrainParams, views: &Views, field: &VmField<f32>) {
    let renderer = renderer(params, views.aabb);
    let pool: Vec<_> =
        views.rays().into_iter().flatten().filter(|r| views.aabb.intersect(r.origin, r.dir).is_some()).collect();
    // A batch as training draws it: a random subset, traced in pool order.
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
    let mut picked = rand::seq::index::sample(&mut rng, pool.len(), params.vm.batch_rays).into_vec();
    picked.sort_unstable();
    let batch: Vec<_> = picked.iter().map(|&i| pool[i]).collect();
    let offsets: Vec<f64> = (0..batch.len()).map(|i| renderer.step * ((i * 37) % 101) as f64 / 101.0).collect();
    // The batch's size for the floor estimate in docs/performance.md.
    let samples: usize = batch.iter().zip(&offsets).map(|(ray, &off)| renderer.samples(ray, off).2).sum();
    println!("batch: {} rays, {samples} samples ({:.0} a ray)", batch.len(), samples as f64 / batch.len() as f64);
    let dense = field.compose();
    let mut dense_out = dense.clone();
    let mut grad_dense = vec![0f32; dense.len()];
    let mut grad = field.contract(&grad_dense);
    let per_view = views.rays();
    let mut adam =
        Adam::new(AdamParams { lr: 0.0, beta1: 0.9, beta2: 0.99, eps: 1e-8, decay_ratio: 1.0, iterations: 1 }, field);
    let mut scratch = field.clone();
    let median_ms = |f: &mut dyn FnMut()| {
        let mut times: Vec<f64> = (0..21)
            .map(|_| {
                let t = Instant::now();
                f();
                t.elapsed().as_secs_f64() * 1e3
            })
            .collect();
        times.sort_by(f64::total_cmp);
        times[times.len() / 2]
    };
    let rows = [
        ("compose", median_ms(&mut || field.compose_into(&mut dense_out))),
        ("render only", median_ms(&mut || drop(renderer.batch(&dense, None, &batch, &offsets, None)))),
        (
            "render + scatter",
            median_ms(&mut || {
                renderer.batch(&dense, None, &batch, &offsets, Some(&mut grad_dense));
            }),
        ),
        ("contract", median_ms(&mut || field.contract_into(&grad_dense, &mut grad))),
        (
            "L1 + TV",
            median_ms(&mut || {
                regularize::l1_and_tv(field, Some(1e-4), Some((params.vm.tv_norm, 1e-5)), &mut grad);
            }),
        ),
        (
            "3-D TV (default only)",
            median_ms(&mut || {
                regularize::tv_dense(&dense, field.n, 1e-4, &mut grad_dense);
            }),
        ),
        (
            "Adam",
            median_ms(&mut || {
                adam.update(&mut scratch, &grad);
            }),
        ),
        ("evaluation (3 views)", median_ms(&mut || drop(view_mse(&renderer, field, None, &per_view)))),
    ];
    println!("kernel medians (ms, 21 repeats):");
    for (name, ms) in rows {
        println!("  {name:<20} {ms:7.3}");
    }
}
