//! The DRR stage's numerics and geometry: analytic line integrals (uniform box, sphere),
//! orientation of the three views, pose error, noise, determinism.

use aret_pipe::geometry::{Aabb, Camera, View};
use aret_pipe::kernels::raymarch::{march_ray, Field};
use aret_pipe::stage::drr::{render_views, Focal, Params, RoiCenter};
use aret_pipe::volume::{Geometry, Volume};
use glam::DVec3;

const IDENTITY: [[f64; 3]; 3] = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];

fn volume(dims: [usize; 3], spacing_mm: [f64; 3], origin_mm: [f64; 3], value: impl Fn([f64; 3]) -> f32) -> Volume<f32> {
    let geometry = Geometry { dims, spacing_mm, origin_mm, direction: IDENTITY };
    let mut data = Vec::with_capacity(geometry.len());
    for k in 0..dims[2] {
        for j in 0..dims[1] {
            for i in 0..dims[0] {
                data.push(value(geometry.voxel_to_patient_mm([i as f64, j as f64, k as f64])));
            }
        }
    }
    Volume { geometry, data }
}

fn params_at_origin() -> Params {
    Params { roi_center: RoiCenter::Mm([0.0; 3]), width_px: 128, height_px: 128, ..Params::default() }
}

#[test]
fn uniform_box_gives_exact_chord_lengths() {
    // A CT of v = 1 whose outer faces are the box [-100, 60] × [-50, 70] × [-40, 30] mm.
    let v = volume([40, 24, 14], [4.0, 5.0, 5.0], [-98.0, -47.5, -37.5], |_| 1.0);
    let params = Params { attenuation_scale: 0.7, ..params_at_origin() };
    let (set, images) = render_views(&params, &v, [0.0; 3], "explicit").unwrap();
    let ct_box = Aabb { min: [-2.5, -1.25, -1.0], max: [1.5, 1.75, 0.75] }; // mm / 40
    let support = ct_box.overlap(&set.aabb);
    let mut checked = 0;
    for (cam, pixels) in set.cameras.iter().zip(&images) {
        for j in 0..cam.height {
            for i in 0..cam.width {
                let expected = support.intersect(cam.eye(), cam.ray_dir(i, j)).map_or(0.0, |(t0, t1)| t1 - t0);
                let got = -f64::from(pixels[i + cam.width * j]).ln() / 0.7;
                assert!(
                    (got - expected).abs() <= 1e-4 * expected.max(1e-3),
                    "{:?} ({i}, {j}): {got} vs {expected}",
                    cam.view
                );
                checked += usize::from(expected > 0.0);
            }
        }
    }
    assert!(checked > 5_000, "many rays cross the box ({checked})");
}

/// An analytic ball of value 1: the marcher's rays and sampling against exact chord lengths.
struct Ball {
    centre: DVec3,
    radius: f64,
}

impl Field for Ball {
    type Ray = (DVec3, DVec3);
    fn prepare(&self, origin: DVec3, dir: DVec3) -> Self::Ray {
        (origin, dir)
    }
    /// The ball's bounding cube: the marcher itself must find where the ball begins and ends.
    fn support(&self, &(o, d): &Self::Ray) -> Option<(f64, f64)> {
        let r = self.radius;
        let cube = Aabb { min: (self.centre - r).to_array(), max: (self.centre + r).to_array() };
        cube.intersect(o, d)
    }
    fn max_step(&self, _: &Self::Ray) -> f64 {
        f64::INFINITY
    }
    fn sample(&self, &(o, d): &Self::Ray, t: f64) -> f64 {
        f64::from(u8::from((o + d * t - self.centre).length() <= self.radius))
    }
}

#[test]
fn ball_gives_exact_chord_lengths_through_every_view() {
    let ball = Ball { centre: DVec3::new(0.3, -0.2, 0.1), radius: 0.9 };
    let aabb = Aabb { min: [-2.5, -1.5, -2.0], max: [3.5, 1.5, 1.5] };
    for view in View::ALL {
        let cam = Camera::new(view, view.pose(50.0), 900.0, 64, 64);
        for j in (0..64).step_by(5) {
            for i in (0..64).step_by(5) {
                let (o, d) = (cam.eye(), cam.ray_dir(i, j));
                let miss = (o - ball.centre).cross(d).length();
                let exact = if miss < ball.radius { 2.0 * (ball.radius.powi(2) - miss * miss).sqrt() } else { 0.0 };
                // Midpoint rule on an indicator: at most one step of error in all (half a step at
                // each surface crossing), so 1e-4 relative wherever the chord is ≥ 0.2 units.
                let step = 2e-5;
                let got = march_ray(&ball, &aabb, o, d, step);
                let tolerance = if exact >= 0.2 { 1e-4 * exact } else { step };
                assert!((got - exact).abs() <= tolerance, "{view:?} ({i}, {j}): {got} vs {exact}");
            }
        }
    }
}

