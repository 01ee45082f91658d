//! Point-in-polygon with the exact boundary behaviour of matplotlib's
//! `Path.contains_points(points, radius=0)`, which pylidc uses to fill radiologist contours.
//!
//! matplotlib runs a crossings test (Eric Haines' "crossings multiply", `point_in_path_impl` in
//! `src/_path.h`): a ray is cast from the point along +x and each edge whose end points lie on
//! different sides of the line `y = ty` (one with `y >= ty`, the other with `y < ty`) is tested
//! with a multiplication instead of a division. For points exactly on an edge, this decides
//! differently from a textbook even-odd test (which divides), and that decides single voxels on
//! real LIDC contours (LIDC-IDRI-0019). All coordinates here are integers, so the comparisons are
//! made exactly in `i64`, as matplotlib's are in `f64` for values this small.

/// A closed polygon built the way pylidc builds `mplpath.Path(C, closed=True)` from a contour.
#[derive(Debug, Clone, PartialEq)]
pub struct MplPolygon {
    /// The distinct polygon vertices `(x, y)`, without the closing repeat of the first one.
    vertices: Vec<[i64; 2]>,
}

impl MplPolygon {
    /// From contour points in drawing order. pylidc appends the first point when the contour is
    /// not already closed; matplotlib then treats the last vertex as `CLOSEPOLY` (its value is
    /// ignored and the path closes back to the first vertex). A path of fewer than three
    /// vertices contains nothing (matplotlib's `points_in_path` returns all false).
    pub fn from_contour(points: &[[i64; 2]]) -> Self {
        let (Some(first), Some(last)) = (points.first(), points.last()) else {
            return Self { vertices: Vec::new() };
        };
        let already_closed = first == last;
        let path_len = points.len() + usize::from(!already_closed);
        let vertices = if path_len < 3 {
            Vec::new()
        } else if already_closed {
            points[..points.len() - 1].to_vec()
        } else {
            points.to_vec()
        };
        Self { vertices }
    }

    /// Whether matplotlib counts point `(tx, ty)` inside: an odd number of edge crossings.
    pub fn contains(&self, tx: i64, ty: i64) -> bool {
        let n = self.vertices.len();
        let mut inside = false;
        for e in 0..n {
            let [x0, y0] = self.vertices[e];
            let [x1, y1] = self.vertices[(e + 1) % n];
            inside ^= edge_crosses_ray(x0, y0, x1, y1, tx, ty);
        }
        inside
    }

    /// Inclusive `(min, max)` corners of the vertices, or `None` for an empty polygon.
    pub fn bounds(&self) -> Option<([i64; 2], [i64; 2])> {
        let first = *self.vertices.first()?;
        Some(self.vertices.iter().fold((first, first), |(lo, hi), v| {
            ([lo[0].min(v[0]), lo[1].min(v[1])], [hi[0].max(v[0]), hi[1].max(v[1])])
        }))
    }
}

impl MplPolygon {
    /// Calls `f(tx, ty)` for every integer point of [`Self::bounds`] that [`Self::contains`]
    /// counts inside, row by row. Exactly the same points, but each row `ty` is decided at once:
    /// an edge that spans the row is crossed by the rays of all `tx` up to a threshold, so the
    /// parity along the row is a running sum of per-edge toggles. The work is the bounding
    /// box's area plus the rows each edge spans, where testing every point against every edge
    /// would cost area × edges (quadratic in a contour's points).
    pub fn for_each_inside(&self, mut f: impl FnMut(i64, i64)) {
        let Some((lo, hi)) = self.bounds() else {
            return;
        };
        let width = (hi[0] - lo[0] + 1) as usize;
        let n = self.vertices.len();
        let edge = |e: usize| (self.vertices[e], self.vertices[(e + 1) % n]);
        // The rows an edge can cross: its two ends on different sides of `y = ty`, that is
        // min(y0, y1) < ty <= max(y0, y1).
        let mut edges_by_row: Vec<Vec<usize>> = vec![Vec::new(); (hi[1] - lo[1] + 1) as usize];
        for e in 0..n {
            let ([_, y0], [_, y1]) = edge(e);
            for ty in y0.min(y1) + 1..=y0.max(y1) {
                edges_by_row[(ty - lo[1]) as usize].push(e);
            }
        }
        let mut toggles = vec![false; width + 1];
        for (row, edges) in edges_by_row.iter().enumerate() {
            let ty = lo[1] + row as i64;
            toggles.fill(false);
            for &e in edges {
                let ([x0, y0], [x1, y1]) = edge(e);
                let last = last_crossing_tx(x0, y0, x1, y1, ty);
                if last >= lo[0] {
                    toggles[0] ^= true;
                    toggles[(last.min(hi[0]) - lo[0] + 1) as usize] ^= true;
                }
            }
            let mut inside = false;
            for (column, &toggle) in toggles[..width].iter().enumerate() {
                inside ^= toggle;
                if inside {
                    f(lo[0] + column as i64, ty);
                }
            }
        }
    }
}

/// For an edge whose ends lie on different sides of `y = ty`: the largest `tx` whose ray the
/// edge crosses by [`edge_crosses_ray`] (it crosses the rays of every smaller `tx`, none of
/// larger). Solves that test's inequality `(y1 − ty)(x0 − x1) ≥ (x1 − tx)(y0 − y1)` for `tx`
/// in integers: with `d = y0 − y1` it reads `tx·d ≥ b`, `b = x1·d − (y1 − ty)(x0 − x1)`.
fn last_crossing_tx(x0: i64, y0: i64, x1: i64, y1: i64, ty: i64) -> i64 {
    let d = y0 - y1;
    let b = x1 * d - (y1 - ty) * (x0 - x1);
    if d < 0 {
        // y1 is the end above the row (`above1`): crossed where the inequality holds,
        // tx·d ≥ b ⇔ tx ≤ b/d, the floor of it in integers.
        (-b).div_euclid(-d)
    } else {
        // y0 is above (`!above1`): crossed where it fails, tx < b/d ⇔ tx ≤ ⌈b/d⌉ − 1.
        -(-b).div_euclid(d) - 1
    }
}

