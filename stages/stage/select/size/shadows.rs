//! Sizing in the views (`[select] sizing = "shadows"`): the fitted field finds the
//! nodule, its three shadows size it.
//!
//! A field fitted to three views blurs a nodule by a few millimetres, and a region cut at half
//! its peak loses what the blur spreads (lab/log.md). The DRRs themselves are sharp:
//! each pixel spans 0.9 mm at the box. So once a rule has its half-maximum region, an
//! ellipsoid is fitted to the nodule's shadow in all three views at once: in a window around
//! where the region projects, each view's optical depth −ln I is modelled as a background plus
//! `contrast × chord`, the ellipsoid's chord along the pixel's ray. The background is what lies
//! in front of and behind the nodule: the fitted field's own line integral with the nodule's
//! neighbourhood (its region grown by `CLEARED_MM`) set to the lung around it, which carries the
//! sharp edges a window can hold (the mediastinum, a rib), plus a quadratic across the window
//! for what the field gets slowly wrong. One ellipsoid (centre,
//! three semi-axes along the patient axes, one contrast) must explain all three shadows, so
//! each axis is seen in two views. The soft-L1 loss lets a rib edge or vessel crossing the
//! window count for little. The nodule's volume is the ellipsoid's, 4/3·π·abc. Its mask is the
//! field's own region around the centre cut at the level that holds that volume: the shadows
//! say how much, σ's shape says where (a nodule is seldom an ellipsoid).
//!
//! The window spans `WINDOW_RADII` equivalent radii of the half-maximum region; the volume
//! interval holds the volumes fitted in windows of 1.5 and 2.5 radii, how much the answer
//! hangs on where the background is read.

use super::{half_max, Inputs, Sized};
use crate::formats::canvas::Canvas;
use crate::formats::exr_image::DrrImage;
use crate::geometry::{Aabb, Camera, SceneFrame};
use crate::kernels::filters::distance_inside_mm;
use crate::kernels::localization::GroundTruthOnGrid;
use crate::kernels::raymarch::{march_ray, VolumeField};
use crate::kernels::robust_fit::{fit_soft_l1, Problem};
use crate::kernels::stats::{median, percentile};
use crate::stage::select::find::Centres;
use crate::stage::select::preview::{on_edge, Sheet, RED};
use crate::stage::select::result::{Selection, ShadowFit};
use crate::stage::sweep::equivalent_diameter_mm;
use crate::volume::Volume;
use glam::DVec3;
use std::collections::HashMap;
use std::f64::consts::PI;
use std::sync::Mutex;

/// The window's radius, in equivalent radii of the half-maximum region (plus a margin).
const WINDOW_RADII: f64 = 2.0;
/// The windows whose volumes bound the volume interval.
const INTERVAL_WINDOW_RADII: [f64; 2] = [1.5, 2.5];
/// Pixels added to every window's radius, so a small nodule's window still holds background.
const WINDOW_MARGIN_PX: f64 = 3.0;
/// The soft-L1 loss's scale, in optical depth: about a tenth of a solid 1 cm nodule's shadow.
const LOSS_SCALE: f64 = 0.01;
/// The fit keeps each semi-axis within [r/k, k·r] of the region's equivalent radius r, and the
/// centre within r of the region's centroid along each axis.
const AXIS_RANGE: f64 = 2.0;
/// How far around the half-maximum region the field is cleared for the background (mm): the
/// fit's blur of the nodule reaches a few millimetres past it.
const CLEARED_MM: f64 = 4.0;
/// The shell beyond the cleared neighbourhood whose lung gives the value it is set to (mm).
const SHELL_MM: f64 = 4.0;
/// Background terms per view: 1, u, v, u², uv, v².
const BACKGROUND_TERMS: usize = 6;
/// Centre (3), log semi-axes (3), contrast (1).
const SHAPE_PARAMS: usize = 7;

