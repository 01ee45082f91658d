//! Randomness with a fixed address. Owns the phantom's two kinds of noise:
//!
//! * [`fbm`]: smooth, spatially correlated value noise at a patient-independent position
//!   (lung parenchyma texture). A pure function of (seed, position), so any voxel can be
//!   evaluated in any order or thread.
//! * [`add_scanner_noise`]: CT quantum noise, Gaussian with a standard deviation in HU and the
//!   fine grain of a reconstruction kernel, drawn from one ChaCha stream per slice so the result
//!   does not depend on how rayon schedules slices.
//!
//! [`stream`] derives the seed of every other random stream (vessel trees) from the phantom
//! seed and a name, so adding a stream never shifts another.

use crate::volume::Volume;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

/// SplitMix64 finaliser: a well-mixed 64-bit hash step.
fn mix64(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// A 64-bit seed for the stream called `name`, number `index`, of phantom seed `seed`.
pub(crate) fn stream_seed(seed: u64, name: &str, index: u64) -> u64 {
    let mut h = mix64(seed);
    for b in name.bytes() {
        h = mix64(h ^ u64::from(b));
    }
    mix64(h ^ index)
}

/// An independent random stream (see [`stream_seed`]).
pub(crate) fn stream(seed: u64, name: &str, index: u64) -> ChaCha8Rng {
    ChaCha8Rng::seed_from_u64(stream_seed(seed, name, index))
}

/// Value at lattice point (x, y, z), uniform in [−1, 1].
fn lattice(seed: u64, x: i32, y: i32, z: i32) -> f32 {
    let h = mix64(seed ^ mix64((x as u32 as u64) | ((y as u32 as u64) << 32)) ^ (z as u32 as u64));
    (h >> 40) as f32 / (1u64 << 23) as f32 - 1.0
}

/// Value noise: lattice values joined by smoothstep-weighted trilinear interpolation, one
/// lattice cell per unit of `p`. Mean 0, range [−1, 1], standard deviation ≈ 0.37.
pub(crate) fn value_noise(seed: u64, p: [f32; 3]) -> f32 {
    let cell = p.map(|c| c.floor());
    let i = cell.map(|c| c as i32);
    let w: [f32; 3] = std::array::from_fn(|a| {
        let t = p[a] - cell[a];
        t * t * (3.0 - 2.0 * t)
    });
    let lerp = |a: f32, b: f32, t: f32| a + (b - a) * t;
    let mut xy = [0.0f32; 4];
    for (n, v) in xy.iter_mut().enumerate() {
        let (dy, dz) = ((n & 1) as i32, (n >> 1) as i32);
        let a = lattice(seed, i[0], i[1] + dy, i[2] + dz);
        let b = lattice(seed, i[0] + 1, i[1] + dy, i[2] + dz);
        *v = lerp(a, b, w[0]);
    }
    lerp(lerp(xy[0], xy[1], w[1]), lerp(xy[2], xy[3], w[1]), w[2])
}

/// Fractal value noise with unit standard deviation (approximately): `octaves` layers, the
/// first with features `period_mm` across, each next one half as large and half as strong.
pub(crate) fn fbm(seed: u64, p_mm: [f32; 3], period_mm: f32, octaves: u32) -> f32 {
    let mut sum = 0.0;
    let mut norm = 0.0;
    let mut amplitude = 1.0;
    let mut freq = 1.0 / period_mm;
    for octave in 0..octaves {
        sum += amplitude * value_noise(seed.wrapping_add(u64::from(octave)), p_mm.map(|c| c * freq));
        norm += amplitude * amplitude;
        amplitude *= 0.5;
        freq *= 2.0;
    }
    // One octave has sd ≈ 0.37 (see `value_noise`).
    sum / (0.37 * norm.sqrt())
}

/// Standard normal deviates by Marsaglia's polar method, two per accepted pair.
struct Gaussian {
    spare: Option<f64>,
}

impl Gaussian {
    fn sample(&mut self, rng: &mut ChaCha8Rng) -> f64 {
        if let Some(s) = self.spare.take() {
            return s;
        }
        loop {
            let u = 2.0 * rng.gen::<f64>() - 1.0;
            let v = 2.0 * rng.gen::<f64>() - 1.0;
            let s = u * u + v * v;
            if s > 0.0 && s < 1.0 {
                let f = (-2.0 * s.ln() / s).sqrt();
                self.spare = Some(v * f);
                return u * f;
            }
        }
    }
}

/// Add CT noise of standard deviation `sd_hu` to every voxel. White Gaussian noise is smoothed
/// in-plane by the binomial kernel [1 2 1]ᵀ[1 2 1]/16 (a reconstruction kernel's ~1-voxel grain)
/// and rescaled so the added noise keeps standard deviation `sd_hu`. Slice `k` uses its own
/// stream, so the result is the same whatever the thread count.
pub(crate) fn add_scanner_noise(ct: &mut Volume<f32>, seed: u64, sd_hu: f32) {
    if sd_hu <= 0.0 {
        return;
    }
    let [cols, rows, _] = ct.geometry.dims;
    if cols == 0 || rows == 0 {
        return;
    }
    // The binomial kernel's weights have sum of squares (6/16)², so it scales sd by 6/16.
    let gain = f64::from(sd_hu) * 16.0 / 6.0;
    ct.data.par_chunks_mut(cols * rows).enumerate().for_each(|(k, slice)| {
        let mut rng = stream(seed, "scanner noise", k as u64);
        let mut gauss = Gaussian { spare: None };
        // One voxel of margin so every output voxel sees a full kernel.
        let (w, h) = (cols + 2, rows + 2);
        let white: Vec<f32> = (0..w * h).map(|_| gauss.sample(&mut rng) as f32).collect();
        // Horizontal pass [1 2 1], then vertical.
        let mut horiz = vec![0.0f32; cols * h];
        for y in 0..h {
            let row = &white[y * w..(y + 1) * w];
            for x in 0..cols {
                horiz[y * cols + x] = row[x] + 2.0 * row[x + 1] + row[x + 2];
            }
        }
        let scale = (gain / 16.0) as f32;
        for y in 0..rows {
            for x in 0..cols {
                let v = horiz[y * cols + x] + 2.0 * horiz[(y + 1) * cols + x] + horiz[(y + 2) * cols + x];
                slice[y * cols + x] += v * scale;
            }
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn value_noise_is_smooth_centred_and_repeatable() {
        let seed = 7;
        let mut sum = 0.0;
        let mut sum2 = 0.0;
        let n = 20_000;
        for s in 0..n {
            let p = [s as f32 * 0.37, (s % 97) as f32 * 0.53, (s % 13) as f32 * 1.1];
            let v = value_noise(seed, p);
            assert!((-1.0..=1.0).contains(&v));
            assert_eq!(v, value_noise(seed, p));
            sum += v as f64;
            sum2 += (v * v) as f64;
            // Correlated: a small step changes the value little.
            let q = [p[0] + 0.01, p[1], p[2]];
            assert!((value_noise(seed, q) - v).abs() < 0.05);
        }
        let mean = sum / n as f64;
        let sd = (sum2 / n as f64 - mean * mean).sqrt();
        assert!(mean.abs() < 0.03, "mean {mean}");
        assert!((sd - 0.37).abs() < 0.06, "sd {sd}");
    }

    #[test]
    fn stream_seeds_differ_by_name_and_index() {
        assert_ne!(stream_seed(1, "a", 0), stream_seed(1, "b", 0));
        assert_ne!(stream_seed(1, "a", 0), stream_seed(1, "a", 1));
        assert_ne!(stream_seed(1, "a", 0), stream_seed(2, "a", 0));
    }
}
