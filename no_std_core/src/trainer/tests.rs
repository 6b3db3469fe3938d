//! Gradient checks of the training pass against finite differences, and the guards that
//! keep a trainer from getting stuck (a dead occupancy grid, a non-finite checkpoint).

use super::*;
use crate::PosePivot;
use crate::frames::RayRun;
use glam::Mat3;

/// A small field with embeddings and pose correction, one 8x8 frame seen from inside the
/// box (so every ray starts at t = 0 and the sample lattice does not move with the pose;
/// the gradient treats sample distances as fixed, which is exact here).
pub(super) fn small_config() -> Config {
    let mut c = Config::DEFAULT;
    c.scales = 2;
    c.resolutions = [8, 16, 0, 0];
    c.features = 8;
    c.density_hidden = 16;
    c.geo_features = 7;
    c.colour_hidden = 16;
    c.sh_bands = 3;
    c.embedding_dim = 4;
    c.pose_correction = true;
    c.occupancy_res = 8;
    c.march_steps = 128;
    // 24 steps of 3 * sqrt(3) / 128 end before any ray from the camera below can leave
    // the box, so every ray keeps exactly 24 samples whatever the pose perturbation.
    c.max_samples_per_ray = 24;
    c.max_frames = 2;
    c.max_pixels_per_frame = 64;
    c.rays_per_batch = 32;
    c.chunks = 2;
    // Two rays per pass: every chunk trains in several passes.
    c.samples_per_chunk = 64;
    c
}

/// Loss of the current batch (sum of squared errors / (3 * rays_per_batch), the quantity
/// the step differentiates) and the frame gradients of slot 0; no update is applied.
fn loss_and_frame_gradients(trainer: &mut Trainer<'_>) -> (f64, [f32; 10]) {
    trainer.forward_backward(&Sequential, &|| false).unwrap();
    let mut sse = 0.0f64;
    let mut grads = [0.0f32; 10];
    for chunk in trainer.chunks.iter_mut() {
        sse += chunk.report.squared_error as f64;
        for (g, c) in grads.iter_mut().zip(chunk.frame_grads.iter()) {
            *g += c;
        }
        chunk.frame_grads.fill(0.0);
        chunk.mlp_grads.fill(0.0);
        chunk.plane_grads.fill(0.0);
        chunk.touched.fill(0);
    }
    (sse / (3.0 * trainer.config.rays_per_batch as f64), grads)
}

#[test]
fn embedding_and_pose_correction_gradients_match_finite_differences() {
    for pivot in [PosePivot::Camera, PosePivot::TargetOrigin] {
        let mut config = small_config();
        config.pose_pivot = pivot;
        check_frame_gradients(config, 0);
    }
    // Halfway into the coarse-to-fine schedule the finer scale is weighted by 0.5.
    let mut config = small_config();
    config.pose_pivot = PosePivot::TargetOrigin;
    config.coarse_to_fine_steps = 10;
    assert_eq!(config.scale_weights_at(5)[..2], [1.0, 0.5]);
    check_frame_gradients(config, 5);
}

/// A held-out view's fit (`fit_view`): the gradients of its loss with respect to the
/// embedding and the pose correction, with the field frozen, against finite differences.
#[test]
fn view_fit_gradients_match_finite_differences() {
    for pivot in [PosePivot::Camera, PosePivot::TargetOrigin] {
        let mut config = small_config();
        config.pose_pivot = pivot;
        let plan = MemoryPlan::new(&config);
        let mut arena = [0u8; 1 << 20];
        let mut trainer = Trainer::new(config, &mut arena[..plan.total]).unwrap();
        put_test_frame(&mut trainer);
        let (camera, pose, pixels) = test_view();
        let view = (&camera, &pose, &pixels[..]);
        let start = [0.2, -0.1, 0.3, 0.05, 0.01, -0.02, 0.015, 0.02, -0.01, 0.03];
        let mut laps = trainer.profile.laps();
        let mut analytic = [0.0f32; 10];
        trainer.fit_pass(
            &Sequential,
            view,
            (0, 8),
            (3, true),
            &start,
            &mut analytic,
            &mut laps,
        );
        assert!(analytic[4..].iter().any(|g| *g != 0.0), "no pose gradient");
        for i in 0..10 {
            let h = if i < 4 { 1e-2 } else { 1e-3 };
            let mut at = |delta: f32| {
                let mut params = start;
                params[i] += delta;
                let mut grad = [0.0f32; 10];
                trainer.fit_pass(
                    &Sequential,
                    view,
                    (0, 8),
                    (3, true),
                    &params,
                    &mut grad,
                    &mut laps,
                ) as f64
            };
            let numeric = ((at(h) - at(-h)) / (2.0 * h as f64)) as f32;
            let scale = numeric.abs().max(analytic[i].abs()).max(1e-4);
            assert!(
                (analytic[i] - numeric).abs() / scale < 0.05,
                "{pivot:?}, parameter {i}: analytic {} vs numeric {numeric}",
                analytic[i]
            );
        }
    }
}

/// Train the small field on the test frame (slot 0) for 100 steps, its pose held.
fn learn_the_test_frame(trainer: &mut Trainer<'_>) {
    let correction = trainer.config.pose_correction;
    trainer.config.pose_correction = false;
    for _ in 0..100 {
        trainer.step(&Sequential).unwrap();
    }
    trainer.config.pose_correction = correction;
}

/// The camera and pose of the test frame (`put_test_frame`).
fn test_frame_pose() -> (Camera, Pose) {
    let rotation = Mat3::from_rotation_y(0.4) * Mat3::from_rotation_x(-0.3);
    let pose = Pose {
        rotation,
        center: Vec3::new(0.2, -0.1, 0.3),
    };
    (test_camera(), pose)
}

/// A held-out view of the small field: camera, pose and random pixels.
fn test_view() -> (Camera, Pose, [u8; 8 * 8 * 3]) {
    let pose = Pose {
        rotation: Mat3::from_rotation_y(-0.2) * Mat3::from_rotation_x(0.35),
        center: Vec3::new(-0.1, 0.2, 0.1),
    };
    let mut rng = rng::Rng::new(5);
    let mut pixels = [0u8; 8 * 8 * 3];
    for p in pixels.iter_mut() {
        *p = (rng.uniform() * 255.0) as u8;
    }
    (test_camera(), pose, pixels)
}

