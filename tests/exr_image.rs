//! The OpenEXR DRR format: bit-exact round trips, byte-identical output across runs and
//! rayon pool sizes, the layout OpenEXR readers rely on, and errors (never panics) on bad bytes.

use aret_pipe::formats::exr_image::{decode, encode, DrrImage, ExrError};

fn sample(width: usize, height: usize) -> DrrImage {
    // Values that exercise every bit pattern class: negatives, subnormals, huge, NaN, infinities.
    let specials = [-0.0, f32::MIN_POSITIVE / 8.0, 3.4e38, f32::NAN, f32::INFINITY, f32::NEG_INFINITY];
    let pixels = (0..width * height)
        .map(|i| if i % 97 == 5 { specials[(i / 97) % specials.len()] } else { (i as f32 * 0.731).sin() * 1e3 })
        .collect();
    DrrImage {
        width,
        height,
        pixels,
        camera_to_world: [[0.6, -0.8, 0.0, 1.5], [0.0, 0.0, -1.0, 50.0], [0.8, 0.6, 0.0, -2.25], [0.0, 0.0, 0.0, 1.0]],
        focal_px: 1280.5,
        units: "scene units (1 unit = 40 mm); pixel value = I/I0".into(),
        view: "coronal".into(),
    }
}

fn bits(pixels: &[f32]) -> Vec<u32> {
    pixels.iter().map(|p| p.to_bits()).collect()
}

fn assert_same(a: &DrrImage, b: &DrrImage) {
    assert_eq!((a.width, a.height), (b.width, b.height));
    assert_eq!(bits(&a.pixels), bits(&b.pixels), "pixels differ");
    assert_eq!(a.camera_to_world, b.camera_to_world);
    assert_eq!(a.focal_px.to_bits(), b.focal_px.to_bits());
    assert_eq!(a.units, b.units);
    assert_eq!(a.view, b.view);
}

fn find(haystack: &[u8], needle: &[u8]) -> Option<usize> {
    haystack.windows(needle.len()).position(|w| w == needle)
}

#[test]
fn round_trip_is_bit_exact() {
    for (w, h) in [(128, 128), (1, 1), (3, 7), (200, 5)] {
        let image = sample(w, h);
        let decoded = decode(&encode(&image).unwrap()).unwrap();
        assert_same(&image, &decoded);
    }
}

#[test]
fn round_trip_keeps_non_ascii_text() {
    let mut image = sample(4, 4);
    image.units = "scene units (1 unit = 40 mm); pixel value = I/I₀, µ in 1/mm".into();
    image.view = "".into();
    let decoded = decode(&encode(&image).unwrap()).unwrap();
    assert_same(&image, &decoded);
}

#[test]
fn bytes_are_deterministic_across_runs_and_pool_sizes() {
    let image = sample(128, 128);
    let first = encode(&image).unwrap();
    assert_eq!(first, encode(&image).unwrap());
    assert_eq!(first, encode(&image.clone()).unwrap());
    for threads in [1, 4] {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
        let bytes = pool.install(|| encode(&image).unwrap());
        assert_eq!(first, bytes, "bytes differ in a pool of {threads} threads");
    }
    // Across processes: the header attribute order must not depend on hash seeds. Attributes
    // are sorted by name, so check the order directly.
    let names = [
        &b"cameraToWorld\0m44f\0"[..],
        b"channels\0chlist\0",
        b"compression\0compression\0",
        b"dataWindow\0box2i\0",
        b"displayWindow\0box2i\0",
        b"focalLengthPixels\0float\0",
        b"imageSize\0v2i\0",
        b"lineOrder\0lineOrder\0",
        b"units\0string\0",
        b"view\0string\0",
    ];
    let at: Vec<usize> = names.iter().map(|n| find(&first, n).expect("attribute present")).collect();
    assert!(at.windows(2).all(|p| p[0] < p[1]), "attributes not sorted by name: {at:?}");
}

