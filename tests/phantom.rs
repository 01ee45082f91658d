//! The synthetic thorax phantom (`aret_pipe::phantom`), its DICOM writer and PNG previews:
//! determinism, tissue HU, the 19 paper patients' real nodules lying in the phantom's lungs,
//! partial-volume nodule insertion, a DICOM round trip through our own reader.

use aret_pipe::formats::dicom::{read_ct_series, DEFAULT_GAP_TOLERANCE};
use aret_pipe::formats::dicom_writer::{write_ct_series, SeriesMeta};
use aret_pipe::formats::png::{axial_slice, coronal_projection, encode_gray8, image_png, LUNG_WINDOW};
use aret_pipe::phantom::{
    add_scanner_noise, ellipsoid_mask, insert_nodule, nodule_hu_for_texture, occupancy_from_fraction,
    occupancy_from_mask, phantom_ct, solid_share_for_texture, textured_nodule, thorax_hu, BoxGrid, NoduleInsert,
    PhantomParams, Thorax, Tissue,
};
use aret_pipe::volume::{Geometry, Volume};
use std::collections::HashMap;
use std::path::PathBuf;

const IDENTITY: [[f64; 3]; 3] = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];

/// A reduced chest CT grid: 360-mm FOV in 128² pixels, 40 slices over 330 mm.
fn small_geometry() -> Geometry {
    let ps = 360.0 / 128.0;
    Geometry {
        dims: [128, 128, 40],
        spacing_mm: [ps, ps, 330.0 / 40.0],
        origin_mm: [-64.0 * ps, -64.0 * ps, -330.0],
        direction: IDENTITY,
    }
}

fn bits(v: &Volume<f32>) -> Vec<u32> {
    v.data.iter().map(|x| x.to_bits()).collect()
}

#[test]
fn same_seed_same_bytes_whatever_the_threads_and_other_seeds_differ() {
    let g = small_geometry();
    let params = PhantomParams::default();
    let one_thread =
        rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap().install(|| phantom_ct(&g, &params, &[]));
    let many = rayon::ThreadPoolBuilder::new().num_threads(3).build().unwrap().install(|| phantom_ct(&g, &params, &[]));
    assert_eq!(one_thread.geometry, g);
    assert!(bits(&one_thread) == bits(&many), "thread count changed the volume");
    let other = phantom_ct(&g, &PhantomParams { seed: 2, ..params.clone() }, &[]);
    let differing = bits(&other).iter().zip(bits(&many)).filter(|(a, b)| **a != *b).count();
    assert!(differing > g.len() / 2, "only {differing} voxels differ with another seed");
}

/// Every third voxel (in each direction) of the small phantom: its label, its noiseless HU
/// and the HU of its neighbour along x.
fn labelled_samples(thorax: &Thorax, hu: &Volume<f32>) -> HashMap<Tissue, Vec<(f32, f32)>> {
    let g = &hu.geometry;
    let mut by_tissue: HashMap<Tissue, Vec<(f32, f32)>> = HashMap::new();
    for k in (1..g.dims[2]).step_by(3) {
        for j in (1..g.dims[1]).step_by(3) {
            for i in (1..g.dims[0] - 1).step_by(3) {
                let p = g.voxel_to_patient_mm([i as f64, j as f64, k as f64]);
                let v = (hu.data[g.index(i, j, k)], hu.data[g.index(i + 1, j, k)]);
                by_tissue.entry(thorax.tissue_at_mm(p)).or_default().push(v);
            }
        }
    }
    by_tissue
}

fn mean(v: &[(f32, f32)]) -> f32 {
    v.iter().map(|s| s.0).sum::<f32>() / v.len() as f32
}

