//! Binary dilation, erosion and closing with a ball (SPEC §3 sweep): the structuring element of
//! radius `r` is every integer offset with x² + y² + z² ≤ r², and the results equal scipy's
//! `binary_dilation` / `binary_erosion` (border value 0) and, for [`close`],
//! `binary_closing(np.pad(mask, r), ball)[r:-r, r:-r, r:-r]`.
//!
//! A ball is not separable, but it is a union of x-segments: for each `(dy, dz)` of the disk
//! dy² + dz² ≤ r², the offsets `|dx| ≤ ⌊√(r² − dy² − dz²)⌋`. So each row is dilated (or eroded)
//! along x once per half-width, 64 voxels to a machine word, and a voxel's result is the OR (or
//! AND) of 13 such rows for r = 2 — a few microseconds for a 64³ volume instead of 33 lookups
//! per voxel.

/// The offsets `[dx, dy, dz]` of the ball of radius `radius`, x fastest: what scipy's
/// `structure` holds, for reference and tests (the kernels use its x-segments).
pub fn ball_offsets(radius: usize) -> Vec<[i64; 3]> {
    let r = radius as i64;
    let mut out = Vec::new();
    for dz in -r..=r {
        for dy in -r..=r {
            for dx in -r..=r {
                if dx * dx + dy * dy + dz * dz <= r * r {
                    out.push([dx, dy, dz]);
                }
            }
        }
    }
    out
}

/// `scipy.ndimage.binary_dilation(mask, ball(radius))`: a voxel is set when any voxel of the
/// ball around it is. Nothing outside the volume is set.
pub fn dilate(mask: &[bool], dims: [usize; 3], radius: usize) -> Vec<bool> {
    Rows::from_mask(mask, dims, 0).dilate(radius).to_mask()
}

/// `scipy.ndimage.binary_erosion(mask, ball(radius))` (border value 0): a voxel stays set when
/// every voxel of the ball around it is set — so voxels within `radius` of the volume's border
/// are always cleared.
pub fn erode(mask: &[bool], dims: [usize; 3], radius: usize) -> Vec<bool> {
    Rows::from_mask(mask, dims, 0).erode(radius).to_mask()
}

/// Closing (dilation, then erosion) on the mask zero-padded by `radius` voxels on every side,
/// cropped back: the closing of the mask in an unbounded empty space, so the volume's border
/// erodes nothing. Equals `binary_closing(np.pad(mask, r), ball)[r:-r, r:-r, r:-r]`.
pub fn close(mask: &[bool], dims: [usize; 3], radius: usize) -> Vec<bool> {
    Rows::from_mask(mask, dims, radius).dilate(radius).erode(radius).to_mask()
}

/// The ball as x-segments: `(dy, dz, half_width)` for every `(dy, dz)` of its disk.
fn disk_rows(radius: usize) -> Vec<(i64, i64, usize)> {
    let r = radius as i64;
    let mut out = Vec::new();
    for dz in -r..=r {
        for dy in -r..=r {
            let left = r * r - dy * dy - dz * dz;
            if left >= 0 {
                out.push((dy, dz, left.isqrt() as usize));
            }
        }
    }
    out
}

/// A boolean volume as bit rows: row `(y, z)` holds x in `words` u64s, bit `x % 64` of word
/// `x / 64`. Bits at `x ≥ nx` are always 0, so shifting them into a row brings in "outside".
/// Rows are stored y-fastest, so the rows of one z-plane are one contiguous run of words.
#[derive(Clone)]
struct Rows {
    dims: [usize; 3],
    words: usize,
    bits: Vec<u64>,
    /// The voxels the caller's mask was padded by (per side, every axis).
    pad: usize,
    /// Input dims before padding.
    inner: [usize; 3],
}

impl Rows {
    fn empty(dims: [usize; 3], pad: usize, inner: [usize; 3]) -> Self {
        let words = dims[0].div_ceil(64);
        Self { dims, words, bits: vec![0; words * dims[1] * dims[2]], pad, inner }
    }

