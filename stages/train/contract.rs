//! The f32 contraction of `dL/dF` onto the VM factors as direct FMA chains: the six products
//! of [`super::field::VmField::contract`] without `matrixmultiply`, which spent half the
//! contraction copying `dL/dF` into its packed layout, six times a step.
//!
//! Bit-identical to the GEMM path, and used only where that path runs `matrixmultiply`'s
//! AVX2 + FMA kernel ([`available`]). That kernel computes every output as an FMA chain over
//! k from zero, in k order, restarting every [`KC`] values of k; the first block is stored as
//! `chain + 0` (its `α·AB + β·C` with `β = 0`, which turns an underflowed `-0` into `+0`)
//! and each later block is added to it. The chains here are the same; `f32::mul_add` is that
//! fused multiply-add (one rounding), and which outputs share a vector does not matter.
//!
//! Two kernels cover the six products, vectorised across outputs so that `dL/dF` is read
//! where it lies: [`along_x`] when the outputs run along F's x axis (the k axis strided),
//! [`along_rank`] when k runs along x (the outputs are then ranks, of a factor transposed
//! beforehand: a factor is a quarter of `dL/dF`'s size). With AVX-512, dP0 has a kernel of its
//! own (`avx512::plane_xy`): its 16 ranks' chains fit the registers, so `dL/dF` is read once.

use super::gemm::{give_spare, take_spare};
use crate::kernels::wide::{self, Width};
use rayon::prelude::*;

/// `matrixmultiply`'s block of k for f32 (`S_KC`).
pub const KC: usize = 256;

/// Outputs along x per vectorised run (two AVX2 vectors).
const RUN: usize = 16;
/// Ranks per [`along_rank`] chain vector (two AVX2 vectors, or one AVX-512 vector); factors
/// are transposed with their rank padded to a multiple of it.
const RANKS: usize = 16;
/// x per dL2 task: one AVX-512 run, or two AVX2 runs.
const LINE_TASK_X: usize = 2 * RUN;
/// Outputs per [`along_rank`] chain vector with AVX-512: 8 vectors of 16 ranks in flight.
const WIDE_OUTPUTS: usize = 8;
/// Outputs of one task along its split axis: uv entries of a plane, or z-planes.
const TASK_NODES: usize = 256;
const TASK_PLANES: usize = 4;

/// Whether the kernels here reproduce the GEMM path: the CPU has AVX2 and FMA, with which
/// `matrixmultiply` runs its FMA kernel.
pub fn available() -> bool {
    wide::has_avx2_fma()
}

