//! The pose corrections beyond their Adam steps: the gauge that keeps their common motion
//! fixed by the labels, and the refinement of one view's pose with the field frozen
//! (Levenberg-Marquardt on its six parameters, with the labels' prior and a robust loss),
//! which also gives the pose's uncertainty.

use super::*;

/// A view's pose-refinement normal equations: `jtj = J^T W J`, `jtr = J^T W r` over its
/// rays and channels (W the robust weights), the robust cost and the weighted squared
/// residuals.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub(super) struct PoseSystem {
    pub(super) jtj: [[f32; POSE_PARAMS]; POSE_PARAMS],
    pub(super) jtr: [f32; POSE_PARAMS],
    /// Sum of the weights (residuals that count) and of the weighted squared residuals.
    pub(super) weights: f32,
    pub(super) squared: f32,
    /// Huber cost of the residuals (filled in from the chunks' reports).
    pub(super) cost: f32,
    /// Jacobian rows: ray channels.
    pub(super) rows: u32,
}

impl PoseSystem {
    /// Add one ray channel's weighted Jacobian row `j` (`sqrt(w) J`), its weighted residual
    /// `r` (`sqrt(w) e`) and its weight `w`.
    pub(super) fn add(&mut self, j: &[f32; POSE_PARAMS], r: f32, w: f32) {
        if !(j.iter().all(|x| x.is_finite()) && r.is_finite()) {
            return;
        }
        for a in 0..POSE_PARAMS {
            for b in 0..POSE_PARAMS {
                self.jtj[a][b] += j[a] * j[b];
            }
            self.jtr[a] += j[a] * r;
        }
        self.weights += w;
        self.squared += r * r;
    }

    /// `other` added to this one.
    fn merge(&mut self, other: &PoseSystem) {
        for a in 0..POSE_PARAMS {
            for b in 0..POSE_PARAMS {
                self.jtj[a][b] += other.jtj[a][b];
            }
            self.jtr[a] += other.jtr[a];
        }
        self.weights += other.weights;
        self.squared += other.squared;
        self.cost += other.cost;
        self.rows += other.rows;
    }
}

/// What a pose refinement found for one view: the refined correction's uncertainty and how
/// well the view fits.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct PoseFit {
    /// Covariance of the six correction parameters `[u, v]` (the inverse of the posterior's
    /// information matrix at the result); infinite where the view does not constrain them.
    pub covariance: [[f32; POSE_PARAMS]; POSE_PARAMS],
    /// 1-sigma attitude uncertainty, degrees (the root of the summed variances of the
    /// rotation angle about the three axes).
    pub rotation_sigma_deg: f32,
    /// 1-sigma camera-position uncertainty, world units (likewise over the three axes).
    pub position_sigma: f32,
    /// Root-mean-square colour residual of the view's refinement rays before the refinement.
    pub rms_before: f32,
    /// The same after it.
    pub rms_after: f32,
    /// Levenberg-Marquardt steps taken (the others were rejected and damped).
    pub steps_taken: u32,
    /// Rays per evaluation.
    pub rays: u32,
}

impl PoseFit {
    /// No refinement: nothing known of the uncertainty.
    fn unrefined(rays: u32) -> Self {
        PoseFit {
            covariance: [[f32::INFINITY; POSE_PARAMS]; POSE_PARAMS],
            rotation_sigma_deg: f32::INFINITY,
            position_sigma: f32::INFINITY,
            rms_before: 0.0,
            rms_after: 0.0,
            steps_taken: 0,
            rays,
        }
    }
}

/// Which of a view's two sets of refinement rays: the one its steps are fitted to, or the
/// one that judges them.
#[derive(Clone, Copy, PartialEq, Eq)]
pub(super) enum RaySet {
    Fit = 0,
    Check = 1,
}

/// Where a refinement takes its view from.
#[derive(Clone, Copy)]
pub(super) enum View<'v> {
    /// A training frame's slot: its pixels, camera and label.
    Slot(usize),
    /// An image outside the store (a held-out view): only the pixels in `columns` are used.
    Image {
        camera: &'v Camera,
        pose: &'v Pose,
        pixels: &'v [u8],
        columns: (u32, u32),
    },
}

