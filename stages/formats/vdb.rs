//! OpenVDB (`.vdb`) writer for float grids, so the density and uncertainty volumes open in
//! Houdini, Blender and anything else built on OpenVDB. No crate writes the format,
//! so this module writes it by hand; `tests/vdb.rs` reads the files back with the vdb-rs crate
//! and `tests/py/test_vdb_openvdb.py` with the official library (`pyopenvdb`, `vdb_print`).
//!
//! What we write (all little-endian):
//! - Header: magic `b" BDV\0\0\0\0"`, file format 224 (what OpenVDB 4 to 12 write; all read it),
//!   library version 11.0, "has grid offsets" = 1, a 36-character UUID derived from a blake3
//!   hash of everything after it (so equal grids give equal bytes), an empty file metadata map
//!   and the grid count.
//! - Per grid: the descriptor (name, `Tree_float_5_4_3`, no instance parent, the absolute file
//!   offsets of the grid, of its leaf data and of its end), the compression flags, the grid
//!   metadata, a `ScaleTranslateMap` transform, the tree topology, then the leaf data.
//! - The tree is OpenVDB's standard float tree: a root whose children are 32³ internal nodes
//!   (4096 voxels a side), each with 16³ internal children (128 voxels), each with 8³ leaves.
//!   Background 0: a voxel is active exactly when its value is not 0; zeros (and -0) are
//!   inactive and not stored, leaves and internal nodes without an active voxel are not
//!   written, and there are no tiles (`vdb/leaves.rs`).
//! - Compression (`vdb/compress.rs`): by default the flags are zip + active mask: each node
//!   stores a flag byte and its active values only, as float32 (never half), deflated with
//!   zlib per node, as OpenVDB does. `Compression::ActiveValuesOnly` leaves out the zlib step.
//!
//! Index space is cell-centred in OpenVDB: index (i, j, k) is the centre of voxel (i, j, k), so
//! the transform maps it to `origin_mm + (i, j, k) · voxel_size_mm` in patient millimetres.

mod compress;
mod leaves;

pub use compress::Compression;
use leaves::{Leaf, LEAF_LOG2, LOWER_LOG2, LOWER_SPAN_LOG2, UPPER_LOG2};
use std::collections::HashSet;
use std::fmt::Write as _;

/// OpenVDB's magic number, as the first 8 bytes of every file.
const MAGIC: i64 = 0x5644_4220;
/// File format 224 (`OPENVDB_FILE_VERSION_MULTIPASS_IO`): what OpenVDB 4 to 12 write, and the
/// newest that Debian's OpenVDB 10 reads without a warning (225, for half grids, came after 12).
const FILE_VERSION: u32 = 224;
/// The library version recorded in the header; readers only report it.
const LIBRARY_VERSION: (u32, u32) = (11, 0);
/// The tree type name for float values with 32³ / 16³ internal nodes and 8³ leaves.
const TREE_TYPE: &str = "Tree_float_5_4_3";

/// In-memory sizes OpenVDB 10 reports for a float tree on a 64-bit machine (measured with
/// pyopenvdb: `file_mem_bytes` of grids with known node counts). Only for `file_mem_bytes`,
/// which readers display (vdb_print, Houdini) but never rely on.
const MEM_TREE: i64 = 1304;
const MEM_UPPER: i64 = 270_348;
const MEM_LOWER: i64 = 33_804;
const MEM_LEAF: i64 = 2_144;

/// What a grid represents, as OpenVDB's `class` metadata names it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum GridClass {
    /// Density in [0, 1] with background 0: volume renderers treat it as a fog/smoke volume.
    FogVolume,
    /// Anything else ("Other" in Houdini's menus).
    Unknown,
}

impl GridClass {
    fn as_str(self) -> &'static str {
        match self {
            GridClass::FogVolume => "fog volume",
            GridClass::Unknown => "unknown",
        }
    }
}