/// Standard deviation of the values and their correlation with the neighbours'.
fn sd_and_neighbour_correlation(v: &[(f32, f32)]) -> (f32, f32) {
    let n = v.len() as f32;
    let (ma, mb) = (mean(v), v.iter().map(|s| s.1).sum::<f32>() / n);
    let cov = v.iter().map(|s| (s.0 - ma) * (s.1 - mb)).sum::<f32>() / n;
    let var_a = v.iter().map(|s| (s.0 - ma).powi(2)).sum::<f32>() / n;
    let var_b = v.iter().map(|s| (s.1 - mb).powi(2)).sum::<f32>() / n;
    (var_a.sqrt(), cov / (var_a * var_b).sqrt())
}

#[test]
fn tissues_have_their_hu_and_the_noise_its_standard_deviation() {
    let g = small_geometry();
    let params = PhantomParams::default();
    let thorax = Thorax::new(&g, &params);
    let hu = thorax.hu();
    let samples = labelled_samples(&thorax, &hu);
    let count = |t: Tissue| samples.get(&t).map_or(0, Vec::len);
    // (tissue, expected mean HU, tolerance): partial volume at the edges of thin or
    // small structures (vessels in the lungs, at 2.8-mm pixels and 8-mm slices) pulls means
    // toward their neighbours.
    let expected = [
        (Tissue::Air, -1000.0, 5.0),
        (Tissue::Lung, params.lung_hu, 50.0),
        (Tissue::Fat, -100.0, 40.0),
        (Tissue::Muscle, 45.0, 40.0),
        (Tissue::Heart, 40.0, 30.0),
        (Tissue::Liver, 60.0, 40.0),
    ];
    let mut keys: Vec<_> = samples.keys().collect();
    keys.sort_by_key(|t| format!("{t:?}"));
    for t in keys {
        println!("{t:?}: {} voxels, mean {:.0} HU", samples[t].len(), mean(&samples[t]));
    }
    for (tissue, want, tol) in expected {
        let v = samples.get(&tissue).unwrap_or_else(|| panic!("no {tissue:?} voxels"));
        let m = mean(v);
        assert!((m - want).abs() < tol, "{tissue:?}: mean {m:.0} HU over {} voxels, want {want}", v.len());
    }
    let bone = mean(&samples[&Tissue::Bone]);
    assert!(bone > 200.0, "bone mean {bone:.0} HU");
    // The lungs are the biggest organ inside the body; the body fills much of the FOV.
    let total: usize = samples.values().map(Vec::len).sum();
    let lung_fraction = count(Tissue::Lung) as f64 / total as f64;
    assert!((0.12..0.4).contains(&lung_fraction), "lungs fill {lung_fraction:.2} of the volume");
    for t in [Tissue::Table, Tissue::Skin, Tissue::PulmonaryVessel, Tissue::Airway, Tissue::Spleen, Tissue::Stomach] {
        assert!(count(t) > 0, "no {t:?} voxels");
    }
    // Lung texture (parenchyma, gravity gradient, small vessels): spatially correlated, not
    // white noise: neighbours 2.8 mm apart are alike.
    let (lung_sd, lung_correlation) = sd_and_neighbour_correlation(&samples[&Tissue::Lung]);
    assert!((15.0..150.0).contains(&lung_sd), "lung texture sd {lung_sd:.1} HU");
    assert!(lung_correlation > 0.3, "lung texture neighbour correlation {lung_correlation:.2}");
    // The parenchyma HU follows the parameter.
    let denser = thorax_hu(&g, &PhantomParams { lung_hu: -800.0, ..params.clone() });
    let lung_voxels: Vec<usize> =
        (0..g.len()).step_by(7).filter(|&n| hu.data[n] < -700.0 && hu.data[n] > -950.0).collect();
    let mean_at = |v: &Volume<f32>| lung_voxels.iter().map(|&n| v.data[n]).sum::<f32>() / lung_voxels.len() as f32;
    let moved = mean_at(&denser) - mean_at(&hu);
    assert!((moved - 50.0).abs() < 5.0, "lung_hu −850 → −800 moved the parenchyma by {moved:.1} HU");

    let mut noisy = hu.clone();
    add_scanner_noise(&mut noisy, &params);
    let n = noisy.data.len() as f64;
    let diffs: Vec<f64> = noisy.data.iter().zip(&hu.data).map(|(a, b)| f64::from(a - b)).collect();
    let m = diffs.iter().sum::<f64>() / n;
    let sd = (diffs.iter().map(|d| (d - m).powi(2)).sum::<f64>() / n).sqrt();
    assert!(m.abs() < 0.5, "noise mean {m:.2}");
    assert!((sd - f64::from(params.noise_hu)).abs() < 0.05 * f64::from(params.noise_hu), "noise sd {sd:.2}");
}

