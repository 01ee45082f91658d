//! Our OpenVDB writer read back by an independent reader, the vdb-rs crate: every active voxel's
//! position and value, nothing else active, the ScaleTranslateMap, the descriptor metadata, two
//! grids in one file, a grid spanning several root children, and `aret-pipe convert`; under
//! both compressions (zip + active values, the default, and active values only), and what zip
//! saves on a CT-like volume that is mostly air.
//! (The official library reads the same files in tests/py/test_vdb_openvdb.py.)

use aret_pipe::formats::mhd;
use aret_pipe::formats::vdb::{encode, encode_with, Compression, FloatGrid, GridClass};
use aret_pipe::volume::{Geometry, Volume};
use rand::{Rng, SeedableRng};
use std::collections::BTreeMap;
use std::io::Cursor;
use vdb_rs::{Map, MetadataValue, VdbLevel, VdbReader};

const BIN: &str = env!("CARGO_BIN_EXE_aret-pipe");

/// Random values, about `zero_fraction` of them exactly 0 (a few -0), the rest of both signs
/// and very different magnitudes.
fn sparse_values(n: usize, zero_fraction: f64, seed: u64) -> Vec<f32> {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    (0..n)
        .map(|_| {
            if rng.gen_bool(zero_fraction) {
                if rng.gen_bool(0.1) {
                    -0.0
                } else {
                    0.0
                }
            } else {
                let v: f32 = rng.gen_range(-1.0..1.0);
                if rng.gen_bool(0.05) {
                    v * 1e-30
                } else {
                    v
                }
            }
        })
        .collect()
}

/// The active voxels a reader must find: every value that is not 0, by (x, y, z).
fn expected_active(dims: [usize; 3], values: &[f32]) -> BTreeMap<[i32; 3], u32> {
    let mut m = BTreeMap::new();
    for z in 0..dims[2] {
        for y in 0..dims[1] {
            for x in 0..dims[0] {
                let v = values[x + dims[0] * (y + dims[1] * z)];
                if v != 0.0 {
                    m.insert([x as i32, y as i32, z as i32], v.to_bits());
                }
            }
        }
    }
    m
}

struct Read {
    active: BTreeMap<[i32; 3], u32>,
    /// The grid's `io::COMPRESS_*` flags: zip 0x1, active mask 0x2.
    compression_flags: u32,
    translation: [f64; 3],
    scale: [f64; 3],
    voxel_size: [f64; 3],
    metadata: std::collections::HashMap<String, MetadataValue>,
}

fn read_grid(bytes: &[u8], name: &str) -> Read {
    let mut reader = VdbReader::new(Cursor::new(bytes)).expect("vdb-rs reads the header");
    let grid = reader.read_grid::<f32>(name).expect("vdb-rs reads the grid");
    let flags = grid.descriptor.compression.bits();
    let mut active = BTreeMap::new();
    for (pos, value, level) in grid.iter() {
        assert!(level == VdbLevel::Voxel, "we write no tiles, found one at {pos:?}");
        let p = [pos.x as i32, pos.y as i32, pos.z as i32];
        assert!(active.insert(p, value.to_bits()).is_none(), "voxel {p:?} listed twice");
    }
    let Map::ScaleTranslateMap { translation, scale_values, voxel_size, .. } = grid.transform else {
        panic!("expected a ScaleTranslateMap, got {:?}", grid.transform);
    };
    Read {
        active,
        compression_flags: flags,
        translation: translation.to_array(),
        scale: scale_values.to_array(),
        voxel_size: voxel_size.to_array(),
        metadata: grid.descriptor.meta_data.0.clone(),
    }
}

/// `grid` read back from `bytes`, written with the default compression (zip + active values).
fn assert_grid_reads_back(bytes: &[u8], grid: &FloatGrid) {
    assert_grid_reads_back_as(bytes, grid, Compression::Zip);
}