/// A pose refinement's normal equations against finite differences of its cost, for both
/// pivots: `J^T W r` is the gradient of the Huber cost, and where the view is the field's
/// own render (residuals of a quantisation step only), `J^T W J` is the cost's curvature
/// along every direction (the second differences cancel the first-order term).
#[test]
fn the_refinement_normal_equations_match_finite_differences() {
    for pivot in [PosePivot::Camera, PosePivot::TargetOrigin] {
        let mut config = small_config();
        config.pose_pivot = pivot;
        config.pose_refine_rays = 32;
        let plan = MemoryPlan::new(&config);
        let mut arena = [0u8; 1 << 20];
        let mut trainer = Trainer::new(config, &mut arena[..plan.total]).unwrap();
        put_test_frame(&mut trainer);
        let (camera, pose, random) = test_view();
        let embedding = [0.05, 0.01, -0.02, 0.015];
        let params = [0.05, 0.01, -0.02, 0.015, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0];
        // Gradient: random pixels, a correction away from zero.
        let view = View::Image {
            camera: &camera,
            pose: &pose,
            pixels: &random,
            columns: (0, 8),
        };
        let x = [0.02, -0.01, 0.03, 0.01, -0.02, 0.015];
        let system = trainer.pose_system(&Sequential, view, &params, &x, (32, RaySet::Fit));
        assert!(system.rows == 3 * 32 && system.weights > 0.0);
        for k in 0..6 {
            let h = if k < 3 { 3e-3 } else { 1e-3 };
            let mut at = |delta: f32| {
                let mut y = x;
                y[k] += delta;
                trainer
                    .pose_system(&Sequential, view, &params, &y, (32, RaySet::Fit))
                    .cost as f64
            };
            let numeric = ((at(h) - at(-h)) / (2.0 * h as f64)) as f32;
            let analytic = system.jtr[k];
            let scale = numeric.abs().max(analytic.abs()).max(1e-4);
            assert!(
                (analytic - numeric).abs() / scale < 0.05,
                "{pivot:?}, J^T W r [{k}]: {analytic} vs {numeric}"
            );
        }
        // Curvature: the view rendered by the field at the label, once the field has
        // learnt the test frame's random pixels (a contrasty field, so that the pose moves
        // the render by more than the pixels' quantisation).
        learn_the_test_frame(&mut trainer);
        let (_, pose) = test_frame_pose();
        let mut image = [0.0f32; 8 * 8 * 3];
        trainer
            .render(&Sequential, &camera, &pose, &embedding, &mut image)
            .unwrap();
        let own = image.map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8);
        let view = View::Image {
            camera: &camera,
            pose: &pose,
            pixels: &own,
            columns: (0, 8),
        };
        let zero = [0.0f32; 6];
        let system = trainer.pose_system(&Sequential, view, &params, &zero, (32, RaySet::Fit));
        let cost = |trainer: &mut Trainer<'_>, d: [f32; 6]| {
            trainer
                .pose_system(&Sequential, view, &params, &d, (32, RaySet::Fit))
                .cost as f64
        };
        let c0 = cost(&mut trainer, zero);
        for (k, l) in [
            (0, 0),
            (1, 1),
            (2, 2),
            (3, 3),
            (4, 4),
            (5, 5),
            (0, 4),
            (1, 3),
            (2, 5),
        ] {
            let h = 4e-3f32;
            let mut d = [0.0f32; 6];
            d[k] += h;
            d[l] += h;
            let plus = cost(&mut trainer, d);
            let minus = cost(&mut trainer, d.map(|v| -v));
            let numeric = (plus + minus - 2.0 * c0) / (h as f64 * h as f64);
            // d^T (J^T W J) d / h^2 with d = h (e_k + e_l).
            let analytic = (system.jtj[k][k] + system.jtj[l][l] + 2.0 * system.jtj[k][l]) as f64;
            let scale = numeric.abs().max(analytic.abs()).max(1e-3);
            assert!(
                (analytic - numeric).abs() / scale < 0.1,
                "{pivot:?}, J^T W J along e{k} + e{l}: {analytic} vs {numeric}"
            );
        }
    }
}

/// The refinement finds a pose the labels missed, and the labels' prior holds it back: the
/// view is the field's render at a corrected pose; refined from its label without a prior,
/// the correction comes back to within a tenth of itself, and its uncertainty is finite;
/// under a prior of a thousandth of the correction's size it stays at the label, and the
/// uncertainty stays within the prior's.
#[test]
fn the_refinement_recovers_a_pose_and_the_prior_pulls_it_to_the_label() {
    let mut config = small_config();
    config.pose_pivot = PosePivot::TargetOrigin;
    config.pose_refine_rays = 32;
    config.pose_refine_iterations = 8;
    let plan = MemoryPlan::new(&config);
    let mut arena = [0u8; 1 << 20];
    let mut trainer = Trainer::new(config, &mut arena[..plan.total]).unwrap();
    put_test_frame(&mut trainer);
    learn_the_test_frame(&mut trainer);
    let (camera, label) = test_frame_pose();
    let embedding = [0.05, 0.01, -0.02, 0.015];
    let truth = [0.01, -0.005, 0.0, 0.004, -0.003, 0.002];
    let moved = PoseCorrection::from_params(&truth, trainer.length_unit)
        .apply(&label, config.pose_pivot_point());
    let mut image = [0.0f32; 8 * 8 * 3];
    trainer
        .render(&Sequential, &camera, &moved, &embedding, &mut image)
        .unwrap();
    let pixels = image.map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8);
    let refine = |trainer: &mut Trainer<'_>| {
        let mut params = [0.0f32; 10];
        params[..4].copy_from_slice(&embedding);
        let fit = trainer.refine_image_pose(
            &Sequential,
            (&camera, &label, &pixels),
            (0, 8),
            &mut params,
            8,
        );
        (params, fit)
    };
    let (free, fit) = refine(&mut trainer);
    let error: f32 = (0..6)
        .map(|i| (free[4 + i] - truth[i]).powi(2))
        .sum::<f32>()
        .sqrt();
    let size: f32 = truth.iter().map(|v| v * v).sum::<f32>().sqrt();
    assert!(
        error < 0.5 * size,
        "refined {:?}, truth {truth:?}, {fit:?}",
        &free[4..]
    );
    assert!(fit.steps_taken > 0 && fit.rms_after < fit.rms_before);
    assert!(fit.rotation_sigma_deg.is_finite() && fit.position_sigma.is_finite());
    for i in 0..6 {
        let sigma = fit.covariance[i][i].sqrt();
        assert!(
            (free[4 + i] - truth[i]).abs() < 3.0 * sigma,
            "parameter {i}: {fit:?}"
        );
    }
    trainer.config.pose_prior_rotation_deg = 1e-3 * 2.0 * 0.005f32.to_degrees();
    trainer.config.pose_prior_position = 1e-3 * 0.01;
    let (held, fit) = refine(&mut trainer);
    let moved: f32 = held[4..].iter().map(|v| v * v).sum::<f32>().sqrt();
    assert!(moved < 0.01 * size, "held {:?}", &held[4..]);
    // The stated attitude noise is the angle's RMS; the label's translation is u itself
    // about the target's origin.
    assert!(fit.rotation_sigma_deg <= trainer.config.pose_prior_rotation_deg * 1.001);
    for i in 0..3 {
        let sigma = trainer.length_unit * fit.covariance[i][i].sqrt();
        assert!(
            sigma <= trainer.config.pose_prior_position * 1.001,
            "{fit:?}"
        );
    }
}

