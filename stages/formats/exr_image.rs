//! OpenEXR files of digitally reconstructed radiographs: one single-channel float image with
//! the camera that rendered it. Owns the file layout and nothing of the pipeline: what the
//! numbers mean is the caller's business, recorded in the `units` and `view` texts.
//!
//! The file is a single-part scanline image, uncompressed, scanlines stored top row first
//! (`lineOrder` INCREASING_Y), with one channel `Y` of type FLOAT (32-bit): `Y` is OpenEXR's
//! luminance channel, the one viewers show as a grey image. Header attributes besides the
//! standard ones:
//!
//! | name                | type     | value                                               |
//! |---------------------|----------|-----------------------------------------------------|
//! | `cameraToWorld`     | `m44f`   | [`DrrImage::camera_to_world`], transposed (below)   |
//! | `focalLengthPixels` | `float`  | [`DrrImage::focal_px`]                              |
//! | `imageSize`         | `v2i`    | (width, height)                                     |
//! | `units`             | `string` | [`DrrImage::units`], UTF-8                          |
//! | `view`              | `string` | [`DrrImage::view`], UTF-8 (OpenEXR's standard name) |
//!
//! **Matrix layout.** [`DrrImage::camera_to_world`] is row-major in the column-vector
//! convention: `p_world = M · (p_camera, 1)`, so the translation is in the last *column*
//! (`m[0][3]`, `m[1][3]`, `m[2][3]`). An `m44f` attribute is an Imath `M44f`: sixteen
//! little-endian floats `x[0][0], x[0][1], …, x[3][3]` (row-major), in Imath's row-vector
//! convention `p' = p · M`, translation in the last *row* (floats 12, 13, 14). We therefore
//! write the transpose, so that Imath (and OpenEXR's Python bindings, which return the
//! attribute as a 4×4 numpy array indexed `[row][column]`) see a correct camera-to-world
//! transform with the translation at `[3][0..3]`; [`decode`] transposes back.
//!
//! **Deterministic bytes.** The same image always encodes to the same bytes: no compression,
//! increasing line order, blocks written on the calling thread, and the header attributes
//! sorted by name (the `exr` crate keeps custom attributes in a hash map, whose order changes
//! from run to run; OpenEXR's own library also writes them sorted by name).

use exr::meta::attribute::{AttributeValue, Text};
use exr::prelude::*;
use std::io::Cursor;
use std::result::Result; // not the prelude's

/// Name of the single channel.
pub const CHANNEL: &str = "Y";
/// Attribute names.
pub const ATTR_CAMERA_TO_WORLD: &str = "cameraToWorld";
pub const ATTR_FOCAL_PX: &str = "focalLengthPixels";
pub const ATTR_IMAGE_SIZE: &str = "imageSize";
pub const ATTR_UNITS: &str = "units";
pub const ATTR_VIEW: &str = "view";

/// A DRR with the camera that rendered it.
#[derive(Debug, Clone, PartialEq)]
pub struct DrrImage {
    pub width: usize,
    pub height: usize,
    /// Row-major, `width * height` values; row 0 is the top row (EXR's first scanline).
    pub pixels: Vec<f32>,
    /// Row-major 4×4, column-vector convention (translation in the last column). Stored
    /// transposed as the `m44f` attribute `cameraToWorld`: see the module docs.
    pub camera_to_world: [[f32; 4]; 4],
    /// Focal length in pixels.
    pub focal_px: f32,
    /// What a scene unit and a pixel value are, e.g. "scene units (1 unit = 40 mm); pixel value = I/I0".
    pub units: String,
    /// Which view this is, e.g. "coronal".
    pub view: String,
}