/// One VM field's f32 factors as [`super::field::VmField`] lays them out: `planes[p]` at
/// `r·N² + u + N·v`, `lines[p]` at `r·N + w`.
#[derive(Clone, Copy)]
pub struct Factors<'a> {
    pub n: usize,
    pub rank: usize,
    pub planes: [&'a [f32]; 3],
    pub lines: [&'a [f32]; 3],
}

/// The factors' gradients, laid out as [`Factors`].
pub struct Gradients<'a> {
    pub planes: [&'a mut [f32]; 3],
    pub lines: [&'a mut [f32]; 3],
}

/// The factors [`along_rank`] reads, transposed to node-major with the rank padded to a
/// multiple of [`RANKS`]: `t[node·stride + r]`; and scratch.
#[derive(Default)]
struct Transposed {
    /// P0 by xy, P1 by x + N·z, L0 by z, L2 by x.
    p0: Vec<f32>,
    p1: Vec<f32>,
    l0: Vec<f32>,
    l2: Vec<f32>,
    /// XZ⊗Y's line gradient per z before the sum over z, `r·N² + z·N + y`.
    partial: Vec<f32>,
}

/// A task's piece of every rank's row of one output.
type Rows<'a> = Vec<&'a mut [f32]>;

/// The contraction's tasks. Four of the six products sum within a z-plane of `dL/dF`, so a
/// slab task runs all four on its planes while they are in cache; the other two sum across
/// planes and run on their own.
enum Task<'a> {
    /// dP0[r, xy] = Σ_z dF[xy, z]·L0[r, z], for a run of xy from `start`.
    PlaneXY { start: usize, dp0: Rows<'a> },
    /// dL2[r, x] = Σ_yz P2[r, yz]·dF[x, yz], for a run of x from `start`.
    LineX { start: usize, dl2: Rows<'a> },
    /// The planes from `z0`: dP1[r, x, z] = Σ_y dF[x, y, z]·L1[r, y]; the per-z terms of
    /// dL1[r, y] = Σ_z Σ_x P1[r, x, z]·dF[x, y, z]; dP2[r, yz] = Σ_x dF[x, yz]·L2[r, x];
    /// dL0[r, z] = Σ_xy P0[r, xy]·dF[xy, z].
    Slab { z0: usize, dp1: Rows<'a>, partial: Rows<'a>, dp2: Rows<'a>, dl0: Rows<'a> },
}

/// The factors transposed for [`contract_prepared`], made ahead by [`prepare`]: they depend
/// on the factors alone, so a training step makes them while it traces the batch, where they
/// fill the workers' idle moments instead of taking a parallel pass of their own.
pub struct Prepared {
    transposed: Transposed,
    /// The factors they were made from (where each starts, and the shape).
    from: ([usize; 6], usize, usize),
}

/// Where `f`'s factors lie, and its shape: what [`Prepared`] was made from.
fn identity(f: &Factors) -> ([usize; 6], usize, usize) {
    let [p0, p1, p2] = f.planes.map(|p| p.as_ptr() as usize);
    let [l0, l1, l2] = f.lines.map(|l| l.as_ptr() as usize);
    ([p0, p1, p2, l0, l1, l2], f.n, f.rank)
}

/// `f`'s factors transposed for [`contract_prepared`] (in parallel).
pub fn prepare(f: Factors) -> Prepared {
    let mut transposed: Transposed = take_spare();
    transpose_all(f, &mut transposed);
    Prepared { transposed, from: identity(&f) }
}

/// The factors' gradient from `grad` (`dL/dF`, `N³` values) into `out`, overwritten, with the
/// CPU's widest vectors.
///
/// # Panics
/// If [`available`] is false.
pub fn contract(f: Factors, grad: &[f32], out: Gradients) {
    contract_prepared(f, prepare(f), grad, out)
}

/// [`contract`] with `f` already [`prepare`]d (the factors unchanged since).
///
/// # Panics
/// If [`available`] is false, or `prepared` was made from other factors.
pub fn contract_prepared(f: Factors, prepared: Prepared, grad: &[f32], out: Gradients) {
    let width = Width::widest().expect("contract: the FMA kernels need AVX2 + FMA");
    contract_with(f, prepared, grad, out, width)
}

/// [`contract_prepared`] with the vectors `width` (one the CPU has): every width gives the
/// same bits.
pub fn contract_with(f: Factors, prepared: Prepared, grad: &[f32], out: Gradients, width: Width) {
    assert!(width.is_available(), "contract: this CPU lacks {width:?}");
    assert!(prepared.from == identity(&f), "contract: prepared from other factors");
    let (n, nn, rank) = (f.n, f.n * f.n, f.rank);
    assert_eq!(grad.len(), nn * n, "contract: dL/dF has N³ values");
    let mut t = prepared.transposed;
    let Gradients { planes: [dp0, dp1, dp2], lines: [dl0, dl1, dl2] } = out;
    let mut partial = std::mem::take(&mut t.partial);
    partial.resize(rank * nn, 0.0);
    let slab_nodes = TASK_PLANES * n;
    // The largest tasks first and the smallest last, so that the workers' last tasks, and the
    // wait for the slower one, are short: dL2's two (1/12 of the work each), the slabs' 16,
    // then dP0's 16 (1/96 each).
    let line_x = pieces(dl2, n, LINE_TASK_X).into_iter().enumerate();
    let mut tasks: Vec<Task> = line_x.map(|(i, dl2)| Task::LineX { start: i * LINE_TASK_X, dl2 }).collect();
    let slabs = pieces(dp1, nn, slab_nodes)
        .into_iter()
        .zip(pieces(&mut partial, nn, slab_nodes))
        .zip(pieces(dp2, nn, slab_nodes))
        .zip(pieces(dl0, n, TASK_PLANES));
    tasks.extend(slabs.enumerate().map(|(i, (((dp1, partial), dp2), dl0))| Task::Slab {
        z0: i * TASK_PLANES,
        dp1,
        partial,
        dp2,
        dl0,
    }));
    let plane_xy = pieces(dp0, nn, TASK_NODES).into_iter().enumerate();
    tasks.extend(plane_xy.map(|(i, dp0)| Task::PlaneXY { start: i * TASK_NODES, dp0 }));
    let kernels = Kernels { f, grad, t: &t, width };
    tasks.into_par_iter().for_each(|task| kernels.run(task));
    // dL1 sums the per-z terms in z order, as the GEMM path does.
    for (line, terms) in dl1.chunks_exact_mut(n).zip(partial.chunks_exact(nn)) {
        let mut planes = terms.chunks_exact(n);
        line.copy_from_slice(planes.next().expect("n ≥ 1"));
        for plane in planes {
            for (d, &p) in line.iter_mut().zip(plane) {
                *d += p;
            }
        }
    }
    t.partial = partial;
    give_spare(t);
}

/// Every rank's row of `out` (`row_len` values each) cut into runs of `per_task`: per task,
/// its run of each row. (Each list is allocated once at its full length: grown push by push,
/// the step's ≈ 300 reallocations here cost ≈ 2 % of a training step.)
fn pieces(out: &mut [f32], row_len: usize, per_task: usize) -> Vec<Rows<'_>> {
    let rows = out.len() / row_len;
    let mut tasks: Vec<Rows> = Vec::with_capacity(row_len.div_ceil(per_task));
    for row in out.chunks_exact_mut(row_len) {
        for (i, piece) in row.chunks_mut(per_task).enumerate() {
            if i == tasks.len() {
                tasks.push(Vec::with_capacity(rows));
            }
            tasks[i].push(piece);
        }
    }
    tasks
}

/// Fills `t` from `f`, in parallel (two of them are as large as a plane).
fn transpose_all(f: Factors, t: &mut Transposed) {
    let (n, nn, rank) = (f.n, f.n * f.n, f.rank);
    let stride = rank.next_multiple_of(RANKS);
    let jobs: [(&[f32], usize, &mut Vec<f32>); 4] = [
        (f.planes[0], nn, &mut t.p0),
        (f.planes[1], nn, &mut t.p1),
        (f.lines[0], n, &mut t.l0),
        (f.lines[2], n, &mut t.l2),
    ];
    let mut pieces = Vec::new();
    for (source, nodes, target) in jobs {
        // Every entry but the padding is overwritten below; the padding's lanes are computed
        // and dropped, so whatever they hold is harmless.
        if target.len() != nodes * stride {
            target.clear();
            target.resize(nodes * stride, 0.0);
        }
        for (i, piece) in target.chunks_mut(TASK_NODES * stride).enumerate() {
            pieces.push((source, nodes, i * TASK_NODES, piece));
        }
    }
    pieces.into_par_iter().for_each(|(source, nodes, first, piece)| {
        wide::with_avx2(
            #[inline(always)]
            || transpose_piece(source, nodes, first, piece, rank),
        )
    });
}

/// One piece of [`transpose_all`]: `piece` holds the nodes from `first` of `source`'s rows
/// (`nodes` values each, one per rank), `piece.len() / nodes` of them. With AVX, 8 nodes × 8
/// ranks at a time (an 8 × 8 transpose in registers); the rest rank by rank.
#[inline(always)]
fn transpose_piece(source: &[f32], nodes: usize, first: usize, piece: &mut [f32], rank: usize) {
    let stride = rank.next_multiple_of(RANKS);
    let count = piece.len() / stride;
    let mut done = 0;
    #[cfg(target_arch = "x86_64")]
    if wide::has_avx2_fma() && rank.is_multiple_of(8) {
        use std::arch::x86_64::*;
        // Eight ranks' rows at a time along the whole piece: the rows lie a plane apart, in
        // one set of L1, so sixteen of them at once evicted one another before each line's
        // second block of 8 nodes was read.
        let whole = count - count % 8;
        for r0 in (0..rank).step_by(8) {
            for block in (0..whole).step_by(8) {
                // SAFETY: the CPU has AVX (checked above).
                let mut rows = [unsafe { _mm256_setzero_ps() }; 8];
                for (i, row) in rows.iter_mut().enumerate() {
                    let values = &source[(r0 + i) * nodes + first + block..][..8];
                    // SAFETY: as above; `values` holds 8 floats.
                    *row = unsafe { _mm256_loadu_ps(values.as_ptr()) };
                }
                // SAFETY: as above.
                let columns = unsafe { wide::transpose_8x8(rows) };
                for (j, column) in columns.into_iter().enumerate() {
                    let entry = &mut piece[(block + j) * stride + r0..][..8];
                    // SAFETY: as above; `entry` holds 8 floats.
                    unsafe { _mm256_storeu_ps(entry.as_mut_ptr(), column) };
                }
            }
        }
        done = whole;
    }
    // Rank by rank: each reads a contiguous run (the ranks are a plane apart).
    for (r, row) in source.chunks_exact(nodes).enumerate() {
        for (entry, &v) in piece[done * stride..].chunks_exact_mut(stride).zip(&row[first + done..]) {
            entry[r] = v;
        }
    }
}

/// What every task reads, and the vectors it runs with.
struct Kernels<'a> {
    f: Factors<'a>,
    grad: &'a [f32],
    t: &'a Transposed,
    width: Width,
}

impl Kernels<'_> {
    /// `task` with AVX2 (runs of [`RUN`] x, 4 outputs a chain vector), or with AVX-512 (runs
    /// of 32 x and [`WIDE_OUTPUTS`] outputs: twice the chains in flight, which hides the FMA
    /// latency that bounded the AVX2 loops; ≈ 14 % faster on Zen 4).
    fn run(&self, task: Task) {
        match self.width {
            Width::Avx512 => wide::with_avx512(
                #[inline(always)]
                || self.run_inline::<{ 2 * RUN }, WIDE_OUTPUTS>(task),
            ),
            Width::Avx2 => wide::with_avx2(
                #[inline(always)]
                || self.run_inline::<RUN, 4>(task),
            ),
        }
    }

    /// `task` with runs of `W` x ([`Kernels::along_x_runs`]) and `J` outputs per chain vector
    /// ([`along_rank`]).
    #[inline(always)]
    fn run_inline<const W: usize, const J: usize>(&self, task: Task) {
        let (n, nn, rank) = (self.f.n, self.f.n * self.f.n, self.f.rank);
        let padded = rank.next_multiple_of(RANKS);
        let t = self.t;
        match task {
            Task::PlaneXY { start, mut dp0 } if J == WIDE_OUTPUTS && dp0[0].len().is_multiple_of(16) => {
                // With AVX-512, all 16 ranks' chains fit the registers: each vector of dF is
                // read once, where it lies (≈ 0.7 % of a training step faster than the copy).
                // A run of another length (N² not a multiple of 16) takes the copy below.
                // SAFETY: J = WIDE_OUTPUTS only inside `with_avx512` (`Kernels::run`).
                unsafe { avx512::plane_xy(self.grad, n, &t.l0, rank, start, &mut dp0) };
            }
            Task::PlaneXY { start, mut dp0 } => {
                // With AVX2, four ranks at a time, so the run is read four times. The chains
                // run across planes, `N²` floats apart: a power of two, at which
                // the run's lines would share a set of L1 and of L2 and evict one another.
                // The task's nodes are first copied plane by plane, rows padded apart.
                let len = dp0[0].len();
                let stride = len + RUN;
                let mut panel = Vec::with_capacity(n * stride);
                for z in 0..n {
                    panel.extend_from_slice(&self.grad[z * nn + start..][..len]);
                    panel.extend_from_slice(&[0.0; RUN]);
                }
                let k = Chain { stride, len: n, factor: self.f.lines[0], values: &panel };
                self.along_x_runs::<W>(&k, 0, 0, len, &mut dp0);
            }
            Task::LineX { start, mut dl2 } => {
                let k = Chain { stride: n, len: nn, factor: self.f.planes[2], values: self.grad };
                let len = dl2[0].len();
                self.along_x_runs::<W>(&k, start, 0, len, &mut dl2);
            }
            Task::Slab { z0, mut dp1, mut partial, mut dp2, mut dl0 } => {
                let depth = dl0[0].len();
                let mut tile = Vec::with_capacity(n);
                let xz_y = Chain { stride: n, len: n, factor: self.f.lines[1], values: self.grad };
                let yz_x = Chain { stride: padded, len: n, factor: &t.l2, values: self.grad };
                for (dz, z) in (z0..z0 + depth).enumerate() {
                    self.along_x_runs::<W>(&xz_y, z * nn, dz * n, n, &mut dp1);
                    let p1 = Chain { stride: padded, len: n, factor: &t.p1[n * z * padded..], values: self.grad };
                    self.along_rank_tiles::<J>(&p1, |y| n * y + nn * z, (dz * n, n), &mut partial, &mut tile);
                    self.along_rank_tiles::<J>(&yz_x, |y| n * (n * z + y), (dz * n, n), &mut dp2, &mut tile);
                }
                let xy_z = Chain { stride: padded, len: nn, factor: &t.p0, values: self.grad };
                // Four outputs a vector: the slab's depth (eight would compute four twice).
                self.along_rank_tiles::<TASK_PLANES>(&xy_z, |dz| nn * (z0 + dz), (0, depth), &mut dl0, &mut tile);
            }
        }
    }

    /// `rows[r][at + i] = chain_k values[source + i + k·stride] · factor[r·len + k]` for `i`
    /// in `0..count`, in runs of `W` and ranks four at a time.
    #[inline(always)]
    fn along_x_runs<const W: usize>(&self, k: &Chain, source: usize, at: usize, count: usize, rows: &mut [&mut [f32]]) {
        let mut i = 0;
        while i + W <= count {
            self.along_x_run::<W>(k, source + i, at + i, rows);
            i += W;
        }
        for i in i..count {
            self.along_x_run::<1>(k, source + i, at + i, rows);
        }
    }

    /// One run of [`Kernels::along_x_runs`], every rank, four at a time; with several blocks
    /// of k, block by block, so that a block's values serve every rank group from L1.
    #[inline(always)]
    fn along_x_run<const W: usize>(&self, k: &Chain, source: usize, at: usize, rows: &mut [&mut [f32]]) {
        let groups = self.f.rank.div_ceil(4);
        if k.len <= KC {
            for g in 0..groups {
                let mut sums = [[0f32; W]; 4];
                add_block(&mut sums, self.rank_group_chain(k, source, g, 0), true);
                store_group(rows, g, at, &sums);
            }
            return;
        }
        let mut sums = vec![[[0f32; W]; 4]; groups];
        for block in (0..k.len).step_by(KC) {
            for (g, sums) in sums.iter_mut().enumerate() {
                add_block(sums, self.rank_group_chain(k, source, g, block), block == 0);
            }
        }
        for (g, sums) in sums.iter().enumerate() {
            store_group(rows, g, at, sums);
        }
    }

    /// Rank group `g`'s chains over the block of k from `block`, for the run at `source`.
    #[inline(always)]
    fn rank_group_chain<const W: usize>(&self, k: &Chain, source: usize, g: usize, block: usize) -> [[f32; W]; 4] {
        let end = (block + KC).min(k.len);
        let factors = [0, 1, 2, 3].map(|i| {
            let r = (4 * g + i).min(self.f.rank - 1);
            &k.factor[r * k.len + block..r * k.len + end]
        });
        along_x(k.values[source + block * k.stride..].chunks(k.stride), factors)
    }

    /// `rows[r][at + j] = chain_k factor[k·stride + r] · values[source(j) + k]` for `j` in
    /// `0..count`, `J` at a time, every rank: into `tile` first, so that the rows (a plane
    /// apart) are written in runs rather than a value at a time.
    #[inline(always)]
    fn along_rank_tiles<const J: usize>(
        &self,
        k: &Chain,
        source: impl Fn(usize) -> usize,
        (at, count): (usize, usize),
        rows: &mut [&mut [f32]],
        tile: &mut Vec<[f32; RANKS]>,
    ) {
        let rank = self.f.rank;
        tile.resize(count, [0.0; RANKS]);
        for r0 in (0..rank).step_by(RANKS) {
            for j0 in (0..count).step_by(J) {
                let js: [usize; J] = std::array::from_fn(|i| (j0 + i).min(count - 1));
                let c = along_rank(js.map(&source), k, r0);
                for (&j, c) in js.iter().zip(c) {
                    tile[j] = c;
                }
            }
            let ranks = &mut rows[r0..(r0 + RANKS).min(rank)];
            tile_to_rows(&tile[..count], at, ranks);
        }
    }
}