fn assert_grid_reads_back_as(bytes: &[u8], grid: &FloatGrid, compression: Compression) {
    let read = read_grid(bytes, grid.name);
    let (flags, description) = match compression {
        Compression::Zip => (0x3, "zip + active values"),
        Compression::ActiveValuesOnly => (0x2, "active values"),
    };
    assert_eq!(read.compression_flags, flags, "{}: compression flags", grid.name);
    let expected = expected_active(grid.dims, grid.values);
    assert!(!expected.is_empty());
    assert_eq!(read.active.len(), expected.len(), "{}: active voxel count", grid.name);
    for (p, bits) in &expected {
        assert_eq!(read.active.get(p), Some(bits), "{}: voxel {p:?}", grid.name);
    }
    // Index (i, j, k) → origin + (i, j, k) · voxel size: translation = origin, scale = size.
    assert_eq!(read.translation, grid.origin_mm, "{}: translation", grid.name);
    assert_eq!(read.scale, grid.voxel_size_mm, "{}: scale", grid.name);
    assert_eq!(read.voxel_size, grid.voxel_size_mm, "{}: voxel size", grid.name);

    let meta = |key: &str| read.metadata.get(key).unwrap_or_else(|| panic!("{}: no metadata `{key}`", grid.name));
    assert_eq!(meta("name"), &MetadataValue::String(grid.name.into()));
    let class = if grid.class == GridClass::FogVolume { "fog volume" } else { "unknown" };
    assert_eq!(meta("class"), &MetadataValue::String(class.into()));
    assert_eq!(meta("file_voxel_count"), &MetadataValue::I64(expected.len() as i64));
    assert_eq!(meta("is_saved_as_half_float"), &MetadataValue::Bool(false));
    assert_eq!(meta("file_compression"), &MetadataValue::String(description.into()));
    let (mut lo, mut hi) = ([i32::MAX; 3], [i32::MIN; 3]);
    for p in expected.keys() {
        for a in 0..3 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
        }
    }
    let vec3i = |v: &MetadataValue| match v {
        MetadataValue::Vec3i(v) => v.to_array(),
        other => panic!("expected vec3i, got {other:?}"),
    };
    assert_eq!(vec3i(meta("file_bbox_min")), lo);
    assert_eq!(vec3i(meta("file_bbox_max")), hi);
}

#[test]
fn odd_sized_anisotropic_grid_reads_back_voxel_for_voxel() {
    let dims = [37, 20, 29];
    let values = sparse_values(dims.iter().product(), 0.4, 1);
    let grid = FloatGrid {
        name: "density",
        dims,
        values: &values,
        voxel_size_mm: [0.703125, 1.25, 2.5],
        origin_mm: [-170.5, 12.25, -312.0],
        class: GridClass::FogVolume,
    };
    let bytes = encode(&[grid]).unwrap();
    assert_grid_reads_back(&bytes, &grid);
    assert_eq!(encode(&[grid]).unwrap(), bytes, "same grid, same bytes");
    let uncompressed = encode_with(&[grid], Compression::ActiveValuesOnly).unwrap();
    assert_grid_reads_back_as(&uncompressed, &grid, Compression::ActiveValuesOnly);
    assert_ne!(uncompressed, bytes);
}

#[test]
fn two_grids_in_one_file_read_back_independently() {
    let (d1, d2) = ([37, 20, 29], [9, 17, 40]);
    let (v1, v2) = (sparse_values(d1.iter().product(), 0.7, 2), sparse_values(d2.iter().product(), 0.2, 3));
    let density = FloatGrid {
        name: "density",
        dims: d1,
        values: &v1,
        voxel_size_mm: [3.75, 1.875, 2.1875],
        origin_mm: [-120.0, -60.0, -70.0],
        class: GridClass::FogVolume,
    };
    let uncertainty = FloatGrid {
        name: "uncertainty",
        dims: d2,
        values: &v2,
        voxel_size_mm: [0.5, 0.5, 1.0],
        origin_mm: [1.0, -2.0, 3.0],
        class: GridClass::Unknown,
    };
    let bytes = encode(&[density, uncertainty]).unwrap();
    let mut names = VdbReader::new(Cursor::new(&bytes)).unwrap().available_grids();
    names.sort();
    assert_eq!(names, ["density", "uncertainty"]);
    // Read in both orders: each grid is found through its own descriptor offsets.
    assert_grid_reads_back(&bytes, &uncertainty);
    assert_grid_reads_back(&bytes, &density);
}

