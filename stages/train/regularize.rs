//! The regularisers of the loss (SPEC §3 train; paper eq. 7–8) and their gradients.
//!
//! L1 = Σ over the three planes and three lines of the mean |value|. TV = Σ over the three
//! density planes of the mean absolute horizontal plus the mean absolute vertical finite
//! difference (`tv_norm = "l1"`, as the paper writes it), or of their squares (`"l2"`, as
//! TensoRF's own TV). At a kink (|0|) the subgradient 0 is used. [`tv_dense`] is the same
//! L1 TV on the composed 3-D field (not in the paper: an option of `[train]`, `lambda_tv3d`).

use super::field::VmField;
use crate::kernels::wide::with_avx2;
use num_traits::Float;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum TvNorm {
    L1,
    L2,
}

/// −1, 0 or 1, branch-free (selects, so loops over it vectorise).
#[inline(always)]
fn sign<T: Float>(x: T) -> T {
    let positive = if x > T::zero() { T::one() } else { T::zero() };
    let negative = if x < T::zero() { T::one() } else { T::zero() };
    positive - negative
}

/// L1 and its gradient (added to `grad` scaled by `weight`).
pub fn l1<T: Float + Send + Sync>(field: &VmField<T>, weight: T, grad: &mut VmField<T>) -> f64 {
    l1_and_tv(field, Some(weight), None, grad).0
}

/// TV of the three density planes and its gradient (added to `grad` scaled by `weight`).
pub fn tv<T: Float + Send + Sync>(field: &VmField<T>, norm: TvNorm, weight: T, grad: &mut VmField<T>) -> f64 {
    l1_and_tv(field, None, Some((norm, weight)), grad).1
}

/// L1 (when `l1` gives its weight) and the planes' TV (when `tv` gives its norm and weight),
/// their gradients added to `grad` scaled by the weights, in one parallel pass: one task per
/// factor component (a plane's `n × n`, a line's `n` values), L1 then TV on each. A training
/// step runs this once rather than one parallel pass per factor and regulariser: the workers'
/// hand-offs between passes cost more than the arithmetic. Returns the unweighted (L1, TV), 0
/// for a term not asked for; every sum runs in one fixed order whatever the thread count.
pub fn l1_and_tv<T: Float + Send + Sync>(
    field: &VmField<T>,
    l1: Option<T>,
    tv: Option<(TvNorm, T)>,
    grad: &mut VmField<T>,
) -> (f64, f64) {
    let penalties = Penalties::new(field, l1, tv);
    let components: Vec<_> = field.components().zip(grad.components_mut()).collect();
    let partials: Vec<(T, T)> = components
        .into_par_iter()
        .map(|((factor, values), (_, g))| {
            with_avx2(
                #[inline(always)]
                || penalties.add_gradient(factor, values, g),
            )
        })
        .collect();
    penalties.values(field, &partials)
}

/// L1 and the planes' TV, component by component: what [`l1_and_tv`] runs in each of its
/// tasks, for a caller that wants more done in the same task (the training loop's Adam).
#[derive(Clone, Copy)]
pub struct Penalties<T> {
    n: usize,
    rank: usize,
    l1: Option<T>,
    /// TV's norm and weight; `None` too when a plane has no neighbours (`n` < 2).
    tv: Option<(TvNorm, T)>,
    /// Differences per plane factor: the TV's mean divides by it.
    tv_count: T,
    /// Whether [`Penalties::add_gradient`] sums the penalties (their values), or only adds
    /// their gradient: a training step needs the values only when it logs them, and the sums,
    /// one long chain of additions each, cost 2–3.5 % of a step (measured in-run).
    summed: bool,
}

impl<T: Float + Send + Sync> Penalties<T> {
    /// The penalties of `field`'s shape, with L1's weight `l1` and TV's norm and weight `tv`.
    pub fn new(field: &VmField<T>, l1: Option<T>, tv: Option<(TvNorm, T)>) -> Self {
        let (n, rank) = (field.n, field.rank);
        let tv_count = T::from(rank * n * n.saturating_sub(1)).expect("count");
        Penalties { n, rank, l1, tv: tv.filter(|_| n >= 2), tv_count, summed: true }
    }

    /// These penalties without their values: [`Penalties::add_gradient`] adds the same
    /// gradient, bit for bit, and returns (0, 0).
    pub fn gradient_only(self) -> Self {
        Penalties { summed: false, ..self }
    }