/// `rows[r][at + j] = tile[j][r]` for every row and every `j` of `tile` (its ranks past
/// `rows.len()` are padding), by 8 × 8 transposes in registers: written per element, LLVM
/// turned the copy into gathers, ≈ 10 % of the contraction's time on one thread.
#[inline(always)]
fn tile_to_rows(tile: &[[f32; RANKS]], at: usize, rows: &mut [&mut [f32]]) {
    let mut done = 0;
    #[cfg(target_arch = "x86_64")]
    if rows.len() == RANKS && wide::has_avx2_fma() {
        use std::arch::x86_64::*;
        while done + 8 <= tile.len() {
            for r0 in (0..RANKS).step_by(8) {
                // SAFETY: the CPU has AVX (checked above); each load reads ranks r0..r0 + 8
                // of one tile entry, each store 8 floats of one row.
                unsafe {
                    let mut entries = [_mm256_setzero_ps(); 8];
                    for (i, entry) in entries.iter_mut().enumerate() {
                        *entry = _mm256_loadu_ps(tile[done + i][r0..r0 + 8].as_ptr());
                    }
                    for (i, column) in wide::transpose_8x8(entries).into_iter().enumerate() {
                        _mm256_storeu_ps(rows[r0 + i][at + done..at + done + 8].as_mut_ptr(), column);
                    }
                }
            }
            done += 8;
        }
    }
    for (r, row) in rows.iter_mut().enumerate() {
        for (out, values) in row[at + done..at + tile.len()].iter_mut().zip(&tile[done..]) {
            *out = values[r];
        }
    }
}

