//! The walk of one ray's samples through the composed field `F`, eight samples (lanes) at a
//! time: each sample's cell and trilinear weights, `σ = ReLU(F + Δ)`, the ray's optical depth
//! and, when recording, its footprints (see [`Records`]).
//!
//! Two kernels do the walk with the same IEEE operations in the same order, so their results
//! are bit-identical: a portable one (any precision), and for f32 on x86-64 CPUs with AVX2 one
//! with 8-lane vectors, chosen at run time. The walk was instruction-bound as scalar code
//! (≈ 150 instructions a sample: saturating conversions, bounds checks); the vector walk takes
//! ≈ 24 a sample, ≈ 25 more when recording. It hands each block to the recorder only after
//! the next block's loads of F are issued, and a block of a ray along x whose samples share
//! one lattice row reads its corners with one load a row instead of 32 pair loads: together
//! ≈ 4 % of a training step.

use super::{CornerWeights, RecordsMut};
use crate::train::gemm::Scalar;

/// Samples per block: one AVX2 vector of f32.
const LANES: usize = 8;

/// One ray's samples: sample `k < count` lies at the continuous node index `q0 + k·dq` of the
/// `n³` lattice whose composed field is `dense`.
pub(super) struct RayWalk<'a, T> {
    pub dense: &'a [T],
    /// Per cell, all ones where the alpha mask keeps it (a lane mask); `None`: no mask.
    pub kept: Option<&'a [u32]>,
    pub q0: [T; 3],
    pub dq: [T; 3],
    pub count: usize,
    pub n: usize,
    /// Δ in σ = ReLU(F + Δ).
    pub shift: T,
}

/// The optical depth `Σ σ_k` of the ray (without `s·δ`) and, with `RECORD`, its footprints
/// (weights unscaled) as the first `len` of `records`, returned with `len`; `records` must
/// then hold at least `count` (the open record is stored every sample, branch-free).
///
/// # Panics
/// If `dense` (or the mask) has fewer than `n³` values, or `n` is outside `[2, 1024]`.
pub(super) fn march<T: Scalar, const RECORD: bool>(walk: &RayWalk<T>, records: RecordsMut<T>) -> (T, usize) {
    let n = walk.n;
    assert!(
        (2..=1024).contains(&n) && walk.dense.len() >= n * n * n,
        "walk: a {n}³ lattice needs {} values",
        n * n * n
    );
    assert!(walk.kept.is_none_or(|k| k.len() >= n * n * n), "walk: the mask must cover the lattice");
    let room = records.cells.len().min(records.weights.len());
    assert!(!RECORD || room >= walk.count, "walk: room for {} records needed", walk.count);
    let RecordsMut { cells, weights } = records;
    #[cfg(target_arch = "x86_64")]
    if let (Some(dense), Some(weights)) = (T::as_f32(walk.dense), CornerWeights::as_f32_mut(&mut *weights)) {
        if std::arch::is_x86_feature_detected!("avx2") {
            let walk = as_f32_walk(walk, dense);
            // SAFETY: the CPU has AVX2 (checked above) and the asserts above give `avx2::march`
            // its lattice and mask sizes, and the recorder room for `count` records.
            let recorder = Recorder::new(cells, weights);
            let (depth, len) = if crate::kernels::wide::has_avx512() {
                // SAFETY: as below, and the CPU has AVX-512F and VL (checked here).
                unsafe { avx2::march_avx512vl::<RECORD>(&walk, recorder) }
            } else {
                unsafe { avx2::march::<RECORD>(&walk, recorder) }
            };
            return (T::from(depth).expect("f32"), len);
        }
    }
    portable::<T, RECORD>(walk, Recorder::new(cells, weights))
}

/// `walk` with its (already f32) values as f32.
#[cfg(target_arch = "x86_64")]
fn as_f32_walk<'a, T: Scalar>(walk: &RayWalk<'a, T>, dense: &'a [f32]) -> RayWalk<'a, f32> {
    let f = |x: T| x.to_f32().expect("f32");
    RayWalk {
        dense,
        kept: walk.kept,
        q0: walk.q0.map(f),
        dq: walk.dq.map(f),
        count: walk.count,
        n: walk.n,
        shift: f(walk.shift),
    }
}

