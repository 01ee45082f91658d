//! The VM-decomposed density field (SPEC §3 train, TensoRF's VM split, attenuation only).
//!
//! Three plane/line pairs — XY⊗Z, XZ⊗Y, YZ⊗X — with `rank` components each, planes `N×N`,
//! lines `N`. The pre-activation at a lattice node is `F[x,y,z] = Σ_r P0_r[x,y]·L0_r[z] +
//! P1_r[x,z]·L1_r[y] + P2_r[y,z]·L2_r[x]`; between nodes it is trilinear in `F` (bilinear ×
//! linear weights multiply out to trilinear ones), so a step composes `F` once
//! ([`VmField::compose`]), marches rays through it, and pulls `dL/dF` back to the factors
//! ([`VmField::contract`]): exact, and far cheaper than sampling the factors per point.
//! Nodes sit at the N cell centres of the box (first node half a cell in from the face).

use super::contract;
use super::gemm::{gemm, gemm_all, gemm_serial, give_spare, take_spare, Layout, Product, Scalar, Shape};
use num_traits::Float;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use rayon::prelude::*;

/// z-planes of the dense field per task of the compose's second pass.
const SLAB_PLANES: usize = 4;

/// The three (plane axes, line axis) pairs, in factor order.
pub const PAIRS: [([usize; 2], usize); 3] = [([0, 1], 2), ([0, 2], 1), ([1, 2], 0)];

/// Factors of the field: `planes[p]` is `rank × N × N` (index `r·N² + u + N·v`, u along the
/// pair's first plane axis), `lines[p]` is `rank × N` (index `r·N + w`).
#[derive(Debug, Clone, PartialEq)]
pub struct VmField<T> {
    pub n: usize,
    pub rank: usize,
    pub planes: [Vec<T>; 3],
    pub lines: [Vec<T>; 3],
}

impl<T: Float + Send + Sync> VmField<T> {
    pub fn zeros(n: usize, rank: usize) -> Self {
        VmField {
            n,
            rank,
            planes: std::array::from_fn(|_| vec![T::zero(); rank * n * n]),
            lines: std::array::from_fn(|_| vec![T::zero(); rank * n]),
        }
    }

    /// TensoRF's initialisation: every factor entry `scale · N(0, 1)`, from a seeded stream.
    pub fn random(n: usize, rank: usize, scale: f64, seed: u64) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut field = Self::zeros(n, rank);
        for v in field.planes.iter_mut().chain(field.lines.iter_mut()) {
            for x in v.iter_mut() {
                let z: f64 = StandardNormal.sample(&mut rng);
                *x = T::from(scale * z).expect("finite");
            }
        }
        field
    }

    /// Number of parameters.
    pub fn len(&self) -> usize {
        3 * self.rank * self.n * (self.n + 1)
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Every factor as one flat list (planes then lines, in pair order).
    pub fn params(&self) -> impl Iterator<Item = &Vec<T>> {
        self.planes.iter().chain(self.lines.iter())
    }

    pub fn params_mut(&mut self) -> impl Iterator<Item = &mut Vec<T>> {
        self.planes.iter_mut().chain(self.lines.iter_mut())
    }

    /// Every factor component (one rank's plane, `n²` values, or line, `n`) with its
    /// factor's index in [`VmField::params`] order: planes 0–2, then lines 3–5.
    pub fn components(&self) -> impl Iterator<Item = (usize, &[T])> {
        let rank = self.rank;
        // An empty field (rank or n zero) has no components.
        self.params().enumerate().filter(|(_, v)| !v.is_empty()).flat_map(move |(f, v)| {
            let len = v.len() / rank;
            v.chunks_exact(len).map(move |c| (f, c))
        })
    }

    /// [`VmField::components`], mutable.
    pub fn components_mut(&mut self) -> impl Iterator<Item = (usize, &mut [T])> {
        let rank = self.rank;
        self.params_mut().enumerate().filter(|(_, v)| !v.is_empty()).flat_map(move |(f, v)| {
            let len = v.len() / rank;
            v.chunks_exact_mut(len).map(move |c| (f, c))
        })
    }
}

