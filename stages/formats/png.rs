//! 8-bit grayscale PNG previews of CT volumes. Owns the display side: HU windows, the
//! slices and projections radiologists look at (axial slice, coronal slice, coronal
//! mean-attenuation projection), resampled to square pixels, and PNG encoding.
//!
//! Display conventions: axial images are seen from the feet (patient right on the image
//! left, anterior at the top); coronal images from the front (patient right on the image
//! left, superior at the top). The slicing helpers expect an axial series with the standard
//! orientation (direction = identity: columns toward patient left, rows toward posterior,
//! slices ascending toward superior), as every LIDC series is.

use crate::volume::Volume;

/// A scalar image, row-major, with square pixels of `pixel_mm`.
#[derive(Debug, Clone, PartialEq)]
pub struct Image {
    pub width: usize,
    pub height: usize,
    pub pixel_mm: f64,
    pub data: Vec<f32>,
}

/// Values from `lo` (black) to `hi` (white).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Window {
    pub lo: f32,
    pub hi: f32,
}

/// Lung window: level −600, width 1500 HU.
pub const LUNG_WINDOW: Window = Window { lo: -1350.0, hi: 150.0 };
/// Mediastinal (soft-tissue) window: level 40, width 400 HU.
pub const MEDIASTINAL_WINDOW: Window = Window { lo: -160.0, hi: 240.0 };

impl Window {
    /// Grey level of `v`, clamped to the window.
    pub fn grey(&self, v: f32) -> u8 {
        let t = (v - self.lo) / (self.hi - self.lo);
        (t.clamp(0.0, 1.0) * 255.0).round() as u8
    }

    /// The window spanning the 0.5th to 99.5th percentiles of `image` (projections).
    pub fn spanning(image: &Image) -> Window {
        let mut v: Vec<f32> = image.data.iter().copied().filter(|v| v.is_finite()).collect();
        if v.is_empty() {
            return Window { lo: 0.0, hi: 1.0 };
        }
        v.sort_by(f32::total_cmp);
        let at = |q: f64| v[((v.len() - 1) as f64 * q).round() as usize];
        let (lo, hi) = (at(0.005), at(0.995));
        Window { lo, hi: if hi > lo { hi } else { lo + 1.0 } }
    }
}

/// PNG bytes of an 8-bit grayscale image, row-major.
pub fn encode_gray8(width: usize, height: usize, pixels: &[u8]) -> Vec<u8> {
    encode_8bit(width, height, ::png::ColorType::Grayscale, pixels)
}

/// PNG bytes of an 8-bit RGB image, row-major, three bytes a pixel.
pub fn encode_rgb8(width: usize, height: usize, rgb: &[u8]) -> Vec<u8> {
    encode_8bit(width, height, ::png::ColorType::Rgb, rgb)
}

fn encode_8bit(width: usize, height: usize, color: ::png::ColorType, bytes: &[u8]) -> Vec<u8> {
    assert_eq!(bytes.len(), color.samples() * width * height, "byte count");
    let mut out = Vec::new();
    {
        let mut encoder = ::png::Encoder::new(&mut out, width as u32, height as u32);
        encoder.set_color(color);
        encoder.set_depth(::png::BitDepth::Eight);
        encoder.set_compression(::png::Compression::Fast);
        let mut writer = encoder.write_header().expect("PNG header to memory");
        writer.write_image_data(bytes).expect("PNG data to memory");
    }
    out
}

/// PNG bytes of `image` shown through `window`.
pub fn image_png(image: &Image, window: Window) -> Vec<u8> {
    let grey: Vec<u8> = image.data.iter().map(|&v| window.grey(v)).collect();
    encode_gray8(image.width, image.height, &grey)
}

/// Axial slice `k`, as stored.
pub fn axial_slice(ct: &Volume<f32>, k: usize) -> Image {
    let [cols, rows, _] = ct.geometry.dims;
    Image {
        width: cols,
        height: rows,
        pixel_mm: ct.geometry.spacing_mm[0],
        data: ct.data[k * cols * rows..(k + 1) * cols * rows].to_vec(),
    }
}

/// Coronal slice through row `row` (constant y), superior at the top, resampled along z
/// to the in-plane pixel size.
pub fn coronal_slice(ct: &Volume<f32>, row: usize) -> Image {
    let [cols, rows, _] = ct.geometry.dims;
    coronal_image(ct, |k, i| ct.data[ct.geometry.index(i, row.min(rows - 1), k)], cols)
}

/// Coronal projection: the mean of (HU + 1000), i.e. attenuation relative to air, along y
/// through the whole volume, shown like a radiograph (dense = bright); resampled as
/// [`coronal_slice`].
pub fn coronal_projection(ct: &Volume<f32>) -> Image {
    let [cols, rows, _] = ct.geometry.dims;
    let mean = |k: usize, i: usize| {
        let sum: f32 = (0..rows).map(|j| ct.data[ct.geometry.index(i, j, k)] + 1000.0).sum();
        sum / rows as f32
    };
    coronal_image(ct, mean, cols)
}

/// An x–z image from `value(slice, column)`, square pixels, superior at the top.
fn coronal_image(ct: &Volume<f32>, value: impl Fn(usize, usize) -> f32, cols: usize) -> Image {
    let slices = ct.geometry.dims[2];
    let pixel_mm = ct.geometry.spacing_mm[0];
    let dz = ct.geometry.spacing_mm[2];
    // Slice values, computed once: slices × columns.
    let plane: Vec<f32> = (0..slices).flat_map(|k| (0..cols).map(move |i| (k, i))).map(|(k, i)| value(k, i)).collect();
    let extent_mm = (slices.saturating_sub(1)) as f64 * dz;
    let height = (extent_mm / pixel_mm).round() as usize + 1;
    let mut data = Vec::with_capacity(height * cols);
    for r in 0..height {
        // Row 0 is the top slice.
        let kf = ((extent_mm - r as f64 * pixel_mm) / dz).clamp(0.0, (slices - 1) as f64);
        let k0 = kf.floor() as usize;
        let k1 = (k0 + 1).min(slices - 1);
        let t = (kf - k0 as f64) as f32;
        for i in 0..cols {
            data.push(plane[k0 * cols + i] * (1.0 - t) + plane[k1 * cols + i] * t);
        }
    }
    Image { width: cols, height, pixel_mm, data }
}
