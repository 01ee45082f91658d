//! The projector's path for a pinhole view that looks along a lattice axis. Its rays step along
//! that axis, and at each plane a pixel row's crossings share their coordinate `s` along one
//! of the two other axes while a pixel column's share `c` along the other: each plane maps to
//! the detector by one scaled affine map, separable in rows and columns. So `A` is, per plane,
//! a row interpolation then a column interpolation of that plane, summed over the planes and
//! weighed per pixel; the interpolation cells of every plane's rows and columns are tabled once.
//!
//! `A` runs a pixel row per task: per plane it blends the two lattice rows its crossings lie
//! between, then reads each column's two neighbours from that blend. `Aᵀ` runs a slab of planes
//! per task: per pixel row it spreads `r·w` over a line buffer by the column weights, and the
//! buffer over the two lattice rows by the row weight, the transpose of the same two steps.

use super::{cell, index_line, others, plane_range, slab_planes, SharedOut};
use crate::geometry::Aabb;
use glam::DVec3;
use rayon::prelude::*;

/// A pixel row's or column's crossing of one plane: the lower lattice index and the two
/// weights (0 and 0 where the crossing lies outside the box).
#[derive(Debug, Clone, Copy, PartialEq, Default, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
pub struct Cell {
    pub index: u32,
    pub lower: f32,
    pub upper: f32,
}

/// A view's rays as a separable resampling of each plane.
#[derive(Debug, Clone, PartialEq)]
pub struct Sheet {
    /// The axis the rays step along.
    pub axis: usize,
    /// The lattice axis a pixel row's crossings share (`s`) and the one a column's share (`c`).
    pub row_axis: usize,
    pub column_axis: usize,
    pub width: usize,
    pub height: usize,
    /// The row of `A` of the view's first pixel.
    pub first_ray: usize,
    /// Per plane `k` and pixel row `j` (index `k·height + j`).
    pub rows: Vec<Cell>,
    /// Per plane `k` and pixel column `i` (index `k·width + i`).
    pub columns: Vec<Cell>,
    /// Each pixel's `s ×` ray length between planes; 0 where its ray misses the box.
    pub weights: Vec<f32>,
    /// Per plane `k` and lattice index `x` along the column axis (index `k·n + x`): the pixel
    /// columns whose cell starts at `x`, a run (the cells grow or shrink with the column).
    pub column_runs: Vec<[u32; 2]>,
    /// The same for the pixel rows along the row axis (what an adjoint that gathers per node
    /// reads: the GPU's).
    pub row_runs: Vec<[u32; 2]>,
    /// Per plane: the pixel columns whose crossing lies inside the box, and the lattice indices
    /// along the column axis they read (`[first, end)` each).
    pub spans: Vec<Span>,
}

/// The columns of one plane that count, and the lattice line they read.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Span {
    pub columns: [usize; 2],
    pub lattice: [usize; 2],
}

impl Span {
    /// The span of one plane's column cells.
    fn of(cells: &[Cell]) -> Span {
        let valid = |c: &Cell| c.lower != 0.0 || c.upper != 0.0;
        let Some(first) = cells.iter().position(valid) else { return Span::default() };
        let end = cells.iter().rposition(valid).expect("one is valid") + 1;
        let (lo, hi) = cells[first..end]
            .iter()
            .filter(|c| valid(c))
            .fold((u32::MAX, 0), |(lo, hi), c| (lo.min(c.index), hi.max(c.index)));
        Span { columns: [first, end], lattice: [lo as usize, hi as usize + 2] }
    }
}

/// What a ray contributes to the tables: its axis, `(s0, ds)`-style parameters along the two
/// other axes, and its weight.
struct RayLine {
    axis: usize,
    start: [f64; 2],
    slope: [f64; 2],
    weight: f64,
}

