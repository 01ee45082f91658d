//! Trilinear interpolation on a lattice, shared by the DRR ray march (sampling the CT) and the
//! training renderer (sampling the composed field and scattering gradients back): values live
//! at integer indices; a continuous index is clamped to `[0, n − 1]` per axis, so beyond the
//! outermost nodes the edge values hold.

/// The cell holding continuous index `q` on a lattice of `dims` (x fastest): the linear index
/// of its lower corner node and the fractional position inside it.
#[inline]
pub fn cell(q: [f64; 3], dims: [usize; 3]) -> (usize, [f64; 3]) {
    let mut base = [0usize; 3];
    let mut frac = [0f64; 3];
    for a in 0..3 {
        let x = q[a].clamp(0.0, (dims[a] - 1) as f64);
        let b = (x as usize).min(dims[a].saturating_sub(2));
        base[a] = b;
        frac[a] = x - b as f64;
    }
    (base[0] + dims[0] * (base[1] + dims[1] * base[2]), frac)
}

/// The 8 corner nodes of the cell at `origin` and their trilinear weights for `frac` (an axis
/// with a single node repeats it with the other weight).
#[inline]
pub fn corners(origin: usize, frac: [f64; 3], dims: [usize; 3]) -> [(usize, f64); 8] {
    let sx = usize::from(dims[0] > 1);
    let sy = dims[0] * usize::from(dims[1] > 1);
    let sz = dims[0] * dims[1] * usize::from(dims[2] > 1);
    let [fx, fy, fz] = frac;
    let (gx, gy, gz) = (1.0 - fx, 1.0 - fy, 1.0 - fz);
    [
        (origin, gx * gy * gz),
        (origin + sx, fx * gy * gz),
        (origin + sy, gx * fy * gz),
        (origin + sx + sy, fx * fy * gz),
        (origin + sz, gx * gy * fz),
        (origin + sx + sz, fx * gy * fz),
        (origin + sy + sz, gx * fy * fz),
        (origin + sx + sy + sz, fx * fy * fz),
    ]
}

/// The interpolated value of `data` (on `dims`) at continuous index `q`.
pub fn sample(data: &[f32], dims: [usize; 3], q: [f64; 3]) -> f64 {
    let (origin, frac) = cell(q, dims);
    corners(origin, frac, dims).iter().map(|&(i, w)| f64::from(data[i]) * w).sum()
}