    /// Adds the penalties' gradient on one component of factor `factor` (planes are 0–2),
    /// `values`, to its gradient `g`; returns its (Σ|x|, TV sum), or (0, 0) when
    /// [`Penalties::gradient_only`]. Inline it into an AVX2 copy ([`with_avx2`]), as
    /// [`l1_and_tv`] does.
    #[inline(always)]
    pub fn add_gradient(&self, factor: usize, values: &[T], g: &mut [T]) -> (T, T) {
        let l1_sum = match self.l1 {
            Some(weight) => {
                let per_entry = weight / T::from(values.len() * self.rank).expect("length");
                for (gi, &xi) in g.iter_mut().zip(values) {
                    *gi = *gi + per_entry * sign(xi);
                }
                if self.summed {
                    lane_sum(values, |v| v.abs())
                } else {
                    T::zero()
                }
            }
            None => T::zero(),
        };
        let tv_sum = match self.tv {
            Some((norm, weight)) if factor < 3 => {
                tv_component(values, g, self.n, norm, weight / self.tv_count, self.summed)
            }
            _ => T::zero(),
        };
        (l1_sum, tv_sum)
    }

    /// The unweighted (L1, TV) from every component's [`Penalties::add_gradient`] result, in
    /// `field`'s component order; 0 for a term not asked for.
    pub fn values(&self, field: &VmField<T>, partials: &[(T, T)]) -> (f64, f64) {
        if self.rank == 0 || self.n == 0 {
            return (0.0, 0.0);
        }
        let mut l1_value = 0.0;
        for (factor, per_component) in field.params().zip(partials.chunks_exact(self.rank)) {
            let sum = per_component.iter().fold(T::zero(), |a, p| a + p.0);
            l1_value += sum.to_f64().expect("finite") / factor.len() as f64;
        }
        let tv_sum = partials[..3 * self.rank].iter().fold(T::zero(), |a, p| a + p.1);
        let tv_value = if self.tv.is_some() { (tv_sum / self.tv_count).to_f64().expect("finite") } else { 0.0 };
        (if self.l1.is_some() { l1_value } else { 0.0 }, tv_value)
    }
}

/// One `n × n` component: the sum of its horizontal and vertical difference penalties, and
/// their gradient, scaled, added to `g`. (Inlined into its caller's AVX2 copy.)
///
/// Row by row, so that the plane, its gradient and the differences stay in L1: each row takes
/// its horizontal differences and the vertical ones towards the next row, then applies to its
/// gradient, value by value, what it owes them and the row above's. Every value is
/// bit-identical to whole-plane passes' (differences, penalties, derivatives, then one update
/// of the gradient per direction and side): the same operations in the same order, and the
/// vertical sum keeps one pass's eight lanes ([`LaneSum`]).
#[inline(always)]
fn tv_component<T: Float>(comp: &[T], g: &mut [T], n: usize, norm: TvNorm, scale: T, summed: bool) -> T {
    // Each difference d_k = b_k − a_k adds |d| (or d²); ∂/∂d_k, scaled, goes to b_k with + and
    // to a_k with −. Slice loops only: they vectorise.
    let (mut right, mut down, mut up) = (vec![T::zero(); n], vec![T::zero(); n], vec![T::zero(); n]);
    let mut horizontal = T::zero();
    let mut vertical = LaneSum::new(n * (n - 1));
    for (j, grow) in g.chunks_exact_mut(n).enumerate() {
        let row = &comp[j * n..(j + 1) * n];
        differences_into(&row[..n - 1], &row[1..], &mut right[..n - 1], norm, scale, |d| {
            if summed {
                horizontal = horizontal + lane_sum(d, |x| penalty(x, norm));
            }
        });
        let next = comp.get((j + 1) * n..(j + 2) * n);
        if let Some(next) = next {
            differences_into(row, next, &mut down, norm, scale, |d| {
                if summed {
                    vertical.add(d, |x| penalty(x, norm));
                }
            });
        }
        match (next.is_some(), j > 0) {
            (true, true) => update_row::<T, true, true>(grow, &right, &down, &up),
            (true, false) => update_row::<T, true, false>(grow, &right, &down, &up),
            (false, true) => update_row::<T, false, true>(grow, &right, &down, &up),
            (false, false) => update_row::<T, false, false>(grow, &right, &down, &up),
        }
        std::mem::swap(&mut down, &mut up);
    }
    horizontal + vertical.total()
}

