//! Nodules in the phantom. Owns the path from a radiologists' mask to HU: a binary
//! bounding-box mask ([`BoxGrid<bool>`]), or a graded one such as the fraction of readers who
//! drew each voxel, becomes a soft partial-volume occupancy ([`occupancy_from_mask`],
//! [`occupancy_from_fraction`]); its tissue follows the LIDC texture rating, a solid core in a
//! ground-glass halo with an internal texture ([`textured_nodule`], [`solid_share_for_texture`]);
//! [`insert_nodule`] blends it into the CT.
//!
//! Index conventions are the volume's: `[column, row, slice]` for origins and sizes, data
//! laid out `[slice][row][column]`. An LIDC/pylidc bbox-local mask `mask[i][j][k]`-style
//! array stored `[k][i][j]` (k slice, i row, j column) with bbox origin `(i0, j0, k0)` is
//! `BoxGrid { origin: [j0, i0, k0], dims: [nj, ni, nk], data }` unchanged.

use super::noise::{fbm, stream_seed};
use crate::kernels::filters::distance_inside_mm;
use crate::volume::Volume;

/// A box of voxel values placed in a volume's index space.
#[derive(Debug, Clone, PartialEq)]
pub struct BoxGrid<T> {
    /// Volume index `[column, row, slice]` of the box's first voxel. May be negative or past
    /// the volume: whatever lies outside is ignored on insertion.
    pub origin: [i64; 3],
    /// `[columns, rows, slices]`.
    pub dims: [usize; 3],
    /// Values, `[slice][row][column]`.
    pub data: Vec<T>,
}

impl<T> BoxGrid<T> {
    /// Position in `data` of box-local voxel (i column, j row, k slice).
    pub fn index(&self, i: usize, j: usize, k: usize) -> usize {
        i + self.dims[0] * (j + self.dims[1] * k)
    }
}

impl BoxGrid<bool> {
    /// The mask as fractions of nodule tissue: 1 where set, 0 elsewhere.
    pub fn as_fraction(&self) -> BoxGrid<f32> {
        let data = self.data.iter().map(|&on| f32::from(u8::from(on))).collect();
        BoxGrid { origin: self.origin, dims: self.dims, data }
    }
}

/// A nodule ready to blend into a CT: where it covers each voxel, and its tissue's attenuation
/// there.
#[derive(Debug, Clone, PartialEq)]
pub struct NoduleInsert {
    /// Fraction of each voxel the nodule fills, in [0, 1].
    pub occupancy: BoxGrid<f32>,
    /// Attenuation of the nodule tissue in each voxel of `occupancy`'s box (its layout), HU.
    pub tissue_hu: Vec<f32>,
}

impl NoduleInsert {
    /// A nodule of one attenuation throughout.
    pub fn uniform(occupancy: BoxGrid<f32>, hu: f32) -> NoduleInsert {
        let tissue_hu = vec![hu; occupancy.data.len()];
        NoduleInsert { occupancy, tissue_hu }
    }
}

/// In-plane partial-volume blur: Gaussian standard deviation in pixels (a CT scanner's
/// in-plane point spread is about a pixel wide).
pub const PARTIAL_VOLUME_SIGMA_PIXELS: f64 = 0.5;

/// Soft occupancy of a binary mask: the mask blurred by a Gaussian of
/// [`PARTIAL_VOLUME_SIGMA_PIXELS`] in-plane pixels, with the *same width in millimetres*
/// along every axis. With thick slices (2.5 mm against 0.7 mm pixels) that width is a small
/// fraction of a slice, so the through-plane extent stays the mask's: each slice's contour
/// stands for its whole slab, as in the LIDC volume convention (voxel count × voxel volume),
/// and no nodule tissue is smeared into neighbouring slabs. The blur is normalised and the
/// box grows by the kernel radius, so the occupancy sums to the mask's voxel count: the
/// inserted nodule keeps the reference volume exactly.
pub fn occupancy_from_mask(mask: &BoxGrid<bool>, spacing_mm: [f64; 3]) -> BoxGrid<f32> {
    occupancy_from_fraction(&mask.as_fraction(), spacing_mm)
}