/// How many rays' worth of residuals carry the evidence of one independent observation: a
/// field's errors are smooth, so neighbouring residuals are alike, and counting every ray as
/// independent would make the evidence (and the reported certainty) this many times too
/// strong. Measured on simulated sets with exact poses (docs/book/src/pose-correction.md): with
/// every ray counted, the true errors were about six times the stated sigma.
pub const RESIDUAL_CORRELATION: f32 = 32.0;

/// Smallest noise variance of a colour channel a refinement assumes: residuals of a field
/// that fits its view to the last bit would otherwise make the evidence infinitely strong.
const MIN_NOISE_VARIANCE: f32 = 1e-6;

impl<'a> Trainer<'a> {
    /// Fix the gauge of the pose corrections: their motion common to every frame (a rigid
    /// motion of all the cameras, which the field can follow by moving itself) is removed, so
    /// the labels, not the field's drift, decide where the scene sits. About a pivot the
    /// common motion is the mean correction; about each camera's own centre, a common turn
    /// `v` also moves every centre by `2 v x c`.
    pub(super) fn fix_pose_gauge(&mut self) {
        let c = self.config;
        let (n, dim) = (c.frame_params(), c.embedding_dim as usize);
        let count = self.frames.len();
        if !c.pose_correction || count < 2 {
            return;
        }
        let params = |this: &Self, slot: usize| -> (Vec3, Vec3) {
            let p = &this.frame_params[slot * n + dim..(slot + 1) * n];
            (Vec3::new(p[0], p[1], p[2]), Vec3::new(p[3], p[4], p[5]))
        };
        let pivot = c.pose_pivot_point();
        let turn_arm = |slot: usize, this: &Self| match pivot {
            Some(_) => Vec3::ZERO,
            None => Vec3::from_array(this.frames.meta[slot].center),
        };
        let mut mean_v = Vec3::ZERO;
        for i in 0..count {
            if let Some(slot) = self.frames.occupied_slot(i) {
                mean_v += params(self, slot).1;
            }
        }
        mean_v /= count as f32;
        let unit = self.length_unit;
        let mut mean_u = Vec3::ZERO;
        for i in 0..count {
            if let Some(slot) = self.frames.occupied_slot(i) {
                let u = params(self, slot).0;
                mean_u += u - mean_v.cross(turn_arm(slot, self)) * (2.0 / unit);
            }
        }
        mean_u /= count as f32;
        for i in 0..count {
            let Some(slot) = self.frames.occupied_slot(i) else {
                continue;
            };
            let shift = mean_u + mean_v.cross(turn_arm(slot, self)) * (2.0 / unit);
            let p = &mut self.frame_params[slot * n + dim..(slot + 1) * n];
            for a in 0..3 {
                p[a] -= shift[a];
                p[3 + a] -= mean_v[a];
            }
        }
    }

    /// Add the labels' prior to the pose corrections' gradients of a training step whose
    /// mean squared error per channel is `mse`, weighed against the photometric loss as the
    /// refinement weighs it: the step's loss gives each frame about `rays / frames` rays,
    /// the refinement `pose_refine_rays` rays of `RESIDUAL_CORRELATION` times the colour
    /// noise, so the prior's gradient `P^T P x` enters scaled by
    /// `2 noise / (3 frames pose_refine_rays)` (with `noise = mse * RESIDUAL_CORRELATION`).
    /// The gradients are the first chunk's, where the step has summed them.
    pub(super) fn add_pose_prior_gradients(&mut self, mse: f32) {
        let c = self.config;
        let count = self.frames.len();
        if (c.pose_prior_rotation_deg <= 0.0 && c.pose_prior_position <= 0.0) || count == 0 {
            return;
        }
        let (n, dim) = (c.frame_params(), c.embedding_dim as usize);
        let noise = mse.max(MIN_NOISE_VARIANCE) * RESIDUAL_CORRELATION;
        let scale = 2.0 * noise / (3.0 * count as f32 * c.pose_refine_rays.max(1) as f32);
        let pivot = c.pose_pivot_point();
        for i in 0..count {
            let Some(slot) = self.frames.occupied_slot(i) else {
                continue;
            };
            // The prior's lever (see `prior_factor`): minus the pivot, or minus the centre.
            let lever = -pivot.unwrap_or(Vec3::from_array(self.frames.meta[slot].center));
            let information = mul_t(&self.prior_factor(lever));
            let x: [f32; POSE_PARAMS] =
                core::array::from_fn(|k| self.frame_params[slot * n + dim + k]);
            let pull = mul_vec(&information, &x);
            let Some(first) = self.chunks.first_mut() else {
                return;
            };
            for (g, p) in first.frame_grads[slot * n + dim..(slot + 1) * n]
                .iter_mut()
                .zip(pull)
            {
                *g += scale * p;
            }
        }
    }