// Compose and contract are matrix products over the rank axis (GEMMs). With the dense field
// `F[x + N·y + N²·z]` and factors `P[r·N² + u + N·v]`, `L[r·N + w]`:
//   XY⊗Z: F as (xy × z)  = P0ᵀ (xy × r) · L0 (r × z)
//   XZ⊗Y: F_z as (x × y) = P1ᵀ[·, z] (x × r) · L1 (r × y), one product per z
//   YZ⊗X: F as (yz × x)  = P2ᵀ (yz × r) · L2 (r × x)
// and contract takes the transposed products of dF with the other factor of each pair.
impl<T: Scalar> VmField<T> {
    /// The dense pre-activation `F` on the node lattice, index `x + N·(y + N·z)`.
    pub fn compose(&self) -> Vec<T> {
        let mut dense = vec![T::zero(); self.n * self.n * self.n];
        self.compose_into(&mut dense);
        dense
    }

    /// [`VmField::compose`] into `dense` (`N³` values, overwritten): a training loop keeps one
    /// buffer rather than allocating a megabyte a step.
    ///
    /// XY⊗Z needs all of P0 for every z, so it runs as one product; the other two pairs then
    /// run slab by slab of z-planes in one parallel pass, adding to each slab while it is in
    /// cache. Every value is summed in the order XY⊗Z, XZ⊗Y, YZ⊗X.
    ///
    /// In f32 on a CPU with AVX2 + FMA (and N a multiple of 16) it runs
    /// [`super::compose::compose`]'s register-tiled FMA chains, bit-identical to the products
    /// here and faster.
    pub fn compose_into(&self, dense: &mut [T]) {
        let (n, r) = (self.n, self.rank);
        let nn = n * n;
        assert_eq!(dense.len(), nn * n, "compose: the dense field has N³ values");
        #[cfg(target_arch = "x86_64")]
        if super::compose::available(n, r) {
            if let (Some(factors), Some(dense)) = (self.f32_factors(), T::as_f32_mut(dense)) {
                return super::compose::compose(factors, dense);
            }
        }
        self.compose_gemm(dense);
    }

    /// [`VmField::compose_into`] by `matrixmultiply`'s products.
    fn compose_gemm(&self, dense: &mut [T]) {
        let (n, r) = (self.n, self.rank);
        let nn = n * n;
        let [p0, p1, p2] = &self.planes;
        let [l0, l1, l2] = &self.lines;
        let one = T::one();
        let lines = Layout::new(0, n, 1);
        gemm(
            Shape { count: 1, m: nn, k: r, n },
            (p0, Layout::new(0, 1, nn)),
            (l0, lines),
            T::zero(),
            (dense, Layout::new(0, 1, nn)),
        );
        dense.par_chunks_mut(nn * SLAB_PLANES).enumerate().for_each(|(slab, planes)| {
            let (z0, depth) = (slab * SLAB_PLANES, planes.len() / nn);
            // XZ⊗Y, per z: F_z (x × y) += P1[·, z]ᵀ (x × r) · L1 (r × y).
            let per_z = Shape { count: depth, m: n, k: r, n };
            let a1 = Layout::new(z0 * n, 1, nn).batched(n);
            gemm_serial(per_z, (p1, a1), (l1, lines), one, (planes, Layout::new(0, 1, n).batched(nn)));
            // YZ⊗X: F (yz × x) += P2ᵀ (yz × r) · L2 (r × x), the slab's rows.
            let rows = Shape { count: 1, m: n * depth, k: r, n };
            gemm_serial(rows, (p2, Layout::new(z0 * n, 1, nn)), (l2, lines), one, (planes, Layout::new(0, n, 1)));
        });
    }

    /// The factors' gradient from the gradient `grad` of the loss with respect to `F`.
    pub fn contract(&self, grad: &[T]) -> VmField<T> {
        let mut out = VmField::zeros(self.n, self.rank);
        self.contract_into(grad, &mut out);
        out
    }

    /// [`VmField::contract`] into `out` (same shape, overwritten): a training loop keeps one.
    ///
    /// In f32 on a CPU with AVX2 + FMA it runs [`contract::contract`]'s direct FMA chains,
    /// bit-identical to the products here and faster (no packing of `grad`); otherwise (f64,
    /// or other CPUs) `matrixmultiply`'s products.
    pub fn contract_into(&self, grad: &[T], out: &mut VmField<T>) {
        self.contract_prepared(grad, out, self.prepare_contraction())
    }