/// A paper patient's scan geometry (scanner axis at the image centre) and its reference
/// nodules: (bbox centre in patient mm, equivalent diameter mm).
fn paper_patient(path: &PathBuf) -> (String, Geometry, Vec<([f64; 3], f64)>) {
    let scan: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
    let ps = scan["pixel_spacing_mm"].as_f64().unwrap();
    let rows = scan["rows"].as_u64().unwrap() as usize;
    let cols = scan["cols"].as_u64().unwrap() as usize;
    let z: Vec<f64> = serde_json::from_value(scan["zvals_mm"].clone()).unwrap();
    let dz = scan["slice_spacing_mm"].as_f64().unwrap();
    let (ox, oy) = (-(cols as f64 / 2.0) * ps, -(rows as f64 / 2.0) * ps);
    let geometry = Geometry {
        dims: [cols, rows, z.len()],
        spacing_mm: [ps, ps, dz],
        origin_mm: [ox, oy, z[0]],
        direction: IDENTITY,
    };
    let nodules = scan["reference"]["clusters"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| {
            let b: Vec<[f64; 2]> = serde_json::from_value(c["consensus_bbox_ijk_inclusive"].clone()).unwrap();
            let centre = |a: usize| (b[a][0] + b[a][1]) / 2.0;
            // i = row (y), j = column (x), k = index into zvals.
            let zc = (z[b[2][0] as usize] + z[b[2][1] as usize]) / 2.0;
            let mm = [ox + centre(1) * ps, oy + centre(0) * ps, zc];
            (mm, c["equivalent_diameter_mm"].as_f64().unwrap())
        })
        .collect();
    (scan["patient_id"].as_str().unwrap().to_string(), geometry, nodules)
}

fn paper_scans() -> Vec<PathBuf> {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tools/cohorts/paper19");
    let mut scans: Vec<PathBuf> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.to_string_lossy().ends_with(".scan.json"))
        .collect();
    scans.sort();
    scans
}

/// Unit directions to the 26 neighbours of a voxel.
fn probe_directions() -> Vec<[f64; 3]> {
    let mut dirs = Vec::new();
    for dz in -1..=1 {
        for dy in -1..=1 {
            for dx in -1..=1 {
                if (dx, dy, dz) != (0, 0, 0) {
                    let v = [dx as f64, dy as f64, dz as f64];
                    let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
                    dirs.push(v.map(|c| c / n));
                }
            }
        }
    }
    dirs
}