    /// `mask` (x-fastest on `dims`) placed `pad` voxels in from every side of a zero volume.
    fn from_mask(mask: &[bool], dims: [usize; 3], pad: usize) -> Self {
        let [nx, ny, nz] = dims;
        assert_eq!(mask.len(), nx * ny * nz, "mask holds {} voxels, dims {dims:?} need {}", mask.len(), nx * ny * nz);
        let mut rows = Self::empty(dims.map(|n| n + 2 * pad), pad, dims);
        if nx == 0 {
            return rows;
        }
        let mut packed = vec![0u64; rows.words];
        for (r, src) in mask.chunks_exact(nx).enumerate() {
            // Whole words of 64 voxels at a time (a loop the compiler vectorises), then moved
            // `pad` bits up into the padded row.
            for (word, chunk) in packed.iter_mut().zip(src.chunks(64)) {
                *word = pack(chunk);
            }
            shift(&packed, pad, true, rows.row_mut(r % ny + pad, r / ny + pad));
        }
        rows
    }

    /// The caller's voxels again: the inner `dims`, without the padding.
    fn to_mask(&self) -> Vec<bool> {
        let (pad, [nx, ny, nz]) = (self.pad, self.inner);
        let mut out = vec![false; nx * ny * nz];
        if nx == 0 {
            return out;
        }
        let mut packed = vec![0u64; self.words];
        for (r, dst) in out.chunks_exact_mut(nx).enumerate() {
            shift(self.row(r % ny + pad, r / ny + pad), pad, false, &mut packed);
            for (chunk, &word) in dst.chunks_mut(64).zip(&packed) {
                unpack(word, chunk);
            }
        }
        out
    }

    fn row(&self, y: usize, z: usize) -> &[u64] {
        let start = self.words * (y + self.dims[1] * z);
        &self.bits[start..start + self.words]
    }

    fn row_mut(&mut self, y: usize, z: usize) -> &mut [u64] {
        let start = self.words * (y + self.dims[1] * z);
        &mut self.bits[start..start + self.words]
    }

    /// Mask of the valid bits of a row's last word.
    fn tail_mask(&self) -> u64 {
        match self.dims[0] % 64 {
            0 => u64::MAX,
            k => (1u64 << k) - 1,
        }
    }

    /// Every row dilated (`grow`) or eroded along x by the segment `|dx| ≤ w`.
    fn along_x(&self, w: usize, grow: bool) -> Vec<u64> {
        let mut out = self.bits.clone();
        let n = self.words;
        if w == 0 || n == 0 {
            return out;
        }
        let tail = self.tail_mask();
        let (mut up, mut down) = (vec![0u64; n], vec![0u64; n]);
        for (src, dst) in self.bits.chunks_exact(n).zip(out.chunks_exact_mut(n)) {
            for s in 1..=w {
                if s < 64 {
                    // The usual case, inline: word k takes the bits carried over from k ∓ 1.
                    for k in 0..n {
                        let lower = if k > 0 { src[k - 1] >> (64 - s) } else { 0 };
                        let higher = if k + 1 < n { src[k + 1] << (64 - s) } else { 0 };
                        let (u, d) = (src[k] << s | lower, src[k] >> s | higher);
                        dst[k] = if grow { dst[k] | u | d } else { dst[k] & u & d };
                    }
                } else {
                    shift(src, s, true, &mut up);
                    shift(src, s, false, &mut down);
                    combine_words(dst, &up, grow);
                    combine_words(dst, &down, grow);
                }
            }
            dst[n - 1] &= tail;
        }
        out
    }

    /// Binary dilation by the ball: the OR over the disk `(dy, dz)` of the x-dilated rows at
    /// `(y − dy, z − dz)` (the ball is symmetric, so these are its reflected offsets too).
    fn dilate(&self, radius: usize) -> Rows {
        self.by_disk(radius, true)
    }

