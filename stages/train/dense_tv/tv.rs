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

    /// `p` on plane `z` of `sigma`; returns `Σ √(|∇σ|² + ε²)` over the plane, in f64.
    pub fn compute(&mut self, sigma: &[f32], n: usize, z: usize, epsilon: f32) -> f64 {
        let plane = n * n;
        let at = &sigma[z * plane..];
        let above = (z + 1 < n).then(|| &sigma[(z + 1) * plane..(z + 2) * plane]);
        let eps2 = epsilon * epsilon;
        let mut sum = 0.0f64;
        for y in 0..n {
            let row = &at[y * n..(y + 1) * n];
            let next_row = (y + 1 < n).then(|| &at[(y + 1) * n..(y + 2) * n]);
            let mut row_sum = 0.0f32;
            for x in 0..n {
                let s = row[x];
                let dx = if x + 1 < n { row[x + 1] - s } else { 0.0 };
                let dy = next_row.map_or(0.0, |r| r[x] - s);
                let dz = above.map_or(0.0, |a| a[x + n * y] - s);
                let m = (dx * dx + dy * dy + dz * dz + eps2).sqrt();
                let i = x + n * y;
                let inverse = 1.0 / m;
                (self.x[i], self.y[i], self.z[i], self.inverse[i]) =
                    (dx * inverse, dy * inverse, dz * inverse, inverse);
                row_sum += m;
            }
            sum += f64::from(row_sum);
        }
        sum
    }
}

/// The TV gradient at node `(x, y)` of a plane whose `p` is `at`, `below` being the plane
/// under it's (`None` on the lowest plane).
#[inline(always)]
pub fn gradient(at: &PlaneDirections, below: Option<&PlaneDirections>, n: usize, x: usize, y: usize) -> f32 {
    let i = x + n * y;
    let from_x = if x > 0 { at.x[i - 1] } else { 0.0 };
    let from_y = if y > 0 { at.y[i - n] } else { 0.0 };
    let from_z = below.map_or(0.0, |b| b.z[i]);
    (from_x - at.x[i]) + (from_y - at.y[i]) + (from_z - at.z[i])
}

/// A bound on the curvature at node `(x, y)` of the TV's quadratic majoriser at the `p`'s σ
/// (`Σ |∇σ|²/(2m)` with m frozen): `6/m` of its own differences and `2/m` of each lower
/// neighbour's that reach it. At most `12/ε`, the smoothed TV's own bound.
#[inline(always)]
pub fn majoriser_curvature(at: &PlaneDirections, below: Option<&PlaneDirections>, n: usize, x: usize, y: usize) -> f32 {
    let i = x + n * y;
    let from_x = if x > 0 { at.inverse[i - 1] } else { 0.0 };
    let from_y = if y > 0 { at.inverse[i - n] } else { 0.0 };
    let from_z = below.map_or(0.0, |b| b.inverse[i]);
    6.0 * at.inverse[i] + 2.0 * (from_x + from_y + from_z)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The TV and its gradient over the whole lattice, plane by plane.
    fn tv(sigma: &[f32], n: usize, epsilon: f32) -> (f64, Vec<f32>) {
        let (mut below, mut at) = (PlaneDirections::new(n), PlaneDirections::new(n));
        let mut sum = 0.0;
        let mut g = vec![0.0; sigma.len()];
        for z in 0..n {
            sum += at.compute(sigma, n, z, epsilon);
            for y in 0..n {
                for x in 0..n {
                    g[x + n * (y + n * z)] = gradient(&at, (z > 0).then_some(&below), n, x, y);
                }
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