#[test]
fn grid_spanning_several_root_children_reads_back() {
    // x crosses the 4096-voxel boundary of the upper internal nodes, y the 128-voxel one of the
    // lower nodes: leaves are written in the tree's depth-first order, not in plain x-y-z order.
    let dims = [4100, 136, 2];
    let mut values = vec![0.0f32; dims.iter().product()];
    let mut set = |x: usize, y: usize, z: usize, v: f32| values[x + dims[0] * (y + dims[1] * z)] = v;
    for (n, &(x, y, z)) in
        [(0, 0, 0), (0, 130, 1), (8, 0, 0), (4095, 135, 1), (4096, 0, 0), (4099, 129, 1), (200, 7, 0)]
            .iter()
            .enumerate()
    {
        set(x, y, z, n as f32 + 0.5);
    }
    let grid = FloatGrid {
        name: "wide",
        dims,
        values: &values,
        voxel_size_mm: [1.0, 1.0, 1.0],
        origin_mm: [0.0; 3],
        class: GridClass::Unknown,
    };
    assert_grid_reads_back(&encode(&[grid]).unwrap(), &grid);
}

#[test]
fn all_zero_grid_is_a_valid_empty_grid() {
    let values = vec![0.0f32; 27];
    let grid = FloatGrid {
        name: "empty",
        dims: [3, 3, 3],
        values: &values,
        voxel_size_mm: [1.0; 3],
        origin_mm: [0.0; 3],
        class: GridClass::Unknown,
    };
    let read = read_grid(&encode(&[grid]).unwrap(), "empty");
    assert!(read.active.is_empty());
    assert_eq!(read.metadata.get("file_voxel_count"), Some(&MetadataValue::I64(0)));
}

/// A CT-like volume on `ct_unit`'s scale ((HU + 1000) / 1400, clamped to [0, 1]): per slice an
/// elliptic body of soft tissue (40 HU) holding two lungs (-850 HU), with integer-HU noise
/// (σ ≈ 20), in air that is exactly 0, about 58 % of the voxels.
fn ct_like(dims: [usize; 3], seed: u64) -> Vec<f32> {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let noise = rand_distr::Normal::new(0.0f64, 20.0).unwrap();
    let [nx, ny, nz] = dims;
    let mut values = Vec::with_capacity(nx * ny * nz);
    let inside =
        |x: f64, y: f64, cx: f64, cy: f64, a: f64, b: f64| ((x - cx) / a).powi(2) + ((y - cy) / b).powi(2) < 1.0;
    for _ in 0..nz {
        for y in 0..ny {
            for x in 0..nx {
                let (u, v) = (x as f64 / nx as f64, y as f64 / ny as f64);
                let hu = if !inside(u, v, 0.5, 0.5, 0.45, 0.3) {
                    None
                } else if inside(u, v, 0.32, 0.48, 0.12, 0.18) || inside(u, v, 0.68, 0.48, 0.12, 0.18) {
                    Some(-850.0)
                } else {
                    Some(40.0)
                };
                let unit = hu.map_or(0.0, |hu: f64| ((hu + rng.sample(noise)).round() + 1000.0) / 1400.0);
                values.push(unit.clamp(0.0, 1.0) as f32);
            }
        }
    }
    values
}

#[test]
fn zip_shrinks_a_mostly_air_ct_like_volume_and_reads_back() {
    let dims = [160, 160, 40];
    let values = ct_like(dims, 7);
    let grid = FloatGrid {
        name: "ct_unit",
        dims,
        values: &values,
        voxel_size_mm: [0.703125, 0.703125, 2.5],
        origin_mm: [-180.0, -180.0, -340.0],
        class: GridClass::Unknown,
    };
    let voxels = values.len();
    let air = values.iter().filter(|v| **v == 0.0).count();
    assert!((0.55..0.62).contains(&(air as f64 / voxels as f64)), "{air} of {voxels} voxels are air");
    let zip = encode(&[grid]).unwrap();
    let active_only = encode_with(&[grid], Compression::ActiveValuesOnly).unwrap();
    let dense = 4 * voxels;
    println!(
        "{voxels} voxels, {air} air: dense float32 {dense} B, active values only {} B, zip {} B",
        active_only.len(),
        zip.len()
    );
    // Air costs nothing in either layout: only the body's values (and 65 B of mask and flag
    // per leaf) are stored.
    assert!(active_only.len() < dense / 2, "active values only: {} B of {dense}", active_only.len());
    // Zip keeps what noise leaves to compress: a quantised value repeats within a leaf.
    assert!(zip.len() < active_only.len() * 2 / 3, "zip: {} B, active values only: {} B", zip.len(), active_only.len());
    assert_grid_reads_back(&zip, &grid);
    assert_grid_reads_back_as(&active_only, &grid, Compression::ActiveValuesOnly);
    // Leaves deflate in parallel tasks of a fixed size: one thread writes the same bytes.
    let one_thread = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
    assert_eq!(one_thread.install(|| encode(&[grid]).unwrap()), zip);
}

