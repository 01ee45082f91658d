//! Benchmark: the image filters of `kernels::filters` on a 64³ volume at 3.75 × 1.875 × 2.1875 mm
//! — Gaussian and blob response at several scales, the distance transform, Otsu's threshold and
//! per-slice hole filling — median (min) of N runs, on one thread and on rayon's default pool.
//! On a loaded machine the minimum is the better estimate of the undisturbed time.
//!
//! `cargo run --release --example bench_filters -- [RUNS]`. Target: a few ms per call.

use aret_pipe::kernels::filters::{
    blob_response, distance_inside_mm, fill_holes_per_slice, gaussian_mm, otsu_threshold,
};
use rand::{Rng, SeedableRng};
use std::time::Instant;

const N: usize = 64;
const DIMS: [usize; 3] = [N; 3];
const SPACING: [f64; 3] = [3.75, 1.875, 2.1875];

fn main() -> anyhow::Result<()> {
    let runs: usize = std::env::args().nth(1).map(|r| r.parse()).transpose()?.unwrap_or(50);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
    let ball = |i: usize| {
        let p = [i % N, i / N % N, i / (N * N)].map(|v| v as f64);
        (0..3).map(|a| ((p[a] - 32.0) * SPACING[a]).powi(2)).sum::<f64>() <= 40.0 * 40.0
    };
    let values: Vec<f32> =
        (0..N * N * N).map(|i| if ball(i) { -800.0 } else { 40.0 } + rng.gen::<f32>() * 100.0).collect();
    let mask: Vec<bool> = (0..N * N * N).map(|i| ball(i) && rng.gen::<f32>() < 0.95).collect();
    let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build()?;
    println!(
        "64³, spacing {SPACING:?} mm, {runs} runs, median (min) in ms: one thread | default pool ({} threads)",
        rayon::current_num_threads()
    );
    let bench = |what: &str, f: &(dyn Fn() -> usize + Sync)| {
        let one = pool.install(|| time(runs, f));
        let all = time(runs, f);
        println!("  {what:28} {:7.2} ({:.2}) | {:7.2} ({:.2})", one.0, one.1, all.0, all.1);
    };
    for sigma in [2.0, 5.0, 10.0] {
        bench(&format!("gaussian σ = {sigma} mm"), &|| gaussian_mm(&values, DIMS, SPACING, sigma).len());
    }
    for s in [2.0, 5.0, 10.0] {
        bench(&format!("blob response s = {s} mm"), &|| blob_response(&values, DIMS, SPACING, s).len());
    }
    bench("distance inside (EDT)", &|| distance_inside_mm(&mask, DIMS, SPACING).len());
    bench("otsu threshold", &|| otsu_threshold(&values).map_or(0, |t| t as usize));
    bench("fill holes per z-slice", &|| fill_holes_per_slice(&mask, DIMS, 2).len());
    Ok(())
}

fn time(runs: usize, f: &(dyn Fn() -> usize + Sync)) -> (f64, f64) {
    let mut ms: Vec<f64> = (0..runs)
        .map(|_| {
            let t = Instant::now();
            std::hint::black_box(f());
            t.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    ms.sort_by(f64::total_cmp);
    (ms[ms.len() / 2], ms[0])
}