/// One dense float volume to write as a sparse OpenVDB grid.
#[derive(Debug, Clone, Copy)]
pub struct FloatGrid<'a> {
    /// The grid's name in the file, e.g. `density`.
    pub name: &'a str,
    /// Voxels along x, y, z.
    pub dims: [usize; 3],
    /// Voxel values, x fastest: index `x + dims[0]·(y + dims[1]·z)`. Zeros are inactive.
    pub values: &'a [f32],
    /// Distance between voxel centres along x, y, z, mm (may differ per axis).
    pub voxel_size_mm: [f64; 3],
    /// Patient-space position of the centre of voxel (0, 0, 0), mm.
    pub origin_mm: [f64; 3],
    pub class: GridClass,
}

#[derive(Debug, thiserror::Error)]
pub enum VdbError {
    #[error("grid `{name}` has {found} values, but dims {dims:?} need {expected}")]
    ValueCount { name: String, dims: [usize; 3], found: usize, expected: usize },
    #[error("grid `{name}`: voxel size {voxel_size_mm:?} mm must be finite and positive on every axis")]
    VoxelSize { name: String, voxel_size_mm: [f64; 3] },
    #[error("grid `{name}`: origin {origin_mm:?} mm must be finite")]
    Origin { name: String, origin_mm: [f64; 3] },
    #[error("grid {index} has an empty name; OpenVDB grids need one")]
    EmptyName { index: usize },
    #[error("grid name {name:?} contains a control character")]
    NameCharacter { name: String },
    #[error("two grids are named `{0}`; names in one file must differ")]
    DuplicateName(String),
    #[error("grid `{name}`: dims {dims:?} exceed OpenVDB's 32-bit signed voxel coordinates")]
    DimsTooLarge { name: String, dims: [usize; 3] },
}

/// The bytes of a `.vdb` file holding `grids`, in order, zip-compressed. Deterministic: equal
/// input, equal bytes.
pub fn encode(grids: &[FloatGrid]) -> Result<Vec<u8>, VdbError> {
    encode_with(grids, Compression::Zip)
}

/// The bytes of a `.vdb` file holding `grids`, in order, their values stored as `compression`
/// says. Deterministic: equal input, equal bytes.
pub fn encode_with(grids: &[FloatGrid], compression: Compression) -> Result<Vec<u8>, VdbError> {
    validate(grids)?;
    let mut out = Out::default();
    out.i64(MAGIC);
    out.u32(FILE_VERSION);
    out.u32(LIBRARY_VERSION.0);
    out.u32(LIBRARY_VERSION.1);
    out.u8(1); // has grid offsets: readers may seek straight to a grid
    let uuid_at = out.len();
    out.bytes(&[b'0'; 36]); // the UUID, filled in once the rest is known
    out.u32(0); // file-level metadata: none
    out.u32(grids.len() as u32);
    for grid in grids {
        write_grid(&mut out, grid, compression);
    }
    let mut bytes = out.0;
    let uuid = content_uuid(&bytes[uuid_at + 36..]);
    bytes[uuid_at..uuid_at + 36].copy_from_slice(uuid.as_bytes());
    Ok(bytes)
}

fn validate(grids: &[FloatGrid]) -> Result<(), VdbError> {
    let mut names = HashSet::new();
    for (index, g) in grids.iter().enumerate() {
        let name = || g.name.to_string();
        if g.name.is_empty() {
            return Err(VdbError::EmptyName { index });
        }
        // OpenVDB separates a grid name from its instance suffix with U+001E; keep names clean.
        if g.name.chars().any(char::is_control) {
            return Err(VdbError::NameCharacter { name: name() });
        }
        if !names.insert(g.name) {
            return Err(VdbError::DuplicateName(name()));
        }
        if g.dims.iter().any(|&d| d > i32::MAX as usize) {
            return Err(VdbError::DimsTooLarge { name: name(), dims: g.dims });
        }
        let expected = g.dims.iter().try_fold(1usize, |n, &d| n.checked_mul(d));
        let Some(expected) = expected else {
            return Err(VdbError::DimsTooLarge { name: name(), dims: g.dims });
        };
        if g.values.len() != expected {
            return Err(VdbError::ValueCount { name: name(), dims: g.dims, found: g.values.len(), expected });
        }
        if !g.voxel_size_mm.iter().all(|s| s.is_finite() && *s > 0.0) {
            return Err(VdbError::VoxelSize { name: name(), voxel_size_mm: g.voxel_size_mm });
        }
        if !g.origin_mm.iter().all(|o| o.is_finite()) {
            return Err(VdbError::Origin { name: name(), origin_mm: g.origin_mm });
        }
    }
    Ok(())
}