/// The refinement's uncertainty follows the evidence: the field's own render of a full
/// view gives a smaller 1-sigma than the same view cut to its two leftmost columns (a target
/// half out of the image) and than a view from four times as far (a tiny target against the
/// black sky).
#[test]
fn a_tiny_or_cut_target_gets_a_larger_pose_uncertainty_than_a_full_view() {
    let mut config = small_config();
    config.pose_pivot = PosePivot::TargetOrigin;
    config.background = [0.0; 3];
    config.pose_refine_rays = 32;
    config.pose_refine_iterations = 2;
    let plan = MemoryPlan::new(&config);
    let mut arena = [0u8; 1 << 20];
    let mut trainer = Trainer::new(config, &mut arena[..plan.total]).unwrap();
    put_test_frame(&mut trainer);
    learn_the_test_frame(&mut trainer);
    let (camera, near) = test_frame_pose();
    // Four times as far along the view axis: the box fills a few pixels.
    let axis = near.rotation * Vec3::Z;
    let far = Pose {
        rotation: near.rotation,
        center: near.center - axis * 6.0,
    };
    let embedding = [0.05, 0.01, -0.02, 0.015];
    let mut fit = |pose: &Pose, columns: (u32, u32)| {
        let mut image = [0.0f32; 8 * 8 * 3];
        trainer
            .render(&Sequential, &camera, pose, &embedding, &mut image)
            .unwrap();
        let pixels = image.map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8);
        let mut params = [0.0f32; 10];
        params[..4].copy_from_slice(&embedding);
        let view = (&camera, pose, &pixels[..]);
        trainer.refine_image_pose(&Sequential, view, columns, &mut params, 2)
    };
    let full = fit(&near, (0, 8));
    let cut = fit(&near, (0, 2));
    let tiny = fit(&far, (0, 8));
    for (name, other) in [("cut", cut), ("tiny", tiny)] {
        assert!(
            other.rotation_sigma_deg > full.rotation_sigma_deg
                && other.position_sigma > full.position_sigma,
            "{name}: {other:?} vs full {full:?}"
        );
    }
}

/// The gauge: the pose corrections' common motion is removed (about a pivot, their mean;
/// about each camera, also the centres' shift a common turn gives), their differences are
/// kept, and fixing it twice changes nothing more.
#[test]
fn the_gauge_removes_the_common_motion_and_keeps_the_differences() {
    for pivot in [PosePivot::Camera, PosePivot::TargetOrigin] {
        let mut config = small_config();
        config.pose_pivot = pivot;
        config.max_frames = 3;
        let plan = MemoryPlan::new(&config);
        let mut arena = [0u8; 1 << 20];
        let mut trainer = Trainer::new(config, &mut arena[..plan.total]).unwrap();
        let (camera, _, pixels) = test_view();
        for (slot, x) in [0.3f32, -0.2, 0.5].into_iter().enumerate() {
            let pose = Pose {
                rotation: Mat3::from_rotation_y(x),
                center: Vec3::new(x, 0.1 * slot as f32, -x),
            };
            trainer
                .set_frame(slot, camera, pose, &pixels, None)
                .unwrap();
        }
        let n = config.frame_params();
        let corrections = [
            [0.01f32, 0.02, -0.03, 0.004, -0.002, 0.001],
            [0.03, -0.01, 0.02, -0.001, 0.003, 0.002],
            [-0.02, 0.01, 0.01, 0.002, 0.001, -0.004],
        ];
        for (slot, x) in corrections.iter().enumerate() {
            trainer.frame_params[slot * n + 4..(slot + 1) * n].copy_from_slice(x);
        }
        let pose = |t: &Trainer<'_>, slot: usize| -> [f32; 6] {
            core::array::from_fn(|i| t.frame_params[slot * n + 4 + i])
        };
        trainer.fix_pose_gauge();
        let fixed: [[f32; 6]; 3] = core::array::from_fn(|s| pose(&trainer, s));
        for k in 3..6 {
            let mean: f32 = fixed.iter().map(|x| x[k]).sum::<f32>() / 3.0;
            assert!(mean.abs() < 1e-7, "{pivot:?}: mean turn {mean}");
            // The turns' differences are kept.
            let kept = (fixed[0][k] - fixed[1][k]) - (corrections[0][k] - corrections[1][k]);
            assert!(kept.abs() < 1e-7);
        }
        for k in 0..3 {
            let mean: f32 = fixed.iter().map(|x| x[k]).sum::<f32>() / 3.0;
            match pivot {
                // About the target the common translation is the mean.
                PosePivot::TargetOrigin => assert!(mean.abs() < 1e-7, "mean shift {mean}"),
                PosePivot::Camera => {}
            }
        }
        trainer.fix_pose_gauge();
        for s in 0..3 {
            let again = pose(&trainer, s);
            for k in 0..6 {
                assert!(
                    (again[k] - fixed[s][k]).abs() < 1e-6,
                    "{pivot:?}: not idempotent"
                );
            }
        }
    }
}

/// The pose corrections' Adam counts its own updates from the warm-up's end: its first
/// update moves every parameter with a gradient by the pose rate itself (Adam's first step),
/// which the global update count (steps after the field's start) would shrink.
#[test]
fn the_pose_block_counts_its_own_updates_from_its_warm_up() {
    let mut config = small_config();
    config.pose_warmup_steps = 5;
    config.max_frames = 1;
    let plan = MemoryPlan::new(&config);
    let mut arena = [0u8; 1 << 20];
    let mut trainer = Trainer::new(config, &mut arena[..plan.total]).unwrap();
    put_test_frame(&mut trainer);
    for _ in 0..5 {
        trainer.step(&Sequential).unwrap();
    }
    assert_eq!(trainer.state.pose_updates, 0);
    let before: [f32; 6] = core::array::from_fn(|i| trainer.frame_params[4 + i]);
    assert_eq!(before, [0.0; 6]);
    let rate = optim::pose_learning_rate(&config, 5);
    trainer.step(&Sequential).unwrap();
    assert_eq!(trainer.state.pose_updates, 1);
    for i in 0..6 {
        let moved = trainer.frame_params[4 + i].abs();
        assert!(
            (moved - rate).abs() < 1e-3 * rate,
            "parameter {i} moved {moved}, the rate is {rate}"
        );
    }
}