/// The footprint being built while walking. Every run of consecutive samples in one cell is
/// a record, closed when the cell changes (branch-free: cell changes and the sign of σ are
/// unpredictable). A run without an active sample holds no weight: the next run takes its
/// slot, so a ray's records all hold weight. Whole blocks without an active sample skip the
/// per-sample work.
struct Recorder<'s, T> {
    cells: &'s mut [u32],
    weights: &'s mut [CornerWeights<T>],
    /// The open record's slot.
    slot: usize,
    /// The open record's cell; `u32::MAX` (no cell) before the first sample.
    open_cell: u32,
    open: [T; 8],
    /// Whether an active sample has added to the open record.
    held: bool,
}

impl<'s, T: Scalar> Recorder<'s, T> {
    fn new(cells: &'s mut [u32], weights: &'s mut [CornerWeights<T>]) -> Self {
        Recorder { cells, weights, slot: 0, open_cell: u32::MAX, open: [T::zero(); 8], held: false }
    }

    /// Adds one sample: its cell, whether σ > 0, its corner weights.
    #[inline(always)]
    fn add(&mut self, cell: u32, active: bool, weights: [T; 8]) {
        let same = cell == self.open_cell;
        self.slot += usize::from(!same & self.held);
        self.held = (self.held & same) | active;
        let (keep, add) = (T::from_index(usize::from(same)), T::from_index(usize::from(active)));
        self.open = std::array::from_fn(|i| self.open[i] * keep + weights[i] * add);
        self.open_cell = cell;
        (self.cells[self.slot], self.weights[self.slot]) = (cell, CornerWeights(self.open));
    }

    /// Adds a block of samples none of which is active, ending in cell `last`: if one leaves
    /// the open record's cell, the record closes and an empty one opens on `last` (the runs in
    /// between hold no weight).
    #[inline(always)]
    fn add_inactive(&mut self, leaves: bool, last: u32) {
        if leaves {
            self.slot += usize::from(self.held);
            (self.open_cell, self.open, self.held) = (last, [T::zero(); 8], false);
        }
    }

    /// Adds a block of samples: all inactive ones at once (see [`Recorder::add_inactive`]),
    /// else one by one.
    #[inline(always)]
    fn add_block(&mut self, cells: &[u32], active: &[bool], weights: &[[T; 8]]) {
        if active.iter().any(|&a| a) {
            for ((&cell, &active), &weights) in cells.iter().zip(active).zip(weights) {
                self.add(cell, active, weights);
            }
        } else if let Some(&last) = cells.last() {
            self.add_inactive(cells.iter().any(|&c| c != self.open_cell), last);
        }
    }

    /// The number of records.
    fn finish(self) -> usize {
        self.slot + usize::from(self.held)
    }
}

/// `max(x, 0)`, as the vector instruction computes it (NaN → 0).
#[inline(always)]
fn at_least_zero<T: Scalar>(x: T) -> T {
    if x > T::zero() {
        x
    } else {
        T::zero()
    }
}

/// `min(x, hi)`, as the vector instruction computes it.
#[inline(always)]
fn at_most<T: Scalar>(x: T, hi: T) -> T {
    if x < hi {
        x
    } else {
        hi
    }
}

/// The walk in plain code, lane by lane, in the vector kernel's operation order.
fn portable<T: Scalar, const RECORD: bool>(walk: &RayWalk<T>, mut recorder: Recorder<T>) -> (T, usize) {
    let n = walk.n;
    let (sy, sz) = (n, n * n);
    let (last_node, last_cell) = (T::from_index(n - 1), T::from_index(n - 2));
    let mut depth = [T::zero(); LANES];
    for k0 in (0..walk.count).step_by(LANES) {
        let valid = (walk.count - k0).min(LANES);
        let (mut cells, mut actives) = ([0u32; LANES], [false; LANES]);
        let mut corner_weights = [[T::zero(); 8]; LANES];
        for (lane, depth) in depth.iter_mut().enumerate() {
            let k = T::from_index(k0) + T::from_index(lane);
            let mut base = [0usize; 3];
            let mut frac = [T::zero(); 3];
            for a in 0..3 {
                let x = at_most(at_least_zero(walk.q0[a] + k * walk.dq[a]), last_node);
                base[a] = at_most(x, last_cell).trunc_index();
                frac[a] = x - T::from_index(base[a]);
            }
            let cell = base[0] + sy * base[1] + sz * base[2];
            let corners = [0, 1, sy, sy + 1, sz, sz + 1, sz + sy, sz + sy + 1].map(|o| walk.dense[cell + o]);
            let weights = trilinear_weights(frac);
            let s: [T; 4] = std::array::from_fn(|i| weights[i] * corners[i] + weights[i + 4] * corners[i + 4]);
            let sigma = ((s[0] + s[1]) + (s[2] + s[3])) + walk.shift;
            let live = lane < valid && walk.kept.is_none_or(|kept| kept[cell] != 0);
            let active = live && sigma > T::zero();
            *depth = *depth + if active { sigma } else { T::zero() };
            (cells[lane], actives[lane], corner_weights[lane]) = (cell as u32, active, weights);
        }
        if RECORD {
            recorder.add_block(&cells[..valid], &actives[..valid], &corner_weights[..valid]);
        }
    }
    let half: [T; 4] = std::array::from_fn(|i| depth[i] + depth[i + 4]);
    ((half[0] + half[2]) + (half[1] + half[3]), if RECORD { recorder.finish() } else { 0 })
}

