//! The VM-decomposed density field (SPEC §3 train, TensoRF's VM split, attenuation only).
//!
//! Three plane/line pairs — XY⊗Z, XZ⊗Y, YZ⊗X — with `rank` components each, planes `N×N`,
//! lines `N`. The pre-activation at a lattice node is `F[x,y,z] = Σ_r P0_r[x,y]·L0_r[z] +
//! P1_r[x,z]·L1_r[y] + P2_r[y,z]·L2_r[x]`; between nodes it is trilinear in `F` (bilinear ×
//! linear weights multiply out to trilinear ones), so a step composes `F` once
//! ([`VmField::compose`]), marches rays through it, and pulls `dL/dF` back to the factors
//! ([`VmField::contract`]): exact, and far cheaper than sampling the factors per point.
//! Nodes sit at the N cell centres of the box (first node half a cell in from the face).

use num_traits::Float;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use rayon::prelude::*;

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

    /// The dense pre-activation `F` on the node lattice, index `x + N·(y + N·z)`. Every loop
    /// runs over a contiguous row, so it vectorises; z-slabs run in parallel.
    pub fn compose(&self) -> Vec<T> {
        let (n, rank) = (self.n, self.rank);
        let mut dense = vec![T::zero(); n * n * n];
        dense.par_chunks_mut(n * n).enumerate().for_each(|(z, slab)| {
            for r in 0..rank {
                let [p0, p1, p2] = [0, 1, 2].map(|p| &self.planes[p][r * n * n..(r + 1) * n * n]);
                let [l0, l1, l2] = [0, 1, 2].map(|p| &self.lines[p][r * n..(r + 1) * n]);
                // XY ⊗ Z: slab += L0[z] · P0 (the whole XY plane).
                axpy(slab, l0[z], p0);
                for y in 0..n {
                    let row = &mut slab[n * y..n * (y + 1)];
                    // XZ ⊗ Y: row += L1[y] · P1[·, z];  YZ ⊗ X: row += P2[y, z] · L2.
                    axpy(row, l1[y], &p1[n * z..n * (z + 1)]);
                    axpy(row, p2[y + n * z], l2);
                }
            }
        });
        dense
    }

    /// The factors' gradient from the gradient `grad` of the loss with respect to `F`.
    pub fn contract(&self, grad: &[T]) -> VmField<T> {
        let (n, rank) = (self.n, self.rank);
        let mut out = VmField::zeros(n, rank);
        let [g0, g1, g2] = &mut out.planes;
        let [h0, h1, h2] = &mut out.lines;
        // One component per task: its plane and line gradients of all three pairs.
        let planes = g0.par_chunks_mut(n * n).zip(g1.par_chunks_mut(n * n)).zip(g2.par_chunks_mut(n * n));
        let lines = h0.par_chunks_mut(n).zip(h1.par_chunks_mut(n)).zip(h2.par_chunks_mut(n));
        planes.zip(lines).enumerate().for_each(|(r, (((dp0, dp1), dp2), ((dl0, dl1), dl2)))| {
            let [p0, p1, p2] = [0, 1, 2].map(|p| &self.planes[p][r * n * n..(r + 1) * n * n]);
            let [l0, l1, l2] = [0, 1, 2].map(|p| &self.lines[p][r * n..(r + 1) * n]);
            for z in 0..n {
                let slab = &grad[n * n * z..n * n * (z + 1)];
                // XY ⊗ Z: dP0 += L0[z]·dF_z, dL0[z] = <dF_z, P0>.
                axpy(dp0, l0[z], slab);
                dl0[z] = dl0[z] + dot(slab, p0);
                for y in 0..n {
                    let row = &slab[n * y..n * (y + 1)];
                    // XZ ⊗ Y: dP1[·, z] += L1[y]·row, dL1[y] += <row, P1[·, z]>.
                    axpy(&mut dp1[n * z..n * (z + 1)], l1[y], row);
                    dl1[y] = dl1[y] + dot(row, &p1[n * z..n * (z + 1)]);
                    // YZ ⊗ X: dP2[y, z] += <row, L2>, dL2 += P2[y, z]·row.
                    dp2[y + n * z] = dp2[y + n * z] + dot(row, l2);
                    axpy(dl2, p2[y + n * z], row);
                }
            }
        });
        out
    }

    /// Every factor as one flat list (planes then lines, in pair order).
    pub fn params(&self) -> impl Iterator<Item = &Vec<T>> {
        self.planes.iter().chain(self.lines.iter())
    }

    pub fn params_mut(&mut self) -> impl Iterator<Item = &mut Vec<T>> {
        self.planes.iter_mut().chain(self.lines.iter_mut())
    }
}

/// `y += a·x`.
fn axpy<T: Float>(y: &mut [T], a: T, x: &[T]) {
    for (yi, &xi) in y.iter_mut().zip(x) {
        *yi = *yi + a * xi;
    }
}

/// `Σ x·y` in a fixed order: eight interleaved partial sums (so it vectorises), then the
/// remainder, then the partials pairwise.
fn dot<T: Float>(x: &[T], y: &[T]) -> T {
    let mut acc = [T::zero(); 8];
    let (xc, yc) = (x.chunks_exact(8), y.chunks_exact(8));
    let (xr, yr) = (xc.remainder(), yc.remainder());
    for (a, b) in xc.zip(yc) {
        for k in 0..8 {
            acc[k] = acc[k] + a[k] * b[k];
        }
    }
    let tail = xr.iter().zip(yr).fold(T::zero(), |t, (&a, &b)| t + a * b);
    ((acc[0] + acc[4]) + (acc[1] + acc[5])) + ((acc[2] + acc[6]) + (acc[3] + acc[7])) + tail
}

#[cfg(test)]
mod tests {
    use super::*;

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