/// Where the darkest pixel of each view lies for a dense marker at patient position `p_mm`.
fn marker_pixels(p_mm: [f64; 3]) -> Vec<(usize, usize)> {
    let v = volume([60, 60, 60], [4.0; 3], [-118.0; 3], |x| {
        let d2: f64 = (0..3).map(|a| (x[a] - p_mm[a]).powi(2)).sum();
        if d2 <= 64.0 {
            1.0
        } else {
            0.0
        }
    });
    let params = Params { focal_px: Focal::Px(900.0), aabb_min: [-3.0; 3], aabb_max: [3.0; 3], ..params_at_origin() };
    let (set, images) = render_views(&params, &v, [0.0; 3], "explicit").unwrap();
    set.cameras
        .iter()
        .zip(&images)
        .map(|(cam, px)| {
            let n = px.iter().enumerate().min_by(|a, b| a.1.total_cmp(b.1)).unwrap().0;
            (n % cam.width, n / cam.width)
        })
        .collect()
}

#[test]
fn markers_appear_where_the_documented_convention_says() {
    // docs/conventions.md: (image column grows →, image row grows ↓)
    //   coronal:  patient +x (left) → right, +z (superior) → DOWN  (the paper's C_cor)
    //   sagittal: +y (posterior) → right, +z (superior) → up
    //   axial:    +x (left) → right, +y (posterior) → up
    let [cor, sag, ax] = <[_; 3]>::try_from(marker_pixels([60.0, 0.0, 0.0])).unwrap();
    assert!(cor.0 > 70 && (60..68).contains(&cor.1), "+x on coronal: {cor:?}");
    assert!((60..68).contains(&sag.0) && (60..68).contains(&sag.1), "+x on sagittal (on axis): {sag:?}");
    assert!(ax.0 > 70 && (60..68).contains(&ax.1), "+x on axial: {ax:?}");
    let [cor, sag, ax] = <[_; 3]>::try_from(marker_pixels([0.0, 60.0, 0.0])).unwrap();
    assert!((60..68).contains(&cor.0) && (60..68).contains(&cor.1), "+y on coronal (on axis): {cor:?}");
    assert!(sag.0 > 70 && (60..68).contains(&sag.1), "+y on sagittal: {sag:?}");
    assert!((60..68).contains(&ax.0) && ax.1 < 58, "+y on axial: {ax:?}");
    let [cor, sag, ax] = <[_; 3]>::try_from(marker_pixels([0.0, 0.0, 60.0])).unwrap();
    assert!((60..68).contains(&cor.0) && cor.1 > 70, "+z on coronal: {cor:?}");
    assert!((60..68).contains(&sag.0) && sag.1 < 58, "+z on sagittal: {sag:?}");
    assert!((60..68).contains(&ax.0) && (60..68).contains(&ax.1), "+z on axial (on axis): {ax:?}");
}

fn small_ct() -> Volume<f32> {
    volume([48, 40, 30], [5.0; 3], [-117.5, -97.5, -72.5], |x| {
        let r2 = (x[0] / 100.0).powi(2) + (x[1] / 80.0).powi(2);
        if r2 < 1.0 {
            0.3 + 0.4 * f32::from(u8::from((x[0] - 20.0).powi(2) + x[1].powi(2) + x[2].powi(2) < 400.0))
        } else {
            0.0
        }
    })
}