    /// What [`VmField::contract_into`]'s FMA kernels first make of the factors alone
    /// ([`contract::prepare`]), to make ahead; `None` where the GEMM path runs.
    pub fn prepare_contraction(&self) -> Option<contract::Prepared> {
        contract::available().then(|| self.f32_factors().map(contract::prepare)).flatten()
    }

    /// [`VmField::contract_into`] with `prepared` made by [`VmField::prepare_contraction`]
    /// from this field, unchanged since.
    pub fn contract_prepared(&self, grad: &[T], out: &mut VmField<T>, prepared: Option<contract::Prepared>) {
        assert!(out.n == self.n && out.rank == self.rank, "contract: the output has the field's shape");
        if let (Some(prepared), Some(factors), Some(grad), Some(gradients)) =
            (prepared, self.f32_factors(), T::as_f32(grad), out.f32_factors_mut())
        {
            return contract::contract_prepared(factors, prepared, grad, gradients);
        }
        self.contract_gemm(grad, out);
    }

    /// The factors as f32, when that is their type: the way into [`contract`]'s kernels.
    fn f32_factors(&self) -> Option<contract::Factors<'_>> {
        let [p0, p1, p2] = &self.planes;
        let [l0, l1, l2] = &self.lines;
        Some(contract::Factors {
            n: self.n,
            rank: self.rank,
            planes: [T::as_f32(p0)?, T::as_f32(p1)?, T::as_f32(p2)?],
            lines: [T::as_f32(l0)?, T::as_f32(l1)?, T::as_f32(l2)?],
        })
    }

    /// [`VmField::f32_factors`], writable.
    fn f32_factors_mut(&mut self) -> Option<contract::Gradients<'_>> {
        let [p0, p1, p2] = &mut self.planes;
        let [l0, l1, l2] = &mut self.lines;
        Some(contract::Gradients {
            planes: [T::as_f32_mut(p0)?, T::as_f32_mut(p1)?, T::as_f32_mut(p2)?],
            lines: [T::as_f32_mut(l0)?, T::as_f32_mut(l1)?, T::as_f32_mut(l2)?],
        })
    }

    /// [`VmField::contract_into`] by `matrixmultiply`'s products.
    fn contract_gemm(&self, grad: &[T], out: &mut VmField<T>) {
        let (n, r) = (self.n, self.rank);
        let nn = n * n;
        let zero = T::zero();
        let planes_t = Layout::new(0, 1, nn); // P as (uv × r)
        let lines_t = Layout::new(0, 1, n); // L as (w × r)
                                            // dP (uv × r) = dF (uv × w) · Lᵀ (w × r);  dL (r × w) = P (r × uv) · dF (uv × w).
        let dense_xy_z = Layout::new(0, 1, nn);
        let dense_yz_x = Layout::new(0, n, 1);
        let plane_shape = Shape { count: 1, m: nn, k: n, n: r };
        let line_shape = Shape { count: 1, m: r, k: nn, n };
        let [dp0, dp1, dp2] = &mut out.planes;
        let [dl0, dl1, dl2] = &mut out.lines;
        // XZ⊗Y, per z: dP1[·, z] (x × r) = dF_z (x × y) · L1ᵀ (y × r), and dL1 (r × y) sums
        // P1[·, z] (r × x) · dF_z (x × y) over z — per-z products first, then the sum in z order.
        let dense_z = Layout::new(0, 1, n).batched(nn);
        let per_z = |m, k, n| Shape { count: self.n, m, k, n };
        // Scratch kept between steps (a quarter megabyte).
        let mut partial: Vec<T> = take_spare();
        partial.resize(n * r * n, zero);
        let line = Layout::new(0, n, 1);
        let p_rows = Layout::new(0, nn, 1);
        // All six products in one parallel pass (each writes its own factor).
        gemm_all(vec![
            Product {
                shape: plane_shape,
                a: (grad, dense_xy_z),
                b: (&self.lines[0], lines_t),
                beta: zero,
                c: (dp0, planes_t),
            },
            Product {
                shape: line_shape,
                a: (&self.planes[0], p_rows),
                b: (grad, dense_xy_z),
                beta: zero,
                c: (dl0, line),
            },
            Product {
                shape: plane_shape,
                a: (grad, dense_yz_x),
                b: (&self.lines[2], lines_t),
                beta: zero,
                c: (dp2, planes_t),
            },
            Product {
                shape: line_shape,
                a: (&self.planes[2], p_rows),
                b: (grad, dense_yz_x),
                beta: zero,
                c: (dl2, line),
            },
            Product {
                shape: per_z(n, n, r),
                a: (grad, dense_z),
                b: (&self.lines[1], lines_t),
                beta: zero,
                c: (dp1, Layout::new(0, 1, nn).batched(n)),
            },
            Product {
                shape: per_z(r, n, n),
                a: (&self.planes[1], p_rows.batched(n)),
                b: (grad, dense_z),
                beta: zero,
                c: (&mut partial, Layout::new(0, n, 1).batched(r * n)),
            },
        ]);
        let mut slabs = partial.chunks_exact(r * n);
        dl1.copy_from_slice(slabs.next().expect("n ≥ 1"));
        for slab in slabs {
            for (d, &p) in dl1.iter_mut().zip(slab) {
                *d = *d + p;
            }
        }
        give_spare(partial);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernels::wide::Width;

    #[test]
    fn compose_matches_the_definition() {
        let f: VmField<f64> = VmField::random(5, 3, 0.5, 7);
        let dense = f.compose();
        let n = 5;
        for (x, y, z) in [(0, 0, 0), (4, 1, 3), (2, 3, 4)] {
            let mut expected = 0.0;
            for r in 0..3 {
                expected += f.planes[0][r * 25 + x + n * y] * f.lines[0][r * n + z];
                expected += f.planes[1][r * 25 + x + n * z] * f.lines[1][r * n + y];
                expected += f.planes[2][r * 25 + y + n * z] * f.lines[2][r * n + x];
            }
            assert!((dense[x + n * (y + n * z)] - expected).abs() < 1e-12);
        }
    }

    /// Whether the FMA path's `x` is the GEMM path's `y` bit for bit. `matrixmultiply` picks
    /// its AVX-512 kernel where the CPU has one, and that kernel keeps the sign of a sum that
    /// underflows to zero where its AVX2 + FMA kernel, which the FMA path mirrors, stores +0:
    /// there ±0 count as one.
    fn same_as_gemm(x: f32, y: f32) -> bool {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx512f") && x == 0.0 && y == 0.0 {
            return true;
        }
        x.to_bits() == y.to_bits()
    }

    /// [`same_as_gemm`] for every value of two fields (or factor lists) in order.
    fn all_same_as_gemm<'a>(a: impl IntoIterator<Item = &'a f32>, b: impl IntoIterator<Item = &'a f32>) -> bool {
        a.into_iter().zip(b).all(|(x, y)| same_as_gemm(*x, *y))
    }

    #[test]
    fn the_fma_contraction_matches_the_gemm_path_bit_for_bit() {
        if !contract::available() {
            eprintln!("skipped: this CPU lacks AVX2 + FMA, so the GEMM path is the only one");
            return;
        }
        // The training size, odd sizes with partial runs and rank groups, chains over the
        // plane longer than one block of k (N² > 256), and values that underflow.
        for (n, rank, seed) in [(64, 16, 1), (5, 3, 2), (20, 17, 3), (9, 4, 4), (9, 8, 5)] {
            let f: VmField<f32> = VmField::random(n, rank, 0.5, seed);
            let mut grad: Vec<f32> = VmField::<f32>::random(n, n, 1.0, seed + 10).planes[0].clone();
            for (i, g) in grad.iter_mut().enumerate().step_by(7) {
                *g = if i % 2 == 0 { 0.0 } else { -1e-40 };
            }
            if seed == 4 {
                // Products that round to ±0: chains that end in -0, which the GEMM path
                // stores as +0.
                grad.fill(-1e-45);
            }
            let mut gemm = VmField::zeros(n, rank);
            f.contract_gemm(&grad, &mut gemm);
            // Every vector width the CPU has: each must give the GEMM path's bits.
            for width in Width::available() {
                let mut fast = VmField::zeros(n, rank);
                let factors = f.f32_factors().expect("f32");
                let prepared = contract::prepare(factors);
                contract::contract_with(factors, prepared, &grad, fast.f32_factors_mut().expect("f32"), width);
                let same = all_same_as_gemm(fast.params().flatten(), gemm.params().flatten());
                assert!(same, "N = {n}, rank = {rank}, {width:?}");
            }
            let mut fast = VmField::zeros(n, rank);
            f.contract_into(&grad, &mut fast);
            let same = all_same_as_gemm(fast.params().flatten(), gemm.params().flatten());
            assert!(same, "N = {n}, rank = {rank}: contract_into");
        }
    }

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn the_fma_compose_matches_the_gemm_path_bit_for_bit() {
        if !super::super::compose::available(16, 1) {
            eprintln!("skipped: this CPU lacks AVX2 + FMA, so the GEMM path is the only one");
            return;
        }
        // The training size, other ranks, and factors whose products round to ±0 (a chain
        // that ends in -0, which the GEMM path stores as +0 in the first product).
        for (n, rank, seed) in [(64, 16, 1), (16, 3, 2), (32, 17, 3), (16, 1, 4)] {
            let mut f: VmField<f32> = VmField::random(n, rank, 0.5, seed);
            for (i, v) in f.planes[1].iter_mut().enumerate().step_by(5) {
                *v = if i % 2 == 0 { 0.0 } else { -1e-40 };
            }
            if seed == 4 {
                f.planes.iter_mut().for_each(|p| p.fill(-1e-30));
                f.lines.iter_mut().for_each(|l| l.fill(1e-30));
            }
            let (mut fast, mut gemm) = (vec![0f32; n * n * n], vec![0f32; n * n * n]);
            f.compose_into(&mut fast);
            f.compose_gemm(&mut gemm);
            assert!(all_same_as_gemm(&fast, &gemm), "N = {n}, rank = {rank}");
            // Every vector width the CPU has (AVX-512 tiles need N a multiple of 32).
            for width in Width::available() {
                let mut fast = vec![0f32; n * n * n];
                super::super::compose::compose_with(f.f32_factors().expect("f32"), &mut fast, width);
                assert!(all_same_as_gemm(&fast, &gemm), "N = {n}, rank = {rank}, {width:?}");
            }
        }
    }

    #[test]
    fn a_contraction_refuses_factors_prepared_from_another_field() {
        let (a, b): (VmField<f32>, VmField<f32>) = (VmField::random(8, 4, 0.5, 1), VmField::random(8, 4, 0.5, 2));
        let Some(prepared) = a.prepare_contraction() else {
            eprintln!("skipped: this CPU lacks AVX2 + FMA, so the GEMM path is the only one");
            return;
        };
        let grad = vec![1f32; 8 * 8 * 8];
        let mut out = VmField::zeros(8, 4);
        let refused = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            b.contract_prepared(&grad, &mut out, Some(prepared));
        }));
        assert!(refused.is_err(), "b contracted with a's transposes");
        // Prepared from itself, the same field contracts as without preparing.
        let mut expected = VmField::zeros(8, 4);
        b.contract_into(&grad, &mut expected);
        b.contract_prepared(&grad, &mut out, b.prepare_contraction());
        assert!(out.params().flatten().zip(expected.params().flatten()).all(|(x, y)| x.to_bits() == y.to_bits()));
    }

    #[test]
    fn contract_is_the_adjoint_of_compose() {
        // <dF, d compose(θ)/dθ · δ> = <contract(dF), δ> for the bilinear compose: check via
        // directional derivative along a random perturbation of the factors.
        let f: VmField<f64> = VmField::random(4, 2, 0.7, 1);
        let delta: VmField<f64> = VmField::random(4, 2, 1.0, 2);
        let grad: Vec<f64> = VmField::<f64>::random(8, 1, 1.0, 3).planes[0][..64].to_vec();
        let eps = 1e-6;
        let shifted = |s: f64| {
            let mut g = f.clone();
            for (a, d) in g.params_mut().zip(delta.params()) {
                for (x, y) in a.iter_mut().zip(d) {
                    *x += s * y;
                }
            }
            g.compose().iter().zip(&grad).map(|(a, b)| a * b).sum::<f64>()
        };
        let numeric = (shifted(eps) - shifted(-eps)) / (2.0 * eps);
        let c = f.contract(&grad);
        let analytic: f64 =
            c.params().zip(delta.params()).map(|(a, d)| a.iter().zip(d).map(|(x, y)| x * y).sum::<f64>()).sum();
        assert!((numeric - analytic).abs() < 1e-7 * analytic.abs().max(1.0), "{numeric} vs {analytic}");
    }
}