#[test]
fn the_paper_patients_nodules_lie_in_the_lungs() {
    let scans = paper_scans();
    assert_eq!(scans.len(), 19);
    let mut outside = Vec::new();
    let mut at_edge = Vec::new();
    let mut total = 0;
    for path in &scans {
        let (id, geometry, nodules) = paper_patient(path);
        let thorax = Thorax::new(&geometry, &PhantomParams::default());
        for (centre, diameter) in nodules {
            total += 1;
            let tissue = thorax.tissue_at_mm(centre);
            if tissue.is_lung_field() {
                continue;
            }
            // Juxtapleural (or juxtacardiac) nodules may sit at the lung's edge: lung must
            // then lie within the nodule's radius (at least 4 mm) of its centre.
            let reach = (diameter / 2.0).max(4.0);
            let lung_near = probe_directions().iter().any(|d| {
                let p = std::array::from_fn(|a| centre[a] + reach * d[a]);
                thorax.tissue_at_mm(p).is_lung_field()
            });
            let line = format!("{id} nodule at {centre:.0?} mm ({diameter:.0} mm): {tissue:?}");
            if lung_near {
                at_edge.push(line);
            } else {
                outside.push(line);
            }
        }
    }
    assert!(total > 50, "{total} nodules");
    // Known: LIDC-IDRI-0010's second nodule (3.8 mm) lies 21 mm left of and 88 mm behind
    // the image centre, low in the chest: where a centred, generic spine has its left
    // pedicle. The real patient's spine must sit off the image centre; the phantom does not
    // move anatomy to fit nodules.
    const KNOWN_OFF_LUNG: &str = "LIDC-IDRI-0010 nodule at [21, 88, -249] mm";
    outside.retain(|line| !line.starts_with(KNOWN_OFF_LUNG));
    println!("{} of {total} nodule centres at a lung edge:\n{}", at_edge.len(), at_edge.join("\n"));
    assert!(
        outside.is_empty(),
        "{} of {total} nodule centres away from the lungs:\n{}",
        outside.len(),
        outside.join("\n")
    );
    assert!(at_edge.len() <= 4, "too many nodules at the lung edge: {}", at_edge.len());
}

/// The binary mask of an ellipsoid of semi-axes `semi_mm` centred in a 0.7 × 0.7 × 2.5 mm grid.
fn ellipsoid_case(semi_mm: [f64; 3]) -> ([f64; 3], BoxGrid<bool>) {
    let spacing = [0.7, 0.7, 2.5];
    let mask = ellipsoid_mask([40.3, 35.6, 12.2], semi_mm, spacing);
    (spacing, mask)
}

#[test]
fn occupancy_from_a_mask_keeps_its_volume_and_softens_its_edge() {
    let semi = [9.0, 7.0, 6.0];
    let (spacing, mask) = ellipsoid_case(semi);
    let voxel_mm3 = spacing.iter().product::<f64>();
    let mask_voxels = mask.data.iter().filter(|&&m| m).count() as f64;
    let occ = occupancy_from_mask(&mask, spacing);
    let occ_voxels: f64 = occ.data.iter().map(|&o| f64::from(o)).sum();
    // Exactly the mask's volume (the reference volume convention), and the true ellipsoid's
    // within the voxelisation error.
    assert!((occ_voxels - mask_voxels).abs() < 1e-3 * mask_voxels, "{occ_voxels} vs {mask_voxels}");
    let true_mm3 = 4.0 / 3.0 * std::f64::consts::PI * semi.iter().product::<f64>();
    let rel = occ_voxels * voxel_mm3 / true_mm3 - 1.0;
    assert!(rel.abs() < 0.05, "volume off by {:.1} %", 100.0 * rel);
    // Soft: values strictly between 0 and 1 on the rim, 1 inside, never above 1; the box
    // grew to hold the blur.
    assert!(occ.data.iter().all(|&o| (0.0..=1.0 + 1e-6).contains(&o)));
    let partial = occ.data.iter().filter(|&&o| o > 0.05 && o < 0.95).count();
    assert!(partial as f64 > 0.2 * mask_voxels, "{partial} partial voxels");
    let centre = occ.index(
        (40.3 - occ.origin[0] as f64).round() as usize,
        (35.6 - occ.origin[1] as f64).round() as usize,
        (12.2 - occ.origin[2] as f64).round() as usize,
    );
    assert!(occ.data[centre] > 0.999);
    assert!(occ.origin[0] < mask.origin[0] && occ.dims[0] > mask.dims[0]);
    // Thick slices: no smearing across slabs (the z extent stays the mask's).
    assert_eq!((occ.origin[2], occ.dims[2]), (mask.origin[2], mask.dims[2]));
}