/// The trilinear weights of the 8 corners at `frac`, in [`CornerWeights`] order.
#[inline(always)]
pub(crate) fn trilinear_weights<T: Scalar>([fx, fy, fz]: [T; 3]) -> [T; 8] {
    let (gx, gy, gz) = (T::one() - fx, T::one() - fy, T::one() - fz);
    let face = [gx * gy, fx * gy, gx * fy, fx * fy];
    [face[0] * gz, face[1] * gz, face[2] * gz, face[3] * gz, face[0] * fz, face[1] * fz, face[2] * fz, face[3] * fz]
}

#[cfg(target_arch = "x86_64")]
mod avx2 {
    use super::{RayWalk, Recorder, LANES};
    use crate::kernels::wide::transpose_8x8;
    use std::arch::x86_64::*;

    /// The walk with 8-lane AVX2 vectors: [`super::portable`] lane for lane.
    ///
    /// # Safety
    /// The CPU must have AVX2; `walk.dense` and `walk.kept` must hold at least `n³` values,
    /// `2 ≤ n ≤ 1024`; with `RECORD`, the recorder must have room for `count` records.
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn march<const RECORD: bool>(walk: &RayWalk<f32>, recorder: Recorder<f32>) -> (f32, usize) {
        march_body::<RECORD>(walk, recorder)
    }

    /// [`march`] compiled with AVX-512VL too: the same 8-lane code, which LLVM then gives 32
    /// vector registers and mask compares (≈ 1.5–2 % of a training step faster on Zen 4).
    ///
    /// # Safety
    /// As [`march`], and the CPU must have AVX-512F and VL.
    #[target_feature(enable = "avx2,avx512f,avx512vl")]
    pub(super) unsafe fn march_avx512vl<const RECORD: bool>(
        walk: &RayWalk<f32>,
        recorder: Recorder<f32>,
    ) -> (f32, usize) {
        march_body::<RECORD>(walk, recorder)
    }