/// Soft occupancy of a graded shape, each voxel's `fraction` in [0, 1] filled with nodule
/// tissue (e.g. the fraction of readers who drew it), blurred as [`occupancy_from_mask`]
/// blurs a mask: it sums to the fractions' sum.
pub fn occupancy_from_fraction(fraction: &BoxGrid<f32>, spacing_mm: [f64; 3]) -> BoxGrid<f32> {
    let sigma_mm = PARTIAL_VOLUME_SIGMA_PIXELS * spacing_mm[0].min(spacing_mm[1]);
    let kernels: [Vec<f32>; 3] = std::array::from_fn(|a| gaussian_kernel(sigma_mm / spacing_mm[a]));
    let radius: [usize; 3] = std::array::from_fn(|a| kernels[a].len() / 2);
    let dims: [usize; 3] = std::array::from_fn(|a| fraction.dims[a] + 2 * radius[a]);
    let mut grid = BoxGrid {
        origin: std::array::from_fn(|a| fraction.origin[a] - radius[a] as i64),
        dims,
        data: vec![0.0f32; dims.iter().product()],
    };
    for k in 0..fraction.dims[2] {
        for j in 0..fraction.dims[1] {
            for i in 0..fraction.dims[0] {
                let n = grid.index(i + radius[0], j + radius[1], k + radius[2]);
                grid.data[n] = fraction.data[fraction.index(i, j, k)].clamp(0.0, 1.0);
            }
        }
    }
    for (axis, kernel) in kernels.iter().enumerate() {
        convolve_axis(&mut grid, axis, kernel);
    }
    grid
}

/// Normalised Gaussian weights of standard deviation `sigma` voxels over ±round(3σ) (a
/// single weight 1 when σ is a small fraction of a voxel: the tails would be < e⁻¹⁸).
fn gaussian_kernel(sigma: f64) -> Vec<f32> {
    let radius = (3.0 * sigma).round().max(0.0) as i64;
    let w: Vec<f64> = (-radius..=radius).map(|d| (-(d * d) as f64 / (2.0 * sigma * sigma)).exp()).collect();
    let sum: f64 = w.iter().sum();
    w.iter().map(|v| (v / sum) as f32).collect()
}

/// Convolve `grid` along `axis` with an odd-length `kernel`, zero outside the box.
fn convolve_axis(grid: &mut BoxGrid<f32>, axis: usize, kernel: &[f32]) {
    if kernel.len() <= 1 {
        return;
    }
    let r = (kernel.len() / 2) as i64;
    let n = grid.dims[axis] as i64;
    let stride = [1, grid.dims[0], grid.dims[0] * grid.dims[1]][axis];
    let src = grid.data.clone();
    let [nx, ny, nz] = grid.dims;
    for k in 0..nz {
        for j in 0..ny {
            for i in 0..nx {
                let pos = [i, j, k][axis] as i64;
                let base = grid.index(i, j, k) as i64 - pos * stride as i64;
                let mut sum = 0.0;
                for (t, w) in kernel.iter().enumerate() {
                    let q = pos + t as i64 - r;
                    if (0..n).contains(&q) {
                        sum += w * src[(base + q * stride as i64) as usize];
                    }
                }
                let idx = grid.index(i, j, k);
                grid.data[idx] = sum;
            }
        }
    }
}

/// Blend a nodule into `ct`: `hu ← (1 − o)·hu + o·tissue_hu` over its box (clipped to the
/// volume).
pub fn insert_nodule(ct: &mut Volume<f32>, nodule: &NoduleInsert) {
    let occ = &nodule.occupancy;
    let vol_dims = ct.geometry.dims;
    for k in 0..occ.dims[2] {
        for j in 0..occ.dims[1] {
            for i in 0..occ.dims[0] {
                let at: [i64; 3] = [occ.origin[0] + i as i64, occ.origin[1] + j as i64, occ.origin[2] + k as i64];
                if (0..3).any(|a| at[a] < 0 || at[a] >= vol_dims[a] as i64) {
                    continue;
                }
                let m = occ.index(i, j, k);
                let o = occ.data[m].clamp(0.0, 1.0);
                if o > 0.0 {
                    let n = ct.geometry.index(at[0] as usize, at[1] as usize, at[2] as usize);
                    let v = &mut ct.data[n];
                    *v += o * (nodule.tissue_hu[m] - *v);
                }
            }
        }
    }
}

