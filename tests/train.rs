//! The TensoRF training kernels: exact gradients (finite differences in f64), the paper's
//! failure mode and its fix, determinism, and fitting a simple scene.

use aret_pipe::geometry::{Aabb, Camera};
use aret_pipe::stage::drr::{render_views, Params as DrrParams, RoiCenter};
use aret_pipe::train::adam::Adam;
use aret_pipe::train::field::VmField;
use aret_pipe::train::fit::{fit, regularize_and_update, renderer, Views};
use aret_pipe::train::params::{DenseTvParams, TrainParams, VmParams};
use aret_pipe::train::regularize::{self, TvNorm};
use aret_pipe::train::render::{Lattice, PhotoLoss, Ray, Renderer};
use glam::DVec3;
use support::chest::chest_ct;

mod support;

const BOX: Aabb = Aabb { min: [-1.0, -0.8, -0.6], max: [1.2, 0.9, 0.7] };

/// Relative error of `a` against `b`, safe near zero.
fn rel(a: f64, b: f64) -> f64 {
    (a - b).abs() / a.abs().max(b.abs()).max(1e-10)
}

/// Walks every `stride`-th entry of every factor; `f(field)` must be the loss.
fn check_gradient(field: &VmField<f64>, grad: &VmField<f64>, stride: usize, loss: impl Fn(&VmField<f64>) -> f64) {
    let h = 1e-6;
    let mut checked = 0;
    for (p, g) in field.params().zip(grad.params()).enumerate().map(|(p, (_, g))| (p, g)) {
        for i in (p..g.len()).step_by(stride) {
            let bump = |s: f64| {
                let mut f = field.clone();
                f.params_mut().nth(p).unwrap()[i] += s * h;
                loss(&f)
            };
            let numeric = (bump(1.0) - bump(-1.0)) / (2.0 * h);
            if numeric.abs() < 1e-9 && g[i].abs() < 1e-9 {
                continue;
            }
            assert!(rel(g[i], numeric) <= 1e-4, "factor {p} entry {i}: analytic {} vs numeric {numeric}", g[i]);
            checked += 1;
        }
    }
    assert!(checked > 20, "only {checked} non-zero gradient entries checked");
}

fn test_rays() -> Vec<Ray> {
    let mut rays = Vec::new();
    for k in 0..24 {
        let a = k as f64 * 0.7;
        let origin = DVec3::new(3.0 * a.cos(), 3.0 * a.sin(), 0.4 * (k as f64 * 1.3).sin());
        let aim = DVec3::new(0.3 * (k as f64).sin(), 0.2 * (k as f64 * 0.5).cos(), 0.1);
        rays.push(Ray { origin, dir: (aim - origin).normalize(), target: 0.3 + 0.02 * k as f64 });
    }
    rays
}

#[test]
fn rendering_loss_gradient_matches_finite_differences() {
    let field: VmField<f64> = VmField::random(6, 2, 0.6, 11);
    let rays = test_rays();
    let offsets: Vec<f64> = (0..rays.len()).map(|k| 0.07 * ((k * 37 % 11) as f64 / 11.0)).collect();
    for kind in [PhotoLoss::Intensity, PhotoLoss::Log] {
        let r = Renderer { lattice: Lattice { n: 6, aabb: BOX }, shift: 0.4, scale: 1.3, step: 0.07, loss: kind };
        let loss = |f: &VmField<f64>| r.batch(&f.compose(), None, &rays, &offsets, None).loss;
        let dense = field.compose();
        let mut grad_dense = vec![0.0; dense.len()];
        let result = r.batch(&dense, None, &rays, &offsets, Some(&mut grad_dense));
        // The loss is the mean of the per-ray errors the kind defines.
        let by_ray = result.predicted.iter().zip(&rays).map(|(&p, ray)| kind.error(p, ray.target)).sum::<f64>();
        assert!(rel(result.loss, by_ray / rays.len() as f64) < 1e-12, "{kind:?}");
        check_gradient(&field, &field.contract(&grad_dense), 3, loss);
    }
    // Log: the squared difference of the optical depths.
    assert!(rel(PhotoLoss::Log.error(0.5, 0.25), (0.25f64.ln() - 0.5f64.ln()).powi(2)) < 1e-15);
}