    /// The body of [`march`] and [`march_avx512vl`].
    #[inline(always)]
    unsafe fn march_body<const RECORD: bool>(walk: &RayWalk<f32>, mut recorder: Recorder<f32>) -> (f32, usize) {
        let n = walk.n as i32;
        let (sy, sz) = (n, n * n);
        let zero = _mm256_setzero_ps();
        let one = _mm256_set1_ps(1.0);
        let lanes = _mm256_setr_ps(0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0);
        let (last_node, last_cell) = (_mm256_set1_ps((n - 1) as f32), _mm256_set1_ps((n - 2) as f32));
        let (q0, dq) = (walk.q0.map(|v| _mm256_set1_ps(v)), walk.dq.map(|v| _mm256_set1_ps(v)));
        let (count, shift) = (_mm256_set1_ps(walk.count as i32 as f32), _mm256_set1_ps(walk.shift));
        let mut depth = zero;
        // A ray mostly along x walks along lattice rows: most of its blocks read their corners
        // from one load a row ([`on_row`]).
        let along_x = walk.dq[0].abs() >= walk.dq[1].abs().max(walk.dq[2].abs());
        let descending = walk.dq[0] < 0.0;
        // The previous block, handed to the recorder once this block's loads are issued, so
        // that its serial merge overlaps them.
        let mut pending: Option<Walked> = None;
        for k0 in (0..walk.count).step_by(LANES) {
            let k = _mm256_add_ps(_mm256_set1_ps(k0 as i32 as f32), lanes);
            let mut base = [_mm256_setzero_si256(); 3];
            let mut frac = [zero; 3];
            for a in 0..3 {
                let q = _mm256_add_ps(q0[a], _mm256_mul_ps(k, dq[a]));
                let x = _mm256_min_ps(_mm256_max_ps(q, zero), last_node);
                base[a] = _mm256_cvttps_epi32(_mm256_min_ps(x, last_cell));
                frac[a] = _mm256_sub_ps(x, _mm256_cvtepi32_ps(base[a]));
            }
            let cell = _mm256_add_epi32(
                _mm256_add_epi32(base[0], _mm256_mullo_epi32(base[1], _mm256_set1_epi32(sy))),
                _mm256_mullo_epi32(base[2], _mm256_set1_epi32(sz)),
            );
            let rows = [0, sy as usize, sz as usize, (sz + sy) as usize];
            let row = if along_x { on_row(base, cell, n, descending) } else { None };
            // SAFETY: every base coordinate is in [0, n − 2], so cell + offset ≤ n³ − 1, inside
            // `dense` (the caller's contract); a row's 8 values from its first cell lie inside
            // its row (`on_row`).
            let corners = match row {
                Some((first, dx)) => unsafe { row_corners(walk.dense, first, dx, rows) },
                None => unsafe { corner_values(walk.dense, cell, rows) },
            };
            let weights = trilinear_weights(frac, one);
            let s: [__m256; 4] = std::array::from_fn(|i| {
                _mm256_add_ps(_mm256_mul_ps(weights[i], corners[i]), _mm256_mul_ps(weights[i + 4], corners[i + 4]))
            });
            let sigma = _mm256_add_ps(_mm256_add_ps(_mm256_add_ps(s[0], s[1]), _mm256_add_ps(s[2], s[3])), shift);
            let mut live = _mm256_cmp_ps::<_CMP_LT_OQ>(k, count);
            if let Some(kept) = walk.kept {
                // SAFETY: cell ≤ n³ − 1 and the mask holds n³ values (the caller's contract).
                let gate = unsafe { _mm256_i32gather_epi32::<4>(kept.as_ptr() as *const i32, cell) };
                live = _mm256_and_ps(live, _mm256_castsi256_ps(gate));
            }
            let active = _mm256_and_ps(live, _mm256_cmp_ps::<_CMP_GT_OQ>(sigma, zero));
            depth = _mm256_add_ps(depth, _mm256_and_ps(active, sigma));
            if RECORD {
                if let Some(previous) = pending {
                    hand_to_recorder(&mut recorder, walk.count, previous);
                }
                pending = Some(Walked { k0, cell, active, weights });
            }
        }
        if let Some(last) = pending {
            hand_to_recorder(&mut recorder, walk.count, last);
        }
        let half = _mm_add_ps(_mm256_castps256_ps128(depth), _mm256_extractf128_ps::<1>(depth));
        let pair = _mm_add_ps(half, _mm_movehl_ps(half, half));
        let total = _mm_add_ss(pair, _mm_shuffle_ps::<1>(pair, pair));
        (_mm_cvtss_f32(total), if RECORD { recorder.finish() } else { 0 })
    }

    /// A walked block of samples from `k0`: their cells, active lanes and corner weights.
    struct Walked {
        k0: usize,
        cell: __m256i,
        active: __m256,
        weights: [__m256; 8],
    }

    /// Hands a walked block of a ray of `count` samples to the recorder.
    #[inline(always)]
    fn hand_to_recorder(recorder: &mut Recorder<f32>, count: usize, block: Walked) {
        let Walked { k0, cell, active, weights } = block;
        let valid = (count - k0).min(LANES);
        // SAFETY (of the intrinsics): only called from `march`, which has AVX2; the store
        // writes a whole local array of the vector's size.
        unsafe {
            // Air (σ = 0) gives whole blocks without an active sample: skip the transpose.
            if _mm256_movemask_ps(active) == 0 {
                let open = _mm256_set1_epi32(recorder.open_cell as i32);
                let same = _mm256_movemask_ps(_mm256_castsi256_ps(_mm256_cmpeq_epi32(cell, open)));
                if !same & ((1 << valid) - 1) != 0 {
                    let mut cells = [0u32; LANES];
                    _mm256_storeu_si256(cells.as_mut_ptr() as *mut __m256i, cell);
                    recorder.add_inactive(true, cells[valid - 1]);
                }
            } else {
                record(recorder, valid, cell, active, weights);
            }
        }
    }