/// Attenuation of ground-glass nodule tissue, HU: at the faint end of published pure
/// ground-glass nodules (docs/phantom.md).
pub const GROUND_GLASS_HU: f32 = -650.0;
/// Attenuation of solid nodule tissue, HU (soft tissue, unenhanced).
pub const SOLID_HU: f32 = 30.0;
/// Standard deviation of the ground glass's internal texture, HU: partly filled alveoli and the
/// small vessels a halo holds make it far more heterogeneous than solid tissue.
pub const GROUND_GLASS_TEXTURE_HU: f32 = 60.0;
/// Standard deviation of the solid core's internal texture, HU.
pub const SOLID_TEXTURE_HU: f32 = 15.0;
/// Size of the internal texture's largest features, mm.
const TEXTURE_PERIOD_MM: f32 = 4.0;

/// The share of a nodule's tissue that is solid, from its LIDC texture rating (median or mode
/// of the radiologists'): 1 non-solid (ground glass) 0, 2 non-solid/mixed 0.3, 3 part-solid
/// 0.6, 4 solid/mixed 0.9, 5 solid 1. No rating, or one outside 1–5: solid.
pub fn solid_share_for_texture(texture: Option<u8>) -> f32 {
    match texture {
        Some(1) => 0.0,
        Some(2) => 0.3,
        Some(3) => 0.6,
        Some(4) => 0.9,
        _ => 1.0,
    }
}

/// Mean attenuation of a nodule of LIDC texture rating `texture`, HU: its solid share at
/// [`SOLID_HU`], the rest at [`GROUND_GLASS_HU`] (−650, −446, −242, −38 and +30 HU for
/// ratings 1–5).
pub fn nodule_hu_for_texture(texture: Option<u8>) -> f32 {
    GROUND_GLASS_HU + solid_share_for_texture(texture) * (SOLID_HU - GROUND_GLASS_HU)
}

/// A nodule of LIDC texture rating `texture` whose tissue fills each voxel of `fraction` by
/// that fraction (a binary mask, or the share of readers who drew it). The deepest
/// [`solid_share_for_texture`] of its tissue is a solid core, the rest a ground-glass halo
/// around it ("deepest": farthest inside the voxels at least half filled, or nearest to them
/// outside). Both carry a spatially correlated texture drawn from `seed`, and the partial-volume
/// blur of [`occupancy_from_fraction`] softens the nodule's edge and the core's alike, so the
/// tissue sums to the fractions' sum and its mean attenuation is [`nodule_hu_for_texture`]'s,
/// up to the texture's mean.
pub fn textured_nodule(fraction: &BoxGrid<f32>, texture: Option<u8>, spacing_mm: [f64; 3], seed: u64) -> NoduleInsert {
    let core = solid_core(fraction, solid_share_for_texture(texture), spacing_mm);
    let core_fraction =
        BoxGrid { data: fraction.data.iter().zip(&core).map(|(&f, &c)| f * c).collect(), ..fraction.clone() };
    let occupancy = occupancy_from_fraction(fraction, spacing_mm);
    let core_occupancy = occupancy_from_fraction(&core_fraction, spacing_mm);
    let (halo_seed, core_seed) = (stream_seed(seed, "ground glass", 0), stream_seed(seed, "solid", 0));
    let mut tissue_hu = Vec::with_capacity(occupancy.data.len());
    let [nx, ny, nz] = occupancy.dims;
    for k in 0..nz {
        for j in 0..ny {
            for i in 0..nx {
                let at = [i, j, k];
                let p_mm: [f32; 3] =
                    std::array::from_fn(|a| ((occupancy.origin[a] + at[a] as i64) as f64 * spacing_mm[a]) as f32);
                let halo = GROUND_GLASS_HU + GROUND_GLASS_TEXTURE_HU * fbm(halo_seed, p_mm, TEXTURE_PERIOD_MM, 2);
                let solid = SOLID_HU + SOLID_TEXTURE_HU * fbm(core_seed, p_mm, TEXTURE_PERIOD_MM, 2);
                let n = occupancy.index(i, j, k);
                let o = occupancy.data[n];
                let solid_part = if o > 0.0 { (core_occupancy.data[n] / o).clamp(0.0, 1.0) } else { 0.0 };
                tissue_hu.push(halo + solid_part * (solid - halo));
            }
        }
    }
    NoduleInsert { occupancy, tissue_hu }
}

