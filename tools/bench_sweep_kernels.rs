//! Benchmark: the sweep/select kernels on 64³ masks — components (26-connectivity), closing
//! with the radius-2 ball, marching cubes of the mask, and the sweep's percentiles — median of
//! N runs each, single-threaded.
//!
//! `cargo run --release --example bench_sweep_kernels -- [RUNS]`. Two masks: a nodule-like one
//! (three overlapping balls, 4 % of the grid) and a sweep-like one at a low threshold (a
//! smooth random field above its 85th percentile: 15 %, many components). Target: each
//! kernel well under 2 ms per mask.

use aret_pipe::kernels::components::{label, Connectivity};
use aret_pipe::kernels::marching_cubes::mesh_mask;
use aret_pipe::kernels::morphology::close;
use aret_pipe::kernels::stats::percentiles;
use aret_pipe::volume::Geometry;
use rand::{Rng, SeedableRng};
use std::time::Instant;

const N: usize = 64;

fn main() -> anyhow::Result<()> {
    let runs: usize = std::env::args().nth(1).map(|r| r.parse()).transpose()?.unwrap_or(50);
    let geometry = Geometry {
        dims: [N; 3],
        spacing_mm: [3.75, 1.875, 2.1875],
        origin_mm: [-120.0, -60.0, -80.0],
        direction: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
    };
    let field = smooth_field(3);
    let mut sorted = field.clone();
    sorted.sort_by(f32::total_cmp);
    let t85 = sorted[sorted.len() * 85 / 100];
    let masks = [("balls", balls()), ("field>p85", field.iter().map(|&v| v >= t85).collect::<Vec<bool>>())];
    let values: Vec<f64> = field.iter().map(|&v| f64::from(v)).collect();
    let ps: Vec<f64> = [85.0, 88.0, 90.0, 91.0, 92.0, 93.0, 94.0, 95.0, 96.0, 97.0, 98.0, 99.0].to_vec();
    println!("64³ masks, {runs} runs each, median (min) in ms:");
    for (name, mask) in &masks {
        let on = mask.iter().filter(|&&v| v).count();
        let components = label(mask, geometry.dims, Connectivity::TwentySix).count();
        let mesh = mesh_mask(mask, &geometry);
        println!("  {name}: {on} voxels set, {components} components, mesh of {} triangles", mesh.triangles.len());
        report("components (26)", runs, || label(mask, geometry.dims, Connectivity::TwentySix).count());
        report("components (6)", runs, || label(mask, geometry.dims, Connectivity::Six).count());
        report("closing (r = 2, padded)", runs, || close(mask, geometry.dims, 2).len());
        report("marching cubes", runs, || mesh_mask(mask, &geometry).triangles.len());
    }
    report("12 percentiles of 64³ values", runs, || percentiles(&values, &ps).map(|v| v.len()).unwrap_or(0));
    Ok(())
}

fn report(what: &str, runs: usize, mut f: impl FnMut() -> usize) {
    let mut ms: Vec<f64> = (0..runs)
        .map(|_| {
            let t = Instant::now();
            std::hint::black_box(f());
            t.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    ms.sort_by(f64::total_cmp);
    println!("    {what:32} {:8.3} ({:.3})", ms[ms.len() / 2], ms[0]);
}

/// Three overlapping balls near the centre, radii 5–7 voxels.
fn balls() -> Vec<bool> {
    let centres = [([30.0, 32.0, 31.0], 7.0), ([36.0, 30.0, 33.0], 6.0), ([32.0, 38.0, 28.0], 5.0)];
    (0..N * N * N)
        .map(|i| {
            let p = [i % N, i / N % N, i / (N * N)].map(|v| v as f64);
            centres.iter().any(|(c, r)| (0..3).map(|a| (p[a] - c[a]).powi(2)).sum::<f64>() <= r * r)
        })
        .collect()
}

/// White noise box-blurred three times along each axis (a smooth, blobby random field).
fn smooth_field(seed: u64) -> Vec<f32> {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let mut f: Vec<f32> = (0..N * N * N).map(|_| rng.gen()).collect();
    let stride = [1, N, N * N];
    for _ in 0..3 {
        for s in stride {
            let g = f.clone();
            for (i, v) in f.iter_mut().enumerate() {
                let c = i / s % N;
                let (lo, hi) = (c.saturating_sub(2), (c + 2).min(N - 1));
                *v = (lo..=hi).map(|k| g[i - c * s + k * s]).sum::<f32>() / (hi - lo + 1) as f32;
            }
        }
    }
    f
}