/// matplotlib's per-edge test for the edge (x0, y0) → (x1, y1) and test point (tx, ty).
fn edge_crosses_ray(x0: i64, y0: i64, x1: i64, y1: i64, tx: i64, ty: i64) -> bool {
    let above0 = y0 >= ty;
    let above1 = y1 >= ty;
    if above0 == above1 {
        return false;
    }
    // "Is the crossing at or right of tx", decided without dividing, as matplotlib does; the
    // comparison's sense flips with the edge direction, hence `== above1`.
    ((y1 - ty) * (x0 - x1) >= (x1 - tx) * (y0 - y1)) == above1
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn square() -> MplPolygon {
        MplPolygon::from_contour(&[[0, 0], [4, 0], [4, 4], [0, 4]])
    }

    #[test]
    fn interior_and_exterior_points() {
        let sq = square();
        assert!(sq.contains(2, 2));
        assert!(sq.contains(1, 3));
        assert!(!sq.contains(5, 2));
        assert!(!sq.contains(-1, 2));
        assert!(!sq.contains(2, 5));
    }

    /// On the boundary of an axis-aligned square matplotlib's rule is half-open in y only:
    /// inside iff `ymin < y <= ymax` and `xmin <= x <= xmax`. A symmetric even-odd rule would
    /// treat the edges alike. These exact values are what the LIDC masks depend on.
    #[test]
    fn boundary_points_follow_matplotlib() {
        let sq = square();
        // Bottom edge y = 0, corners included: no edge has an end strictly below y = 0.
        assert!((0..=4).all(|x| !sq.contains(x, 0)));
        // Top edge y = 4, corners included: only the right edge (x = 4 >= tx) is crossed.
        assert!((0..=4).all(|x| sq.contains(x, 4)));
        // Left and right edges: the crossing at x = tx counts (>=), the left edge is not crossed
        // by a ray starting on it.
        assert!((1..=3).all(|y| sq.contains(0, y) && sq.contains(4, y)));
    }

    #[test]
    fn closed_and_open_contours_are_the_same_polygon() {
        let open = MplPolygon::from_contour(&[[0, 0], [4, 0], [4, 4], [0, 4]]);
        let closed = MplPolygon::from_contour(&[[0, 0], [4, 0], [4, 4], [0, 4], [0, 0]]);
        assert_eq!(open, closed);
    }

    #[test]
    fn degenerate_paths() {
        // Fewer than three path vertices: nothing inside.
        assert!(!MplPolygon::from_contour(&[]).contains(0, 0));
        assert!(!MplPolygon::from_contour(&[[1, 1]]).contains(1, 1));
        assert!(!MplPolygon::from_contour(&[[1, 1], [1, 1]]).contains(1, 1));
        // Two distinct points make a zero-area path there and back, yet matplotlib counts the
        // points on it with y in (0, 4] inside (one edge is crossed "at or right of" tx, its
        // return is not): a two-point LIDC contour paints a line, as in pylidc.
        let seg = MplPolygon::from_contour(&[[0, 0], [0, 4]]);
        let inside: Vec<(i64, i64)> =
            (-1..3).flat_map(|x| (-1..6).map(move |y| (x, y))).filter(|&(x, y)| seg.contains(x, y)).collect();
        assert_eq!(inside, vec![(0, 1), (0, 2), (0, 3), (0, 4)]);
    }

    /// The row-by-row fill gives exactly the points `contains` does, on random polygons
    /// (self-intersecting, repeated and collinear vertices included) and on the test shapes.
    #[test]
    fn row_fill_matches_the_point_test() {
        let mut rng = ChaCha8Rng::seed_from_u64(0x9E37_79B9_7F4A_7C15);
        let mut next = |n: u64| rng.gen_range(0..n) as i64;
        let mut shapes = vec![
            vec![[0, 0], [4, 0], [4, 4], [0, 4]],
            vec![[0, 0], [0, 4]],
            vec![[0, 0], [5, 0], [5, 5], [3, 5], [3, 2], [2, 2], [2, 5], [0, 5]],
        ];
        for _ in 0..400 {
            let len = 1 + next(12) as usize;
            shapes.push((0..len).map(|_| [next(15) - 3, next(15) - 3]).collect());
        }
        for points in shapes {
            let polygon = MplPolygon::from_contour(&points);
            let mut filled = Vec::new();
            polygon.for_each_inside(|x, y| filled.push((x, y)));
            let mut tested = Vec::new();
            if let Some((lo, hi)) = polygon.bounds() {
                for y in lo[1]..=hi[1] {
                    for x in lo[0]..=hi[0] {
                        if polygon.contains(x, y) {
                            tested.push((x, y));
                        }
                    }
                }
            }
            assert_eq!(filled, tested, "{points:?}");
        }
    }

    #[test]
    fn concave_polygon() {
        // A "U": the notch (2, 3) is outside.
        let u = MplPolygon::from_contour(&[[0, 0], [5, 0], [5, 5], [3, 5], [3, 2], [2, 2], [2, 5], [0, 5]]);
        assert!(u.contains(1, 3));
        assert!(u.contains(4, 3));
        assert!(!u.contains(6, 3));
        assert!(u.contains(2, 1));
        assert_eq!(u.bounds(), Some(([0, 0], [5, 5])));
    }
}