    /// `F` at the 8 corners of the 8 samples' cells (one vector per corner, [`CornerWeights`]
    /// order), read as the 4 pairs of x-neighbours at `rows` (the cell's 4 (y, z) rows): 32
    /// 8-byte loads and shuffles are faster than 8 gathers of 8 values on Zen 3.
    ///
    /// # Safety
    /// The CPU must have AVX2, and `cell + row + 1` must lie inside `dense` for every cell
    /// and row.
    #[inline(always)]
    unsafe fn corner_values(dense: &[f32], cell: __m256i, rows: [usize; 4]) -> [__m256; 8] {
        let mut cells = [0u32; LANES];
        _mm256_storeu_si256(cells.as_mut_ptr() as *mut __m256i, cell);
        let mut corners = [_mm256_setzero_ps(); 8];
        for (r, row) in rows.into_iter().enumerate() {
            let pair = |lane: usize| dense.as_ptr().add(cells[lane] as usize + row) as *const f64;
            let two = |a: usize, b: usize| _mm_castpd_ps(_mm_loadh_pd(_mm_load_sd(pair(a)), pair(b)));
            // Samples (0, 1 | 4, 5) and (2, 3 | 6, 7), so the shuffles leave them in order.
            let low = _mm256_insertf128_ps::<1>(_mm256_castps128_ps256(two(0, 1)), two(4, 5));
            let high = _mm256_insertf128_ps::<1>(_mm256_castps128_ps256(two(2, 3)), two(6, 7));
            corners[2 * r] = _mm256_shuffle_ps::<0x88>(low, high);
            corners[2 * r + 1] = _mm256_shuffle_ps::<0xDD>(low, high);
        }
        corners
    }

    /// Whether the block's 8 cells lie on one lattice row (one y and z), at most 6 cells past
    /// the lowest (lane 0, or 7 where x descends along the ray), with 8 nodes of the row from
    /// it: then the lowest cell and each sample's x offset from it.
    #[inline(always)]
    fn on_row(base: [__m256i; 3], cell: __m256i, n: i32, descending: bool) -> Option<(usize, __m256i)> {
        // SAFETY (of the intrinsics): only called from `march`, which has AVX2.
        unsafe {
            let lowest = _mm256_set1_epi32(if descending { 7 } else { 0 });
            let of_lowest = |v: __m256i| _mm256_permutevar8x32_epi32(v, lowest);
            let one_row = _mm256_and_si256(
                _mm256_cmpeq_epi32(base[1], of_lowest(base[1])),
                _mm256_cmpeq_epi32(base[2], of_lowest(base[2])),
            );
            let x0 = of_lowest(base[0]);
            let dx = _mm256_sub_epi32(base[0], x0);
            let outside = _mm256_or_si256(
                _mm256_cmpgt_epi32(dx, _mm256_set1_epi32(6)),
                _mm256_cmpgt_epi32(_mm256_setzero_si256(), dx),
            );
            let fits = _mm256_andnot_si256(outside, one_row);
            if _mm256_movemask_ps(_mm256_castsi256_ps(fits)) != 0xFF || _mm256_cvtsi256_si32(x0) + 8 > n {
                return None;
            }
            Some((_mm256_cvtsi256_si32(of_lowest(cell)) as u32 as usize, dx))
        }
    }

    /// [`corner_values`] for a block on one row ([`on_row`]): each of the cells' 4 rows read
    /// as one vector of 8 values from the lowest cell, each sample's pair picked by permutes
    /// (x-rays' blocks: ≈ a quarter of all).
    ///
    /// # Safety
    /// The CPU must have AVX2; `first + row + 7` must lie inside `dense` for every row, and
    /// every `dx` lie in [0, 6].
    #[inline(always)]
    unsafe fn row_corners(dense: &[f32], first: usize, dx: __m256i, rows: [usize; 4]) -> [__m256; 8] {
        let next = _mm256_add_epi32(dx, _mm256_set1_epi32(1));
        let mut corners = [_mm256_setzero_ps(); 8];
        for (r, row) in rows.into_iter().enumerate() {
            let values = _mm256_loadu_ps(dense.as_ptr().add(first + row));
            corners[2 * r] = _mm256_permutevar8x32_ps(values, dx);
            corners[2 * r + 1] = _mm256_permutevar8x32_ps(values, next);
        }
        corners
    }

