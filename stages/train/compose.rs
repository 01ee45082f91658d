//! The f32 compose of the dense field as direct FMA chains in registers: the three products of
//! [`super::field::VmField::compose`] without `matrixmultiply`, whose packing and 16-long
//! chains ran the compose at ≈ 40 % of the FMA units' peak.
//!
//! Bit-identical to the GEMM path, and used only where that path runs `matrixmultiply`'s
//! AVX2 + FMA kernel ([`available`]). That kernel computes every output of a product as an FMA
//! chain over the rank from zero, in rank order (one block of k: the rank is below
//! [`KC`]); the first product (β = 0) stores `chain + 0` and the other two (β = 1) add their
//! chain to F. So `F = ((XY⊗Z + 0) + XZ⊗Y) + YZ⊗X`, each term a chain here too; which
//! outputs share a vector or a tile does not matter.
//!
//! A tile is 16 x (two vectors) × 2 y × 2 z: eight output vectors, eight independent chains,
//! which keep both FMA units busy. Per rank each product loads four (XY⊗Z, XZ⊗Y) or two
//! (YZ⊗X) vectors of factors and broadcasts two or four scalars for its eight FMAs. The planes
//! are first packed rank-innermost ([`Packed`]): in their own layout a tile's 16 ranks lie
//! 16 KB apart, in one set of L1 (8 ways), and evicted one another.
//!
//! Where the CPU has AVX-512 the same code runs with 16-lane vectors and tiles of 32 x
//! (≈ 1.5 % of a training step faster on Zen 4: eight chains of 8 lanes just cover the FMA
//! latency, so any stall left a unit idle).

use super::contract::{Factors, KC};
use super::gemm::{give_spare, take_spare};
use crate::kernels::wide::{self, F32Lanes, Width};
use rayon::prelude::*;

/// x per tile: two AVX2 vectors (with AVX-512, twice that).
const TILE_X: usize = 16;
/// z-planes per task.
const TASK_PLANES: usize = 4;

/// Whether the kernel here reproduces the GEMM path for an `n³` field of rank `rank`: the CPU
/// has AVX2 and FMA (with which `matrixmultiply` runs its FMA kernel), tiles cover the lattice
/// (`n` a multiple of 16), and the rank fits one block of k.
pub fn available(n: usize, rank: usize) -> bool {
    wide::has_avx2_fma() && n > 0 && n.is_multiple_of(TILE_X) && rank <= KC
}

/// The planes packed with the rank innermost: P0 and P1 by row (y, resp. z), then by a vector's
/// `L` x, then by rank, `L` x per rank (`((row·N/L + x/L)·R + r)·L + x % L`); P2 by node
/// (`(z·N + y)·R + r`).
#[derive(Default)]
struct Packed {
    p0: Vec<f32>,
    p1: Vec<f32>,
    p2: Vec<f32>,
}

/// The dense pre-activation `F[x + N·(y + N·z)]` of `f` into `dense` (`N³` values,
/// overwritten): the planes packed in one parallel pass, then F in slabs of z-planes.
///
/// # Panics
/// If [`available`] is false for `f`, or a factor or `dense` has the wrong length.
pub fn compose(f: Factors, dense: &mut [f32]) {
    compose_with(f, dense, Width::widest().expect("compose: the FMA kernel needs AVX2 + FMA"))
}

