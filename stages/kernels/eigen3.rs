//! Eigenvalues of symmetric 3 × 3 matrices in closed form: the trigonometric solution of the
//! characteristic cubic (Smith, CACM 1961). The Hessian blob filter needs the largest at every
//! voxel; a region's shape needs all three of its covariance.

/// The eigenvalues of the symmetric matrix with diagonal `[a00, a11, a22]` and off-diagonal
/// `[a01, a02, a12]`, largest first.
pub fn eigenvalues(diagonal: [f64; 3], off: [f64; 3]) -> [f64; 3] {
    match cubic(diagonal, off) {
        None => [diagonal[0]; 3],
        Some((q, p, phi)) => {
            let largest = q + 2.0 * p * phi.cos();
            let smallest = q + 2.0 * p * (phi + 2.0 * std::f64::consts::FRAC_PI_3).cos();
            // The trace is the sum of the three.
            [largest, 3.0 * q - largest - smallest, smallest]
        }
    }
}

/// The largest eigenvalue, as [`eigenvalues`] computes it.
pub fn largest_eigenvalue(diagonal: [f64; 3], off: [f64; 3]) -> f64 {
    match cubic(diagonal, off) {
        None => diagonal[0],
        Some((q, p, phi)) => q + 2.0 * p * phi.cos(),
    }
}

/// The mean eigenvalue `q`, the spread `p` and the angle `φ` with eigenvalues
/// `q + 2p·cos(φ + 2πk/3)`; `None` for a multiple of the identity.
fn cubic([a00, a11, a22]: [f64; 3], [a01, a02, a12]: [f64; 3]) -> Option<(f64, f64, f64)> {
    let p1 = a01 * a01 + a02 * a02 + a12 * a12;
    let q = (a00 + a11 + a22) / 3.0;
    let p2 = (a00 - q).powi(2) + (a11 - q).powi(2) + (a22 - q).powi(2) + 2.0 * p1;
    if p2 == 0.0 {
        return None;
    }
    let p = (p2 / 6.0).sqrt();
    // B = (A − qI)/p; r = det(B)/2 ∈ [−1, 1] up to rounding.
    let (b00, b11, b22, b01, b02, b12) = ((a00 - q) / p, (a11 - q) / p, (a22 - q) / p, a01 / p, a02 / p, a12 / p);
    let det = b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02) + b02 * (b01 * b12 - b11 * b02);
    Some((q, p, (det / 2.0).clamp(-1.0, 1.0).acos() / 3.0))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// R·diag(d)·Rᵀ for a rotation of 30° about z then 45° about x, as (diagonal, off-diagonal).
    fn rotated(d: [f64; 3]) -> ([f64; 3], [f64; 3]) {
        let (c1, s1, c2, s2) = (30f64.to_radians().cos(), 30f64.to_radians().sin(), 0.5f64.sqrt(), 0.5f64.sqrt());
        let r = [[c1, -s1, 0.0], [c2 * s1, c2 * c1, -s2], [s2 * s1, s2 * c1, c2]];
        let a = |i: usize, j: usize| (0..3).map(|k| r[i][k] * d[k] * r[j][k]).sum::<f64>();
        ([a(0, 0), a(1, 1), a(2, 2)], [a(0, 1), a(0, 2), a(1, 2)])
    }

    #[test]
    fn eigenvalues_of_known_matrices() {
        assert_eq!(largest_eigenvalue([-3.0, 2.0, -1.0], [0.0; 3]), 2.0);
        assert_eq!(eigenvalues([-4.0; 3], [0.0; 3]), [-4.0; 3]);
        let (diagonal, off) = rotated([-3.0, -1.0, 2.0]);
        let got = eigenvalues(diagonal, off);
        for (g, e) in got.iter().zip([2.0, -1.0, -3.0]) {
            assert!((g - e).abs() < 1e-12, "{got:?}");
        }
        assert_eq!(largest_eigenvalue(diagonal, off), got[0]);
        // A repeated pair.
        let got = eigenvalues(rotated([5.0, 1.0, 1.0]).0, rotated([5.0, 1.0, 1.0]).1);
        assert!(got.iter().zip([5.0, 1.0, 1.0]).all(|(g, e)| (g - e).abs() < 1e-9), "{got:?}");
    }
}
