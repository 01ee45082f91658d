//! Strided matrix products for composing the VM factors into the dense field and contracting
//! its gradient back (the contraction only in f64 and on CPUs without FMA: f32 on FMA CPUs
//! contracts by [`super::contract`]'s bit-identical chains): a bounds-checked, safe front to
//! `matrixmultiply` (which picks AVX/FMA kernels at run time), split into blocks that run in
//! parallel.
//!
//! Blocks depend only on the shape, never on the thread count, and no block splits the inner
//! (k) dimension, so every output element is summed in one fixed order: results are
//! bit-identical on any number of threads.

use num_traits::Float;
use rayon::prelude::*;
use std::any::Any;
use std::sync::{Mutex, PoisonError};

/// The real types the training kernels run in (f32 in training, f64 in gradient checks):
/// a GEMM kernel and a fast index conversion.
pub trait Scalar: Float + Default + Send + Sync + 'static {
    /// The integer part of a value in `[0, i32::MAX]` (a lattice coordinate), by machine
    /// conversion rather than `num_traits`' checked one.
    fn trunc_index(self) -> usize;

    /// A small lattice index as a value (by a 32-bit machine conversion).
    fn from_index(index: usize) -> Self;

    /// The values as f32, when that is their type: the way into f32-only vector kernels.
    fn as_f32(values: &[Self]) -> Option<&[f32]>;

    /// [`Scalar::as_f32`], writable.
    fn as_f32_mut(values: &mut [Self]) -> Option<&mut [f32]>;

    /// `C ← A·B + β·C` on raw strided views.
    ///
    /// # Safety
    /// Every element addressed through `a`, `b` and `c` must lie in live allocations, `c`'s
    /// elements must be distinct and not aliased by anything else during the call.
    #[allow(clippy::too_many_arguments)]
    unsafe fn gemm_raw(
        m: usize,
        k: usize,
        n: usize,
        a: *const Self,
        a_strides: [isize; 2],
        b: *const Self,
        b_strides: [isize; 2],
        beta: Self,
        c: *mut Self,
        c_strides: [isize; 2],
    );
}

macro_rules! scalar {
    ($t:ty, $kernel:path, $as_f32:expr, $as_f32_mut:expr) => {
        impl Scalar for $t {
            #[inline]
            fn trunc_index(self) -> usize {
                self as i32 as usize
            }

            #[inline]
            fn from_index(index: usize) -> Self {
                index as i32 as Self
            }

            fn as_f32(values: &[Self]) -> Option<&[f32]> {
                $as_f32(values)
            }

            fn as_f32_mut(values: &mut [Self]) -> Option<&mut [f32]> {
                $as_f32_mut(values)
            }

            unsafe fn gemm_raw(
                m: usize,
                k: usize,
                n: usize,
                a: *const Self,
                [rsa, csa]: [isize; 2],
                b: *const Self,
                [rsb, csb]: [isize; 2],
                beta: Self,
                c: *mut Self,
                [rsc, csc]: [isize; 2],
            ) {
                $kernel(m, k, n, 1.0, a, rsa, csa, b, rsb, csb, beta, c, rsc, csc)
            }
        }
    };
}
scalar!(f32, matrixmultiply::sgemm, Some, Some);
scalar!(f64, matrixmultiply::dgemm, |_| None, |_| None);

/// Where a (batch of) matrices lives in a flat buffer: element `(i, j)` of matrix `b` is at
/// `offset + b·batch + i·row + j·col`.
#[derive(Debug, Clone, Copy)]
pub struct Layout {
    pub offset: usize,
    pub row: usize,
    pub col: usize,
    pub batch: usize,
}

impl Layout {
    /// A single matrix with the given row and column strides.
    pub const fn new(offset: usize, row: usize, col: usize) -> Layout {
        Layout { offset, row, col, batch: 0 }
    }

    /// The same matrix repeated with stride `batch` between instances.
    pub const fn batched(self, batch: usize) -> Layout {
        Layout { batch, ..self }
    }