    /// Refine the pose correction of the training frame in `slot` with the field frozen:
    /// `pose_refine_iterations` Levenberg-Marquardt steps on its six parameters over
    /// `pose_refine_rays` rays through its target (the same rays each time, sampled at
    /// fixed places), minimising the Huber cost of the colour residuals (saturated pixels
    /// left out) plus the labels' Gaussian prior (`pose_prior_rotation_deg`,
    /// `pose_prior_position`). The result replaces the slot's correction; its uncertainty
    /// comes from the posterior's information matrix. Without pose correction, or with no
    /// iterations, nothing changes and the fit says so (`steps_taken` 0). A store that keeps
    /// a ray reservoir has no whole frame to refine against: refused (`ray_store`).
    pub fn refine_pose<E: Executor>(
        &mut self,
        executor: &E,
        slot: usize,
    ) -> Result<PoseFit, Error> {
        self.require_training()?;
        let c = self.config;
        let n = c.frame_params();
        if self.frames.meta.get(slot).is_none_or(|m| m.occupied == 0) {
            return Err(Error::InvalidFrame { field: "slot" });
        }
        if self.frames.keeps_rays() {
            return Err(Error::InvalidConfig { field: "ray_store" });
        }
        const MOST: usize = 128 + POSE_PARAMS;
        let mut params = [0.0f32; MOST];
        params[..n].copy_from_slice(&self.frame_params[slot * n..(slot + 1) * n]);
        if !c.pose_correction {
            return Ok(PoseFit::unrefined(0));
        }
        let iterations = c.pose_refine_iterations;
        let fit = self.refine(executor, View::Slot(slot), &mut params[..n], iterations);
        {
            self.frame_params[slot * n..(slot + 1) * n].copy_from_slice(&params[..n]);
        }
        Ok(fit)
    }

    /// [`Trainer::refine_pose`] for a view outside the store (test-time alignment):
    /// `params` (embedding, then correction) start and end the refinement; only pixels in
    /// `columns` are used.
    pub(super) fn refine_image_pose<E: Executor>(
        &mut self,
        executor: &E,
        (camera, pose, pixels): (&Camera, &Pose, &[u8]),
        columns: (u32, u32),
        params: &mut [f32],
        iterations: u32,
    ) -> PoseFit {
        let view = View::Image {
            camera,
            pose,
            pixels,
            columns,
        };
        self.refine(executor, view, params, iterations)
    }