#[derive(Debug, thiserror::Error)]
pub enum ExrError {
    #[error("image is {width}x{height} but has {found} pixels")]
    PixelCount { width: usize, height: usize, found: usize },
    #[error("image size {width}x{height} is empty or too large for OpenEXR")]
    Size { width: usize, height: usize },
    #[error("not a readable OpenEXR file: {0}")]
    Exr(#[from] exr::error::Error),
    #[error("OpenEXR file has no channel `Y` (channels: {found:?})")]
    MissingChannel { found: Vec<String> },
    #[error("OpenEXR file has channels {found:?}, expected only `Y`")]
    ExtraChannels { found: Vec<String> },
    #[error("channel `Y` holds {found} samples, expected FLOAT (32-bit)")]
    ChannelType { found: &'static str },
    #[error("channel `Y` is subsampled ({x}, {y}), expected one sample per pixel")]
    Subsampled { x: usize, y: usize },
    #[error("OpenEXR header has no attribute `{0}`")]
    MissingAttribute(&'static str),
    #[error("OpenEXR attribute `{name}` has type {found}, expected {expected}")]
    AttributeType { name: &'static str, found: String, expected: &'static str },
    #[error("OpenEXR attribute `{0}` is not valid UTF-8")]
    NotUtf8(&'static str),
    #[error("imageSize attribute says {attr_width}x{attr_height} but the pixels are {width}x{height}")]
    SizeMismatch { attr_width: i32, attr_height: i32, width: usize, height: usize },
    #[error("internal: the exr crate wrote an unexpected header layout ({0})")]
    HeaderLayout(&'static str),
}

/// Encodes `image` as OpenEXR bytes; the same image always gives the same bytes.
pub fn encode(image: &DrrImage) -> Result<Vec<u8>, ExrError> {
    let (width, height) = (image.width, image.height);
    if image.pixels.len() != width * height {
        return Err(ExrError::PixelCount { width, height, found: image.pixels.len() });
    }
    let (Ok(w), Ok(h)) = (i32::try_from(width), i32::try_from(height)) else {
        return Err(ExrError::Size { width, height });
    };
    if width == 0 || height == 0 {
        return Err(ExrError::Size { width, height });
    }

    let mut attributes = LayerAttributes { view_name: Some(utf8_text(&image.view)), ..Default::default() };
    let other = &mut attributes.other;
    other.insert(
        Text::from(ATTR_CAMERA_TO_WORLD),
        AttributeValue::Matrix4x4(imath_from_column_vector(&image.camera_to_world)),
    );
    other.insert(Text::from(ATTR_FOCAL_PX), AttributeValue::F32(image.focal_px));
    other.insert(Text::from(ATTR_IMAGE_SIZE), AttributeValue::IntVec2(Vec2(w, h)));
    other.insert(Text::from(ATTR_UNITS), AttributeValue::Text(utf8_text(&image.units)));

    let encoding = Encoding {
        compression: Compression::Uncompressed,
        blocks: Blocks::ScanLines,
        line_order: LineOrder::Increasing,
    };
    let channel = AnyChannel::new(CHANNEL, FlatSamples::F32(image.pixels.clone()));
    let layer = Layer::new((width, height), attributes, encoding, AnyChannels::sort(SmallVec::from_vec(vec![channel])));
    let exr_image = Image::from_layer(layer);

    let mut out = Cursor::new(Vec::new());
    exr_image.write().non_parallel().to_buffered(&mut out)?;
    let mut bytes = out.into_inner();
    sort_header_attributes(&mut bytes)?;
    Ok(bytes)
}

/// Decodes OpenEXR bytes written by [`encode`] (or by any writer that follows the same layout).
pub fn decode(bytes: &[u8]) -> Result<DrrImage, ExrError> {
    let image = read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .first_valid_layer()
        .all_attributes()
        .non_parallel()
        .from_buffered(Cursor::new(bytes))?;
    let layer = image.layer_data;
    let (width, height) = (layer.size.width(), layer.size.height());

    let names: Vec<String> = layer.channel_data.list.iter().map(|c| c.name.to_string()).collect();
    let Some(channel) = layer.channel_data.list.iter().find(|c| c.name.as_slice() == CHANNEL.as_bytes()) else {
        return Err(ExrError::MissingChannel { found: names });
    };
    if names.len() != 1 {
        return Err(ExrError::ExtraChannels { found: names });
    }
    if channel.sampling != Vec2(1, 1) {
        return Err(ExrError::Subsampled { x: channel.sampling.x(), y: channel.sampling.y() });
    }
    let pixels = match &channel.sample_data {
        FlatSamples::F32(values) => values.clone(),
        FlatSamples::F16(_) => return Err(ExrError::ChannelType { found: "HALF (16-bit float)" }),
        FlatSamples::U32(_) => return Err(ExrError::ChannelType { found: "UINT (32-bit integer)" }),
    };
    if pixels.len() != width * height {
        return Err(ExrError::PixelCount { width, height, found: pixels.len() });
    }

    let attrs = &layer.attributes;
    let other = |name: &'static str| attrs.other.get(name.as_bytes()).ok_or(ExrError::MissingAttribute(name));
    let wrong = |name: &'static str, found: &AttributeValue, expected: &'static str| ExrError::AttributeType {
        name,
        found: String::from_utf8_lossy(found.kind_name()).into_owned(),
        expected,
    };

    let camera_to_world = match other(ATTR_CAMERA_TO_WORLD)? {
        AttributeValue::Matrix4x4(m) => column_vector_from_imath(m),
        v => return Err(wrong(ATTR_CAMERA_TO_WORLD, v, "m44f")),
    };
    let focal_px = match other(ATTR_FOCAL_PX)? {
        AttributeValue::F32(f) => *f,
        v => return Err(wrong(ATTR_FOCAL_PX, v, "float")),
    };
    let (attr_width, attr_height) = match other(ATTR_IMAGE_SIZE)? {
        AttributeValue::IntVec2(size) => (size.x(), size.y()),
        v => return Err(wrong(ATTR_IMAGE_SIZE, v, "v2i")),
    };
    if usize::try_from(attr_width).ok() != Some(width) || usize::try_from(attr_height).ok() != Some(height) {
        return Err(ExrError::SizeMismatch { attr_width, attr_height, width, height });
    }
    let units = match other(ATTR_UNITS)? {
        AttributeValue::Text(text) => utf8_string(text, ATTR_UNITS)?,
        v => return Err(wrong(ATTR_UNITS, v, "string")),
    };
    let view = match &attrs.view_name {
        Some(text) => utf8_string(text, ATTR_VIEW)?,
        None => return Err(ExrError::MissingAttribute(ATTR_VIEW)),
    };

    Ok(DrrImage { width, height, pixels, camera_to_world, focal_px, units, view })
}

/// OpenEXR strings are bytes; we write UTF-8 (the `exr` crate's `Text::from` would take
/// Latin-1 characters and panic on others).
fn utf8_text(s: &str) -> Text {
    Text::from_slice_unchecked(s.as_bytes())
}

fn utf8_string(text: &Text, name: &'static str) -> Result<String, ExrError> {
    String::from_utf8(text.as_slice().to_vec()).map_err(|_| ExrError::NotUtf8(name))
}

/// Column-vector row-major matrix → the sixteen floats of an Imath `M44f` (its transpose).
fn imath_from_column_vector(m: &[[f32; 4]; 4]) -> [f32; 16] {
    std::array::from_fn(|i| m[i % 4][i / 4])
}

/// The sixteen floats of an Imath `M44f` → column-vector row-major matrix (its transpose).
fn column_vector_from_imath(x: &[f32; 16]) -> [[f32; 4]; 4] {
    std::array::from_fn(|r| std::array::from_fn(|c| x[c * 4 + r]))
}

/// Rewrites the attributes of a single-part header in order of name (byte-wise), in place.
/// The header keeps its length, so the offset table and blocks after it stay valid.
fn sort_header_attributes(bytes: &mut [u8]) -> Result<(), ExrError> {
    const START: usize = 8; // magic number + version field
    let layout = ExrError::HeaderLayout;
    if bytes.len() < START {
        return Err(layout("shorter than magic and version"));
    }
    let flags = u32::from_le_bytes([bytes[4], bytes[5], bytes[6], bytes[7]]);
    if flags & 0x1000 != 0 || flags & 0x800 != 0 {
        return Err(layout("multi-part or deep file"));
    }
    let cstr_end =
        |at: usize| bytes[at..].iter().position(|&b| b == 0).map(|n| at + n).ok_or(layout("unterminated name"));

    // (name range, whole attribute range)
    let mut attributes: Vec<(std::ops::Range<usize>, std::ops::Range<usize>)> = Vec::new();
    let mut at = START;
    loop {
        if at >= bytes.len() {
            return Err(layout("header runs past the end"));
        }
        if bytes[at] == 0 {
            break;
        }
        let name_end = cstr_end(at)?;
        let type_end = cstr_end(name_end + 1)?;
        let size_at = type_end + 1;
        let size_bytes = bytes.get(size_at..size_at + 4).ok_or(layout("attribute size past the end"))?;
        let size = i32::from_le_bytes([size_bytes[0], size_bytes[1], size_bytes[2], size_bytes[3]]);
        let size = usize::try_from(size).map_err(|_| layout("negative attribute size"))?;
        let end = size_at + 4 + size;
        if end > bytes.len() {
            return Err(layout("attribute value past the end"));
        }
        attributes.push((at..name_end, at..end));
        at = end;
    }

    let mut sorted = attributes.clone();
    sorted.sort_by(|a, b| bytes[a.0.clone()].cmp(&bytes[b.0.clone()]));
    let rewritten: Vec<u8> = sorted.iter().flat_map(|(_, whole)| bytes[whole.clone()].iter().copied()).collect();
    bytes[START..at].copy_from_slice(&rewritten);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn transpose_puts_the_translation_in_the_last_row() {
        let mut m = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]];
        m[0][3] = 7.0;
        m[1][3] = 50.0;
        m[2][3] = -3.0;
        let x = imath_from_column_vector(&m);
        assert_eq!(&x[12..16], &[7.0, 50.0, -3.0, 1.0]);
        assert_eq!(column_vector_from_imath(&x), m);
    }
}