    /// The 8 corner weights (one vector per corner, [`CornerWeights`] order) of the 8 samples.
    #[inline(always)]
    fn trilinear_weights([fx, fy, fz]: [__m256; 3], one: __m256) -> [__m256; 8] {
        // SAFETY (of the intrinsics): only called from `march`, which has AVX2.
        unsafe {
            let (gx, gy, gz) = (_mm256_sub_ps(one, fx), _mm256_sub_ps(one, fy), _mm256_sub_ps(one, fz));
            let face = [_mm256_mul_ps(gx, gy), _mm256_mul_ps(fx, gy), _mm256_mul_ps(gx, fy), _mm256_mul_ps(fx, fy)];
            std::array::from_fn(|c| _mm256_mul_ps(face[c % 4], if c < 4 { gz } else { fz }))
        }
    }

    /// Hands the block's first `valid` samples to the recorder ([`Recorder::add`] for each in
    /// turn): their weights masked to +0 where not active (as multiplying by 0 does: the
    /// weights are ≥ +0) and transposed to one row per sample, and where each starts a record
    /// (its cell is not the previous sample's, or the open record's).
    #[inline(always)]
    fn record(recorder: &mut Recorder<f32>, valid: usize, cell: __m256i, active: __m256, weights: [__m256; 8]) {
        let mut block = Block { keep: [0; LANES], cells: [0; LANES], rows: [[0.0; 8]; LANES], starts: 0, actives: 0 };
        // SAFETY (of the intrinsics): only called from `march`, which has AVX2; the stores
        // write whole local arrays of the vectors' sizes.
        unsafe {
            let previous = _mm256_permutevar8x32_epi32(cell, _mm256_setr_epi32(0, 0, 1, 2, 3, 4, 5, 6));
            let previous = _mm256_blend_epi32::<1>(previous, _mm256_set1_epi32(recorder.open_cell as i32));
            let same_cell = _mm256_cmpeq_epi32(cell, previous);
            _mm256_storeu_si256(block.keep.as_mut_ptr() as *mut __m256i, same_cell);
            block.starts = !(_mm256_movemask_ps(_mm256_castsi256_ps(same_cell)) as u32);
            block.actives = _mm256_movemask_ps(active) as u32;
            _mm256_storeu_si256(block.cells.as_mut_ptr() as *mut __m256i, cell);
            for (row, v) in block.rows.iter_mut().zip(transpose_8x8(weights.map(|w| _mm256_and_ps(w, active)))) {
                _mm256_storeu_ps(row.as_mut_ptr(), v);
            }
            add_samples(recorder, &block, valid);
        }
    }

    /// A block's samples for the recorder (see [`record`]).
    struct Block {
        /// All ones where the sample's cell is the previous sample's (or the open record's).
        keep: [u32; LANES],
        cells: [u32; LANES],
        /// Each sample's 8 weights, +0 where the sample is not active.
        rows: [[f32; 8]; LANES],
        /// A bit per sample that starts a run.
        starts: u32,
        /// A bit per active sample.
        actives: u32,
    }

    /// [`Recorder::add`] for the first `valid` samples of `block` in turn, its 0/1 factors as
    /// lane masks (as 0/1 floats they compiled to unpredictable branches). Not inlined: inside
    /// the walk's loop the open record's vector was spilled, putting a store and a load on its
    /// dependency chain.
    #[target_feature(enable = "avx2")]
    #[inline(never)]
    fn add_samples(recorder: &mut Recorder<f32>, block: &Block, valid: usize) {
        let valid = valid.min(LANES);
        if valid == 0 {
            return;
        }
        let (advances, held) = advances(block.starts, block.actives, recorder.held, valid);
        let mut slot = recorder.slot;
        // SAFETY: the loads address whole arrays of 8 f32 (or one u32); each slot is at most
        // the number of samples walked before this one, inside the recorder's room for the
        // ray's samples (the caller's contract).
        unsafe {
            let mut open = _mm256_loadu_ps(recorder.open.as_ptr());
            for lane in 0..valid {
                slot += (advances >> lane & 1) as usize;
                let keep = _mm256_broadcast_ss(&*(block.keep.as_ptr().add(lane) as *const f32));
                open = _mm256_add_ps(_mm256_and_ps(open, keep), _mm256_loadu_ps(block.rows[lane].as_ptr()));
                *recorder.cells.get_unchecked_mut(slot) = block.cells[lane];
                _mm256_store_ps(recorder.weights.get_unchecked_mut(slot).0.as_mut_ptr(), open);
            }
            (recorder.slot, recorder.held, recorder.open_cell) = (slot, held, block.cells[valid - 1]);
            _mm256_storeu_ps(recorder.open.as_mut_ptr(), open);
        }
    }