impl Sheet {
    /// The sheet of one view (`width` pixels a row, rays in pixel order from row `first_ray` of
    /// `A`), when its rays share an origin and an axis and its rows and columns share their
    /// crossings' coordinates; `None` otherwise.
    pub fn of_view(
        aabb: &Aabb,
        n: usize,
        scale: f64,
        rays: &[(DVec3, DVec3)],
        width: usize,
        first_ray: usize,
    ) -> Option<Sheet> {
        let (width, height) = (width, rays.len() / width.max(1));
        if width < 1 || width * height != rays.len() || rays.iter().any(|r| r.0 != rays[0].0) {
            return None;
        }
        let lines: Vec<RayLine> = rays
            .iter()
            .map(|&(origin, dir)| {
                let (a, b) = index_line(aabb, n, origin, dir);
                let axis = (0..3).max_by(|&i, &j| b[i].abs().total_cmp(&b[j].abs())).expect("three axes");
                let slope = others(axis).map(|o| b[o] / b[axis]);
                let start = std::array::from_fn(|o| a[others(axis)[o]] - a[axis] * slope[o]);
                RayLine { axis, start, slope, weight: scale / b[axis].abs() }
            })
            .collect();
        let axis = lines[0].axis;
        if lines.iter().any(|l| l.axis != axis) {
            return None;
        }
        let close = |x: f64, y: f64| (x - y).abs() <= 1e-9 * (1.0 + x.abs().max(y.abs()));
        let same = |a: &RayLine, b: &RayLine, o: usize| close(a.start[o], b.start[o]) && close(a.slope[o], b.slope[o]);
        let pixel = |i: usize, j: usize| &lines[i + width * j];
        // The coordinate shared along a pixel row: o = 1 (v) or o = 0 (u).
        let along_rows = |o: usize| (0..height).all(|j| (1..width).all(|i| same(pixel(i, j), pixel(0, j), o)));
        let along_columns = |o: usize| (0..width).all(|i| (1..height).all(|j| same(pixel(i, j), pixel(i, 0), o)));
        let [u, v] = others(axis);
        let (s, row_axis, column_axis) = if along_rows(1) && along_columns(0) {
            (1, v, u)
        } else if along_rows(0) && along_columns(1) {
            (0, u, v)
        } else {
            return None;
        };
        let c = 1 - s;
        // t ≥ 0 (ahead of the shared origin) bounds the planes alike for every ray.
        let (a, b) = index_line(aabb, n, rays[0].0, rays[0].1);
        let ahead = if b[axis] > 0.0 { (a[axis], f64::INFINITY) } else { (f64::NEG_INFINITY, a[axis]) };
        let table = |start: f64, slope: f64| -> (Vec<Cell>, (f64, f64)) {
            let (lo, hi) = plane_range(start, slope, n).unwrap_or((1.0, 0.0));
            let (lo, hi) = (lo.max(ahead.0), hi.min(ahead.1));
            let cells = (0..n)
                .map(|k| {
                    if (k as f64) < lo || (k as f64) > hi {
                        return Cell::default();
                    }
                    let (index, upper) = cell((start + k as f64 * slope) as f32, n);
                    Cell { index: index as u32, lower: 1.0 - upper, upper }
                })
                .collect();
            (cells, (lo, hi))
        };
        let row_tables: Vec<_> = (0..height).map(|j| table(pixel(0, j).start[s], pixel(0, j).slope[s])).collect();
        let column_tables: Vec<_> = (0..width).map(|i| table(pixel(i, 0).start[c], pixel(i, 0).slope[c])).collect();
        let weights = (0..height)
            .flat_map(|j| (0..width).map(move |i| (i, j)))
            .map(|(i, j)| {
                let ((_, (r0, r1)), (_, (c0, c1))) = (&row_tables[j], &column_tables[i]);
                // The ray meets the box where a plane lies in both ranges.
                let meets = r0.max(*c0).ceil() <= r1.min(*c1).floor();
                if meets {
                    pixel(i, j).weight as f32
                } else {
                    0.0
                }
            })
            .collect();
        let transpose = |tables: Vec<(Vec<Cell>, (f64, f64))>| -> Vec<Cell> {
            let len = tables.len();
            (0..n * len).map(|x| tables[x % len].0[x / len]).collect()
        };
        let columns = transpose(column_tables);
        let column_runs = runs(&columns, width, n)?;
        let rows = transpose(row_tables);
        let row_runs = runs(&rows, height, n)?;
        let spans = columns.chunks(width).map(Span::of).collect();
        Some(Sheet {
            axis,
            row_axis,
            column_axis,
            width,
            height,
            first_ray,
            rows,
            columns,
            weights,
            column_runs,
            row_runs,
            spans,
        })
    }

    fn strides(&self, n: usize) -> [usize; 3] {
        [self.axis, self.row_axis, self.column_axis].map(|a| n.pow(a as u32))
    }

    /// Whether pixel `(i, j)`'s ray meets the box.
    pub fn meets(&self, pixel: usize) -> bool {
        self.weights[pixel] != 0.0
    }