/// The k axis of a product: `len` values, `stride` apart in `factor` ([`along_rank`]) or in
/// `values` ([`along_x`]); `values` is `dL/dF` (or, for XY⊗Z, a copy of part of it).
struct Chain<'a> {
    stride: usize,
    len: usize,
    factor: &'a [f32],
    values: &'a [f32],
}

/// Stores rank group `g`'s sums at `at` in its rows (the last group's padding is dropped).
#[inline(always)]
fn store_group<const W: usize>(rows: &mut [&mut [f32]], g: usize, at: usize, sums: &[[f32; W]; 4]) {
    for (row, values) in rows.iter_mut().skip(4 * g).zip(sums) {
        row[at..at + W].copy_from_slice(values);
    }
}

/// Four ranks' chains over one block of k, for `W` outputs along x: `values[k][i] ·
/// factors[g][k]` (each of `values` starts with the run's `W` values at that k).
#[inline(always)]
fn along_x<'a, const W: usize>(values: impl Iterator<Item = &'a [f32]>, factors: [&[f32]; 4]) -> [[f32; W]; 4] {
    let (mut a0, mut a1, mut a2, mut a3) = ([0f32; W], [0f32; W], [0f32; W], [0f32; W]);
    let [f0, f1, f2, f3] = factors;
    for ((((g, &b0), &b1), &b2), &b3) in values.zip(f0).zip(f1).zip(f2).zip(f3) {
        let g = &g[..W];
        for i in 0..W {
            a0[i] = g[i].mul_add(b0, a0[i]);
            a1[i] = g[i].mul_add(b1, a1[i]);
            a2[i] = g[i].mul_add(b2, a2[i]);
            a3[i] = g[i].mul_add(b3, a3[i]);
        }
    }
    [a0, a1, a2, a3]
}