    /// Which of a block's first `valid` samples move the recorder to a new slot, as bits: those
    /// that start a run (bits `starts`) after a run that held an active sample (bits
    /// `actives`; `held`: the open run before the block did) — and whether the last sample's
    /// run holds one. A run holds one from its first active sample to its end: the bits
    /// between an active sample and the next start or active one are filled by a carry.
    #[inline(always)]
    pub(super) fn advances(starts: u32, actives: u32, held: bool, valid: usize) -> (u32, bool) {
        let lanes = (1u32 << valid) - 1;
        let (starts, actives, held) = (starts & lanes, actives & lanes, u32::from(held));
        let quiet = !(starts | actives) & lanes;
        // Each active sample's carry runs through the quiet samples after it; `held` enters
        // below sample 0.
        let filled = ((quiet + ((actives << 1) | held)) ^ quiet) & quiet;
        let holds = (actives | filled) & lanes;
        ((starts & ((holds << 1) | held)), holds >> (valid - 1) & 1 != 0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// Walks of random rays (some starting or ending outside the lattice, so clamped) through
    /// a random field, with and without a mask.
    /// A ray: first sample's node index, increment, sample count.
    type Case = ([f32; 3], [f32; 3], usize);

    fn cases(n: usize, seed: u64) -> (Vec<f32>, Vec<u32>, Vec<Case>) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let dense = (0..n * n * n).map(|_| rng.gen_range(-1.0..1.0)).collect();
        let kept = (0..n * n * n).map(|_| if rng.gen_bool(0.7) { u32::MAX } else { 0 }).collect();
        let mut rays: Vec<Case> = (0..200)
            .map(|_| {
                let q0 = std::array::from_fn(|_| rng.gen_range(-2.0..n as f32 + 1.0));
                let dq = std::array::from_fn(|_| rng.gen_range(-0.6..0.6));
                (q0, dq, rng.gen_range(0..70))
            })
            .collect();
        // Rays nearly along x, up and down it: most of their blocks lie on one lattice row
        // (the vector walk's row path), some cross rows or run past the row's end.
        rays.extend((0..200).map(|i| {
            let q0 = std::array::from_fn(|_| rng.gen_range(-1.0..n as f32));
            let dx = rng.gen_range(0.2..0.9) * if i % 2 == 0 { 1.0 } else { -1.0 };
            let dq = [dx, rng.gen_range(-0.03..0.03), rng.gen_range(-0.03..0.03)];
            (q0, dq, rng.gen_range(1..3 * n + 8))
        }));
        (dense, kept, rays)
    }

    fn walk_with<'a>(dense: &'a [f32], kept: Option<&'a [u32]>, n: usize, ray: Case) -> RayWalk<'a, f32> {
        RayWalk { dense, kept, q0: ray.0, dq: ray.1, count: ray.2, n, shift: 0.1 }
    }

    /// The walk's depth and records, recorded by `kernel`.
    fn recorded(
        walk: &RayWalk<f32>,
        kernel: impl FnOnce(&RayWalk<f32>, Recorder<f32>) -> (f32, usize),
    ) -> (f32, Vec<(u32, [f32; 8])>) {
        let mut cells = vec![u32::MAX; walk.count];
        let mut weights = vec![CornerWeights([0.0; 8]); walk.count];
        let (depth, len) = kernel(walk, Recorder::new(&mut cells, &mut weights));
        (depth, cells[..len].iter().zip(&weights).map(|(&c, w)| (c, w.0)).collect())
    }

    #[test]
    fn merged_footprints_hold_every_active_samples_weights() {
        // The footprints' weights summed per cell equal the active samples' trilinear weights
        // summed per cell, every record holds weight, and the depth is the sum of the active σ.
        let n = 5;
        let (dense, _, rays) = cases(n, 3);
        for &ray in &rays {
            let walk = walk_with(&dense, None, n, ray);
            let (depth, records) = recorded(&walk, portable::<f32, true>);
            let (mut expected_depth, mut expected) = (0.0f64, std::collections::BTreeMap::new());
            let mut from_records = std::collections::BTreeMap::new();
            for k in 0..ray.2 {
                let one = RayWalk {
                    q0: std::array::from_fn(|a| ray.0[a] + k as f32 * ray.1[a]),
                    count: 1,
                    ..walk_with(&dense, None, n, ray)
                };
                let (sigma, sample) = recorded(&one, portable::<f32, true>);
                expected_depth += f64::from(sigma);
                for (cell, weights) in sample {
                    let w: &mut [f64; 8] = expected.entry(cell).or_insert([0.0; 8]);
                    w.iter_mut().zip(weights).for_each(|(a, b)| *a += f64::from(b));
                }
            }
            for (cell, weights) in records {
                assert!(weights.iter().any(|&w| w != 0.0), "an empty record");
                let w: &mut [f64; 8] = from_records.entry(cell).or_insert([0.0; 8]);
                w.iter_mut().zip(weights).for_each(|(a, b)| *a += f64::from(b));
            }
            assert!((f64::from(depth) - expected_depth).abs() < 1e-4 * expected_depth.max(1.0));
            assert_eq!(expected.keys().collect::<Vec<_>>(), from_records.keys().collect::<Vec<_>>());
            for (a, b) in expected.values().zip(from_records.values()) {
                assert!(a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-5), "{a:?} vs {b:?}");
            }
        }
    }

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn a_blocks_advances_are_the_recorders_one_by_one() {
        // Every block of up to 8 samples: which start a run and which are active, after an
        // open run that held an active sample or not.
        for valid in 1..=LANES {
            for (starts, actives) in (0..1u32 << valid).flat_map(|s| (0..1u32 << valid).map(move |a| (s, a))) {
                for held_before in [false, true] {
                    let (mut held, mut expected) = (held_before, 0);
                    for lane in 0..valid {
                        let start = starts >> lane & 1 != 0;
                        expected |= u32::from(start & held) << lane;
                        held = (held & !start) | (actives >> lane & 1 != 0);
                    }
                    let high = !0u32 << valid;
                    let found = avx2::advances(starts | high, actives | high, held_before, valid);
                    assert_eq!(found, (expected, held), "starts {starts:b}, actives {actives:b}, held {held_before}");
                }
            }
        }
    }

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn the_vector_walks_are_bit_identical_to_the_portable_one() {
        if !std::arch::is_x86_feature_detected!("avx2") {
            eprintln!("no AVX2 on this CPU: nothing to compare");
            return;
        }
        let bits = |(depth, records): (f32, Vec<(u32, [f32; 8])>)| {
            (depth.to_bits(), records.into_iter().map(|(c, w)| (c, w.map(f32::to_bits))).collect::<Vec<_>>())
        };
        for (n, seed) in [(2, 1), (7, 2), (64, 3)] {
            let (dense, kept, rays) = cases(n, seed);
            for mask in [None, Some(kept.as_slice())] {
                for &ray in &rays {
                    let walk = walk_with(&dense, mask, n, ray);
                    let expected = bits(recorded(&walk, portable::<f32, true>));
                    // SAFETY (of each kernel): AVX2 checked above; the field and mask hold n³
                    // values, and `recorded` gives room for `count` records.
                    let avx2 = recorded(&walk, |w, r| unsafe { avx2::march::<true>(w, r) });
                    assert_eq!(bits(avx2), expected, "n {n}, ray {ray:?}");
                    let depth_only = recorded(&walk, |w, r| unsafe { avx2::march::<false>(w, r) }).0;
                    assert_eq!(depth_only.to_bits(), expected.0);
                    if crate::kernels::wide::has_avx512() {
                        // SAFETY: as above, and the CPU has AVX-512F and VL (checked here).
                        let avx512 = recorded(&walk, |w, r| unsafe { avx2::march_avx512vl::<true>(w, r) });
                        assert_eq!(bits(avx512), expected, "n {n}, ray {ray:?}");
                    }
                }
            }
        }
    }
}