    /// The refinement itself (see [`Trainer::refine_pose`]); `params` is updated in place.
    fn refine<E: Executor>(
        &mut self,
        executor: &E,
        view: View<'_>,
        params: &mut [f32],
        iterations: u32,
    ) -> PoseFit {
        let c = self.config;
        let dim = c.embedding_dim as usize;
        let rays = c.pose_refine_rays as usize;
        let (label, _) = self.view_camera(view);
        let arm = match c.pose_pivot_point() {
            Some(p) => label.center - p,
            None => Vec3::ZERO,
        };
        let prior = self.prior_factor(arm - label.center);
        let prior_info = mul_t(&prior);
        let mut fit = PoseFit::unrefined(rays as u32);
        if rays == 0 {
            return fit;
        }
        let mut x: [f32; POSE_PARAMS] = core::array::from_fn(|i| params[dim + i]);
        let mut system = self.pose_system(executor, view, params, &x, (rays, RaySet::Fit));
        // The same number of other rays of the view judge each step: a step that only fits
        // the field's own errors on the fitting rays does not lower their cost.
        let check = (rays, RaySet::Check);
        let mut checked = if iterations > 0 {
            self.pose_system(executor, view, params, &x, check).cost
        } else {
            0.0
        };
        let rms = |s: &PoseSystem| libm::sqrtf(s.squared / s.weights.max(1.0));
        fit.rms_before = rms(&system);
        // The colour noise is estimated once, at the start, so that every evaluation
        // weighs the same objective.
        let noise = (system.squared / (system.weights - POSE_PARAMS as f32).max(1.0))
            .max(MIN_NOISE_VARIANCE)
            * RESIDUAL_CORRELATION;
        let objective = |s: &PoseSystem, x: &[f32; POSE_PARAMS]| {
            let r = mul_vec(&prior, x);
            s.cost / noise + 0.5 * dot(&r, &r)
        };
        let mut current = objective(&system, &x);
        let mut damping = 1e-3f32;
        for _ in 0..iterations {
            // (J^T W J / noise + P^T P + damping diag) dx = -(J^T W r / noise + P^T P x)
            let mut a = [[0.0f32; POSE_PARAMS]; POSE_PARAMS];
            let prior_grad = mul_vec(&prior_info, &x);
            let mut b = [0.0f32; POSE_PARAMS];
            for i in 0..POSE_PARAMS {
                for j in 0..POSE_PARAMS {
                    a[i][j] = system.jtj[i][j] / noise + prior_info[i][j];
                }
                b[i] = -(system.jtr[i] / noise + prior_grad[i]);
            }
            for (i, row) in a.iter_mut().enumerate() {
                row[i] += damping * row[i].max(1e-12) + 1e-12;
            }
            let Some(dx) = solve(&a, &b) else {
                damping *= 10.0;
                continue;
            };
            let trial: [f32; POSE_PARAMS] = core::array::from_fn(|i| x[i] + dx[i]);
            if !trial.iter().all(|v| v.is_finite()) {
                damping *= 10.0;
                continue;
            }
            let trial_system =
                self.pose_system(executor, view, params, &trial, (rays, RaySet::Fit));
            let value = objective(&trial_system, &trial);
            let trial_checked = if value.is_finite() && value <= current {
                self.pose_system(executor, view, params, &trial, check).cost
            } else {
                f32::INFINITY
            };
            if trial_checked <= checked {
                (x, system, current, checked) = (trial, trial_system, value, trial_checked);
                damping = (damping * 0.1).max(1e-7);
                fit.steps_taken += 1;
            } else {
                damping *= 10.0;
            }
        }
        params[dim..dim + POSE_PARAMS].copy_from_slice(&x);
        fit.rms_after = rms(&system);
        // The posterior's information at the result: the data's (Gauss-Newton) and the
        // prior's. Its inverse is the covariance of the six parameters.
        let mut information = [[0.0f32; POSE_PARAMS]; POSE_PARAMS];
        for i in 0..POSE_PARAMS {
            for j in 0..POSE_PARAMS {
                information[i][j] = system.jtj[i][j] / noise + prior_info[i][j];
            }
        }
        if let Some(covariance) = inverse(&information) {
            fit.covariance = covariance;
            // Attitude: the turn is 2 v (radians). Position: the centre moves by
            // unit * u + 2 v x arm (about a pivot), i.e. [unit I, -2 [arm]x] [u; v].
            let turn: f32 = (3..6).map(|i| 4.0 * covariance[i][i]).sum();
            fit.rotation_sigma_deg = libm::sqrtf(turn.max(0.0)).to_degrees();
            let m = centre_jacobian(self.length_unit, arm);
            let mut position = 0.0f32;
            for row in &m {
                let mc = mul_vec(&covariance, row);
                position += dot(row, &mc);
            }
            fit.position_sigma = libm::sqrtf(position.max(0.0));
        }
        fit
    }

    /// The label pose and camera of `view`.
    fn view_camera(&self, view: View<'_>) -> (Pose, Camera) {
        match view {
            View::Slot(slot) => {
                let meta = self.frames.meta[slot];
                (meta.pose(), meta.camera())
            }
            View::Image { camera, pose, .. } => (*pose, *camera),
        }
    }

    /// The prior's square-root information `P` (`|P x|² / 2` is the prior's cost), in the
    /// labels' own terms (a relative pose label: the target's attitude and position seen
    /// from the camera, as SPEED+ states their noise): the turn `2 v` over the stated
    /// attitude noise per axis (`pose_prior_rotation_deg / sqrt(3)`, the stated figure being
    /// the angle's), and the label's translation error, the centre's shift less the part a
    /// turn about the target's origin gives, `unit u + 2 v x lever` (`lever` = the arm
    /// about the pivot minus the centre: zero about the target, minus the centre about the
    /// camera), over the stated position noise per axis. Rows of zeros where none is stated.
    fn prior_factor(&self, lever: Vec3) -> [[f32; POSE_PARAMS]; POSE_PARAMS] {
        let c = self.config;
        let mut p = [[0.0f32; POSE_PARAMS]; POSE_PARAMS];
        if c.pose_prior_position > 0.0 {
            let m = centre_jacobian(self.length_unit, lever);
            for (row, m) in p.iter_mut().zip(m) {
                *row = m.map(|v| v / c.pose_prior_position);
            }
        }
        if c.pose_prior_rotation_deg > 0.0 {
            let per_axis = c.pose_prior_rotation_deg.to_radians() / libm::sqrtf(3.0);
            for a in 0..3 {
                p[3 + a][3 + a] = 2.0 / per_axis;
            }
        }
        p
    }

