//! Benchmark: the DRR stage's rendering — three 128² views of a 512×512×~130 CT — median of N.
//!
//! `cargo run --release --example bench_drr -- [RUNS]`. The CT is the phantom of LIDC-IDRI-0001
//! (real geometry, 512×512×133), normalised as the `hu` stage does; the scene is centred on
//! its target nodule as by default. Target: ≤ 0.3 s on 2 cores.

use aret_pipe::formats::lidc_xml;
use aret_pipe::kernels::consensus::{scan_truth, GroundTruthParams, ScanGeometry};
use aret_pipe::phantom::patient::{generate, ScanInfo};
use aret_pipe::phantom::PhantomParams;
use aret_pipe::stage::drr::{render_views, Params};
use aret_pipe::stage::hu;
use std::time::Instant;

fn main() -> anyhow::Result<()> {
    let runs: usize = std::env::args().nth(1).map(|r| r.parse()).transpose()?.unwrap_or(5);
    let cohort = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tools/cohorts/paper19");
    let scan = ScanInfo::parse(&std::fs::read_to_string(cohort.join("LIDC-IDRI-0001.scan.json"))?, "scan.json")?;
    let xml = std::fs::read_to_string(cohort.join("LIDC-IDRI-0001.xml"))?;
    let reads = lidc_xml::parse(&xml)?;
    let phantom = generate(&scan, &reads, ("LIDC-IDRI-0001.xml".into(), xml.clone()), &PhantomParams::default())?;
    let ct_unit = phantom.ct.map(|h| hu::hu_to_unit(f64::from(h).round(), &hu::Params::default()));
    let lidc = ScanGeometry::new(scan.zvals_mm.clone(), scan.pixel_spacing_mm, scan.rows, scan.cols)?;
    let truth = scan_truth(&reads, &lidc, scan.slice_thickness_mm, &GroundTruthParams::default())?;
    let [i, j, k] = truth.largest().and_then(|n| n.centroid_ijk).expect("a target nodule");
    let centre = ct_unit.geometry.voxel_to_patient_mm([j, i, k]);
    let params = Params::default();
    let mut seconds = Vec::with_capacity(runs);
    for _ in 0..runs {
        let t = Instant::now();
        let (_, images) = render_views(&params, &ct_unit, centre, "nodule")?;
        seconds.push(t.elapsed().as_secs_f64());
        assert_eq!(images.len(), 3);
    }
    seconds.sort_by(f64::total_cmp);
    let d = ct_unit.geometry.dims;
    let list: Vec<String> = seconds.iter().map(|s| format!("{s:.3}")).collect();
    println!(
        "drr: three {}² views of {}x{}x{} on {} threads: runs (s) {}",
        params.width_px,
        d[0],
        d[1],
        d[2],
        rayon::current_num_threads(),
        list.join(" ")
    );
    println!("median drr render: {:.3} s (target <= 0.3 s)", seconds[seconds.len() / 2]);
    Ok(())
}