    /// Binary erosion by the ball: the AND over the disk of the x-eroded rows at
    /// `(y + dy, z + dz)`, where a row outside the volume is all zeros (scipy's border value 0).
    fn erode(&self, radius: usize) -> Rows {
        self.by_disk(radius, false)
    }

    /// One whole z-plane of rows at a time: for a disk offset, the rows of plane z that have a
    /// partner row inside the volume are one contiguous run of words, and so are the partners.
    fn by_disk(&self, radius: usize, grow: bool) -> Rows {
        let disk = disk_rows(radius);
        let mut by_width: Vec<Option<Vec<u64>>> = vec![None; radius + 1];
        for &(_, _, w) in &disk {
            if by_width[w].is_none() {
                by_width[w] = Some(self.along_x(w, grow));
            }
        }
        let [_, ny, nz] = self.dims.map(|n| n as i64);
        let words = self.words;
        let mut out = Rows::empty(self.dims, self.pad, self.inner);
        if !grow {
            let tail = self.tail_mask();
            for row in out.bits.chunks_exact_mut(words.max(1)) {
                row.fill(u64::MAX);
                if let Some(last) = row.last_mut() {
                    *last = tail;
                }
            }
        }
        let plane = words * ny as usize;
        for &(dy, dz, w) in &disk {
            let src = by_width[w].as_ref().expect("every width of the disk is computed");
            // Dilation reads row (y − dy, z − dz), erosion row (y + dy, z + dz).
            let (dy, dz) = if grow { (-dy, -dz) } else { (dy, dz) };
            // Rows y of the plane whose partner y + dy lies in [0, ny).
            let (y0, y1) = (0.max(-dy), ny.min(ny - dy));
            for z in 0..nz {
                let dst = &mut out.bits[z as usize * plane..(z as usize + 1) * plane];
                let zz = z + dz;
                if !(0..nz).contains(&zz) || y0 >= y1 {
                    if !grow {
                        dst.fill(0);
                    }
                    continue;
                }
                let run = |a: i64, b: i64| a as usize * words..b as usize * words;
                let from = &src[zz as usize * plane..(zz as usize + 1) * plane];
                combine_words(&mut dst[run(y0, y1)], &from[run(y0 + dy, y1 + dy)], grow);
                if !grow {
                    dst[run(0, y0)].fill(0);
                    dst[run(y1, ny)].fill(0);
                }
            }
        }
        out
    }
}

/// `dst |= src` (`grow`) or `dst &= src`, word by word.
fn combine_words(dst: &mut [u64], src: &[u64], grow: bool) {
    if grow {
        dst.iter_mut().zip(src).for_each(|(d, s)| *d |= s);
    } else {
        dst.iter_mut().zip(src).for_each(|(d, s)| *d &= s);
    }
}

/// `out[x] = src[x − s]` when `up` (towards higher x), else `out[x] = src[x + s]`; zeros shift
/// in. `src` and `out` have the same length.
fn shift(src: &[u64], s: usize, up: bool, out: &mut [u64]) {
    let n = src.len();
    let (q, b) = (s / 64, (s % 64) as u32);
    out.fill(0);
    if q >= n {
        return;
    }
    // Whole words first, then the bits within words (b = 0 needs no carry: `>> 64` overflows).
    if up {
        out[q..].copy_from_slice(&src[..n - q]);
        if b > 0 {
            for k in (1..n).rev() {
                out[k] = out[k] << b | out[k - 1] >> (64 - b);
            }
            out[0] <<= b;
        }
    } else {
        out[..n - q].copy_from_slice(&src[q..]);
        if b > 0 {
            for k in 0..n - 1 {
                out[k] = out[k] >> b | out[k + 1] << (64 - b);
            }
            out[n - 1] >>= b;
        }
    }
}