#[test]
fn the_gradient_holds_for_rays_through_many_scatter_slabs_both_ways() {
    // On a 20³ lattice the scatter works in two z-slabs; steep rays cross them upwards and
    // downwards (their footprints stored in walk order, read backwards when descending), and
    // flat ones stay in one.
    let n = 20;
    let field: VmField<f64> = VmField::random(n, 2, 0.6, 5);
    let rays: Vec<Ray> = (0..16)
        .map(|k| {
            let a = k as f64 * 0.9;
            let (up, flat) = (if k % 2 == 0 { 1.0 } else { -1.0 }, k % 4 == 3);
            let origin = DVec3::new(0.3 * a.cos(), 0.25 * a.sin(), if flat { 0.1 } else { -2.0 * up });
            let aim = DVec3::new(0.1 * a.sin(), -0.1 * a.cos(), if flat { 0.12 } else { 0.05 * up });
            let dir = if flat { DVec3::new(a.cos(), a.sin(), 0.01) } else { aim - origin };
            Ray { origin, dir: dir.normalize(), target: 0.4 + 0.01 * k as f64 }
        })
        .collect();
    let offsets: Vec<f64> = (0..rays.len()).map(|k| 0.03 * ((k * 7 % 5) as f64 / 5.0)).collect();
    let r =
        Renderer { lattice: Lattice { n, aabb: BOX }, shift: 0.4, scale: 1.3, step: 0.03, loss: PhotoLoss::Intensity };
    let loss = |f: &VmField<f64>| r.batch(&f.compose(), None, &rays, &offsets, None).loss;
    let dense = field.compose();
    let mut grad_dense = vec![0.0; dense.len()];
    r.batch(&dense, None, &rays, &offsets, Some(&mut grad_dense));
    check_gradient(&field, &field.contract(&grad_dense), 7, loss);
}

#[test]
fn regulariser_gradients_match_finite_differences() {
    let field: VmField<f64> = VmField::random(5, 2, 1.0, 5);
    let mut grad = VmField::zeros(5, 2);
    regularize::l1(&field, 1.0, &mut grad);
    check_gradient(&field, &grad, 2, |f| regularize::l1(f, 0.0, &mut VmField::zeros(5, 2)));
    for norm in [TvNorm::L1, TvNorm::L2] {
        let mut grad = VmField::zeros(5, 2);
        regularize::tv(&field, norm, 1.0, &mut grad);
        check_gradient(&field, &grad, 1, |f| regularize::tv(f, norm, 0.0, &mut VmField::zeros(5, 2)));
    }
}

#[test]
fn the_fused_regularise_and_update_pass_equals_its_two_passes_bit_for_bit() {
    // The training loop adds L1 + TV and updates by Adam in one pass per factor component;
    // the result must be l1_and_tv, then Adam::update, to the last bit.
    for (norm, seed) in [(TvNorm::L1, 3), (TvNorm::L2, 4)] {
        let vm = VmParams { lambda_l1: 0.3, lambda_tv: 0.7, tv_norm: norm, ..VmParams::default() };
        let params = TrainParams { vm, ..TrainParams::tensorf() };
        let field: VmField<f32> = VmField::random(16, 3, 1.0, seed);
        let grad: VmField<f32> = VmField::random(16, 3, 0.1, seed + 10);
        let (mut a_field, mut a_grad, mut a_adam) = (field.clone(), grad.clone(), Adam::new(params.vm.adam(), &field));
        let (mut b_field, mut b_grad, mut b_adam) = (field.clone(), grad.clone(), Adam::new(params.vm.adam(), &field));
        let (mut c_field, mut c_adam) = (field.clone(), Adam::new(params.vm.adam(), &field));
        for _ in 0..3 {
            let (l1, tv) = regularize::l1_and_tv(&a_field, Some(0.3), Some((norm, 0.7)), &mut a_grad);
            let lr = a_adam.update(&mut a_field, &a_grad);
            let fused = regularize_and_update(&params, &mut b_field, &mut b_grad, &mut b_adam, true);
            assert_eq!(fused, (lr, (l1, tv)));
            assert_eq!(a_grad, b_grad, "{norm:?}: gradients");
            assert_eq!(a_field, b_field, "{norm:?}: updated factors");
            // Unlogged, the values are left out and the update is the same.
            let mut c = (c_field.clone(), grad.clone(), c_adam);
            let unlogged = regularize_and_update(&params, &mut c.0, &mut c.1, &mut c.2, false);
            assert_eq!(unlogged, (lr, (0.0, 0.0)));
            assert_eq!(c.1, b_grad, "{norm:?}: gradients, unlogged");
            assert_eq!(c.0, b_field, "{norm:?}: updated factors, unlogged");
            (c_field, c_adam) = (c.0, c.2);
            (a_grad, b_grad) = (grad.clone(), grad.clone());
        }
        assert_ne!(a_field, field, "the update moved the factors");
    }
}