/// One row's TV derivatives applied to its gradient `g`, each value's in the order of the
/// whole-plane passes: − its right difference's (`right[i]`), + its left one's
/// (`right[i − 1]`), − the one towards the next row (`down[i]`, if `DOWN`), + the one from the
/// row above (`up[i]`, if `UP`).
#[inline(always)]
fn update_row<T: Float, const DOWN: bool, const UP: bool>(g: &mut [T], right: &[T], down: &[T], up: &[T]) {
    let n = g.len();
    let vertical = |x: T, i: usize| {
        let x = if DOWN { x - down[i] } else { x };
        if UP {
            x + up[i]
        } else {
            x
        }
    };
    g[0] = vertical(g[0] - right[0], 0);
    for i in 1..n - 1 {
        g[i] = vertical((g[i] - right[i]) + right[i - 1], i);
    }
    g[n - 1] = vertical(g[n - 1] + right[n - 2], n - 1);
}

/// A difference's penalty: |d| or d².
#[inline(always)]
fn penalty<T: Float>(d: T, norm: TvNorm) -> T {
    match norm {
        TvNorm::L1 => d.abs(),
        TvNorm::L2 => d * d,
    }
}

/// A difference's penalty's derivative, scaled.
#[inline(always)]
fn derivative<T: Float>(d: T, norm: TvNorm, scale: T) -> T {
    match norm {
        TvNorm::L1 => scale * sign(d),
        TvNorm::L2 => scale * (d + d),
    }
}

/// [`lane_sum`] of a sequence of `len` values handed over in pieces: the same eight lanes
/// over its whole chunks of eight, the same tail, so the same result.
struct LaneSum<T> {
    lanes: [T; 8],
    tail: T,
    /// Values taken so far, and how many fall in whole chunks.
    at: usize,
    chunked: usize,
}

impl<T: Float> LaneSum<T> {
    fn new(len: usize) -> Self {
        LaneSum { lanes: [T::zero(); 8], tail: T::zero(), at: 0, chunked: len - len % 8 }
    }

    /// Adds `f` of the next values (chunk by chunk where they line up, else one by one).
    #[inline(always)]
    fn add(&mut self, values: &[T], f: impl Fn(T) -> T) {
        if self.at.is_multiple_of(8) && values.len().is_multiple_of(8) && self.at + values.len() <= self.chunked {
            for chunk in values.chunks_exact(8) {
                for (lane, &v) in self.lanes.iter_mut().zip(chunk) {
                    *lane = *lane + f(v);
                }
            }
            self.at += values.len();
            return;
        }
        for &v in values {
            if self.at < self.chunked {
                self.lanes[self.at % 8] = self.lanes[self.at % 8] + f(v);
            } else {
                self.tail = self.tail + f(v);
            }
            self.at += 1;
        }
    }

    fn total(&self) -> T {
        let l = &self.lanes;
        ((l[0] + l[4]) + (l[1] + l[5])) + ((l[2] + l[6]) + (l[3] + l[7])) + self.tail
    }
}

/// The differences `b − a` into `step`; returns their penalty summed, and leaves in `step` the
/// penalty's derivative, scaled.
#[inline(always)]
fn penalise<T: Float>(a: &[T], b: &[T], step: &mut [T], norm: TvNorm, scale: T) -> T {
    let mut sum = T::zero();
    differences_into(a, b, step, norm, scale, |d| sum = lane_sum(d, |x| penalty(x, norm)));
    sum
}

/// The differences `b − a` into `step`, handed to `sum` (to add up their penalties), then
/// replaced in `step` by the penalty's derivative, scaled.
#[inline(always)]
fn differences_into<T: Float>(a: &[T], b: &[T], step: &mut [T], norm: TvNorm, scale: T, sum: impl FnOnce(&[T])) {
    for ((s, &x), &y) in step.iter_mut().zip(a).zip(b) {
        *s = y - x;
    }
    sum(step);
    step.iter_mut().for_each(|s| *s = derivative(*s, norm, scale));
}

/// Each difference's derivative `step[k]` taken from `g[k]` and added to `g[k + shift]`.
#[inline(always)]
fn apply_step<T: Float>(g: &mut [T], shift: usize, step: &[T]) {
    for (gi, &s) in g.iter_mut().zip(step) {
        *gi = *gi - s;
    }
    for (gi, &s) in g[shift..].iter_mut().zip(step) {
        *gi = *gi + s;
    }
}