/// Each rule's half-maximum region, sized by the ellipsoid that best explains its shadows: the
/// shadows say how much, σ's own shape at that volume says where.
pub fn size(inputs: &Inputs, centres: &Centres) -> [Sized; 3] {
    let views = inputs.views.expect("sizing by shadows reads the views");
    half_max::size_then(inputs, centres, |centre, cut, region| {
        shadow_selection(
            views,
            (&region.0, &region.1),
            inputs.density,
            inputs.scored.region.as_deref(),
            inputs.gt,
            |v| half_max::region_of_volume(inputs.scored, inputs.sweep, centre, cut.reach_mm, v),
        )
    })
}

/// The three views as the fit reads them: nominal cameras (the ones training used) and optical
/// depths.
pub struct Views {
    pub views: Vec<(Camera, Vec<f64>)>,
    pub frame: SceneFrame,
    pub aabb: Aabb,
}

impl Views {
    /// Pairs each camera with its DRR (of the camera's size), as optical depths −ln(I/I0).
    pub fn new(cameras: &[Camera], images: &[DrrImage], frame: SceneFrame, aabb: Aabb) -> Views {
        let views = cameras
            .iter()
            .zip(images)
            .map(|(camera, image)| {
                let depths = image.pixels.iter().map(|&i| -f64::from(i).max(1e-12).ln()).collect();
                (*camera, depths)
            })
            .collect();
        Views { views, frame, aabb }
    }
}

/// An ellipsoid with axes along the patient (scene) axes, in scene units.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Ellipsoid {
    pub centre: DVec3,
    pub semi_axes: DVec3,
}

impl Ellipsoid {
    /// Length of the ray `eye + t·dir` (unit `dir`) inside the ellipsoid and within `t ∈ [t0, t1]`.
    pub fn chord(&self, eye: DVec3, dir: DVec3, (t0, t1): (f64, f64)) -> f64 {
        let o = (eye - self.centre) / self.semi_axes;
        let d = dir / self.semi_axes;
        let (a, b, c) = (d.dot(d), 2.0 * o.dot(d), o.dot(o) - 1.0);
        let disc = b * b - 4.0 * a * c;
        if disc <= 0.0 {
            return 0.0;
        }
        let root = disc.sqrt();
        let (enter, exit) = ((-b - root) / (2.0 * a), (-b + root) / (2.0 * a));
        (exit.min(t1) - enter.max(t0)).max(0.0)
    }

    pub fn volume(&self) -> f64 {
        4.0 / 3.0 * PI * self.semi_axes.x * self.semi_axes.y * self.semi_axes.z
    }
}

/// One window pixel: its ray (clipped to the box), optical depth less the field's background,
/// and the basis of the quadratic.
struct Pixel {
    dir: DVec3,
    box_t: (f64, f64),
    depth: f64,
    basis: [f64; BACKGROUND_TERMS],
}

/// Where a ball of `radius` (scene units) around `centre` projects in `camera`'s image: its
/// centre's pixel coordinates and its radius in pixels; `None` behind the camera.
fn projected_disc(camera: &Camera, centre: DVec3, radius: f64) -> Option<(f64, f64, f64)> {
    let (u0, v0) = camera.project(centre)?;
    let (u1, _) = camera.project(centre + radius * camera.pose().x_axis.truncate())?;
    Some((u0, v0, (u1 - u0).abs()))
}