#[test]
fn dense_tv_gradient_matches_finite_differences() {
    // Through the composition too: the factor gradient of TV(compose(factors)).
    let field: VmField<f64> = VmField::random(5, 2, 1.0, 9);
    let dense = field.compose();
    let mut grad_dense = vec![0.0; dense.len()];
    let value = regularize::tv_dense(&dense, 5, 1.0, &mut grad_dense);
    let loss = |f: &VmField<f64>| regularize::tv_dense(&f.compose(), 5, 0.0, &mut vec![0.0; 125]);
    assert_eq!(value, loss(&field), "the weight does not change the value");
    check_gradient(&field, &field.contract(&grad_dense), 1, loss);
    // Against the definition: the three axes' mean absolute forward differences.
    let at = |x: usize, y: usize, z: usize| dense[x + 5 * (y + 5 * z)];
    let mut sums = [0.0; 3];
    for z in 0..5 {
        for y in 0..5 {
            for x in 0..5 {
                if x < 4 {
                    sums[0] += (at(x + 1, y, z) - at(x, y, z)).abs()
                }
                if y < 4 {
                    sums[1] += (at(x, y + 1, z) - at(x, y, z)).abs()
                }
                if z < 4 {
                    sums[2] += (at(x, y, z + 1) - at(x, y, z)).abs()
                }
            }
        }
    }
    assert!(rel(value, sums.iter().sum::<f64>() / 100.0) < 1e-12);
}

/// Three 48² DRRs of the small chest-like CT without its spine: body, two lungs, a sphere.
fn phantom_views() -> (Vec<Camera>, Vec<Vec<f32>>, Aabb) {
    let drr = DrrParams { width_px: 48, height_px: 48, roi_center: RoiCenter::Mm([0.0; 3]), ..DrrParams::default() };
    let (set, images) = render_views(&drr, &chest_ct(false), [0.0; 3], "explicit").unwrap();
    (set.cameras, images, set.aabb)
}

/// A small VM fit with `vm`'s keys (rank 6, 1024 rays a batch) on a 24³ lattice.
fn small(vm: VmParams) -> TrainParams {
    TrainParams { grid: 24, log_every: 50, vm: VmParams { rank: 6, batch_rays: 1024, ..vm }, ..TrainParams::tensorf() }
}

#[test]
fn the_papers_failure_mode_never_moves_the_photometric_loss() {
    let (cameras, images, aabb) = phantom_views();
    let views = Views { cameras: &cameras, images: &images, aabb };
    // Δ = −10, s = 25: ReLU is zero everywhere, so the rendering gradient is exactly zero.
    let broken =
        TrainParams { scale: 25.0, ..small(VmParams { shift: -10.0, iterations: 100, ..VmParams::default() }) };
    let field: VmField<f32> = VmField::random(24, 6, 0.1, 3);
    let dense = field.compose();
    let rays: Vec<Ray> = views.rays().concat();
    let r = renderer(&broken, aabb);
    let mut grad = vec![0f32; dense.len()];
    r.batch(&dense, None, &rays[..2048], &vec![0.01; 2048], Some(&mut grad));
    assert!(grad.iter().all(|&g| g == 0.0), "photometric gradient is exactly zero");
    let fitted = fit(&broken, &views, |_| {});
    let first = &fitted.log[0];
    let last = fitted.log.last().unwrap();
    // Batches differ from one logged iteration to the next; the full-view error must not.
    assert_eq!(first.psnr_db, last.psnr_db, "full-view error unchanged after 100 iterations");
    assert!(last.l1 < first.l1, "the regularisers still shrink the factors");
    // With every regulariser off (λ1 = λ2 = 0, and no 3-D TV) nothing at all changes.
    let frozen_vm = VmParams { lambda_l1: 0.0, lambda_tv: 0.0, lambda_tv3d: 0.0, iterations: 20, ..broken.vm.clone() };
    let frozen = TrainParams { vm: frozen_vm.clone(), ..broken.clone() };
    let a = fit(&frozen, &views, |_| {});
    let b = fit(&TrainParams { vm: VmParams { iterations: 1, ..frozen_vm }, ..frozen.clone() }, &views, |_| {});
    assert_eq!(a.field, b.field, "zero gradient: the factors stay at their initial values");
}