#[test]
fn occupancy_from_a_graded_shape_keeps_its_sum_and_its_half_level() {
    // Two readers: an inner ellipsoid both drew (fraction 1), a rim only one drew (0.5).
    let (spacing, outer) = ellipsoid_case([9.0, 7.0, 6.0]);
    let inner = ellipsoid_mask([40.3, 35.6, 12.2], [6.0, 5.0, 4.0], spacing);
    let at = |m: &BoxGrid<bool>, i: usize, j: usize, k: usize| {
        let g = [
            i as i64 + outer.origin[0] - m.origin[0],
            j as i64 + outer.origin[1] - m.origin[1],
            k as i64 + outer.origin[2] - m.origin[2],
        ];
        (0..3).all(|a| g[a] >= 0 && (g[a] as usize) < m.dims[a])
            && m.data[m.index(g[0] as usize, g[1] as usize, g[2] as usize)]
    };
    let mut data = Vec::with_capacity(outer.data.len());
    for k in 0..outer.dims[2] {
        for j in 0..outer.dims[1] {
            for i in 0..outer.dims[0] {
                data.push(0.5 * (f32::from(u8::from(at(&outer, i, j, k))) + f32::from(u8::from(at(&inner, i, j, k)))));
            }
        }
    }
    let fraction = BoxGrid { origin: outer.origin, dims: outer.dims, data };
    let occ = occupancy_from_fraction(&fraction, spacing);
    let want: f64 = fraction.data.iter().map(|&f| f64::from(f)).sum();
    let got: f64 = occ.data.iter().map(|&o| f64::from(o)).sum();
    assert!((got - want).abs() < 1e-3 * want, "{got} vs {want}");
    // Along x through the centre (slab 12, row 36), 0.7 mm pixels: full inside what both drew
    // (6 mm), half on the rim only one drew (11 px = 7.7 mm), nothing past the outer 9 mm.
    let value = |x: usize| {
        occ.data[occ.index(x - occ.origin[0] as usize, 36 - occ.origin[1] as usize, 12 - occ.origin[2] as usize)]
    };
    assert!(value(40) > 0.999, "{}", value(40));
    assert!((value(40 + 11) - 0.5).abs() < 0.01, "{}", value(51));
    assert!(value(40 + 16) < 1e-3, "{}", value(56));
    // A binary shape as fractions is the mask's occupancy, bit for bit.
    let binary = BoxGrid {
        origin: outer.origin,
        dims: outer.dims,
        data: outer.data.iter().map(|&on| f32::from(u8::from(on))).collect(),
    };
    assert_eq!(occupancy_from_fraction(&binary, spacing), occupancy_from_mask(&outer, spacing));
}

#[test]
fn inserting_a_nodule_blends_its_hu_by_occupancy() {
    let g = Geometry { dims: [80, 70, 25], spacing_mm: [0.7, 0.7, 2.5], origin_mm: [0.0; 3], direction: IDENTITY };
    let background = -850.0f32;
    let mut ct = Volume { geometry: g.clone(), data: vec![background; g.len()] };
    let (spacing, mask) = ellipsoid_case([9.0, 7.0, 6.0]);
    let hu = nodule_hu_for_texture(Some(5));
    let nodule = NoduleInsert::uniform(occupancy_from_mask(&mask, spacing), hu);
    insert_nodule(&mut ct, &nodule);
    let excess: f64 = ct.data.iter().map(|&v| f64::from(v - background)).sum();
    let occupied: f64 = nodule.occupancy.data.iter().map(|&o| f64::from(o)).sum();
    let want = occupied * f64::from(hu - background);
    assert!((excess - want).abs() < 1e-3 * want.abs(), "{excess} vs {want}");
    assert_eq!(ct.data[g.index(40, 36, 12)], hu);
    // Texture ratings: solid brightest, ground glass darkest, unrated solid.
    let hu: Vec<f32> = (1..=5).map(|t| nodule_hu_for_texture(Some(t))).collect();
    assert!(hu.windows(2).all(|w| w[0] < w[1]), "{hu:?}");
    assert!((0.0..=50.0).contains(&hu[4]) && hu[0] < -500.0);
    assert_eq!(nodule_hu_for_texture(None), hu[4]);
    // A box hanging off the volume is clipped, not a panic.
    let mut edge = nodule.clone();
    edge.occupancy.origin = [-5, -5, -3];
    insert_nodule(&mut ct, &edge);
}