/// `Σ f(x)` over `values` in eight interleaved partial sums (so the loop vectorises), then
/// the remainder, then the partials pairwise: one fixed order.
#[inline(always)]
pub(crate) fn lane_sum<T: Float>(values: &[T], f: impl Fn(T) -> T) -> T {
    let mut lanes = [T::zero(); 8];
    let chunks = values.chunks_exact(8);
    let tail = chunks.remainder().iter().fold(T::zero(), |t, &v| t + f(v));
    for chunk in chunks {
        for k in 0..8 {
            lanes[k] = lanes[k] + f(chunk[k]);
        }
    }
    ((lanes[0] + lanes[4]) + (lanes[1] + lanes[5])) + ((lanes[2] + lanes[6]) + (lanes[3] + lanes[7])) + tail
}

/// 3-D TV of the composed field `F` (an `n³` lattice, index `x + n·(y + n·z)`): the sum over
/// the three axes of the mean absolute forward difference — the same penalty as the plane TV,
/// but on what the renderer actually sees, so a streak that the planes and lines compose into
/// is penalised even when each factor is smooth. Its gradient, scaled by `weight`, is added to
/// `grad_dense` (the dense gradient the contraction turns into factor gradients). Returns the
/// unweighted value.
pub fn tv_dense<T: Float + Send + Sync>(dense: &[T], n: usize, weight: T, grad_dense: &mut [T]) -> f64 {
    let nn = n * n;
    assert_eq!(dense.len(), nn * n, "dense field is not n³");
    assert_eq!(grad_dense.len(), dense.len(), "gradient and field differ in size");
    if n < 2 {
        return 0.0;
    }
    let count = T::from(nn * (n - 1)).expect("count");
    let scale = weight / count;
    // Each z-slice owns its gradient slice: it takes the differences towards both neighbours
    // (within the slice, and to the slices above and below) but adds only the forward ones
    // (x, y, and z to the next slice) to the value, so every difference is counted once.
    let per_slice: Vec<T> = grad_dense
        .par_chunks_exact_mut(nn)
        .enumerate()
        .map(|(z, g)| {
            with_avx2(
                #[inline(always)]
                || {
                    let here = &dense[z * nn..(z + 1) * nn];
                    let mut value = T::zero();
                    let mut step = vec![T::zero(); nn];
                    // Along x: rows of n, each with n − 1 differences.
                    for (row, grow) in here.chunks_exact(n).zip(g.chunks_exact_mut(n)) {
                        let s = &mut step[..n - 1];
                        value = value + penalise(&row[..n - 1], &row[1..], s, TvNorm::L1, scale);
                        // Node k gains the difference before it and loses its own, in that order (as
                        // adding pair by pair would), as one slice loop that vectorises.
                        grow[0] = grow[0] - s[0];
                        for ((gk, &before), &own) in grow[1..n - 1].iter_mut().zip(&s[..n - 2]).zip(&s[1..]) {
                            *gk = (*gk + before) - own;
                        }
                        grow[n - 1] = grow[n - 1] + s[n - 2];
                    }
                    // Along y: the slice against itself shifted by one row.
                    value = value + penalise(&here[..nn - n], &here[n..], &mut step[..nn - n], TvNorm::L1, scale);
                    apply_step(g, n, &step[..nn - n]);
                    // Along z: to the next slice (counted here) and from the previous one (counted
                    // there, so its penalty is not added again).
                    if z + 1 < n {
                        value =
                            value + penalise(here, &dense[(z + 1) * nn..(z + 2) * nn], &mut step, TvNorm::L1, scale);
                        g.iter_mut().zip(&step).for_each(|(gi, &s)| *gi = *gi - s);
                    }
                    if z > 0 {
                        penalise(&dense[(z - 1) * nn..z * nn], here, &mut step, TvNorm::L1, scale);
                        g.iter_mut().zip(&step).for_each(|(gi, &s)| *gi = *gi + s);
                    }
                    value
                },
            )
        })
        .collect();
    let value = per_slice.into_iter().fold(T::zero(), |a, b| a + b);
    (value / count).to_f64().expect("finite")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_lane_sum_in_pieces_is_the_whole_lane_sum() {
        // Lengths with and without a tail, pieces that line up with the chunks and pieces
        // that do not.
        for (len, piece) in [(4032, 64), (4032, 63), (90, 9), (90, 8), (7, 3), (64, 64)] {
            let values: Vec<f32> = (0..len).map(|i| ((i * 7919) % 1000) as f32 * 1e-3 - 0.31).collect();
            let mut sum = LaneSum::new(len);
            for p in values.chunks(piece) {
                sum.add(p, |d: f32| d.abs());
            }
            assert_eq!(sum.total().to_bits(), lane_sum(&values, |d: f32| d.abs()).to_bits(), "{len} in {piece}s");
        }
    }
}