#[test]
fn coarse_to_fine_hides_the_finer_scales_at_first_and_uses_all_after_its_steps() {
    let mut config = small_config();
    config.coarse_to_fine_steps = 100;
    config.steps = 200;
    let weights = |step| config.scale_weights_at(step);
    assert_eq!(weights(0), [1.0, 0.0, 0.0, 0.0]);
    assert_eq!(weights(100), [1.0; 4]);
    assert!(weights(30)[1] > weights(20)[1] && weights(30)[1] < 1.0);
    let mut arena = [0u8; 1 << 20];
    let arena = &mut arena[..MemoryPlan::new(&config).total];
    let mut trainer = Trainer::new(config, arena).unwrap();
    put_test_frame(&mut trainer);
    let f = config.features as usize;
    let fine = trainer.geometry.first_texel[1] * f..trainer.planes.len();
    let (loss, _) = loss_and_frame_gradients(&mut trainer);
    // At step 0 the finer scale neither changes the loss nor gets a gradient.
    for v in trainer.planes[fine.clone()].iter_mut() {
        *v = f16::from_f32(v.to_f32() * 0.5);
    }
    trainer.forward_backward(&Sequential, &|| false).unwrap();
    let same: f64 = trainer
        .chunks
        .iter()
        .map(|c| c.report.squared_error as f64)
        .sum();
    assert_eq!(same / (3.0 * config.rays_per_batch as f64), loss);
    for chunk in trainer.chunks.iter() {
        assert!(chunk.plane_grads[fine.clone()].iter().all(|&g| g == 0.0));
        assert!(chunk.plane_grads[..fine.start].iter().any(|&g| g != 0.0));
    }
    // Past the schedule it does.
    trainer.state.step = 100;
    let (after, _) = loss_and_frame_gradients(&mut trainer);
    assert_ne!(after, loss);
}

#[test]
fn pose_corrections_neither_learn_nor_get_gradients_during_the_warm_up() {
    let mut config = small_config();
    config.pose_warmup_steps = 3;
    let mut arena = [0u8; 1 << 20];
    let arena = &mut arena[..MemoryPlan::new(&config).total];
    let mut trainer = Trainer::new(config, arena).unwrap();
    put_test_frame(&mut trainer);
    let dim = config.embedding_dim as usize;
    for _ in 0..3 {
        let (_, grads) = loss_and_frame_gradients(&mut trainer);
        assert!(grads[dim..].iter().all(|&g| g == 0.0), "{grads:?}");
        assert!(grads[..dim].iter().any(|&g| g != 0.0), "{grads:?}");
        trainer.step(&Sequential).unwrap();
        assert!(trainer.frame_params[dim..dim + 6].iter().all(|&p| p == 0.0));
    }
    let (_, grads) = loss_and_frame_gradients(&mut trainer);
    assert!(grads[dim..].iter().any(|&g| g != 0.0), "{grads:?}");
    trainer.step(&Sequential).unwrap();
    assert!(trainer.frame_params[dim..dim + 6].iter().any(|&p| p != 0.0));
}

#[test]
fn masked_out_pixels_train_against_a_random_background_per_ray() {
    let mut config = small_config();
    config.background = [1.0; 3];
    config.rays_per_batch = 256;
    for random_background in [false, true] {
        config.random_background = random_background;
        let mut arena = [0u8; 1 << 20];
        let arena = &mut arena[..MemoryPlan::new(&config).total];
        let mut trainer = Trainer::new(config, arena).unwrap();
        let camera = test_camera();
        let pose = Pose {
            rotation: Mat3::IDENTITY,
            center: Vec3::new(0.0, 0.0, -3.0),
        };
        // Left half: the target (grey 100, mask 255); right half: white sky (mask 0).
        let mask: [u8; 64] = core::array::from_fn(|p| if p % 8 < 4 { 255 } else { 0 });
        let pixels: [u8; 192] = core::array::from_fn(|k| if mask[k / 3] != 0 { 100 } else { 255 });
        trainer
            .set_frame(0, camera, pose, &pixels, Some(&mask))
            .unwrap();
        trainer.sample_rays(&Sequential).unwrap();
        let (mut target_rays, mut sky_rays, mut lowest, mut highest) = (0, 0, 1.0f32, 0.0f32);
        for ray in trainer.rays.iter() {
            let (target, background) = (ray.target, ray.background);
            if (target[0] - 100.0 / 255.0).abs() < 1e-6 {
                // On the target the pixel is the target, whatever the background.
                target_rays += 1;
                assert_eq!(background, [1.0; 3]);
            } else {
                // In the sky the target colour is the ray's background.
                sky_rays += 1;
                for (t, b) in target.iter().zip(background) {
                    assert!((t - b).abs() < 1e-6, "{target:?} {background:?}");
                }
                for b in background {
                    assert!((0.0..=1.0).contains(&b));
                    lowest = lowest.min(b);
                    highest = highest.max(b);
                }
            }
        }
        assert!(
            target_rays > 50 && sky_rays > 50,
            "{target_rays} {sky_rays}"
        );
        if random_background {
            assert!(lowest < 0.1 && highest > 0.9, "{lowest} {highest}");
        } else {
            assert_eq!((lowest, highest), (1.0, 1.0));
        }
    }
}

/// The 8x8 camera of the tests' frames.
fn test_camera() -> Camera {
    Camera {
        width: 8,
        height: 8,
        fx: 6.0,
        fy: 6.0,
        cx: 4.0,
        cy: 4.0,
    }
}

/// One 8x8 frame of random pixels in slot 0, seen from inside the box.
pub(super) fn put_test_frame(trainer: &mut Trainer<'_>) {
    let (camera, pose) = test_frame_pose();
    let mut rng = rng::Rng::new(11);
    let mut pixels = [0u8; 8 * 8 * 3];
    for p in pixels.iter_mut() {
        *p = (rng.uniform() * 255.0) as u8;
    }
    trainer.set_frame(0, camera, pose, &pixels, None).unwrap();
}

fn check_frame_gradients(config: Config, step: u32) {
    let plan = MemoryPlan::new(&config);
    let mut arena = [0u8; 1 << 20];
    let Some(arena) = arena.get_mut(..plan.total) else {
        panic!("test arena too small: {}", plan.total)
    };
    let mut trainer = Trainer::new(config, arena).unwrap();
    trainer.state.step = step;
    put_test_frame(&mut trainer);
    let start = [0.3, -0.2, 0.1, 0.25, 0.01, -0.02, 0.015, 0.02, -0.01, 0.03];
    trainer.frame_params[..10].copy_from_slice(&start);
    let (_, analytic) = loss_and_frame_gradients(&mut trainer);
    for i in 0..10 {
        let h = if i < 4 { 1e-2 } else { 1e-3 };
        let mut at = |x: f32| {
            trainer.frame_params[i] = x;
            let (loss, _) = loss_and_frame_gradients(&mut trainer);
            trainer.frame_params[i] = start[i];
            loss
        };
        let numeric = ((at(start[i] + h) - at(start[i] - h)) / (2.0 * h as f64)) as f32;
        let scale = numeric.abs().max(analytic[i].abs()).max(1e-4);
        assert!(
            (analytic[i] - numeric).abs() / scale < 0.05,
            "{:?}, parameter {i}: analytic {} vs numeric {numeric}",
            config.pose_pivot,
            analytic[i]
        );
    }
}

