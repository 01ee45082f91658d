//! The smoothed 3-D total variation `Σ √(|∇σ|² + ε²)` over an `n³` lattice (index
//! `x + n·(y + n·z)`), forward differences in lattice steps with none across the far faces, and
//! its gradient `∂TV/∂σ_i = Σ_a p_a(i − e_a) − p_a(i)` with `p = ∇σ / √(|∇σ|² + ε²)`.
//!
//! Computed a z-plane at a time: a plane's gradient needs `p` on that plane and the one below,
//! so a task that owns planes `z0..z1` computes `p` once on each and once on `z0 − 1`.

/// `p` on one z-plane, a component per array (index `x + n·y`).
pub struct PlaneDirections {
    pub x: Vec<f32>,
    pub y: Vec<f32>,
    pub z: Vec<f32>,
    /// `1 / √(|∇σ|² + ε²)`.
    pub inverse: Vec<f32>,
}

impl PlaneDirections {
    pub fn new(n: usize) -> PlaneDirections {
        PlaneDirections { x: vec![0.0; n * n], y: vec![0.0; n * n], z: vec![0.0; n * n], inverse: vec![0.0; n * n] }
    }

    /// `p` on plane `z` of `sigma`.
    pub fn compute(&mut self, sigma: &[f32], n: usize, z: usize, epsilon: f32) {
        let plane = n * n;
        let at = &sigma[z * plane..(z + 1) * plane];
        // Beyond a far face there is no difference: there a node reads itself.
        let above = if z + 1 < n { &sigma[(z + 1) * plane..(z + 2) * plane] } else { at };
        let eps2 = epsilon * epsilon;
        for y in 0..n {
            let r = y * n..(y + 1) * n;
            let (row, up) = (&at[r.clone()], &above[r.clone()]);
            let next_row = if y + 1 < n { &at[r.start + n..r.end + n] } else { row };
            let (px, py, pz) = (&mut self.x[r.clone()], &mut self.y[r.clone()], &mut self.z[r.clone()]);
            let inverse = &mut self.inverse[r];
            let mut direction = |x: usize, dx: f32| {
                let (dy, dz) = (next_row[x] - row[x], up[x] - row[x]);
                let i = 1.0 / (dx * dx + dy * dy + dz * dz + eps2).sqrt();
                (px[x], py[x], pz[x], inverse[x]) = (dx * i, dy * i, dz * i, i);
            };
            let last = n - 1;
            for x in 0..last {
                direction(x, row[x + 1] - row[x]);
            }
            direction(last, 0.0);
        }
    }

    /// `Σ √(|∇σ|² + ε²)` over the plane, in f64.
    pub fn smoothed_sum(&self) -> f64 {
        self.inverse.iter().map(|&i| 1.0 / f64::from(i)).sum()
    }
}

/// The TV's gradient and a bound on its majoriser's curvature along row `y` of a plane whose `p`
/// is `at`, `below` being the plane under it's (`None` on the lowest plane), into `gradient`
/// and `curvature` (`n` each). The majoriser is `Σ |∇σ|²/(2m)` with m frozen at the `p`'s σ;
/// the bound is `6/m` of a node's own differences and `2/m` of each lower neighbour's that
/// reach it, at most `12/ε`, the smoothed TV's own.
pub fn row_terms(
    at: &PlaneDirections,
    below: Option<&PlaneDirections>,
    n: usize,
    y: usize,
    gradient: &mut [f32],
    curvature: &mut [f32],
) {
    let r = y * n..(y + 1) * n;
    let (gradient, curvature) = (&mut gradient[..n], &mut curvature[..n]);
    let (px, py, pz, inverse) = (&at.x[r.clone()], &at.y[r.clone()], &at.z[r.clone()], &at.inverse[r.clone()]);
    for x in 0..n {
        gradient[x] = -(px[x] + py[x] + pz[x]);
        curvature[x] = 6.0 * inverse[x];
    }
    for x in 1..n {
        gradient[x] += px[x - 1];
        curvature[x] += 2.0 * inverse[x - 1];
    }
    if y > 0 {
        let (py, inverse) = (&at.y[r.start - n..r.start], &at.inverse[r.start - n..r.start]);
        for x in 0..n {
            gradient[x] += py[x];
            curvature[x] += 2.0 * inverse[x];
        }
    }
    if let Some(b) = below {
        let (pz, inverse) = (&b.z[r.clone()], &b.inverse[r]);
        for x in 0..n {
            gradient[x] += pz[x];
            curvature[x] += 2.0 * inverse[x];
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The TV and its gradient over the whole lattice, plane by plane.
    fn tv(sigma: &[f32], n: usize, epsilon: f32) -> (f64, Vec<f32>) {
        let (mut below, mut at) = (PlaneDirections::new(n), PlaneDirections::new(n));
        let mut sum = 0.0;
        let mut g = vec![0.0; sigma.len()];
        let mut curvature = vec![0.0; n];
        for z in 0..n {
            at.compute(sigma, n, z, epsilon);
            sum += at.smoothed_sum();
            for y in 0..n {
                let row = n * (y + n * z);
                row_terms(&at, (z > 0).then_some(&below), n, y, &mut g[row..row + n], &mut curvature);
            }
            std::mem::swap(&mut below, &mut at);
        }
        (sum, g)
    }

    #[test]
    fn the_gradient_matches_finite_differences() {
        let n = 4;
        let sigma: Vec<f32> = (0..64).map(|i| ((i * 29) % 13) as f32 * 0.07).collect();
        let wide: Vec<f64> = sigma.iter().map(|&v| f64::from(v)).collect();
        // The sum in f64 straight from the definition, for the finite differences.
        let plain = |s: &[f64]| -> f64 {
            let mut sum = 0.0;
            for i in 0..64 {
                let c = [i % n, (i / n) % n, i / (n * n)];
                let d: Vec<f64> =
                    (0..3).map(|a| if c[a] + 1 < n { s[i + [1, n, n * n][a]] - s[i] } else { 0.0 }).collect();
                sum += (d.iter().map(|v| v * v).sum::<f64>() + 0.05f64 * 0.05).sqrt();
            }
            sum
        };
        let (sum, gradient) = tv(&sigma, n, 0.05);
        assert!((sum - plain(&wide)).abs() < 1e-5 * sum, "{sum} against {}", plain(&wide));
        for i in [0, 5, 21, 42, 63] {
            let h = 1e-6;
            let (mut up, mut down) = (wide.clone(), wide.clone());
            up[i] += h;
            down[i] -= h;
            let numeric = (plain(&up) - plain(&down)) / (2.0 * h);
            assert!((numeric - f64::from(gradient[i])).abs() < 1e-5, "node {i}: {numeric} against {}", gradient[i]);
        }
    }
}