    /// The largest index addressed by `count` matrices of `rows × cols`.
    fn last_index(&self, count: usize, rows: usize, cols: usize) -> usize {
        self.offset + (count - 1) * self.batch + (rows - 1) * self.row + (cols - 1) * self.col
    }

    /// True when no two (batch, row, col) positions share an element: sorted by stride, each
    /// stride must step past everything the smaller ones reach.
    fn is_injective(&self, count: usize, rows: usize, cols: usize) -> bool {
        let mut axes: Vec<(usize, usize)> =
            [(self.batch, count), (self.row, rows), (self.col, cols)].into_iter().filter(|&(_, e)| e > 1).collect();
        axes.sort_unstable();
        let mut reach = 0;
        for (stride, extent) in axes {
            if stride <= reach {
                return false;
            }
            reach += (extent - 1) * stride;
        }
        true
    }
}

/// The product's shape: `count` independent products of an `m × k` by a `k × n` matrix.
#[derive(Debug, Clone, Copy)]
pub struct Shape {
    pub count: usize,
    pub m: usize,
    pub k: usize,
    pub n: usize,
}

/// Most blocks one product is split into, and the fewest rows or columns in a block (each
/// block repacks the operand it does not split). Fixed: the split must not depend on the
/// thread count.
const MAX_BLOCKS: usize = 16;
const MIN_BLOCK: usize = 32;

/// `C ← A·B + β·C` for every matrix of the batch (`β = 0` overwrites C).
///
/// Panics if a layout addresses beyond its buffer or C's layout maps two elements to one.
pub fn gemm<T: Scalar>(shape: Shape, a: (&[T], Layout), b: (&[T], Layout), beta: T, c: (&mut [T], Layout)) {
    gemm_all(vec![Product { shape, a, b, beta, c }]);
}