/// The backward pass compacts the density rows to the samples the early stop keeps: the
/// gradients of rays cut off after `k` samples equal, bit for bit, those of the same rays
/// marched to `k` samples only. The density is made uniform (no weight into the density
/// output, its bias set) so that every ray is cut at the same sample; the geometry features
/// still vary, so every layer, the planes and the pose corrections get gradients.
#[test]
fn samples_cut_off_leave_the_gradients_of_rays_that_end_there() {
    const RAYS: u32 = 16;
    fn gradients(max_samples: u16, arena: &mut [u8]) -> (u32, u32, u64) {
        let mut config = small_config();
        config.max_samples_per_ray = max_samples;
        config.rays_per_batch = RAYS;
        // One pass per chunk either way, so the mini-batches hold the same samples.
        config.samples_per_chunk = 256;
        let plan = MemoryPlan::new(&config);
        let Some(arena) = arena.get_mut(..plan.total) else {
            panic!("test arena too small: {}", plan.total)
        };
        let mut trainer = Trainer::new(config, arena).unwrap();
        put_test_frame(&mut trainer);
        trainer.frame_params[..10]
            .copy_from_slice(&[0.3, -0.2, 0.1, 0.25, 0.01, -0.02, 0.015, 0.02, -0.01, 0.03]);
        let out = trainer.layout.layers[DENSITY_OUT];
        for w in trainer.mlp[out.weights..out.biases]
            .iter_mut()
            .step_by(out.outputs)
        {
            *w = 0.0;
        }
        trainer.mlp[out.biases] = 25.0f32.ln();
        trainer.forward_backward(&Sequential, &|| false).unwrap();
        let (mut kept, mut marched, mut hash) = (0, 0, 0xcbf2_9ce4_8422_2325u64);
        for chunk in trainer.chunks.iter() {
            kept += chunk.report.samples;
            marched += chunk.report.marched;
            let grads = [&*chunk.mlp_grads, &*chunk.plane_grads, &*chunk.frame_grads];
            for v in grads.into_iter().flatten() {
                hash = (hash ^ v.to_bits() as u64).wrapping_mul(0x100_0000_01b3);
            }
        }
        (kept, marched, hash)
    }
    let mut arena = [0u8; 1 << 20];
    let (kept, marched, cut) = gradients(24, &mut arena);
    assert!(kept < marched, "the density cuts the rays short");
    assert_eq!(kept % RAYS, 0, "every ray is cut at the same sample");
    let k = (kept / RAYS) as u16;
    let (kept_short, marched_short, ended) = gradients(k, &mut arena);
    assert_eq!((kept_short, marched_short), (kept, kept));
    assert_eq!(cut, ended, "cut after {k} of 24 samples");
}

#[test]
fn plane_tv_smooths_the_planes_and_only_the_texels_a_step_touches() {
    let mut rough = [0.0f64; 2];
    let mut untouched_kept = [false; 2];
    for (run, weight) in [0.0, 1.0].into_iter().enumerate() {
        let mut config = small_config();
        config.plane_tv_weight = weight;
        config.warmup_steps = 0;
        config.learning_rate = 0.05;
        let mut arena = [0u8; 1 << 20];
        let arena = &mut arena[..MemoryPlan::new(&config).total];
        let mut trainer = Trainer::new(config, arena).unwrap();
        put_test_frame(&mut trainer);
        let start: heapless::Vec<f16, 8192> = trainer.planes.iter().copied().collect();
        for _ in 0..20 {
            trainer.step(&Sequential).unwrap();
        }
        rough[run] = field::plane_tv(trainer.planes, &trainer.geometry);
        // The camera inside the box never reaches the far corner's texels.
        let changed = trainer
            .planes
            .iter()
            .zip(&start)
            .filter(|(a, b)| a != b)
            .count();
        untouched_kept[run] = changed > 0 && changed < start.len();
    }
    assert!(rough[1] < 0.5 * rough[0], "{rough:?}");
    assert_eq!(untouched_kept, [true; 2]);
}

#[test]
fn a_dead_occupancy_grid_reopens_so_training_keeps_sampling() {
    // Zero planes give every cell exactly the same density, equal to the mean the threshold
    // is capped at, so no cell exceeds it: the grid would sample nothing ever again.
    let mut config = small_config();
    config.init_low = 0.0;
    config.init_high = 0.0;
    config.occupancy_threshold = 1e30;
    let plan = MemoryPlan::new(&config);
    let mut arena = [0u8; 1 << 20];
    let mut trainer = Trainer::new(config, &mut arena[..plan.total]).unwrap();
    trainer.refresh_occupancy(&Sequential);
    assert_eq!(trainer.occupancy_fraction(), 1.0);
    put_test_frame(&mut trainer);
    let report = trainer.step(&Sequential).unwrap();
    assert!(report.samples > 0 && !report.skipped, "{report:?}");
}

#[test]
fn a_checkpoint_section_with_a_nan_or_an_infinity_is_refused() {
    let config = small_config();
    let plan = MemoryPlan::new(&config);
    let mut arena = [0u8; 1 << 20];
    let mut trainer = Trainer::new(config, &mut arena[..plan.total]).unwrap();
    let mut buffer = [0u8; 1 << 16];
    let nan = f32::NAN.to_ne_bytes();
    let inf = f32::INFINITY.to_ne_bytes();
    let f16_inf = f16::NEG_INFINITY.to_ne_bytes();
    for (name, at, value) in [
        ("mlp", 4, &nan[..]),
        ("frame_params", 0, &inf[..]),
        ("planes", 2, &f16_inf[..]),
    ] {
        let saved = trainer
            .sections()
            .iter()
            .find(|(n, _)| *n == name)
            .unwrap()
            .1;
        let bytes = &mut buffer[..saved.len()];
        bytes.copy_from_slice(saved);
        bytes[at..at + value.len()].copy_from_slice(value);
        assert_eq!(
            trainer.restore_section(name, bytes),
            Err(Error::NonFiniteSection {
                name,
                index: at / value.len()
            })
        );
    }
}

