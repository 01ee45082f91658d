//! Benchmark: from a trained model to the nodule, for one patient — grid (compose, σ at the
//! nodes, |∇σ|, the VDB file), sweep (12 thresholds), select (ground-truth coverage, the three
//! rules, oracle) and the marching-cubes mesh with its OBJ text, each as the default pipeline
//! runs it: sweep finds the lung field and the local contrast, select regenerates the levels from
//! the sweep's lung field and localizes the blob. Target ≤ 100 ms.
//!
//! `cargo run --release --example bench_select -- [PATIENT_OUT_DIR] [RUNS]`: the folder holds
//! `model.safetensors`, `cameras.json`, `gt_mask.mhd/.raw` and `ground_truth.json` (default
//! `out/LIDC-IDRI-0001` after `aret-pipe run pipeline.toml --until select`).

use aret_pipe::formats::{mhd, model, obj, vdb};
use aret_pipe::kernels::localization::ground_truth_on_grid;
use aret_pipe::kernels::marching_cubes::mesh_mask;
use aret_pipe::kernels::mesh::{enclosed_volume_mm3, vertex_normals};
use aret_pipe::stage::drr::CameraSet;
use aret_pipe::stage::grid::{gradient_magnitude_unit, lattice_geometry, node_density};
use aret_pipe::stage::ingest::truth::GroundTruth;
use aret_pipe::stage::select::{centres, Analysis, Params as SelectParams, Rule};
use aret_pipe::stage::sweep::{levels_of, scored, Params};
use aret_pipe::volume::Volume;
use std::time::Instant;

fn main() -> anyhow::Result<()> {
    let mut args = std::env::args().skip(1);
    let dir = std::path::PathBuf::from(args.next().unwrap_or_else(|| "out/LIDC-IDRI-0001".into()));
    let runs: usize = args.next().map(|s| s.parse()).transpose()?.unwrap_or(11);
    let read = |name: &str| std::fs::read(dir.join(name));
    let set: CameraSet = serde_json::from_slice(&read("cameras.json")?)?;
    let (field, mask, meta) = model::decode(&read("model.safetensors")?)?;
    let gt_mask: Volume<u8> = mhd::decode(&String::from_utf8(read("gt_mask.mhd")?)?, &read("gt_mask.raw")?)?;
    let truth: GroundTruth = serde_json::from_slice(&read("ground_truth.json")?)?;
    let annotated = truth.target.map(|t| truth.nodules[t].annotated_diameter_mm);
    let mut phases: Vec<[f64; 6]> = Vec::new();
    for _ in 0..runs {
        let t = Instant::now();
        let geometry = lattice_geometry(meta.grid, &meta.aabb, &set.frame);
        let density = Volume { geometry: geometry.clone(), data: node_density(field.clone(), mask.clone(), &meta) };
        let uncertainty = gradient_magnitude_unit(&density);
        let grid = |name, values| vdb::FloatGrid {
            name,
            dims: geometry.dims,
            values,
            voxel_size_mm: geometry.spacing_mm,
            origin_mm: geometry.origin_mm,
            class: vdb::GridClass::FogVolume,
        };
        std::hint::black_box(vdb::encode(&[grid("density", &density.data), grid("uncertainty", &uncertainty)])?);
        let t_grid = t.elapsed().as_secs_f64();
        // The sweep stage: the lung field, the local contrast, the levels.
        let params = Params::default();
        let swept = scored(&density, &params, None)?;
        let t_lungs = t.elapsed().as_secs_f64();
        std::hint::black_box(levels_of(&swept, &params)?);
        let t_sweep = t.elapsed().as_secs_f64();
        // The select stage regenerates the levels from the sweep's lung field, then localizes.
        let scored = scored(&density, &params, swept.region)?;
        let levels = levels_of(&scored, &params)?;
        let gt = ground_truth_on_grid(&gt_mask, &density.geometry)?;
        let analysis = Analysis::new(&levels, Some(&gt), &density.geometry);
        let t_analysis = t.elapsed().as_secs_f64();
        let select = SelectParams::default();
        let blobs =
            aret_pipe::stage::blobs::search(&select.blob.search(), &density, scored.region.as_deref(), annotated);
        let centres = centres(
            &select,
            &density.geometry,
            Some(&blobs),
            set.frame.roi_center_mm,
            Some(&gt.coverage),
            &|_, _| true.into(), // the built-in default sizes with the candidates: the strongest blob
        );
        let through = |rule: Rule| centres.of(rule).map(|c| c.linear(density.geometry.dims));
        let picks: Vec<_> = [Rule::Guided, Rule::BlindLargest, Rule::BlindPersistent]
            .into_iter()
            .filter_map(|r| analysis.choose(r, annotated, through(r)).map(|at| (r, at, analysis.describe(r, at))))
            .collect();
        std::hint::black_box(analysis.oracle());
        let t_select = t.elapsed().as_secs_f64();
        let (_, (i, label), _) = picks.first().expect("a candidate");
        let mesh = mesh_mask(&levels[*i].components.mask_of(*label), &density.geometry);
        std::hint::black_box((
            enclosed_volume_mm3(&mesh),
            obj::encode(&mesh.vertices, Some(&vertex_normals(&mesh)), &mesh.triangles, &[]),
        ));
        let t_mesh = t.elapsed().as_secs_f64();
        phases.push([
            t_grid,
            t_lungs - t_grid,
            t_sweep - t_lungs,
            t_analysis - t_sweep,
            t_select - t_analysis,
            t_mesh - t_select,
        ]);
    }
    let median = |k: usize| {
        let mut v: Vec<f64> = phases.iter().map(|p| p[k]).collect();
        v.sort_by(f64::total_cmp);
        v[v.len() / 2] * 1e3
    };
    let mut totals: Vec<f64> = phases.iter().map(|p| p.iter().sum::<f64>()).collect();
    totals.sort_by(f64::total_cmp);
    println!(
        "grid {:.1} ms, sweep {:.1} ms (lung field + contrast {:.1}, levels {:.1}), select {:.1} ms (levels again + \
         ground truth {:.1}, blob centres + rules {:.1}), mesh {:.1} ms; total median {:.1} ms over {runs} runs on {} \
         threads (target ≤ 100 ms)",
        median(0),
        median(1) + median(2),
        median(1),
        median(2),
        median(3) + median(4),
        median(3),
        median(4),
        median(5),
        totals[totals.len() / 2] * 1e3,
        rayon::current_num_threads()
    );
    Ok(())
}