#[test]
fn pose_error_moves_only_the_rendering_cameras() {
    let ct = small_ct();
    let (nominal, clean) = render_views(&params_at_origin(), &ct, [0.0; 3], "explicit").unwrap();
    let params = Params { pose_error_deg: 2.0, pose_error_mm: 3.0, seed: 7, ..params_at_origin() };
    let (set, moved) = render_views(&params, &ct, [0.0; 3], "explicit").unwrap();
    assert_eq!(set.cameras, nominal.cameras, "training keeps the nominal poses");
    let rendered = set.rendered_with.as_ref().expect("the rendering cameras are recorded");
    for (r, n) in rendered.iter().zip(&nominal.cameras) {
        let angle = (glam::DMat3::from_mat4(r.pose()).transpose() * glam::DMat3::from_mat4(n.pose())).to_cols_array();
        let trace = angle[0] + angle[4] + angle[8];
        let degrees = ((trace - 1.0) / 2.0).clamp(-1.0, 1.0).acos().to_degrees();
        assert!((degrees - 2.0).abs() < 1e-6, "rotation {degrees}°");
    }
    assert_ne!(moved, clean);
}

#[test]
fn noise_is_seeded_and_photon_noise_has_poisson_spread() {
    let ct = small_ct();
    let noisy = |seed: u64| {
        let params = Params { photons: 10_000.0, seed, ..params_at_origin() };
        render_views(&params, &ct, [0.0; 3], "explicit").unwrap().1
    };
    let (a, b, c) = (noisy(1), noisy(1), noisy(2));
    assert_eq!(a, b);
    assert_ne!(a, c);
    let clean = render_views(&params_at_origin(), &ct, [0.0; 3], "explicit").unwrap().1;
    // Relative error ≈ 1/sqrt(N0 · I): its variance, normalised, averages to 1.
    let z: Vec<f64> = a[0]
        .iter()
        .zip(&clean[0])
        .filter(|(_, &c)| c > 0.05)
        .map(|(&n, &c)| (f64::from(n) - f64::from(c)) / (f64::from(c) / 10_000.0).sqrt())
        .collect();
    let var = z.iter().map(|x| x * x).sum::<f64>() / z.len() as f64;
    assert!((var - 1.0).abs() < 0.1, "normalised variance {var}");
}

#[test]
fn same_inputs_give_identical_images_whatever_the_thread_count() {
    let ct = small_ct();
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
        pool.install(|| render_views(&params_at_origin(), &ct, [0.0; 3], "explicit").unwrap().1)
    };
    assert_eq!(run(1), run(4));
}

#[test]
fn tiles_lay_boxes_on_a_grid_centred_on_the_lungs_and_key_only_a_tiling() {
    use aret_pipe::engine::Stage;
    use aret_pipe::stage::drr::{Drr, RoiMode, TileParams};
    let tiling = Params { roi_center: RoiCenter::Mode(RoiMode::Tiles), ..Params::default() };
    assert_eq!(tiling.tile_count(), 18);
    // The default box (x −100…140, y ±60, z −80…60 mm about its origin): box centres at
    // ±66 mm in x, −74/0/74 in y, −120/0/120 in z from the lungs; x slowest, z fastest.
    let lungs = [10.0, -20.0, 30.0];
    let origin = |t| tiling.tile_origin_mm(lungs, t);
    assert_eq!(origin(0), [10.0 - 66.0 - 20.0, -20.0 - 74.0, 30.0 - 120.0 + 10.0]);
    assert_eq!(origin(1), [10.0 - 66.0 - 20.0, -20.0 - 74.0, 30.0 + 10.0]);
    assert_eq!(origin(17), [10.0 + 66.0 - 20.0, -20.0 + 74.0, 30.0 + 120.0 + 10.0]);
    let names = Drr { params: tiling.clone() }.replica_names();
    assert_eq!((names.len(), names[0].as_str(), names[17].as_str()), (18, "tile00", "tile17"));
    assert!(Drr { params: tiling.clone() }.params().get("tiles").is_some());
    // Any other ROI centre neither fans out nor has the tiling in its cache key.
    let lungs_only = Drr { params: Params { roi_center: RoiCenter::Mode(RoiMode::Lungs), ..tiling.clone() } };
    assert!(lungs_only.replica_names().is_empty());
    assert!(lungs_only.params().get("tiles").is_none());
    let counts = TileParams { counts: [2, 0, 3], ..TileParams::default() };
    assert!(Params { tiles: counts, ..tiling.clone() }.check().unwrap_err().to_string().contains("[drr.tiles] counts"));
    let bad_step = Params { tiles: TileParams { step_mm: [1.0, -1.0, 1.0], ..TileParams::default() }, ..tiling };
    assert!(bad_step.check().unwrap_err().to_string().contains("[drr.tiles] step_mm"));
}