/// Up to 64 booleans as the low bits of a word (element `b` → bit `b`).
fn pack(chunk: &[bool]) -> u64 {
    let mut word = 0;
    let mut bytes = chunk.chunks_exact(8);
    for (i, eight) in bytes.by_ref().enumerate() {
        // Eight 0/1 bytes as one u64; the multiply moves byte i's bit to bit 56 + i with no
        // two partial products on one bit (so no carries), and the shift keeps those eight.
        let v = u64::from_le_bytes(std::array::from_fn(|k| u8::from(eight[k])));
        word |= (v.wrapping_mul(0x0102_0408_1020_4080) >> 56) << (8 * i);
    }
    let done = chunk.len() / 8 * 8;
    for (b, &v) in bytes.remainder().iter().enumerate() {
        word |= u64::from(v) << (done + b);
    }
    word
}

/// The low `chunk.len()` bits of `word` as booleans (bit `b` → element `b`).
fn unpack(word: u64, chunk: &mut [bool]) {
    const BYTE: [[bool; 8]; 256] = {
        let mut table = [[false; 8]; 256];
        let mut v = 0;
        while v < 256 {
            let mut b = 0;
            while b < 8 {
                table[v][b] = v >> b & 1 == 1;
                b += 1;
            }
            v += 1;
        }
        table
    };
    let done = chunk.len() / 8 * 8;
    let mut bytes = chunk.chunks_exact_mut(8);
    for (i, eight) in bytes.by_ref().enumerate() {
        eight.copy_from_slice(&BYTE[(word >> (8 * i)) as u8 as usize]);
    }
    for (b, d) in bytes.into_remainder().iter_mut().enumerate() {
        *d = word >> (done + b) & 1 == 1;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// Dilation or erosion straight from the definition, with the offset list.
    fn reference(mask: &[bool], dims: [usize; 3], radius: usize, grow: bool) -> Vec<bool> {
        let ball = ball_offsets(radius);
        let [nx, ny, nz] = dims.map(|n| n as i64);
        let at = |x: i64, y: i64, z: i64| {
            (0..nx).contains(&x)
                && (0..ny).contains(&y)
                && (0..nz).contains(&z)
                && mask[(x + nx * (y + ny * z)) as usize]
        };
        let mut out = Vec::with_capacity(mask.len());
        for z in 0..nz {
            for y in 0..ny {
                for x in 0..nx {
                    let mut hits = ball.iter().map(|o| at(x + o[0], y + o[1], z + o[2]));
                    out.push(if grow { hits.any(|v| v) } else { hits.all(|v| v) });
                }
            }
        }
        out
    }

    fn pad(mask: &[bool], dims: [usize; 3], p: usize) -> (Vec<bool>, [usize; 3]) {
        let pd = dims.map(|n| n + 2 * p);
        let mut out = vec![false; pd.iter().product()];
        for z in 0..dims[2] {
            for y in 0..dims[1] {
                for x in 0..dims[0] {
                    out[x + p + pd[0] * (y + p + pd[1] * (z + p))] = mask[x + dims[0] * (y + dims[1] * z)];
                }
            }
        }
        (out, pd)
    }

    fn crop(mask: &[bool], pd: [usize; 3], p: usize) -> Vec<bool> {
        let mut out = Vec::new();
        for z in p..pd[2] - p {
            for y in p..pd[1] - p {
                for x in p..pd[0] - p {
                    out.push(mask[x + pd[0] * (y + pd[1] * z)]);
                }
            }
        }
        out
    }

    #[test]
    fn the_radius_2_ball_is_the_specs() {
        let ball = ball_offsets(2);
        assert_eq!(ball.len(), 33); // 1 + 6 + 12 + 8 + 6: |o|² ∈ {0, 1, 2, 3, 4}
        assert!(ball.iter().all(|o| o.iter().map(|c| c * c).sum::<i64>() <= 4));
        let widths: usize = disk_rows(2).iter().map(|&(_, _, w)| 2 * w + 1).sum();
        assert_eq!(widths, 33);
        assert_eq!(ball_offsets(0), vec![[0, 0, 0]]);
    }

    #[test]
    fn single_voxel_dilates_to_the_ball_and_erodes_away() {
        let dims = [7, 7, 7];
        let mut m = vec![false; 343];
        m[3 + 7 * (3 + 7 * 3)] = true;
        let d = dilate(&m, dims, 2);
        assert_eq!(d.iter().filter(|&&v| v).count(), 33);
        assert!(erode(&m, dims, 1).iter().all(|&v| !v));
        assert_eq!(erode(&d, dims, 2), m);
        assert_eq!(close(&m, dims, 2), m); // a ball's closing of one voxel is that voxel
    }

    #[test]
    fn empty_full_and_border() {
        let dims = [5, 4, 3];
        let (empty, full) = (vec![false; 60], vec![true; 60]);
        assert_eq!(dilate(&empty, dims, 2), empty);
        assert_eq!(close(&empty, dims, 2), empty);
        assert_eq!(dilate(&full, dims, 2), full);
        // Unpadded erosion clears everything within the radius of the border…
        assert_eq!(erode(&full, dims, 1), reference(&full, dims, 1, false));
        assert!(erode(&full, dims, 2).iter().all(|&v| !v));
        // …closing, padded, keeps a full volume full.
        assert_eq!(close(&full, dims, 2), full);
    }

    #[test]
    fn closing_fills_a_gap_narrower_than_the_ball() {
        // Two slabs two voxels apart along x, filling the volume's y and z extent.
        let dims = [8, 9, 9];
        let m: Vec<bool> = (0..8 * 9 * 9).map(|i| matches!(i % 8, 0..=2 | 5..=7)).collect();
        let closed = close(&m, dims, 2);
        // Closing only adds, and the border clears nothing; the gap fills where the ball fits
        // between the slabs (2 voxels in from the y and z ends: beyond those, empty space).
        assert!(m.iter().zip(&closed).all(|(&a, &b)| !a || b));
        for z in 2..7 {
            for y in 2..7 {
                assert!(closed[3 + 8 * (y + 9 * z)] && closed[4 + 8 * (y + 9 * z)], "({y}, {z})");
            }
        }
        assert!(!closed[3]); // at the corner the gap stays open
    }

    #[test]
    fn matches_the_definition_on_random_masks() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(2);
        // nx of 1, 63, 64, 65 and 130 cover one word, its edge and several words.
        for dims in [[1, 5, 4], [63, 3, 4], [64, 4, 3], [65, 5, 5], [130, 3, 3], [9, 11, 10]] {
            for &density in &[0.1, 0.5, 0.9] {
                let n: usize = dims.iter().product();
                let m: Vec<bool> = (0..n).map(|_| rng.gen_bool(density)).collect();
                for radius in [0, 1, 2, 3] {
                    assert_eq!(
                        dilate(&m, dims, radius),
                        reference(&m, dims, radius, true),
                        "dilate {dims:?} r {radius}"
                    );
                    assert_eq!(
                        erode(&m, dims, radius),
                        reference(&m, dims, radius, false),
                        "erode {dims:?} r {radius}"
                    );
                    let (padded, pd) = pad(&m, dims, radius);
                    let closed = reference(&reference(&padded, pd, radius, true), pd, radius, false);
                    assert_eq!(close(&m, dims, radius), crop(&closed, pd, radius), "close {dims:?} r {radius}");
                }
            }
        }
    }

    #[test]
    fn word_shifts() {
        let src = [0x8000_0000_0000_0001u64, 0x1];
        let mut out = [0u64; 2];
        shift(&src, 1, true, &mut out);
        assert_eq!(out, [0x2, 0x3]);
        shift(&src, 1, false, &mut out);
        assert_eq!(out, [0x4000_0000_0000_0000 | 0x8000_0000_0000_0000, 0]);
        shift(&src, 64, true, &mut out);
        assert_eq!(out, [0, 0x8000_0000_0000_0001]);
        shift(&src, 65, false, &mut out);
        assert_eq!(out, [0, 0]);
    }
}