/// [`compose`] with the vectors `width` (one the CPU has; AVX-512 runs where `N` is a multiple
/// of its 32-x tile, else AVX2): every width gives the same bits.
pub fn compose_with(f: Factors, dense: &mut [f32], width: Width) {
    let (n, nn, rank) = (f.n, f.n * f.n, f.rank);
    assert!(width.is_available(), "compose: this CPU lacks {width:?}");
    assert!(available(n, rank), "compose: the FMA kernel needs AVX2 + FMA and N a multiple of {TILE_X}");
    assert_eq!(dense.len(), nn * n, "compose: the dense field has N³ values");
    assert!(f.planes.iter().all(|p| p.len() == rank * nn) && f.lines.iter().all(|l| l.len() == rank * n));
    let wide = width == Width::Avx512 && n.is_multiple_of(2 * TILE_X);
    // The planes are packed by a vector's x: half a tile.
    let lanes = if wide { TILE_X } else { TILE_X / 2 };
    let mut packed: Packed = take_spare();
    for v in [&mut packed.p0, &mut packed.p1, &mut packed.p2] {
        v.resize(rank * nn, 0.0);
    }
    let rows = rank * n;
    let jobs = packed.p0.chunks_mut(rows).map(|out| (f.planes[0], out, true));
    let jobs = jobs.chain(packed.p1.chunks_mut(rows).map(|out| (f.planes[1], out, true)));
    let jobs = jobs.chain(packed.p2.chunks_mut(rows).map(|out| (f.planes[2], out, false)));
    let jobs: Vec<_> = jobs.enumerate().map(|(i, (plane, out, by_x))| (i % n, plane, out, by_x)).collect();
    jobs.into_par_iter().for_each(|(row, plane, out, by_x)| pack_row(plane, n, rank, row, out, by_x.then_some(lanes)));
    let planes = [packed.p0.as_slice(), packed.p1.as_slice(), packed.p2.as_slice()];
    dense.par_chunks_mut(nn * TASK_PLANES).enumerate().for_each(|(task, slab)| {
        // SAFETY: `available` checked AVX2 + FMA and the tiling; the factor lengths are
        // checked above and the packed planes have the same; `slab` is whole z-planes
        // (TASK_PLANES divides N, a multiple of 16); `wide` checked AVX-512 and N a multiple
        // of its tile, and the planes are packed for its vectors.
        let z0 = task * TASK_PLANES;
        if wide {
            use std::arch::x86_64::__m512;
            wide::with_avx512(
                #[inline(always)]
                || unsafe { compose_tiles::<__m512>(n, rank, planes, f.lines, z0, slab) },
            )
        } else {
            use std::arch::x86_64::__m256;
            wide::with_avx2(
                #[inline(always)]
                || unsafe { compose_tiles::<__m256>(n, rank, planes, f.lines, z0, slab) },
            )
        }
    });
    give_spare(packed);
}

/// Packs row `row` of `plane` (all ranks) into `out` (`rank·N` values): by `lanes` x then rank
/// when `by_x` is `Some(lanes)` (P0, P1), else by node then rank (P2, whose row is a z: nodes
/// y + N·z).
fn pack_row(plane: &[f32], n: usize, rank: usize, row: usize, out: &mut [f32], by_x: Option<usize>) {
    let nn = n * n;
    for r in 0..rank {
        let source = &plane[r * nn + row * n..][..n];
        // Runs of a constant length are moved in registers; of a run-time length, each by a
        // call to `memmove` (≈ 1.3 % of a training step).
        match by_x {
            Some(8) => pack_runs::<8>(source, rank, r, out),
            Some(16) => pack_runs::<16>(source, rank, r, out),
            Some(lanes) => panic!("pack_row: vectors of 8 or 16 lanes, not {lanes}"),
            None => {
                for (y, &v) in source.iter().enumerate() {
                    out[y * rank + r] = v;
                }
            }
        }
    }
}

/// Rank `r`'s row `source` into `out` by runs of `L` x (see [`pack_row`]).
#[inline(always)]
fn pack_runs<const L: usize>(source: &[f32], rank: usize, r: usize, out: &mut [f32]) {
    for (b, run) in source.chunks_exact(L).enumerate() {
        let run: &[f32; L] = run.try_into().expect("L values");
        out[(b * rank + r) * L..][..L].copy_from_slice(run);
    }
}

