//! Generate the phantom on LIDC-IDRI-0001's scan geometry with a nodule-like ellipsoid at its
//! first reference nodule, print timings, and write preview PNGs.
//!
//! ```sh
//! cargo run --release --example phantom_preview -- [OUT_DIR] [--extra]
//! ```
//!
//! Writes `phantom_axial.png` (axial slice through the nodule, lung window),
//! `phantom_coronal.png` (coronal slice through it, lung window) and
//! `phantom_projection.png` (coronal mean-attenuation projection) into OUT_DIR (default
//! `target/phantom_preview`); `--extra` adds axial slices at several heights in lung and
//! mediastinal windows.

use aret_pipe::formats::png::{
    axial_slice, coronal_projection, coronal_slice, image_png, Window, LUNG_WINDOW, MEDIASTINAL_WINDOW,
};
use aret_pipe::phantom::{add_scanner_noise, ellipsoid_mask, insert_nodule, textured_nodule, PhantomParams, Thorax};
use aret_pipe::volume::Geometry;
use std::path::{Path, PathBuf};
use std::time::Instant;

const SCAN: &str = "tools/cohorts/paper19/LIDC-IDRI-0001.scan.json";

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let extra = args.iter().any(|a| a == "--extra");
    let out = args
        .iter()
        .find(|a| !a.starts_with("--"))
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from("target/phantom_preview"));
    std::fs::create_dir_all(&out)?;

    let scan: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(SCAN)?)?;
    let geometry = scan_geometry(&scan)?;
    let cluster = &scan["reference"]["clusters"][0];
    let bbox: Vec<[f64; 2]> = serde_json::from_value(cluster["consensus_bbox_ijk_inclusive"].clone())?;
    let texture = cluster["context"]["texture_mode"].as_u64().map(|t| t as u8);
    // bbox is (i row, j column, k slice); volume indices are (column, row, slice).
    let centre = [(bbox[1][0] + bbox[1][1]) / 2.0, (bbox[0][0] + bbox[0][1]) / 2.0, (bbox[2][0] + bbox[2][1]) / 2.0];
    let s = geometry.spacing_mm;
    let semi_axes_mm = [
        (bbox[1][1] - bbox[1][0] + 1.0) * s[0] / 2.0,
        (bbox[0][1] - bbox[0][0] + 1.0) * s[1] / 2.0,
        (bbox[2][1] - bbox[2][0] + 1.0) * s[2] / 2.0,
    ];
    println!(
        "{}: {:?} voxels of {:?} mm; nodule at voxel {centre:?}, semi-axes {semi_axes_mm:.1?} mm, texture {texture:?}",
        scan["patient_id"].as_str().unwrap_or("?"),
        geometry.dims,
        geometry.spacing_mm
    );

    let params = PhantomParams::default();
    let t0 = Instant::now();
    let thorax = Thorax::new(&geometry, &params);
    let t_layout = t0.elapsed();
    let mut ct = thorax.hu();
    let t_hu = t0.elapsed();
    let fraction = ellipsoid_mask(centre, semi_axes_mm, s).as_fraction();
    let nodule = textured_nodule(&fraction, texture, s, params.seed);
    insert_nodule(&mut ct, &nodule);
    add_scanner_noise(&mut ct, &params);
    let t_all = t0.elapsed();
    println!(
        "layout (vessel trees: {} segments) {:.2} s, anatomy {:.2} s, nodule + noise {:.2} s: total {:.2} s on {} threads",
        thorax.vessel_segments(),
        t_layout.as_secs_f64(),
        (t_hu - t_layout).as_secs_f64(),
        (t_all - t_hu).as_secs_f64(),
        t_all.as_secs_f64(),
        rayon::current_num_threads()
    );
    let centre_mm = geometry.voxel_to_patient_mm(centre);
    println!("tissue at the nodule centre (without it): {:?}", thorax.tissue_at_mm(centre_mm));
    report_lung_hu(&thorax, &geometry, centre[2].round() as usize + 8);

    let (k, row) = (centre[2].round() as usize, centre[1].round() as usize);
    write(&out, "phantom_axial.png", &image_png(&axial_slice(&ct, k), LUNG_WINDOW))?;
    write(&out, "phantom_coronal.png", &image_png(&coronal_slice(&ct, row), LUNG_WINDOW))?;
    let projection = coronal_projection(&ct);
    write(&out, "phantom_projection.png", &image_png(&projection, Window::spanning(&projection)))?;
    if extra {
        let n = geometry.dims[2];
        for frac in [0.1, 0.25, 0.4, 0.55, 0.62, 0.7, 0.8, 0.9] {
            let k = ((n - 1) as f64 * frac).round() as usize;
            let img = axial_slice(&ct, k);
            write(&out, &format!("axial_{k:03}_lung.png"), &image_png(&img, LUNG_WINDOW))?;
            write(&out, &format!("axial_{k:03}_mediastinal.png"), &image_png(&img, MEDIASTINAL_WINDOW))?;
        }
        write(&out, "coronal_mediastinal.png", &image_png(&coronal_slice(&ct, row), MEDIASTINAL_WINDOW))?;
    }
    println!("previews in {}", out.display());
    Ok(())
}

/// Mean and standard deviation of the noiseless HU of voxels labelled lung parenchyma on
/// slice `k` (every 4th pixel).
fn report_lung_hu(thorax: &Thorax, geometry: &Geometry, k: usize) {
    let hu = thorax.hu();
    let mut values = Vec::new();
    for j in (0..geometry.dims[1]).step_by(4) {
        for i in (0..geometry.dims[0]).step_by(4) {
            let p = geometry.voxel_to_patient_mm([i as f64, j as f64, k as f64]);
            if thorax.tissue_at_mm(p) == aret_pipe::phantom::Tissue::Lung {
                values.push(f64::from(hu.data[geometry.index(i, j, k)]));
            }
        }
    }
    let n = values.len() as f64;
    let mean = values.iter().sum::<f64>() / n;
    let sd = (values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n).sqrt();
    println!("lung parenchyma on slice {k} (noiseless): mean {mean:.0} HU, sd {sd:.0} HU over {n} voxels");
}

fn write(dir: &Path, name: &str, bytes: &[u8]) -> anyhow::Result<()> {
    std::fs::write(dir.join(name), bytes)?;
    Ok(())
}

/// The scan's voxel grid: 512² pixels with the scanner axis at the image centre, slices at
/// the listed z positions (their median spacing).
fn scan_geometry(scan: &serde_json::Value) -> anyhow::Result<Geometry> {
    let ps = scan["pixel_spacing_mm"].as_f64().ok_or_else(|| anyhow::anyhow!("pixel_spacing_mm"))?;
    let rows = scan["rows"].as_u64().unwrap_or(512) as usize;
    let cols = scan["cols"].as_u64().unwrap_or(512) as usize;
    let z: Vec<f64> = serde_json::from_value(scan["zvals_mm"].clone())?;
    let mut gaps: Vec<f64> = z.windows(2).map(|w| w[1] - w[0]).collect();
    gaps.sort_by(f64::total_cmp);
    let dz = gaps.get(gaps.len() / 2).copied().unwrap_or(2.5);
    Ok(Geometry {
        dims: [cols, rows, z.len()],
        spacing_mm: [ps, ps, dz],
        origin_mm: [-(cols as f64 / 2.0) * ps, -(rows as f64 / 2.0) * ps, z[0]],
        direction: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
    })
}