/// How much of each voxel's tissue in `fraction`'s box is the solid core: the deepest tissue,
/// `share` of it, by signed depth (the distance inside the voxels at least half filled, or minus
/// the distance to them outside). Voxels deeper than the cut are solid, shallower ones ground
/// glass, and those at the cut's depth share what remains, so the core holds exactly `share`.
fn solid_core(fraction: &BoxGrid<f32>, share: f32, spacing_mm: [f64; 3]) -> Vec<f32> {
    let tissue = |n: usize| f64::from(fraction.data[n].clamp(0.0, 1.0));
    if share >= 1.0 || share <= 0.0 {
        return vec![if share >= 1.0 { 1.0 } else { 0.0 }; fraction.data.len()];
    }
    // Pad by a voxel of nothing, so a shape touching the box's side has an outside there.
    let dims: [usize; 3] = std::array::from_fn(|a| fraction.dims[a] + 2);
    let padded = |i: usize, j: usize, k: usize| i + 1 + dims[0] * (j + 1 + dims[1] * (k + 1));
    let mut shape = vec![false; dims.iter().product()];
    for k in 0..fraction.dims[2] {
        for j in 0..fraction.dims[1] {
            for i in 0..fraction.dims[0] {
                shape[padded(i, j, k)] = fraction.data[fraction.index(i, j, k)] >= 0.5;
            }
        }
    }
    let outside: Vec<bool> = shape.iter().map(|&s| !s).collect();
    let inside_mm = distance_inside_mm(&shape, dims, spacing_mm);
    let outside_mm = distance_inside_mm(&outside, dims, spacing_mm);
    let mut depth = Vec::with_capacity(fraction.data.len());
    for k in 0..fraction.dims[2] {
        for j in 0..fraction.dims[1] {
            for i in 0..fraction.dims[0] {
                let p = padded(i, j, k);
                depth.push(inside_mm[p] - outside_mm[p]);
            }
        }
    }
    let mut order: Vec<usize> = (0..depth.len()).filter(|&n| tissue(n) > 0.0).collect();
    order.sort_by(|&a, &b| depth[b].total_cmp(&depth[a]));
    let wanted = f64::from(share) * order.iter().map(|&n| tissue(n)).sum::<f64>();
    let mut core = vec![0.0f32; fraction.data.len()];
    let mut held = 0.0;
    for level in order.chunk_by(|&a, &b| depth[a] == depth[b]) {
        let at_level: f64 = level.iter().map(|&n| tissue(n)).sum();
        let part = ((wanted - held) / at_level).clamp(0.0, 1.0);
        if part <= 0.0 {
            break;
        }
        for &n in level {
            core[n] = part as f32;
        }
        held += part * at_level;
    }
    core
}

/// A binary ellipsoid mask (test objects, previews): semi-axes `semi_axes_mm` (x, y, z),
/// centred at fractional volume index `centre` (column, row, slice), on voxels of
/// `spacing_mm`; a voxel is in if its centre is.
pub fn ellipsoid_mask(centre: [f64; 3], semi_axes_mm: [f64; 3], spacing_mm: [f64; 3]) -> BoxGrid<bool> {
    let half: [f64; 3] = std::array::from_fn(|a| semi_axes_mm[a] / spacing_mm[a]);
    let origin: [i64; 3] = std::array::from_fn(|a| (centre[a] - half[a]).floor() as i64);
    let dims: [usize; 3] = std::array::from_fn(|a| ((centre[a] + half[a]).ceil() as i64 - origin[a] + 1) as usize);
    let mut data = Vec::with_capacity(dims.iter().product());
    for k in 0..dims[2] {
        for j in 0..dims[1] {
            for i in 0..dims[0] {
                let at = [i, j, k];
                let r2: f64 = (0..3)
                    .map(|a| {
                        let d = (origin[a] + at[a] as i64) as f64 - centre[a];
                        (d / half[a]).powi(2)
                    })
                    .sum();
                data.push(r2 <= 1.0);
            }
        }
    }
    BoxGrid { origin, dims, data }
}