    /// One evaluation of a refinement at correction `x`: three Jacobian passes (one per
    /// colour channel) over the view's `rays` refinement rays (in batches of at most
    /// `rays_per_batch`), reduced in batch and chunk order.
    pub(super) fn pose_system<E: Executor>(
        &mut self,
        executor: &E,
        view: View<'_>,
        params: &[f32],
        x: &[f32; POSE_PARAMS],
        (rays, set): (usize, RaySet),
    ) -> PoseSystem {
        let c = self.config;
        let (dim, n) = (c.embedding_dim as usize, c.frame_params());
        const MOST: usize = 128 + POSE_PARAMS;
        let mut at = [0.0f32; MOST];
        at[..dim].copy_from_slice(&params[..dim]);
        at[dim..n].copy_from_slice(x);
        let (label, _) = self.view_camera(view);
        let mut total = PoseSystem::default();
        // In batches of at most the ray batch's size.
        let batch = c.rays_per_batch as usize;
        for first in (0..rays).step_by(batch.max(1)) {
            let count = batch.min(rays - first);
            self.refinement_rays(view, x, set, (first, count));
            for channel in 0..3 {
                let pass = Pass::PoseJacobian {
                    params: &at[..n],
                    center: label.center.to_array(),
                    channel,
                };
                for chunk in self.chunks.iter_mut() {
                    chunk.pose_system = PoseSystem::default();
                }
                self.with_chunks(pass, count, |shared, chunks| {
                    executor.for_each(chunks, |chunk| chunk.train(shared))
                });
                for chunk in self.chunks.iter_mut() {
                    chunk.pose_system.cost = chunk.report.robust_cost;
                    total.merge(&chunk.pose_system);
                    // The frozen field's and the embedding's gradients are not wanted.
                    chunk.mlp_grads.fill(0.0);
                    chunk.frame_grads[..n].fill(0.0);
                }
            }
        }
        total
    }

    /// The view's refinement rays `first..first + rays` into the batch, through correction
    /// `x`: pixels of
    /// its target's box (the foreground box; for an image, of its bright pixels, within its
    /// columns), drawn from the seed and the view alone, so every evaluation uses the same.
    fn refinement_rays(
        &mut self,
        view: View<'_>,
        x: &[f32; POSE_PARAMS],
        set: RaySet,
        (first, rays): (usize, usize),
    ) {
        let c = self.config;
        let correction = PoseCorrection::from_params(x, self.length_unit);
        let pivot = c.pose_pivot_point();
        let (label, camera) = self.view_camera(view);
        let width = camera.width as u32;
        let (key, [x0, x1, y0, y1]) = match view {
            View::Slot(slot) => (slot as u64, self.frames.meta[slot].foreground_box()),
            View::Image {
                pixels, columns, ..
            } => (
                u64::MAX,
                crate::frames::foreground_box_within(width, camera.height as u32, columns, |i| {
                    pixels
                        .get(i * 3..i * 3 + 3)
                        .is_some_and(crate::frames::is_bright)
                }),
            ),
        };
        for r in 0..rays {
            let index = (first + r) as u64 | (set as u64) << 40;
            let bits = rng::hash(c.seed, domain::REFINE, key, index);
            let i = x0 + rng::below(bits, (x1 - x0).max(1));
            let j = y0 + rng::below(bits.rotate_right(32), (y1 - y0).max(1));
            let pixel = (j * width + i) as usize;
            let px: [u8; 3] = match view {
                View::Slot(slot) => {
                    let at = (slot * self.frames.max_pixels + pixel) * 3;
                    core::array::from_fn(|ch| self.frames.pixels.get(at + ch).copied().unwrap_or(0))
                }
                View::Image { pixels, .. } => {
                    core::array::from_fn(|ch| pixels.get(pixel * 3 + ch).copied().unwrap_or(0))
                }
            };
            let (o, d) = Self::pixel_ray(&camera, &label, i, j);
            self.rays[r] = BatchRay {
                origin: correction.origin(o, pivot).to_array(),
                direction: correction.rotate(d).to_array(),
                target: px.map(|v| v as f32 * (1.0 / 255.0)),
                label_direction: d.to_array(),
                background: c.background,
            };
        }
    }
}