/// The ellipsoid whose shadows, over `background(eye, dir)` (the line integral of what is not
/// the nodule) plus a quadratic, best explain the three views in windows of `window_radii` ×
/// `radius` (scene units) around `centre` (scene), with its contrast, or `None` when no view has
/// a pixel there.
pub fn fit_ellipsoid(
    views: &Views,
    background: &dyn Fn(DVec3, DVec3) -> f64,
    centre: DVec3,
    radius: f64,
    window_radii: f64,
) -> Option<(Ellipsoid, f64)> {
    let windows: Vec<(DVec3, Vec<Pixel>)> = views
        .views
        .iter()
        .filter_map(|(camera, depths)| {
            let (u0, v0, ball_px) = projected_disc(camera, centre, radius)?;
            let radius_px = ball_px * window_radii + WINDOW_MARGIN_PX;
            let eye = camera.eye();
            let rows =
                (v0 - radius_px).floor().max(0.0) as usize..((v0 + radius_px).ceil() as usize).min(camera.height);
            let mut pixels = Vec::new();
            for j in rows {
                for i in
                    (u0 - radius_px).floor().max(0.0) as usize..((u0 + radius_px).ceil() as usize).min(camera.width)
                {
                    let (u, v) = ((i as f64 + 0.5 - u0) / radius_px, (j as f64 + 0.5 - v0) / radius_px);
                    if u * u + v * v > 1.0 {
                        continue;
                    }
                    let dir = camera.ray_dir(i, j);
                    let Some(box_t) = views.aabb.intersect(eye, dir) else { continue };
                    let depth = depths[i + camera.width * j] - background(eye, dir);
                    pixels.push(Pixel { dir, box_t, depth, basis: [1.0, u, v, u * u, u * v, v * v] });
                }
            }
            (!pixels.is_empty()).then_some((eye, pixels))
        })
        .collect();
    if windows.is_empty() {
        return None;
    }
    let shape = |x: &[f64]| Ellipsoid {
        centre: DVec3::new(x[0], x[1], x[2]),
        semi_axes: DVec3::new(x[3].exp(), x[4].exp(), x[5].exp()),
    };
    // Each pixel's chord through the last shape evaluated: most evaluations (the Jacobian's
    // columns of the background's coefficients) move the background alone.
    let chords: Mutex<([f64; 6], Vec<f64>)> = Mutex::new(([f64::NAN; 6], Vec::new()));
    let residuals = |x: &[f64], r: &mut [f64]| {
        let mut chords = chords.lock().expect("a fit runs on one thread");
        let (key, chords) = &mut *chords;
        if key.iter().zip(x).any(|(k, v)| k.to_bits() != v.to_bits()) {
            let ellipsoid = shape(x);
            chords.clear();
            chords.extend(
                windows.iter().flat_map(|(eye, pixels)| pixels.iter().map(|p| ellipsoid.chord(*eye, p.dir, p.box_t))),
            );
            *key = std::array::from_fn(|i| x[i]);
        }
        let contrast = x[6];
        let mut k = 0;
        for (w, (_, pixels)) in windows.iter().enumerate() {
            let coefficients = &x[SHAPE_PARAMS + BACKGROUND_TERMS * w..][..BACKGROUND_TERMS];
            for p in pixels {
                let background: f64 = p.basis.iter().zip(coefficients).map(|(b, c)| b * c).sum();
                r[k] = background + contrast * chords[k] - p.depth;
                k += 1;
            }
        }
    };
    let n = SHAPE_PARAMS + BACKGROUND_TERMS * windows.len();
    let (mut lower, mut upper) = (vec![f64::NEG_INFINITY; n], vec![f64::INFINITY; n]);
    let mut x0 = vec![0.0; n];
    for a in 0..3 {
        x0[a] = centre[a];
        (lower[a], upper[a]) = (centre[a] - radius, centre[a] + radius);
        x0[3 + a] = radius.ln();
        (lower[3 + a], upper[3 + a]) = ((radius / AXIS_RANGE).ln(), (radius * AXIS_RANGE).ln());
    }
    // A nodule is denser than what surrounds it; half a solid nodule's contrast to start.
    (x0[6], lower[6]) = (0.5, 0.0);
    for (w, (_, pixels)) in windows.iter().enumerate() {
        x0[SHAPE_PARAMS + BACKGROUND_TERMS * w] = median(&pixels.iter().map(|p| p.depth).collect::<Vec<_>>());
    }
    let residual_count = windows.iter().map(|(_, p)| p.len()).sum();
    let problem = Problem { residuals: &residuals, residual_count, lower, upper, loss_scale: LOSS_SCALE };
    let x = fit_soft_l1(&problem, &x0).x;
    Some((shape(&x), x[6]))
}