#[test]
fn a_textured_nodule_is_a_solid_core_in_a_ground_glass_halo_with_its_ratings_mean() {
    let (spacing, mask) = ellipsoid_case([10.0, 9.0, 8.0]);
    let fraction = mask.as_fraction();
    let centre = |n: &NoduleInsert| {
        let at =
            [40 - n.occupancy.origin[0], 36 - n.occupancy.origin[1], 12 - n.occupancy.origin[2]].map(|v| v as usize);
        n.tissue_hu[n.occupancy.index(at[0], at[1], at[2])]
    };
    for rating in 1..=5u8 {
        let nodule = textured_nodule(&fraction, Some(rating), spacing, 11);
        assert_eq!(nodule, textured_nodule(&fraction, Some(rating), spacing, 11), "rating {rating}: not deterministic");
        assert_ne!(nodule.tissue_hu, textured_nodule(&fraction, Some(rating), spacing, 12).tissue_hu);
        // The tissue is the mask's, whatever the rating.
        let occupied: f64 = nodule.occupancy.data.iter().map(|&o| f64::from(o)).sum();
        assert!((occupied - mask.data.iter().filter(|&&m| m).count() as f64).abs() < 1e-2, "rating {rating}");
        // Its mean attenuation is the rating's, up to the texture's mean over the nodule.
        let weighted: f64 =
            nodule.occupancy.data.iter().zip(&nodule.tissue_hu).map(|(&o, &h)| f64::from(o) * f64::from(h)).sum();
        let mean = weighted / occupied;
        let want = f64::from(nodule_hu_for_texture(Some(rating)));
        assert!((mean - want).abs() < 25.0, "rating {rating}: mean {mean:.0} HU against {want} HU");
        // Solid at the centre from non-solid/mixed on; ground glass at the rim below solid (for
        // solid/mixed the halo is thinner than a voxel, so the rim is a mixture).
        let rim = nodule.occupancy.data.iter().zip(&nodule.tissue_hu).filter(|(&o, _)| o > 0.05 && o < 0.5);
        let rim_max = rim.map(|(_, &h)| h).fold(f32::MIN, f32::max);
        let mut filled = nodule.occupancy.data.iter().zip(&nodule.tissue_hu).filter(|(&o, _)| o > 0.0);
        match rating {
            1 => assert!(filled.all(|(_, &h)| h < -350.0), "ground glass throughout"),
            5 => assert!(filled.all(|(_, &h)| h > -60.0), "solid throughout"),
            _ => {
                let halo = if rating == 4 { -150.0 } else { -350.0 };
                assert!(rim_max < halo, "rating {rating}: the rim reaches {rim_max} HU");
                assert!(centre(&nodule) > -60.0, "rating {rating}: the centre is {} HU", centre(&nodule));
            }
        }
    }
    let ratings: Vec<f32> = (1..=5).map(|t| solid_share_for_texture(Some(t))).collect();
    assert_eq!(ratings, [0.0, 0.3, 0.6, 0.9, 1.0]);
    assert_eq!(solid_share_for_texture(None), 1.0);
}