fn write_mhd(dir: &std::path::Path, name: &str, volume: &Volume<f32>) -> std::path::PathBuf {
    let (header, raw) = mhd::encode(volume, &format!("{name}.raw"));
    std::fs::write(dir.join(format!("{name}.raw")), raw).unwrap();
    let path = dir.join(format!("{name}.mhd"));
    std::fs::write(&path, header).unwrap();
    path
}

#[test]
fn convert_writes_a_metaimage_volume_as_a_vdb_grid() {
    let dir = tempfile::tempdir().unwrap();
    let geometry = Geometry {
        dims: [11, 6, 5],
        spacing_mm: [0.75, 0.75, 2.5],
        origin_mm: [-40.0, 10.5, -200.25],
        direction: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
    };
    let volume = Volume { data: sparse_values(geometry.len(), 0.5, 4), geometry };
    let input = write_mhd(dir.path(), "density", &volume);
    let output = dir.path().join("density.vdb");
    let out = std::process::Command::new(BIN)
        .arg("convert")
        .arg(&input)
        .arg(&output)
        .arg("--class")
        .arg("fog")
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let bytes = std::fs::read(&output).unwrap();
    // The grid is named after the input file and placed as the MetaImage places the volume.
    let expected = FloatGrid {
        name: "density",
        dims: volume.geometry.dims,
        values: &volume.data,
        voxel_size_mm: volume.geometry.spacing_mm,
        origin_mm: volume.geometry.origin_mm,
        class: GridClass::FogVolume,
    };
    assert_grid_reads_back(&bytes, &expected);
    assert_eq!(bytes, encode(&[expected]).unwrap());
}

#[test]
fn convert_refuses_a_rotated_volume() {
    let dir = tempfile::tempdir().unwrap();
    let geometry = Geometry {
        dims: [2, 2, 2],
        spacing_mm: [1.0; 3],
        origin_mm: [0.0; 3],
        direction: [[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]],
    };
    let input = write_mhd(dir.path(), "ct", &Volume { data: vec![1.0; 8], geometry });
    let output = dir.path().join("ct.vdb");
    let out = std::process::Command::new(BIN).arg("convert").arg(&input).arg(&output).output().unwrap();
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("TransformMatrix") && stderr.contains("cannot rotate"), "{stderr}");
    assert!(!output.exists());
}

#[test]
fn convert_pairs_names_and_classes_with_inputs_in_order() {
    let dir = tempfile::tempdir().unwrap();
    let geometry = |spacing| Geometry {
        dims: [4, 3, 2],
        spacing_mm: spacing,
        origin_mm: [1.0, 2.0, 3.0],
        direction: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
    };
    let a = Volume { data: sparse_values(24, 0.3, 5), geometry: geometry([1.0, 1.0, 2.0]) };
    let b = Volume { data: sparse_values(24, 0.3, 6), geometry: geometry([0.5, 0.5, 0.5]) };
    let (pa, pb) = (write_mhd(dir.path(), "a", &a), write_mhd(dir.path(), "b", &b));
    let output = dir.path().join("ab.vdb");
    let run = |extra: &[&str]| {
        std::process::Command::new(BIN).arg("convert").arg(&pa).arg(&pb).arg(&output).args(extra).output().unwrap()
    };
    let out = run(&["--grid", "density", "--grid", "uncertainty", "--class", "fog", "--class", "other"]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let bytes = std::fs::read(&output).unwrap();
    for (name, v, class) in [("density", &a, GridClass::FogVolume), ("uncertainty", &b, GridClass::Unknown)] {
        let g = v.geometry.clone();
        let expected = FloatGrid {
            name,
            dims: g.dims,
            values: &v.data,
            voxel_size_mm: g.spacing_mm,
            origin_mm: g.origin_mm,
            class,
        };
        assert_grid_reads_back(&bytes, &expected);
    }
    let out = run(&["--grid", "density"]);
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("--grid is given 1 time(s) for 2 input(s)"), "{stderr}");
}
