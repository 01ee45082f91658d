//! An RGB picture that previews are drawn on: pictures pasted in, rectangles filled, and text
//! in an 8×8 bitmap font (the `font8x8` crate's basic Latin, scaled by whole pixels) for the
//! labels a reader needs: titles, legends, orientation letters, scale bars.

use super::png;
use font8x8::{UnicodeFonts, BASIC_FONTS};

/// Pixels a glyph takes at scale 1 (the font's cell).
pub const GLYPH_PX: usize = 8;

/// `width × height` RGB pixels, row-major from the top.
pub struct Canvas {
    pub width: usize,
    pub height: usize,
    pub rgb: Vec<u8>,
}

impl Canvas {
    pub fn new(width: usize, height: usize, background: [u8; 3]) -> Canvas {
        let (width, height) = (width.max(1), height.max(1));
        Canvas { width, height, rgb: background.repeat(width * height) }
    }

    /// `rgb` (`width` pixels a row) with its top-left corner at (`left`, `top`), clipped to the canvas.
    pub fn paste(&mut self, left: usize, top: usize, width: usize, rgb: &[u8]) {
        let height = rgb.len() / (3 * width.max(1));
        for r in 0..height.min(self.height.saturating_sub(top)) {
            let w = width.min(self.width.saturating_sub(left));
            let at = 3 * (left + self.width * (top + r));
            self.rgb[at..at + 3 * w].copy_from_slice(&rgb[3 * width * r..3 * (width * r + w)]);
        }
    }

    /// A filled rectangle, clipped to the canvas.
    pub fn fill(&mut self, left: usize, top: usize, width: usize, height: usize, colour: [u8; 3]) {
        for r in top..(top + height).min(self.height) {
            for c in left..(left + width).min(self.width) {
                self.rgb[3 * (c + self.width * r)..3 * (c + self.width * r) + 3].copy_from_slice(&colour);
            }
        }
    }

    /// `text` from (`left`, `top`), each glyph `scale` × 8 pixels square; characters the font
    /// lacks show as `?`. Returns the width drawn.
    pub fn text(&mut self, left: usize, top: usize, text: &str, colour: [u8; 3], scale: usize) -> usize {
        let scale = scale.max(1);
        for (n, ch) in text.chars().enumerate() {
            let glyph = BASIC_FONTS.get(ch).or_else(|| BASIC_FONTS.get('?')).unwrap_or([0; 8]);
            let x0 = left + n * GLYPH_PX * scale;
            for (gy, bits) in glyph.iter().enumerate() {
                for gx in (0..GLYPH_PX).filter(|&gx| bits & (1 << gx) != 0) {
                    self.fill(x0 + gx * scale, top + gy * scale, scale, scale, colour);
                }
            }
        }
        text_width(text, scale)
    }

    /// `text` on a filled box `pad` pixels wider on each side, so it reads over any picture.
    pub fn label(&mut self, left: usize, top: usize, text: &str, colours: ([u8; 3], [u8; 3]), scale: usize) {
        let pad = scale.max(1);
        let (ink, ground) = colours;
        self.fill(left, top, text_width(text, scale) + 2 * pad, GLYPH_PX * scale.max(1) + 2 * pad, ground);
        self.text(left + pad, top + pad, text, ink, scale);
    }

    pub fn png(&self) -> Vec<u8> {
        png::encode_rgb8(self.width, self.height, &self.rgb)
    }
}

/// The width `text` takes at `scale`.
pub fn text_width(text: &str, scale: usize) -> usize {
    text.chars().count() * GLYPH_PX * scale.max(1)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn text_sets_the_glyphs_pixels_and_nothing_outside_its_cells() {
        let mut c = Canvas::new(40, 12, [0; 3]);
        let drawn = c.text(2, 2, "I1", [255; 3], 1);
        assert_eq!(drawn, 16);
        let lit: Vec<(usize, usize)> = (0..12)
            .flat_map(|r| (0..40).map(move |x| (x, r)))
            .filter(|&(x, r)| c.rgb[3 * (x + 40 * r)] == 255)
            .collect();
        assert!(!lit.is_empty());
        assert!(lit.iter().all(|&(x, r)| (2..18).contains(&x) && (2..10).contains(&r)), "{lit:?}");
        // Both glyphs are drawn: the letter and the digit differ.
        let left: Vec<_> = lit.iter().filter(|p| p.0 < 10).map(|p| (p.0 - 2, p.1)).collect();
        let right: Vec<_> = lit.iter().filter(|p| p.0 >= 10).map(|p| (p.0 - 10, p.1)).collect();
        assert!(!left.is_empty() && !right.is_empty() && left != right);
    }

    #[test]
    fn paste_and_fill_clip_to_the_canvas() {
        let mut c = Canvas::new(4, 3, [0; 3]);
        c.paste(2, 1, 3, &[9u8; 3 * 3 * 3]);
        c.fill(3, 2, 5, 5, [7; 3]);
        let at = |x: usize, y: usize| c.rgb[3 * (x + 4 * y)];
        assert_eq!((at(1, 1), at(2, 1), at(3, 1), at(2, 2), at(3, 2), at(2, 0)), (0, 9, 9, 9, 7, 0));
    }
}