/// [`RANKS`] ranks' chains for `J` outputs: `factor[k·stride + r0 + r] · values[sources[j] + k]`;
/// `J` is 4, or [`WIDE_OUTPUTS`] inside `with_avx512`.
#[inline(always)]
fn along_rank<const J: usize>(sources: [usize; J], k: &Chain, r0: usize) -> [[f32; RANKS]; J] {
    #[cfg(target_arch = "x86_64")]
    if J == WIDE_OUTPUTS {
        // SAFETY: `Kernels::run` takes J = WIDE_OUTPUTS only for `Width::Avx512`, inside
        // `with_avx512`.
        return unsafe { avx512::along_rank(sources, k, r0) };
    }
    assert_eq!(J, 4, "along_rank: 4 outputs, or {WIDE_OUTPUTS} with AVX-512");
    let mut c = [[0f32; RANKS]; J];
    for block in (0..k.len).step_by(KC) {
        let end = (block + KC).min(k.len);
        let [g0, g1, g2, g3] = [0, 1, 2, 3].map(|j| &k.values[sources[j] + block..sources[j] + end]);
        let factor = k.factor[block * k.stride..end * k.stride].chunks_exact(k.stride);
        let (mut a0, mut a1, mut a2, mut a3) = ([0f32; RANKS], [0f32; RANKS], [0f32; RANKS], [0f32; RANKS]);
        for ((((f, &d0), &d1), &d2), &d3) in factor.zip(g0).zip(g1).zip(g2).zip(g3) {
            let f = &f[r0..r0 + RANKS];
            for i in 0..RANKS {
                a0[i] = f[i].mul_add(d0, a0[i]);
                a1[i] = f[i].mul_add(d1, a1[i]);
                a2[i] = f[i].mul_add(d2, a2[i]);
                a3[i] = f[i].mul_add(d3, a3[i]);
            }
        }
        let mut sums = [[0f32; RANKS]; J];
        sums.copy_from_slice(&[a0, a1, a2, a3]);
        add_block(&mut c, sums, block == 0);
    }
    c
}