#[test]
fn a_written_series_reads_back_to_the_same_hu_and_geometry() {
    let g = Geometry {
        dims: [64, 48, 6],
        spacing_mm: [5.625, 7.5, 55.0],
        origin_mm: [-180.0, -180.0, -330.0],
        direction: IDENTITY,
    };
    let mut ct = phantom_ct(&g, &PhantomParams::default(), &[]);
    ct.data[0] = 40000.0; // saturates
    let meta = SeriesMeta {
        patient_id: "LIDC-IDRI-0001".into(),
        study_instance_uid: "1.2.826.0.1.3680043.8.498.10".into(),
        series_instance_uid: "1.2.826.0.1.3680043.8.498.11".into(),
        sop_instance_uids: Vec::new(),
        slice_thickness_mm: Some(2.5),
        series_description: "synthetic thorax".into(),
    };
    let files = write_ct_series(&ct, &meta).unwrap();
    assert_eq!(files.len(), 6);
    assert_eq!(files[0].0, "000001.dcm");
    let dir = tempfile::tempdir().unwrap();
    let paths: Vec<PathBuf> = files
        .iter()
        .map(|(name, bytes)| {
            let p = dir.path().join(name);
            std::fs::write(&p, bytes).unwrap();
            p
        })
        .collect();
    let series = read_ct_series(&paths, DEFAULT_GAP_TOLERANCE).unwrap();
    assert!(series.skipped.is_empty());
    assert_eq!(series.hu.geometry.dims, g.dims);
    for a in 0..3 {
        assert!((series.hu.geometry.spacing_mm[a] - g.spacing_mm[a]).abs() < 1e-6);
        assert!((series.hu.geometry.origin_mm[a] - g.origin_mm[a]).abs() < 1e-6);
    }
    assert_eq!(series.hu.geometry.direction, IDENTITY);
    assert_eq!(series.slice_thickness_mm, Some(2.5));
    let want: Vec<i16> = ct.data.iter().map(|&v| (f64::from(v).round()).clamp(-33792.0, 31743.0) as i16).collect();
    assert_eq!(series.hu.data[0], 31743);
    assert_eq!(&series.hu.data[1..], &want[1..]);
    // The pseudonymous ID is the only patient attribute.
    let obj = dicom_object::open_file(&paths[0]).unwrap();
    let text = |tag| obj.element(tag).unwrap().to_str().unwrap().trim().to_string();
    use dicom_dictionary_std::tags;
    assert_eq!(text(tags::PATIENT_ID), "LIDC-IDRI-0001");
    assert_eq!(text(tags::PATIENT_NAME), "LIDC-IDRI-0001");
    assert_eq!(text(tags::MODALITY), "CT");
    // Wrong UID counts and invalid UIDs are refused.
    let bad = SeriesMeta { sop_instance_uids: vec!["1.2.3".into()], ..meta.clone() };
    assert!(write_ct_series(&ct, &bad).unwrap_err().to_string().contains("1 SOP instance UIDs for 6 slices"));
    let bad = SeriesMeta { series_instance_uid: "1.2.x".into(), ..meta };
    assert!(write_ct_series(&ct, &bad).is_err());
}

#[test]
fn previews_are_pngs_with_square_pixels_superior_up() {
    let g = small_geometry();
    let ct = thorax_hu(&g, &PhantomParams::default());
    let axial = axial_slice(&ct, 20);
    assert_eq!((axial.width, axial.height), (128, 128));
    let projection = coronal_projection(&ct);
    // 330 mm − one slice of height at 2.8125-mm pixels, rows ≈ extent / pixel + 1.
    let extent = 39.0 * g.spacing_mm[2];
    assert_eq!(projection.height, (extent / g.spacing_mm[0]).round() as usize + 1);
    // Superior at the top: the top row crosses the neck (no lungs), the projection of the
    // lungs is darker than that of the abdomen at the bottom.
    let row_mean = |r: usize| projection.data[r * 128 + 40..r * 128 + 88].iter().sum::<f32>() / 48.0;
    let (top, middle, bottom) = (row_mean(2), row_mean(projection.height / 2), row_mean(projection.height - 3));
    assert!(middle < top && middle < bottom, "top {top} middle {middle} bottom {bottom}");
    let png = image_png(&axial, LUNG_WINDOW);
    let decoder = png::Decoder::new(std::io::Cursor::new(png));
    let reader = decoder.read_info().unwrap();
    assert_eq!((reader.info().width, reader.info().height), (128, 128));
    assert_eq!(reader.info().color_type, png::ColorType::Grayscale);
    assert_eq!(encode_gray8(2, 1, &[0, 255])[..8], [0x89, b'P', b'N', b'G', 0x0D, 0x0A, 0x1A, 0x0A]);
}