/// Also the sphere-in-lung fit: every rendered view reaches ≥ 35 dB.
#[test]
fn the_fix_lowers_the_loss_tenfold_and_fits_the_sphere_scene_to_35_db() {
    let (cameras, images, aabb) = phantom_views();
    let views = Views { cameras: &cameras, images: &images, aabb };
    let fixed = small(VmParams { iterations: 300, ..VmParams::default() });
    let fitted = fit(&fixed, &views, |_| {});
    let full_view_mse =
        |row: &aret_pipe::train::fit::LogRow| row.psnr_db.iter().map(|p| 10f64.powf(-p / 10.0)).sum::<f64>();
    let (first, last) = (full_view_mse(&fitted.log[0]), full_view_mse(fitted.log.last().unwrap()));
    assert!(last * 10.0 <= first, "full-view photometric loss {first} → {last}");
    let psnr = &fitted.log.last().unwrap().psnr_db;
    assert!(psnr.iter().all(|&p| p >= 35.0), "sphere-in-lung views reach 35 dB: {psnr:?}");
}

#[test]
fn one_seed_gives_identical_factors_another_differs() {
    let (cameras, images, aabb) = phantom_views();
    let views = Views { cameras: &cameras, images: &images, aabb };
    let run = |seed: u64, threads: usize| {
        let p = small(VmParams { iterations: 40, seed, ..VmParams::default() });
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
        pool.install(|| fit(&p, &views, |_| {}).field)
    };
    let a = run(1, 1);
    assert_eq!(a, run(1, 3));
    assert_ne!(a, run(2, 2));
}

/// `model = "truth"`: each node is its cell's mean of the CT in the fit's units, and air
/// outside the CT. A constant CT gives exactly v · attenuation / s inside it.
#[test]
fn the_perfect_field_is_the_cts_cell_means_in_the_fits_units() {
    use aret_pipe::geometry::SceneFrame;
    use aret_pipe::kernels::raymarch::VolumeField;
    use aret_pipe::train::truth::cell_means;
    use aret_pipe::volume::{Geometry, Volume};
    // A CT of v = 0.5 over x ∈ [−100, 0) mm: the left half of a box 200 mm wide (scene units of 40 mm).
    let geometry = Geometry {
        dims: [20, 10, 10],
        spacing_mm: [5.0, 12.0, 12.0],
        origin_mm: [-97.5, -54.0, -54.0],
        direction: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
    };
    let ct = Volume { data: vec![0.5f32; geometry.len()], geometry };
    let frame = SceneFrame { roi_center_mm: [0.0; 3], mm_per_unit: 40.0 };
    let lattice = Lattice { n: 8, aabb: Aabb { min: [-2.5, -1.0, -1.0], max: [2.5, 1.0, 1.0] } };
    let sigma = cell_means(&VolumeField::new(&ct, &frame), 5.0 / 40.0, &lattice, 3.0);
    for z in 0..8 {
        for y in 0..8 {
            for x in 0..8 {
                let v = sigma[x + 8 * (y + 8 * z)];
                // Cells are 25 mm wide in x: 0–3 lie inside the CT (x < 0), 4–7 outside.
                let want = if x < 4 { 1.5 } else { 0.0 };
                assert!((v - want).abs() < 1e-6, "node ({x}, {y}, {z}): σ = {v}, want {want}");
            }
        }
    }
}