fn write_grid(out: &mut Out, grid: &FloatGrid, compression: Compression) {
    let leaves = leaves::leaves(grid.dims, grid.values);
    // Descriptor: name, tree type, instance parent (none), then three offsets patched below.
    out.string(grid.name);
    out.string(TREE_TYPE);
    out.string("");
    let offsets_at = out.len();
    out.bytes(&[0; 24]);
    let grid_pos = out.len();
    out.u32(compression.flags());
    write_metadata(out, grid, &leaves, compression);
    write_transform(out, grid);
    write_topology(out, &leaves, compression);
    let block_pos = out.len();
    out.bytes(&compress::leaf_buffers(&leaves, compression));
    let end_pos = out.len();
    for (n, pos) in [grid_pos, block_pos, end_pos].into_iter().enumerate() {
        let at = offsets_at + 8 * n;
        out.0[at..at + 8].copy_from_slice(&(pos as i64).to_le_bytes());
    }
}

/// The grid's metadata map, in `std::map` (byte-wise name) order, as OpenVDB writes it: the
/// class, the creator, the `file_*` statistics OpenVDB adds on write (readers show them without
/// loading the tree), the half-float flag (false: values are float32) and the name.
fn write_metadata(out: &mut Out, grid: &FloatGrid, leaves: &[Leaf], compression: Compression) {
    let voxels: i64 = leaves.iter().map(|l| l.active_count() as i64).sum();
    let (bbox_min, bbox_max) = leaves::active_bbox(leaves);
    let uppers = leaves::count_distinct(leaves.iter().map(Leaf::upper_origin));
    let lowers = leaves::count_distinct(leaves.iter().map(Leaf::lower_origin));
    let mem = MEM_TREE + MEM_UPPER * uppers + MEM_LOWER * lowers + MEM_LEAF * leaves.len() as i64;

    let entries: [(&str, Meta); 9] = [
        ("class", Meta::Str(grid.class.as_str())),
        ("creator", Meta::Str("aret-pipe")),
        ("file_bbox_max", Meta::Vec3i(bbox_max)),
        ("file_bbox_min", Meta::Vec3i(bbox_min)),
        ("file_compression", Meta::Str(compression.description())),
        ("file_mem_bytes", Meta::Int64(mem)),
        ("file_voxel_count", Meta::Int64(voxels)),
        ("is_saved_as_half_float", Meta::Bool(false)),
        ("name", Meta::Str(grid.name)),
    ];
    debug_assert!(entries.windows(2).all(|w| w[0].0 < w[1].0), "metadata must be in map order");
    out.u32(entries.len() as u32);
    for (key, value) in entries {
        out.string(key);
        value.write(out);
    }
}

enum Meta<'a> {
    Str(&'a str),
    Vec3i([i32; 3]),
    Int64(i64),
    Bool(bool),
}

impl Meta<'_> {
    /// Type name, byte count, value: OpenVDB's `Metadata::write` after the name.
    fn write(&self, out: &mut Out) {
        match self {
            Meta::Str(s) => {
                out.string("string");
                out.string(s);
            }
            Meta::Vec3i(v) => {
                out.string("vec3i");
                out.u32(12);
                v.iter().for_each(|&c| out.i32(c));
            }
            Meta::Int64(v) => {
                out.string("int64");
                out.u32(8);
                out.i64(*v);
            }
            Meta::Bool(b) => {
                out.string("bool");
                out.u32(1);
                out.u8(*b as u8);
            }
        }
    }
}

