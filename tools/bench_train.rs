//! Benchmark: training on the CPU with the paper's configuration (64³, rank 16, 2048 rays per
//! batch, 3000 iterations) on one patient's DRRs — seconds per iteration and per patient.
//!
//! `cargo run --release --example bench_train -- [DRR_DIR] [ITERATIONS] [RUNS]`: DRR_DIR holds
//! `cameras.json` and `drr_*.exr` (default `out/LIDC-IDRI-0001` of the default pipeline).
//! Prints the median over RUNS of the time per iteration, and the projected time for 3000.

use aret_pipe::formats::exr_image;
use aret_pipe::stage::drr::CameraSet;
use aret_pipe::train::fit::{fit, TrainParams, Views};
use std::time::Instant;

fn main() -> anyhow::Result<()> {
    let mut args = std::env::args().skip(1);
    let dir = std::path::PathBuf::from(args.next().unwrap_or_else(|| "out/LIDC-IDRI-0001".into()));
    let iterations: usize = args.next().map(|s| s.parse()).transpose()?.unwrap_or(300);
    let runs: usize = args.next().map(|s| s.parse()).transpose()?.unwrap_or(3);
    let set: CameraSet = serde_json::from_slice(&std::fs::read(dir.join("cameras.json"))?)?;
    let images: Vec<Vec<f32>> = set
        .cameras
        .iter()
        .map(|c| Ok(exr_image::decode(&std::fs::read(dir.join(format!("drr_{}.exr", c.view.name())))?)?.pixels))
        .collect::<anyhow::Result<_>>()?;
    let views = Views { cameras: &set.cameras, images: &images, aabb: set.aabb };
    let params = TrainParams { iterations, log_every: iterations, ..TrainParams::default() };
    let mut per_iteration = Vec::new();
    for run in 0..runs {
        let t = Instant::now();
        let fitted = fit(&params, &views, |_| {});
        let s = t.elapsed().as_secs_f64();
        let last = fitted.log.last().expect("a log row");
        println!("run {run}: {iterations} iterations in {s:.2} s; PSNR {:?} dB", last.psnr_db);
        per_iteration.push(s / iterations as f64);
    }
    per_iteration.sort_by(f64::total_cmp);
    let median = per_iteration[per_iteration.len() / 2];
    println!(
        "median {:.2} ms per iteration on {} threads → {:.1} s per patient at 3000 iterations (target ≤ 10 s)",
        median * 1e3,
        rayon::current_num_threads(),
        median * 3000.0
    );
    Ok(())
}