#[test]
fn layout_is_what_openexr_readers_expect() {
    let image = sample(128, 128);
    let bytes = encode(&image).unwrap();
    assert_eq!(&bytes[..4], &[0x76, 0x2f, 0x31, 0x01], "magic number");
    assert_eq!(bytes[4], 2, "version 2, single-part scanline");
    // One FLOAT (pixel type 2) channel named Y with sampling (1, 1).
    let ch = find(&bytes, b"channels\0chlist\0").unwrap() + "channels\0chlist\0".len();
    let size = i32::from_le_bytes(bytes[ch..ch + 4].try_into().unwrap());
    assert_eq!(size, 2 + 16 + 1);
    let list = &bytes[ch + 4..ch + 4 + size as usize];
    assert_eq!(&list[..2], b"Y\0");
    assert_eq!(i32::from_le_bytes(list[2..6].try_into().unwrap()), 2, "FLOAT");
    assert_eq!(i32::from_le_bytes(list[10..14].try_into().unwrap()), 1, "x sampling");
    assert_eq!(i32::from_le_bytes(list[14..18].try_into().unwrap()), 1, "y sampling");
    // Uncompressed (0) and increasing line order (0).
    let c = find(&bytes, b"compression\0compression\0").unwrap() + "compression\0compression\0".len();
    assert_eq!(&bytes[c..c + 5], &[1, 0, 0, 0, 0]);
    let l = find(&bytes, b"lineOrder\0lineOrder\0").unwrap() + "lineOrder\0lineOrder\0".len();
    assert_eq!(&bytes[l..l + 5], &[1, 0, 0, 0, 0]);
    // The matrix is stored transposed (Imath row-vector convention): translation in floats 12..15.
    let m = find(&bytes, b"cameraToWorld\0m44f\0").unwrap() + "cameraToWorld\0m44f\0".len();
    assert_eq!(i32::from_le_bytes(bytes[m..m + 4].try_into().unwrap()), 64);
    let floats: Vec<f32> = bytes[m + 4..m + 68].chunks(4).map(|c| f32::from_le_bytes(c.try_into().unwrap())).collect();
    assert_eq!(&floats[12..16], &[1.5, 50.0, -2.25, 1.0]);
    assert_eq!(&floats[0..4], &[0.6, 0.0, 0.8, 0.0], "first column of camera_to_world");
    // Uncompressed FLOAT data: 128 scanlines of 128 × 4 bytes, each with an 8-byte block header.
    let header_end = bytes.len() - 128 * (8 + 128 * 4) - 128 * 8;
    let first_block = u64::from_le_bytes(bytes[header_end..header_end + 8].try_into().unwrap()) as usize;
    assert_eq!(first_block, header_end + 128 * 8, "offset table right after the header");
    assert_eq!(&bytes[first_block..first_block + 8], &[0, 0, 0, 0, 0, 2, 0, 0], "line 0, 512 bytes");
    let first_pixel = f32::from_le_bytes(bytes[first_block + 8..first_block + 12].try_into().unwrap());
    assert_eq!(first_pixel.to_bits(), image.pixels[0].to_bits());
}

#[test]
fn encode_rejects_a_wrong_pixel_count() {
    let mut image = sample(4, 4);
    image.pixels.pop();
    let err = encode(&image).unwrap_err();
    assert!(matches!(err, ExrError::PixelCount { width: 4, height: 4, found: 15 }), "{err}");
    let mut empty = sample(1, 1);
    empty.width = 0;
    empty.pixels.clear();
    assert!(matches!(encode(&empty), Err(ExrError::Size { .. })));
}

#[test]
fn truncated_and_garbage_input_give_errors_not_panics() {
    let bytes = encode(&sample(16, 16)).unwrap();
    for len in (0..bytes.len()).step_by(7).chain([bytes.len() - 1]) {
        assert!(decode(&bytes[..len]).is_err(), "decoded a file truncated to {len} bytes");
    }
    // Random bytes, with and without a valid magic number and version in front.
    let mut state = 0x9e37_79b9_7f4a_7c15_u64;
    let mut next = || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        state as u8
    };
    for n in [0, 1, 8, 64, 1000, 5000] {
        let garbage: Vec<u8> = (0..n).map(|_| next()).collect();
        assert!(decode(&garbage).is_err());
        let mut with_magic = bytes[..8].to_vec();
        with_magic.extend_from_slice(&garbage);
        assert!(decode(&with_magic).is_err());
    }
    // Any byte of the header and offset table overwritten: an error or an image, never a panic.
    let blocks_start = bytes.len() - 16 * (8 + 16 * 4);
    for i in 4..blocks_start {
        for value in [0x00, 0xff, bytes[i] ^ 0x80, bytes[i].wrapping_add(1)] {
            let mut corrupted = bytes.clone();
            corrupted[i] = value;
            let _ = decode(&corrupted);
        }
    }
    let err = decode(b"not an exr file at all").unwrap_err();
    assert!(matches!(err, ExrError::Exr(_)), "{err}");
}

/// Replaces an attribute's name with another of the same length, so the file stays valid.
fn rename(bytes: &[u8], from: &str, to: &str) -> Vec<u8> {
    assert_eq!(from.len(), to.len());
    let mut out = bytes.to_vec();
    let at = find(bytes, format!("{from}\0").as_bytes()).expect("attribute present");
    out[at..at + from.len()].copy_from_slice(to.as_bytes());
    out
}