/// `ScaleTranslateMap`: index → world is `index · scale + translation`. OpenVDB stores the
/// derived vectors too (voxel size, 1/scale, 1/scale², 1/(2·scale)) and reads them back as
/// they are, so they must be consistent.
fn write_transform(out: &mut Out, grid: &FloatGrid) {
    let scale = grid.voxel_size_mm;
    let inverse = scale.map(|s| 1.0 / s);
    out.string("ScaleTranslateMap");
    for v in [grid.origin_mm, scale, scale.map(f64::abs), inverse, inverse.map(|i| i * i), inverse.map(|i| i / 2.0)] {
        v.iter().for_each(|&c| out.f64(c));
    }
}

/// The tree's structure, depth first: buffer count, background, root tiles and children; per
/// internal node its child and value masks and its (all inactive, background) tile values;
/// per leaf its value mask. The voxel values follow separately (`write_grid`).
fn write_topology(out: &mut Out, leaves: &[Leaf], compression: Compression) {
    let mut tile_values = compress::ValueWriter::new(compression);
    out.u32(1); // one value buffer per leaf
    out.f32(0.0); // background
    out.u32(0); // root tiles
    let uppers: Vec<&[Leaf]> = leaves.chunk_by(|a, b| a.upper_origin() == b.upper_origin()).collect();
    out.u32(uppers.len() as u32);
    for upper in uppers {
        upper[0].upper_origin().iter().for_each(|&c| out.i32(c));
        let lowers: Vec<&[Leaf]> = upper.chunk_by(|a, b| a.lower_origin() == b.lower_origin()).collect();
        let mut children = vec![0u64; 1 << (3 * UPPER_LOG2 - 6)];
        for lower in &lowers {
            set_bit(&mut children, leaves::child_offset(lower[0].lower_origin(), UPPER_LOG2, LOWER_SPAN_LOG2));
        }
        write_internal_node(out, &children, &mut tile_values);
        for lower in lowers {
            let mut children = vec![0u64; 1 << (3 * LOWER_LOG2 - 6)];
            for leaf in lower {
                set_bit(&mut children, leaves::child_offset(leaf.origin, LOWER_LOG2, LEAF_LOG2));
            }
            write_internal_node(out, &children, &mut tile_values);
            for leaf in lower {
                out.mask(&leaf.mask);
            }
        }
    }
}

/// An internal node's child mask, its value mask (no active tiles), and its tile values: all
/// inactive background, so none is stored (an empty chunk under zip).
fn write_internal_node(out: &mut Out, child_mask: &[u64], tile_values: &mut compress::ValueWriter) {
    out.mask(child_mask);
    out.mask(&vec![0u64; child_mask.len()]);
    tile_values.write(out, std::iter::empty());
}

fn set_bit(words: &mut [u64], n: usize) {
    words[n >> 6] |= 1 << (n & 63);
}

/// A UUID-shaped identifier from a blake3 hash of `content` (version 8, "custom", per RFC 9562):
/// OpenVDB wants one per file and only compares them, so a content hash keeps output
/// deterministic where OpenVDB would use random bits.
fn content_uuid(content: &[u8]) -> String {
    let mut b: [u8; 16] = blake3::hash(content).as_bytes()[..16].try_into().expect("16 of 32 bytes");
    b[6] = (b[6] & 0x0f) | 0x80;
    b[8] = (b[8] & 0x3f) | 0x80;
    let mut s = String::with_capacity(36);
    for (i, byte) in b.iter().enumerate() {
        if matches!(i, 4 | 6 | 8 | 10) {
            s.push('-');
        }
        let _ = write!(s, "{byte:02x}");
    }
    s
}

/// Little-endian output, with OpenVDB's length-prefixed strings and word-wise bit masks.
#[derive(Default)]
struct Out(Vec<u8>);