/// `half_max` (a rule's half-maximum selection) sized by its shadows: the fitted ellipsoid's
/// volume, with the volumes fitted in the narrower and wider windows as its interval. Its mask
/// and centroid are `region_of_volume`'s region at that volume (the field's own shape of the
/// nodule: a nodule is seldom an ellipsoid); the candidate keeps the half-maximum region's
/// threshold and label (where it was found). `None` when no view sees it.
pub fn shadow_selection(
    views: &Views,
    (half_max, half_max_mask): (&Selection, &[bool]),
    density: &Volume<f32>,
    lungs: Option<&[bool]>,
    gt: Option<&GroundTruthOnGrid>,
    region_of_volume: impl Fn(f64) -> Option<(Vec<bool>, [f64; 3])>,
) -> Option<(Selection, Vec<bool>)> {
    let mm_per_unit = views.frame.mm_per_unit;
    let region = &half_max.candidate;
    let centre = views.frame.to_scene(DVec3::from(region.centroid_mm));
    let radius = 0.5 * region.diameter_mm / mm_per_unit;
    let cleared = without_nodule(density, half_max_mask, lungs);
    let field = VolumeField::new(&cleared, &views.frame);
    // The fits' windows overlap: each ray is marched once.
    let marched = Mutex::new(HashMap::new());
    let background = |eye: DVec3, dir: DVec3| {
        let ray = [eye.x, eye.y, eye.z, dir.x, dir.y, dir.z].map(f64::to_bits);
        let mut marched = marched.lock().expect("the fits run on one thread");
        *marched.entry(ray).or_insert_with(|| march_ray(&field, &views.aabb, eye, dir, f64::INFINITY))
    };
    let volume_mm3 = |e: &Ellipsoid| e.volume() * mm_per_unit.powi(3);
    let (ellipsoid, contrast) = fit_ellipsoid(views, &background, centre, radius, WINDOW_RADII)?;
    let volume = volume_mm3(&ellipsoid);
    let mut interval = [volume; 2];
    for window in INTERVAL_WINDOW_RADII {
        if let Some((e, _)) = fit_ellipsoid(views, &background, centre, radius, window) {
            interval = [interval[0].min(volume_mm3(&e)), interval[1].max(volume_mm3(&e))];
        }
    }
    let (mask, centroid_mm) = region_of_volume(volume)?;
    let candidate = crate::stage::sweep::Candidate {
        voxels: mask.iter().filter(|&&m| m).count(),
        volume_mm3: volume,
        diameter_mm: equivalent_diameter_mm(volume),
        centroid_mm,
        ..region.clone()
    };
    let localization = gt.map(|gt| gt.compare(&mask, &density.geometry));
    let shadows = ShadowFit {
        centre_mm: views.frame.to_patient_mm(ellipsoid.centre).to_array(),
        semi_axes_mm: (ellipsoid.semi_axes * mm_per_unit).to_array(),
        contrast,
    };
    let selection = Selection {
        rule: half_max.rule,
        candidate,
        volume_interval_mm3: interval,
        localization,
        shadows: Some(shadows),
        tile: None,
    };
    Some((selection, mask))
}

/// `density` with every node within `CLEARED_MM` of the nodule's `region` set to the median of
/// the lung (`lungs`, or every node without it) in the `SHELL_MM` beyond: the field as if the
/// nodule and its blur were parenchyma.
fn without_nodule(density: &Volume<f32>, region: &[bool], lungs: Option<&[bool]>) -> Volume<f32> {
    let g = &density.geometry;
    let outside: Vec<bool> = region.iter().map(|&r| !r).collect();
    let distance = distance_inside_mm(&outside, g.dims, g.spacing_mm); // to the region
    let in_shell = |i: usize| distance[i] > CLEARED_MM && distance[i] <= CLEARED_MM + SHELL_MM;
    let mut shell: Vec<f64> = (0..region.len())
        .filter(|&i| in_shell(i) && lungs.is_none_or(|l| l[i]))
        .map(|i| f64::from(density.data[i]))
        .collect();
    if shell.is_empty() {
        shell = (0..region.len()).filter(|&i| in_shell(i)).map(|i| f64::from(density.data[i])).collect();
    }
    let lung = if shell.is_empty() { 0.0 } else { median(&shell) as f32 };
    let data = density.data.iter().zip(&distance).map(|(&v, &d)| if d <= CLEARED_MM { lung } else { v }).collect();
    Volume { geometry: g.clone(), data }
}

/// Screen pixels per DRR pixel in `shadows.png`.
const PREVIEW_ZOOM: usize = 4;