/// [`compose`] for the z-planes from `z0` that `slab` holds, from the packed `planes`, in
/// vectors `V`: tiles of 2 vectors of x × 2 y × 2 z.
///
/// # Safety
/// The CPU must have `V`'s features (AVX2 and FMA for `__m256`, AVX-512F and VL as well for
/// `__m512`: call it inside `wide::with_avx2` or `wide::with_avx512`); `N` a multiple of
/// 2·`V::LANES`; every packed plane `rank·N²` values, packed by `V::LANES` x, every line
/// `rank·N`; `slab` an even number of whole z-planes from `z0`.
#[inline(always)]
unsafe fn compose_tiles<V: F32Lanes>(
    n: usize,
    rank: usize,
    planes: [&[f32]; 3],
    lines: [&[f32]; 3],
    z0: usize,
    slab: &mut [f32],
) {
    let nn = n * n;
    let [p0, p1, p2] = planes.map(|p| p.as_ptr());
    let [l0, l1, l2] = lines.map(|l| l.as_ptr());
    let out = slab.as_mut_ptr();
    let zero = V::zero();
    let depth = slab.len() / nn;
    let lanes = V::LANES;
    // Output vector v of a tile: x + lanes·(v % 2), y + (v / 2) % 2, z + v / 4.
    let at = |y: usize, dz: usize, x: usize, v: usize| (dz + v / 4) * nn + (y + (v / 2) % 2) * n + x + lanes * (v % 2);
    for dz in (0..depth).step_by(2) {
        let z = z0 + dz;
        for y in (0..n).step_by(2) {
            for x in (0..n).step_by(2 * lanes) {
                let tile = Tile { n, rank, x };
                // XY⊗Z: P0[r, x, y] · L0[r, z], stored as chain + 0.
                let acc = tile.plane_rows::<V, true>(p0, y, l0, z);
                for (v, a) in acc.iter().enumerate() {
                    a.add(zero).store(out.add(at(y, dz, x, v)));
                }
                // XZ⊗Y: P1[r, x, z] · L1[r, y], added.
                add_tile(out, &tile.plane_rows::<V, false>(p1, z, l1, y), |v| at(y, dz, x, v));
                // YZ⊗X: P2[r, y, z] · L2[r, x], added.
                let mut acc = [zero; 8];
                for r in 0..rank {
                    let line = [V::load(l2.add(r * n + x)), V::load(l2.add(r * n + x + lanes))];
                    for yz in 0..4 {
                        let p = V::splat(p2.add(((z + yz / 2) * n + y + yz % 2) * rank + r));
                        for (xv, l) in line.iter().enumerate() {
                            let v = 4 * (yz / 2) + 2 * (yz % 2) + xv;
                            acc[v] = l.mul_add(p, acc[v]);
                        }
                    }
                }
                add_tile(out, &acc, |v| at(y, dz, x, v));
            }
        }
    }
}

/// A tile's place: its first x, and the field's size.
struct Tile {
    n: usize,
    rank: usize,
    x: usize,
}

impl Tile {
    /// The chains of a product whose plane is read by rows of x (XY⊗Z, XZ⊗Y): `P[r, x, row +
    /// i] · L[r, at + d]` for i, d ∈ {0, 1}, from the packed plane `plane` and the line `line`.
    /// `ROWS_ALONG_Y`: the plane's rows are the tile's y and the line runs along its z (XY⊗Z);
    /// else the other way round (XZ⊗Y). Returned in the tile's vector order.
    ///
    /// # Safety
    /// The CPU must have `V`'s features; `plane` a plane packed by `V::LANES` x and `line` a
    /// line of the field, with `row + 1` and `at + 1` inside the lattice.
    #[inline(always)]
    unsafe fn plane_rows<V: F32Lanes, const ROWS_ALONG_Y: bool>(
        &self,
        plane: *const f32,
        row: usize,
        line: *const f32,
        at: usize,
    ) -> [V; 8] {
        let lanes = V::LANES;
        let (n, rank, b) = (self.n, self.rank, self.x / lanes);
        let mut acc = [V::zero(); 8];
        for r in 0..rank {
            let l = [V::splat(line.add(r * n + at)), V::splat(line.add(r * n + at + 1))];
            for ix in 0..4 {
                let (i, xv) = (ix / 2, ix % 2);
                // The packed row's vector of `lanes` x from block b + xv, rank r.
                let p = V::load(plane.add((((row + i) * (n / lanes) + b + xv) * rank + r) * lanes));
                for (d, l) in l.iter().enumerate() {
                    let v = if ROWS_ALONG_Y { 4 * d + 2 * i + xv } else { 4 * i + 2 * d + xv };
                    acc[v] = p.mul_add(*l, acc[v]);
                }
            }
        }
        acc
    }
}

/// `out[at(v)..][..8] += acc[v]` for the tile's eight vectors.
///
/// # Safety
/// The CPU must have `V`'s features; every `at(v) + V::LANES` must lie inside `out`'s allocation.
#[inline(always)]
unsafe fn add_tile<V: F32Lanes>(out: *mut f32, acc: &[V; 8], at: impl Fn(usize) -> usize) {
    for (v, a) in acc.iter().enumerate() {
        let p = out.add(at(v));
        V::load(p).add(*a).store(p);
    }
}