/// [`along_rank`] in explicit AVX-512 code: written portably, LLVM vectorised eight outputs'
/// chains across the outputs, with gathers (over 20× slower). The same FMA chains, lane by lane.
#[cfg(target_arch = "x86_64")]
mod avx512 {
    use super::{Chain, KC, RANKS};
    use std::arch::x86_64::*;

    // A chain vector is one AVX-512 vector of ranks.
    const _: () = assert!(RANKS == 16);

    /// dP0[r, xy] = Σ_z dF[xy, z]·L0[r, z] for the task's run of xy from `start` (`rows[r]`
    /// its piece of rank r's row), 16 xy a vector and 16 ranks at a time: each vector of
    /// `dL/dF`, read where it lies, serves 16 chains. `l0` is L0 by z, ranks padded to
    /// [`RANKS`]. Each chain is [`super::along_x`]'s, stored as `chain + 0`. The run's length
    /// must be a multiple of 16.
    ///
    /// # Safety
    /// The CPU must have AVX-512F (call it inside `wide::with_avx512`).
    #[inline(always)]
    pub unsafe fn plane_xy(grad: &[f32], n: usize, l0: &[f32], rank: usize, start: usize, rows: &mut [&mut [f32]]) {
        const LANES: usize = 16;
        let (nn, len) = (n * n, rows[0].len());
        assert!(len.is_multiple_of(LANES), "plane_xy: runs of whole vectors");
        assert!(rows.len() == rank && rows.iter().all(|r| r.len() == len) && start + len <= nn);
        let stride = rank.next_multiple_of(RANKS);
        assert!(grad.len() >= n * nn && l0.len() >= n * stride);
        let zero = _mm512_setzero_ps();
        for at in (0..len).step_by(LANES) {
            for r0 in (0..rank).step_by(RANKS) {
                let mut acc = [zero; RANKS];
                for z in 0..n {
                    // The asserts above keep these reads inside `grad` and `l0`.
                    let g = _mm512_loadu_ps(grad.as_ptr().add(z * nn + start + at));
                    let factor = l0.as_ptr().add(z * stride + r0);
                    for (i, a) in acc.iter_mut().enumerate() {
                        *a = _mm512_fmadd_ps(g, _mm512_set1_ps(*factor.add(i)), *a);
                    }
                }
                for (row, a) in rows.iter_mut().skip(r0).zip(acc) {
                    _mm512_storeu_ps(row[at..at + LANES].as_mut_ptr(), _mm512_add_ps(a, zero));
                }
            }
        }
    }