/// `shadows.png`: each view's optical depth around the fitted ellipsoid (coronal, sagittal,
/// axial, left to right; DRR pixels enlarged `PREVIEW_ZOOM`×, grey from the crop's 1st to 99th
/// percentile), the ellipsoid's shadow outlined in red: what the volume was read from. `title`
/// heads the sheet; each view is named, with the ellipsoid's semi-axes and volume below.
pub fn shadows_png(views: &Views, fit: &ShadowFit, title: &str) -> Vec<u8> {
    let frame = &views.frame;
    let ellipsoid = Ellipsoid {
        centre: frame.to_scene(DVec3::from(fit.centre_mm)),
        semi_axes: DVec3::from(fit.semi_axes_mm) / frame.mm_per_unit,
    };
    let reach = ellipsoid.semi_axes.max_element() * WINDOW_RADII;
    let (panels, names): (Vec<Canvas>, Vec<&str>) = views
        .views
        .iter()
        .filter_map(|(camera, depths)| {
            let (u0, v0, reach_px) = projected_disc(camera, ellipsoid.centre, reach)?;
            let half = (reach_px + WINDOW_MARGIN_PX).ceil() as i64;
            let side = 2 * half as usize + 1;
            let pixel = |c: usize, r: usize| {
                let (i, j) = (u0.floor() as i64 - half + c as i64, v0.floor() as i64 - half + r as i64);
                ((0..camera.width as i64).contains(&i) && (0..camera.height as i64).contains(&j))
                    .then_some((i as usize, j as usize))
            };
            let depth = |c, r| pixel(c, r).map(|(i, j)| depths[i + camera.width * j]);
            let inside = |c, r| {
                pixel(c, r).is_some_and(|(i, j)| {
                    let dir = camera.ray_dir(i, j);
                    views.aabb.intersect(camera.eye(), dir).is_some_and(|t| ellipsoid.chord(camera.eye(), dir, t) > 0.0)
                })
            };
            let crop: Vec<f64> = (0..side * side).filter_map(|k| depth(k % side, k / side)).collect();
            let (lo, hi) = (percentile(&crop, 1.0).ok()?, percentile(&crop, 99.0).ok()?);
            let shadow: Vec<bool> = (0..side * side).map(|k| inside(k % side, k / side)).collect();
            let edge = |c, r| on_edge(|c, r| shadow[c + side * r], side, side, c, r);
            let zoomed = side * PREVIEW_ZOOM;
            let mut rgb = vec![0u8; 3 * zoomed * zoomed];
            for (k, px) in rgb.chunks_exact_mut(3).enumerate() {
                let (c, r) = ((k % zoomed) / PREVIEW_ZOOM, (k / zoomed) / PREVIEW_ZOOM);
                px.copy_from_slice(&match depth(c, r) {
                    _ if edge(c, r) => RED,
                    Some(t) => [((t - lo) / (hi - lo).max(1e-9) * 255.0).clamp(0.0, 255.0) as u8; 3],
                    None => [0, 0, 64],
                });
            }
            Some((Canvas { width: zoomed, height: zoomed, rgb }, camera.view.name()))
        })
        .unzip();
    let [a, b, c] = fit.semi_axes_mm;
    let volume_mm3 = 4.0 / 3.0 * PI * a * b * c;
    let row = format!("semi-axes {a:.1} x {b:.1} x {c:.1} mm, {volume_mm3:.0} mm3; each DRR pixel {PREVIEW_ZOOM}x");
    let legend = [(RED, "the fitted ellipsoid's shadow"), ([0, 0, 64], "outside the view")];
    Sheet { title, badge: None, legend: &legend, columns: &names, rows: vec![(row, panels)] }.png()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::View;

    #[test]
    fn chord_of_a_sphere_through_its_centre_is_its_diameter_and_is_clipped_by_the_box() {
        let e = Ellipsoid { centre: DVec3::ZERO, semi_axes: DVec3::new(0.5, 0.5, 0.5) };
        let eye = DVec3::new(0.0, 0.0, 10.0);
        assert!((e.chord(eye, DVec3::NEG_Z, (0.0, 100.0)) - 1.0).abs() < 1e-12);
        assert!((e.chord(eye, DVec3::NEG_Z, (0.0, 10.0)) - 0.5).abs() < 1e-12);
        assert_eq!(e.chord(eye + DVec3::X, DVec3::NEG_Z, (0.0, 100.0)), 0.0);
        // Off axis by 0.3: chord 2·√(0.25 − 0.09) = 0.8.
        assert!((e.chord(eye + 0.3 * DVec3::Y, DVec3::NEG_Z, (0.0, 100.0)) - 0.8).abs() < 1e-12);
    }

    #[test]
    fn clearing_the_nodule_sets_its_neighbourhood_to_the_lung_around_it() {
        use crate::volume::Geometry;
        let n = 24;
        let geometry = Geometry {
            dims: [n; 3],
            spacing_mm: [1.0; 3],
            origin_mm: [0.0; 3],
            direction: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        };
        let at = |i: usize| [i % n, (i / n) % n, i / (n * n)];
        let from_centre = |i: usize| at(i).iter().map(|&c| (c as f64 - 12.0).powi(2)).sum::<f64>().sqrt();
        // A 2 mm nodule, its 3 mm blur, lung of 0.1 and, beyond x = 20, wall of 0.9 outside the lungs.
        let data: Vec<f32> = (0..n * n * n)
            .map(|i| match (from_centre(i), at(i)[0]) {
                (d, _) if d <= 2.0 => 1.0,
                (d, _) if d <= 5.0 => 0.5,
                (_, x) if x >= 20 => 0.9,
                _ => 0.1,
            })
            .collect();
        let region: Vec<bool> = (0..data.len()).map(|i| from_centre(i) <= 2.0).collect();
        let lungs: Vec<bool> = (0..data.len()).map(|i| at(i)[0] < 20).collect();
        let density = Volume { geometry, data };
        let cleared = without_nodule(&density, &region, Some(&lungs));
        for i in 0..cleared.data.len() {
            // Within 4 mm of the region (which reaches 2 mm from the centre): the lung's 0.1.
            let expected = if from_centre(i) <= 5.9 { 0.1 } else { density.data[i] };
            if (from_centre(i) - 6.0).abs() > 0.2 {
                assert_eq!(cleared.data[i], expected, "node {:?}", at(i));
            }
        }
    }

    /// Renders an ellipsoid of contrast 0.6 over a tilted background into three 96² views of a
    /// 2-unit box, as the drr stage's cameras see it, and fits it back from a rough start.
    #[test]
    fn recovers_an_ellipsoid_from_its_three_shadows() {
        let truth = Ellipsoid { centre: DVec3::new(0.05, -0.04, 0.03), semi_axes: DVec3::new(0.30, 0.22, 0.26) };
        let aabb = Aabb::new([-1.0; 3], [1.0; 3]);
        let (size, focal) = (96, 2000.0);
        let views: Vec<(Camera, Vec<f64>)> = View::ALL
            .iter()
            .map(|&view| {
                let camera = Camera::new(view, view.pose(50.0), focal, size, size);
                let depths = (0..size * size)
                    .map(|p| {
                        let (i, j) = (p % size, p / size);
                        let dir = camera.ray_dir(i, j);
                        let chord =
                            aabb.intersect(camera.eye(), dir).map_or(0.0, |t| truth.chord(camera.eye(), dir, t));
                        0.8 + 0.002 * i as f64 - 0.001 * j as f64 + 0.6 * chord
                    })
                    .collect();
                (camera, depths)
            })
            .collect();
        let views = Views { views, frame: SceneFrame { roi_center_mm: [0.0; 3], mm_per_unit: 40.0 }, aabb };
        let start = DVec3::new(0.0, 0.0, 0.0);
        let (fit, contrast) = fit_ellipsoid(&views, &|_, _| 0.0, start, 0.2, WINDOW_RADII).unwrap();
        assert!((contrast - 0.6).abs() < 0.02, "{contrast}");
        assert!((fit.centre - truth.centre).length() < 0.01, "{fit:?}");
        assert!((fit.semi_axes - truth.semi_axes).abs().max_element() < 0.01, "{fit:?}");
    }
}
