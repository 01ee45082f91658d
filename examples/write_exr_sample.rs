//! Write a known DRR as OpenEXR, for independent readers (`tests/py/test_exr_openexr.py`).
//!
//! ```sh
//! cargo run --example write_exr_sample -- OUT.exr
//! ```
//!
//! The image is 128×128 with pixel (x, y) = x + 1000·y + 0.25 (row y = 0 at the top); the
//! camera sits at y = 50 scene units, rotated +90° about x (camera +y → world +z, camera +z
//! → world −y); focal 1280.5 px; view "coronal".

use aret_pipe::formats::exr_image::{encode, DrrImage};

fn main() -> anyhow::Result<()> {
    let path = std::env::args().nth(1).ok_or_else(|| anyhow::anyhow!("usage: write_exr_sample OUT.exr"))?;
    let (width, height) = (128, 128);
    let pixels = (0..height).flat_map(|y| (0..width).map(move |x| x as f32 + 1000.0 * y as f32 + 0.25)).collect();
    let image = DrrImage {
        width,
        height,
        pixels,
        camera_to_world: [[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, 50.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]],
        focal_px: 1280.5,
        units: "scene units (1 unit = 40 mm); pixel value = I/I0".into(),
        view: "coronal".into(),
    };
    std::fs::write(&path, encode(&image)?)?;
    println!("wrote {path}");
    Ok(())
}