    /// [`super::along_rank`] for `J` outputs, one 16-lane vector of ranks each.
    ///
    /// # Safety
    /// The CPU must have AVX-512F (call it inside `wide::with_avx512`).
    #[inline(always)]
    pub unsafe fn along_rank<const J: usize>(sources: [usize; J], k: &Chain, r0: usize) -> [[f32; RANKS]; J] {
        let mut c = [_mm512_setzero_ps(); J];
        for block in (0..k.len).step_by(KC) {
            let len = (block + KC).min(k.len) - block;
            let g = sources.map(|s| s + block);
            assert!(g.iter().all(|&s| s + len <= k.values.len()), "along_rank: a chain runs past dL/dF");
            let factor = &k.factor[block * k.stride + r0..];
            assert!(len == 0 || (len - 1) * k.stride + RANKS <= factor.len(), "along_rank: short factor");
            let mut a = [_mm512_setzero_ps(); J];
            for kk in 0..len {
                // The asserts above keep these reads inside `factor` and `values`; checked
                // indexing in this loop cost a compare per FMA.
                let f = _mm512_loadu_ps(factor.as_ptr().add(kk * k.stride));
                for j in 0..J {
                    let d = _mm512_set1_ps(*k.values.get_unchecked(g[j] + kk));
                    a[j] = _mm512_fmadd_ps(f, d, a[j]);
                }
            }
            for j in 0..J {
                c[j] = if block == 0 { _mm512_add_ps(a[j], _mm512_setzero_ps()) } else { _mm512_add_ps(c[j], a[j]) };
            }
        }
        c.map(|v| std::mem::transmute::<__m512, [f32; RANKS]>(v))
    }
}

/// `c ← block + 0` for the first block of k, `c ← c + block` for the others.
#[inline(always)]
fn add_block<const W: usize, const G: usize>(c: &mut [[f32; W]; G], block: [[f32; W]; G], first: bool) {
    for (c, b) in c.iter_mut().zip(block) {
        for (c, b) in c.iter_mut().zip(b) {
            *c = if first { b + 0.0 } else { *c + b };
        }
    }
}