#[test]
fn point_queries_agree_with_rendering_and_do_not_depend_on_the_partition() {
    let config = small_config();
    let mut arena = [0u8; 1 << 20];
    let arena = &mut arena[..MemoryPlan::new(&config).total];
    let mut trainer = Trainer::new(config, arena).unwrap();
    put_test_frame(&mut trainer);
    for _ in 0..3 {
        trainer.step(&Sequential).unwrap();
    }
    // Rays given one by one render exactly what the camera's pixel rays render.
    let (camera, pose) = (test_camera(), trainer.frames.meta[0].pose());
    let pixels = camera.pixel_count();
    let mut image = [0.0f32; 64 * 3];
    trainer
        .render(&Sequential, &camera, &pose, &[0.0; 4], &mut image)
        .unwrap();
    let (mut origins, mut directions) = ([[0.0f32; 3]; 64], [[0.0f32; 3]; 64]);
    for p in 0..pixels {
        let (o, d) = Trainer::pixel_ray(&camera, &pose, p as u32 % 8, p as u32 / 8);
        origins[p] = o.to_array();
        // Not unit length: render_rays normalises.
        directions[p] = (d * 3.0).to_array();
    }
    let mut rays = [0.0f32; 64 * 3];
    trainer
        .render_rays(&Sequential, &origins, &directions, &[0.0; 4], &mut rays)
        .unwrap();
    let close = image.iter().zip(&rays).all(|(a, b)| (a - b).abs() < 1e-6);
    assert!(close, "{image:?} vs {rays:?}");
    // A zero direction misses the box: background, no panic.
    directions[0] = [0.0; 3];
    trainer
        .render_rays(&Sequential, &origins, &directions, &[0.0; 4], &mut rays)
        .unwrap();
    assert_eq!(&rays[..3], &config.background);
    // Densities: positive and finite, the same whether asked for all at once or one by one
    // (each chunk takes a different share), and wrong lengths are errors.
    let mut points = [[0.0f32; 3]; 100];
    for (i, p) in points.iter_mut().enumerate() {
        let t = i as f32 / 99.0;
        *p = [-1.2 + 2.4 * t, 0.7 - 1.3 * t, 0.3 * t];
    }
    points[7] = [f32::NAN, 0.0, f32::INFINITY];
    let mut all = [0.0f32; 100];
    trainer.density_at(&Sequential, &points, &mut all).unwrap();
    for (p, sigma) in points.iter().zip(&all) {
        let mut one = [0.0f32];
        trainer
            .density_at(&Sequential, core::slice::from_ref(p), &mut one)
            .unwrap();
        assert_eq!(one[0].to_bits(), sigma.to_bits());
        assert!(sigma.is_finite() && *sigma >= 0.0, "{sigma}");
    }
    assert!(all.iter().any(|s| *s != all[0]));
    assert!(matches!(
        trainer.density_at(&Sequential, &points, &mut all[..99]),
        Err(Error::BufferSize { .. })
    ));
}

/// A step given up part-way (`step_or_stop`: before it starts, after a few of a chunk's
/// passes, in the other chunk's last pass) leaves no trace: every checkpoint section and
/// every gradient buffer is as before it, and the steps after it give the reports and the
/// bits of a trainer that was never stopped. A stop request that comes after the last pass
/// lets the step finish.
#[test]
fn a_step_given_up_part_way_leaves_the_trainer_as_it_was() {
    use core::sync::atomic::{AtomicUsize, Ordering};
    // Pose correction and embeddings learn from step 0; each chunk trains its 16 rays in 8
    // passes: a step asks 17 times (once before it starts, once before each pass).
    let config = small_config();
    let plan = MemoryPlan::new(&config);
    let mut arenas = [[0u8; 3 << 17]; 2];
    let [whole_arena, stopped_arena] = &mut arenas;
    let mut whole = Trainer::new(config, &mut whole_arena[..plan.total]).unwrap();
    let mut stopped = Trainer::new(config, &mut stopped_arena[..plan.total]).unwrap();
    put_test_frame(&mut whole);
    put_test_frame(&mut stopped);
    let gradients_clear = |trainer: &Trainer<'_>| {
        trainer.chunks.iter().all(|c| {
            c.plane_grads
                .iter()
                .chain(c.mlp_grads.iter())
                .all(|&g| g == 0.0)
                && c.frame_grads.iter().all(|&g| g == 0.0)
                && c.touched.iter().all(|&w| w == 0)
        })
    };
    for give_up_at in [0, 1, 4, 9, 16, 17] {
        let polls = AtomicUsize::new(0);
        let stop = || polls.fetch_add(1, Ordering::SeqCst) >= give_up_at;
        let report = stopped.step_or_stop(&Sequential, &stop).unwrap();
        if give_up_at < 17 {
            assert_eq!(report, None, "stop at poll {give_up_at}");
            assert!(polls.load(Ordering::SeqCst) > give_up_at);
            assert!(stopped.sections() == whole.sections(), "poll {give_up_at}");
            assert!(gradients_clear(&stopped), "poll {give_up_at}");
            let report = stopped.step(&Sequential).unwrap();
            assert_eq!(report, whole.step(&Sequential).unwrap());
        } else {
            assert_eq!(polls.load(Ordering::SeqCst), 17);
            assert_eq!(report, Some(whole.step(&Sequential).unwrap()));
        }
        assert!(stopped.sections() == whole.sections(), "poll {give_up_at}");
        assert!(gradients_clear(&stopped));
    }
    assert_eq!(stopped.state().step, 6);
    assert!(stopped.state().pose_updates > 0);
}

/// The small config with a ray reservoir of `rays` pixels, half of them foreground, and room
/// for 64 frames' parameters.
fn reservoir_config(rays: u32) -> Config {
    let mut c = small_config();
    c.max_frames = 64;
    c.ray_store = rays;
    c.foreground_fraction = 0.5;
    c
}

/// Test frame `k` of the reservoir tests: red says which frame, green and blue where the
/// pixel is; odd frames have a mask that lets the left half through.
fn numbered_frame(k: u8) -> ([u8; 8 * 8 * 3], Option<[u8; 64]>) {
    let mut pixels = [0u8; 8 * 8 * 3];
    for (i, px) in pixels.chunks_exact_mut(3).enumerate() {
        px.copy_from_slice(&[10 + k, 20 + 20 * (i % 8) as u8, 20 + 20 * (i / 8) as u8]);
    }
    let mask = (k % 2 == 1).then(|| core::array::from_fn(|i| if i % 8 < 4 { 255 } else { 0 }));
    (pixels, mask)
}

/// Ingest [`numbered_frame`] `k` as arrival `k`, at the test pose.
fn ingest_numbered_frame(trainer: &mut Trainer<'_>, k: u8) -> Ingested {
    let (camera, pose) = test_frame_pose();
    let (pixels, mask) = numbered_frame(k);
    let mask = mask.as_ref().map(|m| &m[..]);
    trainer
        .ingest_frame(k as u32, camera, pose, &pixels, mask)
        .unwrap()
}