#[test]
fn errors_name_what_is_missing_or_wrong() {
    let bytes = encode(&sample(8, 8)).unwrap();
    let message = |b: &[u8]| decode(b).unwrap_err().to_string();

    // The channel list entry "Y\0" becomes "Z\0".
    let ch = find(&bytes, b"channels\0chlist\0").unwrap() + "channels\0chlist\0".len() + 4;
    let mut no_y = bytes.clone();
    no_y[ch] = b'Z';
    let err = decode(&no_y).unwrap_err();
    assert!(matches!(&err, ExrError::MissingChannel { found } if found == &["Z".to_string()]), "{err}");
    assert!(err.to_string().contains("no channel `Y`"), "{err}");

    for (attribute, renamed) in
        [("cameraToWorld", "cameraToWorlX"), ("focalLengthPixels", "focalLengthPixelX"), ("imageSize", "imageSizX")]
    {
        let m = message(&rename(&bytes, attribute, renamed));
        assert_eq!(m, format!("OpenEXR header has no attribute `{attribute}`"));
    }
    assert_eq!(message(&rename(&bytes, "units", "unitX")), "OpenEXR header has no attribute `units`");
    assert_eq!(message(&rename(&bytes, "view", "viex")), "OpenEXR header has no attribute `view`");

    // imageSize that disagrees with the data window.
    let s = find(&bytes, b"imageSize\0v2i\0").unwrap() + "imageSize\0v2i\0".len() + 4;
    let mut wrong_size = bytes.clone();
    wrong_size[s] = 9;
    let err = decode(&wrong_size).unwrap_err();
    assert!(matches!(err, ExrError::SizeMismatch { attr_width: 9, attr_height: 8, width: 8, height: 8 }), "{err}");
}

#[test]
fn a_wrong_attribute_type_is_reported() {
    // Re-type `imageSize` from v2i to v2f in place: same type-name length and value size.
    let bytes = encode(&sample(8, 8)).unwrap();
    let at = find(&bytes, b"imageSize\0v2i\0").unwrap() + "imageSize\0v2".len();
    let mut retyped = bytes.clone();
    retyped[at] = b'f';
    let err = decode(&retyped).unwrap_err();
    assert_eq!(err.to_string(), "OpenEXR attribute `imageSize` has type v2f, expected v2i");
}

/// A 2×2 file written by the `exr` crate itself with the given channels and none of our attributes.
fn foreign_file(channels: Vec<exr::prelude::AnyChannel<exr::prelude::FlatSamples>>) -> Vec<u8> {
    use exr::prelude::*;
    let image = Image::from_channels((2, 2), AnyChannels::sort(SmallVec::from_vec(channels)));
    let mut out = std::io::Cursor::new(Vec::new());
    image.write().non_parallel().to_buffered(&mut out).unwrap();
    out.into_inner()
}

#[test]
fn wrong_channels_are_reported() {
    use exr::prelude::{f16, AnyChannel, FlatSamples};
    let half = foreign_file(vec![AnyChannel::new("Y", FlatSamples::F16(vec![f16::ONE; 4]))]);
    assert_eq!(
        decode(&half).unwrap_err().to_string(),
        "channel `Y` holds HALF (16-bit float) samples, expected FLOAT (32-bit)"
    );
    let uint = foreign_file(vec![AnyChannel::new("Y", FlatSamples::U32(vec![1; 4]))]);
    assert!(matches!(decode(&uint), Err(ExrError::ChannelType { .. })));

    let rgb: Vec<_> = ["R", "G", "B"].iter().map(|n| AnyChannel::new(*n, FlatSamples::F32(vec![0.5; 4]))).collect();
    assert_eq!(
        decode(&foreign_file(rgb)).unwrap_err().to_string(),
        r#"OpenEXR file has no channel `Y` (channels: ["B", "G", "R"])"#
    );
    let ya: Vec<_> = ["Y", "A"].iter().map(|n| AnyChannel::new(*n, FlatSamples::F32(vec![0.5; 4]))).collect();
    assert!(matches!(decode(&foreign_file(ya)), Err(ExrError::ExtraChannels { .. })));

    // A plain FLOAT Y image without our attributes.
    let plain = foreign_file(vec![AnyChannel::new("Y", FlatSamples::F32(vec![0.5; 4]))]);
    assert_eq!(decode(&plain).unwrap_err().to_string(), "OpenEXR header has no attribute `cameraToWorld`");
}

/// Written when `EXR_SAMPLE_OUT` is set, for pointing other readers at a file.
#[test]
fn writes_a_sample_when_asked() {
    if let Some(path) = std::env::var_os("EXR_SAMPLE_OUT") {
        std::fs::write(path, encode(&sample(128, 128)).unwrap()).unwrap();
    }
}