/// How the six parameters move the corrected camera centre (to first order, at zero):
/// `unit u + 2 v x arm`, rows x, y, z.
fn centre_jacobian(unit: f32, arm: Vec3) -> [[f32; POSE_PARAMS]; 3] {
    // v x arm = -arm x v: the matrix of -[arm]x.
    let cross = [
        [0.0, arm.z, -arm.y],
        [-arm.z, 0.0, arm.x],
        [arm.y, -arm.x, 0.0],
    ];
    core::array::from_fn(|r| {
        core::array::from_fn(|k| {
            if k < 3 {
                if k == r { unit } else { 0.0 }
            } else {
                2.0 * cross[r][k - 3]
            }
        })
    })
}

fn dot(a: &[f32; POSE_PARAMS], b: &[f32; POSE_PARAMS]) -> f32 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

fn mul_vec(m: &[[f32; POSE_PARAMS]; POSE_PARAMS], x: &[f32; POSE_PARAMS]) -> [f32; POSE_PARAMS] {
    core::array::from_fn(|i| dot(&m[i], x))
}

/// `m^T m`.
fn mul_t(m: &[[f32; POSE_PARAMS]; POSE_PARAMS]) -> [[f32; POSE_PARAMS]; POSE_PARAMS] {
    core::array::from_fn(|i| {
        core::array::from_fn(|j| (0..POSE_PARAMS).map(|k| m[k][i] * m[k][j]).sum())
    })
}

/// The Cholesky factor `L` of a symmetric positive definite `a` (`a = L L^T`), or `None`.
fn cholesky(a: &[[f32; POSE_PARAMS]; POSE_PARAMS]) -> Option<[[f32; POSE_PARAMS]; POSE_PARAMS]> {
    let mut l = [[0.0f32; POSE_PARAMS]; POSE_PARAMS];
    for i in 0..POSE_PARAMS {
        for j in 0..=i {
            let mut s = a[i][j];
            for k in 0..j {
                s -= l[i][k] * l[j][k];
            }
            if i == j {
                if !(s > 0.0 && s.is_finite()) {
                    return None;
                }
                l[i][i] = libm::sqrtf(s);
            } else {
                l[i][j] = s / l[j][j];
            }
        }
    }
    Some(l)
}

/// `a x = b` for a symmetric positive definite `a`, or `None`.
fn solve(
    a: &[[f32; POSE_PARAMS]; POSE_PARAMS],
    b: &[f32; POSE_PARAMS],
) -> Option<[f32; POSE_PARAMS]> {
    let l = cholesky(a)?;
    Some(cholesky_solve(&l, b))
}

fn cholesky_solve(
    l: &[[f32; POSE_PARAMS]; POSE_PARAMS],
    b: &[f32; POSE_PARAMS],
) -> [f32; POSE_PARAMS] {
    let mut y = [0.0f32; POSE_PARAMS];
    for i in 0..POSE_PARAMS {
        let mut s = b[i];
        for k in 0..i {
            s -= l[i][k] * y[k];
        }
        y[i] = s / l[i][i];
    }
    let mut x = [0.0f32; POSE_PARAMS];
    for i in (0..POSE_PARAMS).rev() {
        let mut s = y[i];
        for k in i + 1..POSE_PARAMS {
            s -= l[k][i] * x[k];
        }
        x[i] = s / l[i][i];
    }
    x
}

/// The inverse of a symmetric positive definite `a`, or `None`.
fn inverse(a: &[[f32; POSE_PARAMS]; POSE_PARAMS]) -> Option<[[f32; POSE_PARAMS]; POSE_PARAMS]> {
    let l = cholesky(a)?;
    let mut inv = [[0.0f32; POSE_PARAMS]; POSE_PARAMS];
    for j in 0..POSE_PARAMS {
        let mut e = [0.0f32; POSE_PARAMS];
        e[j] = 1.0;
        let column = cholesky_solve(&l, &e);
        for i in 0..POSE_PARAMS {
            inv[i][j] = column[i];
        }
    }
    Some(inv)
}