/// Entries per slot of one reservoir part, checking that each entry holds its own frame's
/// pixel at its position and its mask value.
fn reservoir_counts(trainer: &Trainer<'_>, part: usize, first_frame: &[u8; 64]) -> [u32; 64] {
    let mut counts = [0u32; 64];
    for index in 0..trainer.state.rays.filled[part] as usize {
        let ray = trainer.frames.ray(part, index).unwrap();
        let (x, y) = ray.position;
        let k = first_frame[ray.slot] + (ray.slot as u8);
        let (pixels, mask) = numbered_frame(k);
        let at = (y * 8 + x) as usize;
        assert_eq!(
            ray.entry.rgb,
            pixels[at * 3..at * 3 + 3],
            "entry {index} of part {part}"
        );
        assert_eq!(ray.entry.alpha, mask.map_or(255, |m| m[at]));
        counts[ray.slot] += 1;
    }
    counts
}

/// A ray reservoir fed 40 frames holds each of them alike (the first ones are not crowded
/// out by the last, nor the last by the first), every entry is its own frame's pixel with its
/// mask value, no pixel is kept twice, and both parts are full. Emptying a slot removes its
/// entries; a frame put into an occupied slot replaces its predecessor's entries, taking the
/// places left free up to the pixels of its region.
#[test]
fn a_ray_reservoir_keeps_every_frame_alike() {
    let config = reservoir_config(4000);
    let plan = MemoryPlan::new(&config);
    let mut arena = [0u8; 1 << 20];
    let mut trainer = Trainer::new(config, &mut arena[..plan.total]).unwrap();
    let (camera, pose) = test_frame_pose();
    for k in 0..40u8 {
        let stored = ingest_numbered_frame(&mut trainer, k);
        assert_eq!(stored, Ingested::Stored { slot: k as usize });
        assert!(trainer.frames.pixels(k as usize).is_none());
    }
    assert_eq!(trainer.state.rays.filled, [2000, 2000]);
    // Each frame takes an equal share of each part's 2000 places among the frames held, but
    // no more than the 64 pixels its region holds (the foreground box is the whole 8 x 8
    // frame here): the first 31 fill the parts, and 50 places per frame at the end.
    assert_eq!(trainer.state.rays.offered, [40, 40]);
    let zero = [0u8; 64];
    for part in 0..2 {
        let counts = reservoir_counts(&trainer, part, &zero);
        assert!(
            counts[..40].iter().all(|&n| n == 50),
            "part {part}: {counts:?}"
        );
    }
    // No pixel is kept twice.
    assert!(reservoir_pixels_are_distinct(&trainer));

    let before = reservoir_counts(&trainer, 1, &zero);
    trainer.clear_frame(3);
    let after = reservoir_counts(&trainer, 1, &zero);
    assert_eq!(after[3], 0);
    assert_eq!(trainer.state.rays.filled[1], 2000 - before[3]);
    // Frame 45 into slot 5 (frame 5's): slot 5's entries now hold frame 45's pixels. Slot 3's
    // places are free, so it keeps all 64 pixels of its region and no other frame gives up any.
    let (pixels, mask) = numbered_frame(45);
    trainer
        .set_frame(5, camera, pose, &pixels, mask.as_ref().map(|m| &m[..]))
        .unwrap();
    let mut first = [0u8; 64];
    first[5] = 40;
    let replaced = reservoir_counts(&trainer, 1, &first);
    assert_eq!(replaced[5], 64);
    assert!(
        (0..40)
            .filter(|&s| s != 3 && s != 5)
            .all(|s| replaced[s] == 50)
    );
    assert_eq!(trainer.state.rays.filled[1], 2000 - 50 - 50 + 64);
    // A frame whose foreground box holds fewer pixels (one lit pixel in the corner: a 5 x 5
    // box with the margin) than its predecessor's entries keeps one entry per pixel of it;
    // the rest of the predecessor's entries leave the part.
    let filled = trainer.state.rays.filled[1];
    let mut corner = [0u8; 64];
    corner[0] = 255;
    trainer
        .set_frame(6, camera, pose, &pixels, Some(&corner))
        .unwrap();
    let in_slot_6 = (0..trainer.state.rays.filled[1] as usize)
        .filter(|&i| trainer.frames.ray(1, i).unwrap().slot == 6)
        .count() as u32;
    assert!(before[6] > 25, "{}", before[6]);
    assert_eq!(in_slot_6, 25);
    assert_eq!(trainer.state.rays.filled[1], filled - (before[6] - 25));
    assert!(reservoir_pixels_are_distinct(&trainer));
}

/// Whether every reservoir entry of a part is a different pixel of its slot (8 x 8 frames).
fn reservoir_pixels_are_distinct(trainer: &Trainer<'_>) -> bool {
    (0..2).all(|part| {
        let mut seen = [[false; 64]; 64];
        (0..trainer.state.rays.filled[part] as usize).all(|index| {
            let ray = trainer.frames.ray(part, index).unwrap();
            let (x, y) = ray.position;
            let pixel = &mut seen[ray.slot][(y * 8 + x) as usize];
            !core::mem::replace(pixel, true)
        })
    })
}

/// Training from a ray reservoir depends only on the seed and the frames in order, and a
/// trainer restored from its sections goes on bit for bit.
#[test]
fn training_from_a_ray_reservoir_is_deterministic_and_resumes_exactly() {
    let config = reservoir_config(600);
    let plan = MemoryPlan::new(&config);
    let mut arenas = [[0u8; 1 << 19]; 3];
    let [a, b, c] = &mut arenas;
    fn run(config: Config, arena: &mut [u8], steps: u32) -> Trainer<'_> {
        let mut trainer = Trainer::new(config, arena).unwrap();
        for k in 0..12u8 {
            ingest_numbered_frame(&mut trainer, k);
            for _ in 0..steps {
                trainer.step(&Sequential).unwrap();
            }
        }
        trainer
    }
    let first = run(config, &mut a[..plan.total], 2);
    let second = run(config, &mut b[..plan.total], 2);
    assert_eq!(first.sections(), second.sections());
    assert!(first.state.updates > 0 && first.state.skipped == 0);
    let mut restored = Trainer::new(config, &mut c[..plan.total]).unwrap();
    for (name, bytes) in second.sections() {
        restored.restore_section(name, bytes).unwrap();
    }
    let (mut second, mut first) = (second, first);
    for trainer in [&mut first, &mut second, &mut restored] {
        trainer.step(&Sequential).unwrap();
    }
    assert_eq!(restored.sections(), first.sections());
    // A whole-frame refinement has no frame to read here.
    assert_eq!(
        restored.refine_pose(&Sequential, 0).map(|_| ()),
        Err(Error::InvalidConfig { field: "ray_store" })
    );
}