impl Out {
    fn len(&self) -> usize {
        self.0.len()
    }
    fn bytes(&mut self, b: &[u8]) {
        self.0.extend_from_slice(b);
    }
    fn u8(&mut self, v: u8) {
        self.0.push(v);
    }
    fn u32(&mut self, v: u32) {
        self.bytes(&v.to_le_bytes());
    }
    fn i32(&mut self, v: i32) {
        self.bytes(&v.to_le_bytes());
    }
    fn i64(&mut self, v: i64) {
        self.bytes(&v.to_le_bytes());
    }
    fn f32(&mut self, v: f32) {
        self.bytes(&v.to_le_bytes());
    }
    fn f64(&mut self, v: f64) {
        self.bytes(&v.to_le_bytes());
    }
    /// u32 byte count, then the bytes (no terminator).
    fn string(&mut self, s: &str) {
        self.u32(s.len() as u32);
        self.bytes(s.as_bytes());
    }
    /// A node mask: bit `n` is bit `n % 64` of word `n / 64`.
    fn mask(&mut self, words: &[u64]) {
        for w in words {
            self.bytes(&w.to_le_bytes());
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grid<'a>(name: &'a str, dims: [usize; 3], values: &'a [f32]) -> FloatGrid<'a> {
        FloatGrid {
            name,
            dims,
            values,
            voxel_size_mm: [1.0, 2.0, 3.0],
            origin_mm: [0.0; 3],
            class: GridClass::FogVolume,
        }
    }

    #[test]
    fn rejects_bad_grids_naming_the_problem() {
        let v = vec![1.0f32; 24];
        let e = encode(&[grid("d", [2, 3, 5], &v)]).unwrap_err();
        assert!(matches!(e, VdbError::ValueCount { found: 24, expected: 30, .. }), "{e}");
        assert!(e.to_string().contains("`d`"));
        for bad in [[1.0, 0.0, 1.0], [1.0, -2.0, 1.0], [f64::NAN, 1.0, 1.0], [1.0, 1.0, f64::INFINITY]] {
            let g = FloatGrid { voxel_size_mm: bad, ..grid("d", [2, 3, 4], &v) };
            assert!(matches!(encode(&[g]), Err(VdbError::VoxelSize { .. })), "{bad:?}");
        }
        let g = FloatGrid { origin_mm: [0.0, f64::NAN, 0.0], ..grid("d", [2, 3, 4], &v) };
        assert!(matches!(encode(&[g]), Err(VdbError::Origin { .. })));
        assert!(matches!(
            encode(&[grid("a", [2, 3, 4], &v), grid("", [2, 3, 4], &v)]),
            Err(VdbError::EmptyName { index: 1 })
        ));
        assert!(matches!(encode(&[grid("a\u{1e}0", [2, 3, 4], &v)]), Err(VdbError::NameCharacter { .. })));
        let two = [grid("a", [2, 3, 4], &v), grid("a", [2, 3, 4], &v)];
        assert!(matches!(encode(&two), Err(VdbError::DuplicateName(n)) if n == "a"));
        let huge = [1usize << 31, 1, 1];
        assert!(matches!(encode(&[grid("a", huge, &v)]), Err(VdbError::DimsTooLarge { .. })));
        let overflow = [1usize << 30, 1 << 30, 1 << 30];
        assert!(matches!(encode(&[grid("a", overflow, &v)]), Err(VdbError::DimsTooLarge { .. })));
    }

    #[test]
    fn bytes_depend_only_on_content() {
        let mut values: Vec<f32> = (0..60).map(|i| (i % 7) as f32).collect();
        let a = encode(&[grid("d", [3, 4, 5], &values)]).unwrap();
        assert_eq!(a, encode(&[grid("d", [3, 4, 5], &values)]).unwrap());
        assert_eq!(&a[..8], b" BDV\0\0\0\0");
        let uuid = std::str::from_utf8(&a[21..57]).unwrap();
        assert_eq!(uuid.len(), 36);
        assert_eq!(uuid.split('-').map(str::len).collect::<Vec<_>>(), [8, 4, 4, 4, 12]);
        values[1] = 0.5;
        let b = encode(&[grid("d", [3, 4, 5], &values)]).unwrap();
        assert_ne!(&a[21..57], &b[21..57], "another content, another UUID");
    }
}