/// One product of [`gemm_all`]: `C ← A·B + β·C` for every matrix of the batch.
pub struct Product<'a, T> {
    pub shape: Shape,
    pub a: (&'a [T], Layout),
    pub b: (&'a [T], Layout),
    pub beta: T,
    pub c: (&'a mut [T], Layout),
}

/// Several independent products (each its own output) in one parallel pass over all their
/// blocks: the contraction's six products cost six hand-offs between the workers otherwise.
///
/// Panics as [`gemm`] does, for any of them.
pub fn gemm_all<T: Scalar>(products: Vec<Product<T>>) {
    let plans: Vec<Plan<T>> = products.into_iter().filter_map(Plan::new).collect();
    blocks_of(&plans).into_par_iter().for_each(|(p, q, i, j)| {
        // SAFETY: `Plan::new` checked every addressed element against its slice and C's layout
        // for injectivity; the blocks (disjoint (q, i, j) ranges) write disjoint elements of
        // their own product's C, borrowed mutably for the whole call, and no two products share
        // a C (each is its own `&mut`).
        unsafe { plans[p].block(q, i, j) }
    });
}

/// [`gemm`] on the calling thread alone: for products that are already one task of a
/// parallel pass. Its blocks are [`gemm`]'s, so its results are bit-identical.
pub fn gemm_serial<T: Scalar>(shape: Shape, a: (&[T], Layout), b: (&[T], Layout), beta: T, c: (&mut [T], Layout)) {
    let plans: Vec<Plan<T>> = Plan::new(Product { shape, a, b, beta, c }).into_iter().collect();
    for (p, q, i, j) in blocks_of(&plans) {
        // SAFETY: as in `gemm_all`, one block at a time.
        unsafe { plans[p].block(q, i, j) }
    }
}

/// Every block of every plan: (plan, batch entry, row, column).
fn blocks_of<T>(plans: &[Plan<T>]) -> Vec<(usize, usize, usize, usize)> {
    plans
        .iter()
        .enumerate()
        .flat_map(|(p, plan)| {
            let Shape { count, m, n, .. } = plan.shape;
            let (rows_per, cols_per) = (plan.rows_per, plan.cols_per);
            (0..count).flat_map(move |q| {
                (0..m).step_by(rows_per).flat_map(move |i| (0..n).step_by(cols_per).map(move |j| (p, q, i, j)))
            })
        })
        .collect()
}

/// A checked product of [`gemm_all`]: raw views of its operands and its block size.
struct Plan<T> {
    shape: Shape,
    a: (SharedPtr<T>, Layout),
    b: (SharedPtr<T>, Layout),
    beta: T,
    c: (SharedPtr<T>, Layout),
    rows_per: usize,
    cols_per: usize,
}

impl<T: Scalar> Plan<T> {
    /// The product's plan, after checking its layouts; `None` when it is empty.
    fn new(Product { shape, a: (a, la), b: (b, lb), beta, c: (c, lc) }: Product<T>) -> Option<Plan<T>> {
        let Shape { count, m, k, n } = shape;
        if count == 0 || m == 0 || n == 0 {
            return None;
        }
        assert!(lc.is_injective(count, m, n), "gemm: output layout {lc:?} aliases for {shape:?}");
        assert!(lc.last_index(count, m, n) < c.len(), "gemm: output layout {lc:?} exceeds its buffer");
        if k > 0 {
            assert!(la.last_index(count, m, k) < a.len(), "gemm: A layout {la:?} exceeds its buffer");
            assert!(lb.last_index(count, k, n) < b.len(), "gemm: B layout {lb:?} exceeds its buffer");
        }
        // Blocks: one per batch entry, or the larger of m and n cut into equal runs.
        let (rows_per, cols_per) = if count > 1 {
            (m, n)
        } else if m >= n {
            (m.div_ceil(MAX_BLOCKS).max(MIN_BLOCK), n)
        } else {
            (m, n.div_ceil(MAX_BLOCKS).max(MIN_BLOCK))
        };
        let shared = |p: &[T]| SharedPtr(p.as_ptr() as *mut T);
        Some(Plan {
            shape,
            a: (shared(a), la),
            b: (shared(b), lb),
            beta,
            c: (SharedPtr(c.as_mut_ptr()), lc),
            rows_per,
            cols_per,
        })
    }

    /// The block of batch entry `q` at row `i`, column `j`.
    ///
    /// # Safety
    /// The operands `new` checked must still be borrowed as then, and no other block writing
    /// this one's elements may run at the same time.
    unsafe fn block(&self, q: usize, i: usize, j: usize) {
        let Shape { m, k, n, .. } = self.shape;
        let ((a, la), (b, lb), (c, lc)) = (&self.a, &self.b, &self.c);
        let (rows, cols) = (self.rows_per.min(m - i), self.cols_per.min(n - j));
        let signed = |l: &Layout| [l.row as isize, l.col as isize];
        T::gemm_raw(
            rows,
            k,
            cols,
            a.0.add(la.offset + q * la.batch + i * la.row),
            signed(la),
            b.0.add(lb.offset + q * lb.batch + j * lb.col),
            signed(lb),
            self.beta,
            c.0.add(lc.offset + q * lc.batch + i * lc.row + j * lc.col),
            signed(lc),
        )
    }
}

/// Scratch buffers the training kernels keep from one step to the next (at most this many).
/// Allocating and freeing a step's megabytes of scratch made the allocator return the memory
/// to the OS and fault it in again every step: ≈ 700 page faults an iteration, ≈ 40% of the
/// step under load.
const MAX_SPARE: usize = 256;
static SPARE: Mutex<Vec<Box<dyn Any + Send>>> = Mutex::new(Vec::new());

/// A kept buffer (set) of type `B`, or a new one; its contents are whatever it last held.
pub(crate) fn take_spare<B: Any + Send + Default>() -> B {
    let mut spare = SPARE.lock().unwrap_or_else(PoisonError::into_inner);
    match spare.iter().rposition(|b| b.is::<B>()) {
        Some(i) => *spare.swap_remove(i).downcast::<B>().expect("checked type"),
        None => B::default(),
    }
}

/// Keeps `buffers` for a later step.
pub(crate) fn give_spare<B: Any + Send>(buffers: B) {
    let mut spare = SPARE.lock().unwrap_or_else(PoisonError::into_inner);
    if spare.len() < MAX_SPARE {
        spare.push(Box::new(buffers));
    }
}

/// A raw pointer shared by the block tasks of one [`gemm_all`] call.
struct SharedPtr<T>(*mut T);
// SAFETY: used only inside `gemm_all`, whose blocks read A and B and write disjoint parts of C.
unsafe impl<T: Send> Send for SharedPtr<T> {}
unsafe impl<T: Sync> Sync for SharedPtr<T> {}

#[cfg(test)]
mod tests {
    use super::*;

    fn reference(shape: Shape, a: (&[f64], Layout), b: (&[f64], Layout), c: (&mut [f64], Layout)) {
        for q in 0..shape.count {
            for i in 0..shape.m {
                for j in 0..shape.n {
                    let s: f64 = (0..shape.k)
                        .map(|p| {
                            a.0[a.1.offset + q * a.1.batch + i * a.1.row + p * a.1.col]
                                * b.0[b.1.offset + q * b.1.batch + p * b.1.row + j * b.1.col]
                        })
                        .sum();
                    c.0[c.1.offset + q * c.1.batch + i * c.1.row + j * c.1.col] = s;
                }
            }
        }
    }

    #[test]
    fn strided_batched_products_match_the_definition() {
        let shape = Shape { count: 3, m: 37, k: 5, n: 21 };
        let a: Vec<f64> = (0..3 * 37 * 5).map(|i| ((i * 7919) % 101) as f64 / 50.0 - 1.0).collect();
        let b: Vec<f64> = (0..3 * 5 * 21).map(|i| ((i * 104729) % 97) as f64 / 48.0 - 1.0).collect();
        // A column-major per batch entry, B shared (batch stride 0), C transposed and interleaved.
        let la = Layout::new(0, 1, 37).batched(37 * 5);
        let lb = Layout::new(0, 21, 1);
        let lc = Layout::new(2, 3 * 21, 3).batched(1);
        let mut c = vec![0.0; 2 + 3 * 21 * 37];
        let mut expected = c.clone();
        gemm(shape, (&a, la), (&b, lb), 0.0, (&mut c, lc));
        reference(shape, (&a, la), (&b, lb), (&mut expected, lc));
        for (x, y) in c.iter().zip(&expected) {
            assert!((x - y).abs() < 1e-12);
        }
        // Single products split into blocks along the longer side, both ways round.
        let a: Vec<f64> = (0..400).map(|i| ((i * 7919) % 101) as f64 / 50.0 - 1.0).collect();
        let b: Vec<f64> = (0..400).map(|i| ((i * 104729) % 97) as f64 / 48.0 - 1.0).collect();
        for (m, n) in [(100, 3), (3, 100)] {
            let shape = Shape { count: 1, m, k: 4, n };
            let la = Layout::new(0, 4, 1);
            let lb = Layout::new(0, 1, 4);
            let mut c = vec![1.0; m * n];
            let mut expected = vec![0.0; m * n];
            gemm(shape, (&a, la), (&b, lb), 1.0, (&mut c, Layout::new(0, n, 1)));
            reference(shape, (&a, la), (&b, lb), (&mut expected, Layout::new(0, n, 1)));
            assert!(c.iter().zip(&expected).all(|(x, y)| (x - 1.0 - y).abs() < 1e-12));
        }
    }

    #[test]
    #[should_panic(expected = "aliases")]
    fn an_aliasing_output_is_refused() {
        let shape = Shape { count: 1, m: 4, k: 1, n: 4 };
        let (a, b) = (vec![1.0f32; 4], vec![1.0f32; 4]);
        let mut c = vec![0.0f32; 16];
        gemm(shape, (&a, Layout::new(0, 1, 1)), (&b, Layout::new(0, 1, 1)), 0.0, (&mut c, Layout::new(0, 2, 1)));
    }
}