/// A restored reservoir is not trusted: runs and counts of any values (a checkpoint written
/// by something else, its checksum valid) panic neither training nor the frames that arrive
/// after them, and each arriving frame's run holds its own pixels.
#[test]
fn a_ray_reservoir_with_arbitrary_runs_trains_and_takes_frames() {
    let config = reservoir_config(600);
    let plan = MemoryPlan::new(&config);
    let mut arena = [0u8; 1 << 19];
    let mut trainer = Trainer::new(config, &mut arena[..plan.total]).unwrap();
    for k in 0..6u8 {
        ingest_numbered_frame(&mut trainer, k);
    }
    for round in 0..40u64 {
        let bits = |i: u64| rng::hash(round, 0x5eed, i, 0);
        for slot in 0..6 {
            for part in 0..2 {
                let b = bits(slot as u64 * 2 + part as u64);
                // Small values half the time, so runs overlap and fit as well as overflow.
                let scale = |v: u64| {
                    if b & 1 == 0 {
                        (v % 700) as u32
                    } else {
                        v as u32
                    }
                };
                trainer.frames.meta[slot].rays[part] = RayRun {
                    start: scale(b >> 8),
                    count: scale(b >> 24),
                    offset: (b >> 40) as u32,
                    stride: (b >> 20) as u32,
                };
            }
        }
        trainer.state.rays.filled = [bits(100) as u32 % 800, bits(101) as u32];
        let _ = trainer.step(&Sequential);
        let k = 6 + (round % 40) as u8;
        let Ingested::Stored { slot } = ingest_numbered_frame(&mut trainer, k) else {
            continue;
        };
        for part in 0..2 {
            for index in 0..trainer.state.rays.filled[part] as usize {
                let Some(ray) = trainer.frames.ray(part, index).filter(|r| r.slot == slot) else {
                    continue;
                };
                let (pixels, mask) = numbered_frame(k);
                let at = (ray.position.1 * 8 + ray.position.0) as usize;
                assert_eq!(ray.entry.rgb, pixels[at * 3..at * 3 + 3], "round {round}");
                assert_eq!(ray.entry.alpha, mask.map_or(255, |m| m[at]));
            }
        }
        let _ = trainer.step(&Sequential);
    }
}

/// Share of a few batches' rays drawn from slot 0 of a trainer whose two frames have running
/// losses `losses`.
fn share_of_slot_zero(config: Config, losses: [f32; 2], ray_store: u32) -> f64 {
    let mut config = config;
    config.ray_store = ray_store;
    let plan = MemoryPlan::new(&config);
    let mut arena = [0u8; 1 << 19];
    let mut trainer = Trainer::new(config, &mut arena[..plan.total]).unwrap();
    let (camera, pose) = test_frame_pose();
    for slot in 0..2 {
        let (pixels, _) = numbered_frame(slot as u8);
        trainer
            .set_frame(slot, camera, pose, &pixels, None)
            .unwrap();
        trainer.frames.meta[slot].loss = losses[slot];
    }
    let (mut zero, mut all) = (0usize, 0usize);
    for step in 0..20 {
        trainer.state.step = step;
        trainer.sample_rays(&Sequential).unwrap();
        zero += trainer.ray_frames.iter().filter(|&&s| s == 0).count();
        all += trainer.ray_frames.len();
    }
    zero as f64 / all as f64
}

/// With `loss_weighted_frames`, frames are drawn in proportion to their running loss (a
/// frame at a sixteenth of the largest loss gets about one ray in seventeen), for whole frames
/// and a ray reservoir alike; without it, or before any loss is known, uniformly. A training
/// step moves the drawn frames' losses towards their rays' errors, and a frame put in starts
/// at the largest loss.
#[test]
fn loss_weighted_draws_follow_the_frames_running_losses() {
    let mut config = small_config();
    config.loss_weighted_frames = true;
    for ray_store in [0, 400] {
        let weighted = share_of_slot_zero(config, [1.0, 1.0 / 16.0], ray_store);
        assert!((0.88..0.99).contains(&weighted), "{ray_store}: {weighted}");
        let unknown = share_of_slot_zero(config, [0.0, 0.0], ray_store);
        assert!((0.35..0.65).contains(&unknown), "{ray_store}: {unknown}");
    }
    let mut plain = config;
    plain.loss_weighted_frames = false;
    let uniform = share_of_slot_zero(plain, [1.0, 1.0 / 16.0], 0);
    assert!((0.35..0.65).contains(&uniform), "{uniform}");

    let plan = MemoryPlan::new(&config);
    let mut arena = [0u8; 1 << 19];
    let mut trainer = Trainer::new(config, &mut arena[..plan.total]).unwrap();
    put_test_frame(&mut trainer);
    assert_eq!(trainer.frames.meta[0].loss, 0.0);
    trainer.step(&Sequential).unwrap();
    let learned = trainer.frames.meta[0].loss;
    assert!(learned > 0.0 && learned.is_finite(), "{learned}");
    let (camera, pose) = test_frame_pose();
    let (pixels, _) = numbered_frame(3);
    trainer.set_frame(1, camera, pose, &pixels, None).unwrap();
    assert_eq!(trainer.frames.meta[1].loss, learned);
}

/// A schedule planned anew changes the learning rates from the next step on and nothing else
/// of the config; one the config would refuse (fewer steps than the warm-up, a decay start
/// outside [0, 1)) leaves the trainer as it was.
#[test]
fn a_rescheduled_trainer_decays_over_its_new_steps_and_refuses_a_schedule_that_cannot_be() {
    let mut config = small_config();
    config.steps = u32::MAX;
    config.warmup_steps = 4;
    let plan = MemoryPlan::new(&config);
    let mut arena = [0u8; 1 << 20];
    let mut trainer = Trainer::new(config, &mut arena[..plan.total]).unwrap();
    assert_eq!(
        optim::learning_rate(trainer.config(), 99),
        config.learning_rate
    );
    trainer.reschedule(200, 0.5).unwrap();
    let rescheduled = *trainer.config();
    assert_eq!((rescheduled.steps, rescheduled.lr_decay_start), (200, 0.5));
    assert_eq!(
        Config {
            steps: config.steps,
            lr_decay_start: config.lr_decay_start,
            ..rescheduled
        },
        config
    );
    // The peak until half of the 196 steps after warm-up, the final rate at the last step.
    assert_eq!(
        optim::learning_rate(&rescheduled, 101),
        config.learning_rate
    );
    let last = optim::learning_rate(&rescheduled, 199);
    let end = config.learning_rate * config.final_lr_factor;
    assert!((last - end).abs() < 1e-3 * config.learning_rate, "{last}");
    for (steps, decay_start) in [(3, 0.5), (200, 1.0), (200, f32::NAN), (0, 0.0)] {
        assert!(trainer.reschedule(steps, decay_start).is_err());
        assert_eq!(*trainer.config(), rescheduled);
    }
}