    /// The view's depths through `sigma`, into `depths` (by row of `A`).
    pub fn project(&self, sigma: &[f32], n: usize, depths: &mut [f64]) {
        let [plane, row_stride, column] = self.strides(n);
        let (width, height) = (self.width, self.height);
        let view = &mut depths[self.first_ray..self.first_ray + width * height];
        view.par_chunks_mut(width).enumerate().for_each_init(
            || (vec![0.0f32; n], vec![0.0f32; width]),
            |(blended, sums), (j, depths)| {
                sums.fill(0.0);
                for k in 0..n {
                    let row = self.rows[k * height + j];
                    if row.lower == 0.0 && row.upper == 0.0 {
                        continue;
                    }
                    let Span { columns: [first, end], lattice: [lo, hi] } = self.spans[k];
                    let lower = &sigma[k * plane + row.index as usize * row_stride..];
                    let upper = &lower[row_stride..];
                    if column == 1 {
                        let pairs = blended[lo..hi].iter_mut().zip(&lower[lo..hi]).zip(&upper[lo..hi]);
                        for ((b, &a), &c) in pairs {
                            *b = row.lower * a + row.upper * c;
                        }
                    } else {
                        for (x, b) in blended.iter_mut().enumerate().take(hi).skip(lo) {
                            *b = row.lower * lower[x * column] + row.upper * upper[x * column];
                        }
                    }
                    let cells = &self.columns[k * width + first..k * width + end];
                    for (sum, c) in sums[first..end].iter_mut().zip(cells) {
                        let i = c.index as usize;
                        *sum += c.lower * blended[i] + c.upper * blended[i + 1];
                    }
                }
                let weights = &self.weights[j * width..(j + 1) * width];
                for ((d, &s), &w) in depths.iter_mut().zip(sums.iter()).zip(weights) {
                    *d = f64::from(w) * f64::from(s);
                }
            },
        );
    }

    /// Adds the view's `Aᵀ r` to `out`.
    pub fn back_project(&self, r: &[f64], n: usize, out: &mut [f32]) {
        let [plane, row_stride, column] = self.strides(n);
        let (width, height) = (self.width, self.height);
        let view = &r[self.first_ray..self.first_ray + width * height];
        let weighted: Vec<f32> = view.iter().zip(&self.weights).map(|(&r, &w)| r as f32 * w).collect();
        let planes = slab_planes(plane);
        let out = SharedOut(out.as_mut_ptr());
        (0..n.div_ceil(planes)).into_par_iter().for_each_init(
            || vec![0.0f32; n],
            |buffer, slab| {
                for k in slab * planes..((slab + 1) * planes).min(n) {
                    let cells = &self.columns[k * width..(k + 1) * width];
                    for j in 0..height {
                        let row = self.rows[k * height + j];
                        if row.lower == 0.0 && row.upper == 0.0 {
                            continue;
                        }
                        let v = &weighted[j * width..(j + 1) * width];
                        // Lattice index x takes the columns whose cell starts there (their
                        // lower weight) and those whose cell starts at x − 1 (their upper one).
                        let [lo, hi] = self.spans[k].lattice;
                        let runs = &self.column_runs[k * n + lo..k * n + hi];
                        let buffer = &mut buffer[lo..hi];
                        let mut from_below = 0.0f32;
                        for (b, &[start, end]) in buffer.iter_mut().zip(runs) {
                            let (mut at, mut above) = (from_below, 0.0f32);
                            for i in start as usize..end as usize {
                                at += cells[i].lower * v[i];
                                above += cells[i].upper * v[i];
                            }
                            *b = at;
                            from_below = above;
                        }
                        let lower = k * plane + row.index as usize * row_stride + lo * column;
                        if column == 1 {
                            // SAFETY: two lattice rows of plane `k` (n apart or more, so
                            // disjoint), which only this slab's task writes, inside the lattice.
                            let (low, high) =
                                unsafe { (out.row(lower, hi - lo), out.row(lower + row_stride, hi - lo)) };
                            for ((l, h), &b) in low.iter_mut().zip(high.iter_mut()).zip(buffer.iter()) {
                                *l += row.lower * b;
                                *h += row.upper * b;
                            }
                            continue;
                        }
                        for (x, &b) in buffer.iter().enumerate() {
                            let i = lower + x * column;
                            // SAFETY: nodes of plane `k`, which only this slab's task writes,
                            // inside the lattice (`cell` keeps the row index below n − 1).
                            unsafe {
                                *out.at(i) += row.lower * b;
                                *out.at(i + row_stride) += row.upper * b;
                            }
                        }
                    }
                }
            },
        );
    }
}

/// For each plane and lattice index `x`, the run of pixel columns (or rows) whose cell starts at
/// `x` (empty runs where none does); `None` when some plane's cells are not a monotone run.
fn runs(cells_per_plane: &[Cell], width: usize, n: usize) -> Option<Vec<[u32; 2]>> {
    let mut runs = vec![[0u32; 2]; n * n];
    for (k, cells) in cells_per_plane.chunks(width).enumerate() {
        let runs = &mut runs[k * n..(k + 1) * n];
        let mut last: Option<u32> = None;
        for (i, c) in cells.iter().enumerate() {
            if c.lower == 0.0 && c.upper == 0.0 {
                continue;
            }
            let run = &mut runs[c.index as usize];
            if last == Some(c.index) {
                run[1] = i as u32 + 1;
            } else if run[1] > run[0] {
                return None; // x was left and came back: not a monotone run
            } else {
                *run = [i as u32, i as u32 + 1];
            }
            last = Some(c.index);
        }
    }
    Some(runs)
}