/// The perfect field renders the views it was not fitted to, the closer the finer its lattice,
/// and in the right units: σ scaled by 0.9 or 1.1 renders them worse.
#[test]
fn the_perfect_field_reproduces_the_views() {
    use aret_pipe::kernels::raymarch::VolumeField;
    use aret_pipe::train::dense_tv::evaluate_views;
    use aret_pipe::train::params::FieldModel;
    use aret_pipe::train::truth::cell_means;
    let drr = DrrParams { width_px: 48, height_px: 48, roi_center: RoiCenter::Mm([0.0; 3]), ..DrrParams::default() };
    let ct = chest_ct(false);
    let (set, images) = render_views(&drr, &ct, [0.0; 3], "explicit").unwrap();
    let views = Views { cameras: &set.cameras, images: &images, aabb: set.aabb };
    let psnr_db = |grid: usize, factor: f32| {
        let params = TrainParams { model: FieldModel::Truth, grid, scale: 2.0, ..TrainParams::default() };
        let r = renderer(&params, set.aabb);
        let voxel = 4.0 / set.frame.mm_per_unit; // chest_ct's finest side, 4 mm
        let sigma =
            cell_means(&VolumeField::new(&ct, &set.frame), voxel, &r.lattice, set.attenuation_scale / params.scale);
        let scaled: Vec<f32> = sigma.iter().map(|v| v * factor).collect();
        evaluate_views(&params, &views, &r, &scaled).psnr_db
    };
    let (coarse, fine) = (psnr_db(24, 1.0), psnr_db(48, 1.0));
    let (low, high) = (psnr_db(48, 0.9), psnr_db(48, 1.1));
    for view in 0..3 {
        assert!(fine[view] > 34.0, "view {view}: the CT on a 48³ lattice renders at {:.1} dB", fine[view]);
        assert!(fine[view] > coarse[view] + 5.0, "view {view}: 24³ {:.1} dB, 48³ {:.1} dB", coarse[view], fine[view]);
        assert!(fine[view] > low[view].max(high[view]), "view {view}: {fine:?} against ×0.9 {low:?}, ×1.1 {high:?}");
    }
}
/// The fits' cache keys do not depend on the CT (only the ceiling reads it), and the
/// ceiling's key holds only what it depends on: the lattice and s.
#[test]
fn only_the_perfect_field_reads_the_ct_and_its_key_ignores_the_fits_keys() {
    use aret_pipe::engine::Stage;
    use aret_pipe::stage::train::Train;
    use aret_pipe::train::params::FieldModel;
    let stage = |model, iterations| {
        let (vm, dense_tv) =
            (VmParams { iterations, ..VmParams::default() }, DenseTvParams { iterations, ..DenseTvParams::default() });
        Train { params: TrainParams { model, vm, dense_tv, ..TrainParams::default() } }
    };
    for model in [FieldModel::Vm, FieldModel::DenseTv] {
        assert!(!stage(model, 10).reads("hu", "ct_unit.raw"), "{model:?} reads the CT");
        assert!(stage(model, 10).reads("drr", "drr_axial.exr"));
    }
    let truth = stage(FieldModel::Truth, 10);
    assert!(truth.reads("hu", "ct_unit.raw") && truth.reads("hu", "ct_unit.mhd"));
    assert_eq!(truth.params(), stage(FieldModel::Truth, 99).params());
    let keys: Vec<String> = truth.params().as_object().unwrap().keys().cloned().collect();
    assert_eq!(keys, ["grid", "model", "scale"]);
    assert_ne!(stage(FieldModel::Vm, 10).params(), stage(FieldModel::Vm, 99).params());
    assert_ne!(stage(FieldModel::DenseTv, 10).params(), stage(FieldModel::DenseTv, 99).params());
    // A fit's key holds its own model's table and not the other's.
    let dense = stage(FieldModel::DenseTv, 10).params();
    assert!(dense.get("dense_tv").is_some() && dense.get("vm").is_none() && dense.get("threads").is_none(), "{dense}");
    let vm = stage(FieldModel::Vm, 10).params();
    assert!(vm.get("vm").is_some() && vm.get("dense_tv").is_none(), "{vm}");
}
