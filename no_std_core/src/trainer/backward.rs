//! A chunk's training pass: forward, loss and the hand-written backward pass.

use super::chunk::{
    ChunkReport, colour_rows_of, density_rows_of, embedding_of, lane_rays, ray_runs,
    row_scale_weights, split_rows,
};
use super::*;

impl Chunk<'_> {
    /// Forward, loss and backward for this chunk's rays of the batch, in as many passes as
    /// the sample capacity needs; each pass keeps its activations for its backward pass.
    pub(super) fn train(&mut self, shared: &Shared<'_>) {
        let c = shared.config;
        self.report = ChunkReport::default();
        if shared.pose_gradients {
            self.ray_grads.fill(0.0);
        }
        // Loss: sum of squared errors over the batch, normalised by the batch size.
        let norm = 1.0 / (3.0 * c.rays_per_batch as f32);
        let (mut first, end) = (self.first_ray, self.first_ray + self.ray_count);
        while first < end {
            // A stop request is heard between passes: the rest of the rays are left and the
            // step is abandoned (`Trainer::step_or_stop`).
            if shared.stop.is_some_and(|stop| stop()) {
                self.report.stopped = true;
                return;
            }
            let mut laps = shared.timer.laps();
            let (rays, marched, n) = self.forward_pass(shared, first, end, true, &mut laps);
            for r in 0..rays {
                let (start, kept_end) = (self.ray_start[r] as usize, self.kept_end[r] as usize);
                let ray = &shared.rays[first + r];
                let (colour, _) = render::composite_forward(
                    &self.sigma[start..kept_end],
                    &self.rgb[start..kept_end],
                    shared.optical_step,
                    ray.background,
                );
                let target = ray.target;
                let mut d_colour = [0.0f32; 3];
                let mut ray_error = 0.0f32;
                for ch in 0..3 {
                    let e = colour[ch] - target[ch];
                    self.report.squared_error += e * e;
                    ray_error += e * e;
                    d_colour[ch] = 2.0 * e * norm;
                }
                if let Some(loss) = self.ray_loss.get_mut(first + r - self.first_ray) {
                    *loss = ray_error;
                }
                if let Some(ch) = shared.jacobian_channel {
                    // A refinement's Jacobian pass: the backward pass of the one channel's
                    // colour itself, scaled by the root of its robust weight, gives the
                    // ray's weighted Jacobian row.
                    let e = colour[ch] - target[ch];
                    let (weight, cost) = robust_residual(e, target);
                    let root = libm::sqrtf(weight);
                    d_colour = [0.0; 3];
                    d_colour[ch] = root;
                    let g = first + r - self.first_ray;
                    let g = &mut self.ray_grads[g * RAY_GRAD_FLOATS..(g + 1) * RAY_GRAD_FLOATS];
                    g[6] = root * e;
                    g[7] = weight;
                    self.report.robust_cost += cost;
                }
                render::composite_backward(
                    &self.sigma[start..kept_end],
                    &self.rgb[start..kept_end],
                    shared.optical_step,
                    colour,
                    d_colour,
                    &mut self.d_sigma[start..kept_end],
                    &mut self.d_rgb[start..kept_end],
                );
            }
            laps.lap(Stage::Compositing, &mut self.times);
            self.backward(shared, n, &mut laps);
            self.report.rays += rays as u32;
            self.report.samples += n as u32;
            self.report.marched += marched as u32;
            first += rays;
        }
        if shared.pose_gradients {
            let mut laps = shared.timer.laps();
            if shared.jacobian_channel.is_some() {
                self.add_to_pose_system(shared);
            } else {
                self.fold_ray_gradients(shared, self.ray_count);
            }
            laps.lap(Stage::PlaneBackward, &mut self.times);
        }
    }

    /// A refinement's Jacobian pass: each ray's weighted Jacobian row with respect to the
    /// six pose parameters into the chunk's normal equations (J^T W J, J^T W r).
    fn add_to_pose_system(&mut self, shared: &Shared<'_>) {
        let Some((params, center)) = shared.fit_pose else {
            return;
        };
        let correction = PoseCorrection::from_params(&params, shared.length_unit);
        let arm = shared
            .config
            .pose_pivot_point()
            .map(|p| Vec3::from_array(center) - p);
        let system = &mut self.pose_system;
        for r in 0..self.ray_count {
            let g = &self.ray_grads[r * RAY_GRAD_FLOATS..(r + 1) * RAY_GRAD_FLOATS];
            let label = Vec3::from_array(shared.rays[self.first_ray + r].label_direction);
            let j = pose_parameter_gradient(&correction, label, arm, g, shared.length_unit);
            system.add(&j, g[6], g[7]);
        }
        system.rows += self.ray_count as u32;
    }

    /// Move each ray's origin and direction gradients to its frame's pose correction (the
    /// fitted view's, in the first frame-gradient slot, while fitting one).
    fn fold_ray_gradients(&mut self, shared: &Shared<'_>, rays: usize) {
        let c = shared.config;
        let n = c.frame_params();
        let dim = c.embedding_dim as usize;
        let pivot = c.pose_pivot_point();
        for r in 0..rays {
            let ray = self.first_ray + r;
            // The correction's parameters, the label's camera centre and the slot.
            let (params, center, slot) = match (shared.fit_pose, shared.embedding) {
                (Some((params, center)), _) => (params, Some(center), 0),
                (None, Embedding::PerFrame(all)) => {
                    let slot = shared.ray_frames[ray] as usize;
                    let params: [f32; POSE_PARAMS] = core::array::from_fn(|i| {
                        all.get(slot * n + dim + i).copied().unwrap_or(0.0)
                    });
                    (params, shared.frame_meta.get(slot).map(|m| m.center), slot)
                }
                (None, Embedding::Fixed(_)) => return,
            };
            let g = &self.ray_grads[r * RAY_GRAD_FLOATS..r * RAY_GRAD_FLOATS + 6];
            let correction = PoseCorrection::from_params(&params, shared.length_unit);
            let label = Vec3::from_array(shared.rays[ray].label_direction);
            let arm = match (pivot, center) {
                (Some(p), Some(center)) => Some(Vec3::from_array(center) - p),
                _ => None,
            };
            let d = pose_parameter_gradient(&correction, label, arm, g, shared.length_unit);
            let dst = &mut self.frame_grads[slot * n + dim..(slot + 1) * n];
            for (a, b) in dst.iter_mut().zip(d) {
                *a += b;
            }
        }
    }

    /// Push the compositing gradients of a pass (`n` samples kept) back through its stored
    /// activations, one mini-batch of kept samples at a time: the colour MLP, then the
    /// density MLP (its rows compacted to the kept samples by the forward pass, so that the
    /// samples cut off cost nothing), the planes and the poses.
    /// `laps` charges each mini-batch's parts to their stages.
    fn backward(&mut self, shared: &Shared<'_>, n: usize, laps: &mut Laps) {
        let c = shared.config;
        let layout = shared.layout;
        let (sh_len, geo_len, dim) = (
            c.sh_values(),
            c.geo_features as usize,
            c.embedding_dim as usize,
        );
        let features = c.density_inputs();
        let frame_params = c.frame_params();
        let pose = shared.pose_gradients;
        let p = shared.mlp;
        let layer = |i: usize| layout.layers[i];
        let (density_rows, colour_rows) = (density_activation_rows(c), colour_activation_rows(c));
        let values_len = 3 * features;
        let extent = shared.aabb.max - shared.aabb.min;
        let weights = row_scale_weights(shared);
        // A view fit without pose correction wants only the embedding's gradient.
        let density = !shared.fitting_view || pose;
        // A view fit only wants the spatial gradient: the frozen planes get none.
        let mut sink = if shared.fitting_view {
            PlaneGrads {
                grads: &mut [],
                touched: &mut [],
            }
        } else {
            PlaneGrads {
                grads: self.plane_grads,
                touched: self.touched,
            }
        };
        for base in (0..n).step_by(LANES) {
            let lanes = LANES.min(n - base);
            let b = base / LANES;
            let act = colour_rows_of(
                c,
                &mut self.colour_store[b * colour_rows..(b + 1) * colour_rows],
            );
            let (density_grad, grad) = split_rows(c, self.gradients);
            let kept = &self.kept_index[base..base + lanes];
            // Output gradients; unused lanes stay zero and so contribute nothing.
            for row in grad.rgb.iter_mut() {
                row.fill(0.0);
            }
            for (l, &s) in kept.iter().enumerate() {
                for ch in 0..3 {
                    grad.rgb[ch][l] =
                        self.d_rgb[s as usize][ch] * field::sigmoid_grad(act.rgb[ch][l]);
                }
            }
            let g = &mut *self.mlp_grads;
            let (l_out, l2, l1) = (
                layer(COLOUR_OUT),
                layer(COLOUR_HIDDEN2),
                layer(COLOUR_HIDDEN1),
            );
            backward_layer(
                p,
                g,
                l_out,
                act.hidden2,
                grad.rgb,
                Some(grad.hidden2),
                self.lane_major,
            );
            field::relu_backward(act.hidden2, grad.hidden2);
            backward_layer(
                p,
                g,
                l2,
                act.hidden1,
                grad.hidden2,
                Some(grad.hidden1),
                self.lane_major,
            );
            field::relu_backward(act.hidden1, grad.hidden1);
            // The first layer: its geometry rows sample by sample, its ray term (view
            // encoding and embedding, see `ray_term`) once per run of a ray's samples.
            let hidden = l1.outputs;
            let w1 = &p[l1.weights..l1.biases];
            let (dw1, db1) = g[l1.weights..l1.biases + hidden].split_at_mut(l1.biases - l1.weights);
            let geo_rows = sh_len * hidden..(sh_len + geo_len) * hidden;
            // d loss / d geometry features goes straight to the density MLP's output
            // gradients (rows 1 ..; row 0, the density's, is set below), and only when the
            // density part runs.
            let (d_density_out, d_geo) = density_grad.out.split_at_mut(1);
            let lane_major = field::layer_backward(
                &w1[geo_rows.clone()],
                act.geo,
                grad.hidden1,
                density.then_some(d_geo),
                &mut dw1[geo_rows],
                db1,
                self.lane_major,
            );
            let rays = lane_rays(kept, self.sample_ray);
            let mut sum = [0.0f32; MAX_COLOUR_HIDDEN];
            let sum = &mut sum[..hidden];
            let stride = hidden.div_ceil(8) * 8;
            for (start, end) in ray_runs(&rays[..lanes]) {
                let r = rays[start] as usize;
                // d loss / d ray term: the run's first-layer gradients summed over its lanes
                // in order (from -0.0, as `Iterator::sum`), a lane-major row at a time where
                // the layer's backward pass left them so (the adds then run side by side).
                sum.fill(-0.0);
                if lane_major {
                    for l in start..end {
                        let row = &self.lane_major[l * stride..l * stride + hidden];
                        for (s, g) in sum.iter_mut().zip(row) {
                            *s += g;
                        }
                    }
                } else {
                    for (s, row) in sum.iter_mut().zip(grad.hidden1.iter()) {
                        *s = row[start..end].iter().sum();
                    }
                }
                let (_, d) = Self::ray(shared, r);
                let mut sh = [0.0f32; 16];
                field::sh_forward(c.sh_bands as usize, d.to_array(), &mut sh);
                let mut d_sh = [0.0f32; 16];
                for k in 0..sh_len {
                    fused::axpy(&mut dw1[k * hidden..(k + 1) * hidden], sh[k], sum);
                    if pose {
                        d_sh[k] = fused::dot(&w1[k * hidden..(k + 1) * hidden], sum);
                    }
                }
                let embedding = embedding_of(shared, r);
                let slot = shared.ray_frames.get(r).copied().unwrap_or(0) as usize;
                let d_embedding = match (shared.fitting_view, shared.embedding) {
                    (true, _) => self.frame_grads.get_mut(..dim),
                    (false, Embedding::PerFrame(_)) => self
                        .frame_grads
                        .get_mut(slot * frame_params..slot * frame_params + dim),
                    (false, Embedding::Fixed(_)) => None,
                };
                if let Some(d_embedding) = d_embedding {
                    for (k, (e, de)) in embedding.iter().zip(d_embedding).enumerate() {
                        let row =
                            (sh_len + geo_len + k) * hidden..(sh_len + geo_len + k + 1) * hidden;
                        fused::axpy(&mut dw1[row.clone()], *e, sum);
                        *de += fused::dot(&w1[row], sum);
                    }
                }
                if pose {
                    // The view encoding's share of d loss / d direction.
                    let d_view =
                        field::sh_backward(c.sh_bands as usize, d.to_array(), &d_sh[..sh_len]);
                    let at = (r - self.first_ray) * RAY_GRAD_FLOATS;
                    let g = &mut self.ray_grads[at + 3..at + 6];
                    for a in 0..3 {
                        g[a] += d_view[a];
                    }
                }
            }
            laps.lap(Stage::ColourBackward, &mut self.times);
            if !density {
                continue;
            }

            let act = density_rows_of(
                c,
                &mut self.density_store[b * density_rows..(b + 1) * density_rows],
            );
            // The density's output gradient (the geometry features' came from the colour
            // MLP above); unused lanes stay zero and so contribute nothing.
            let d_density = &mut d_density_out[0];
            d_density.fill(0.0);
            for (l, &s) in kept.iter().enumerate() {
                // d sigma / d raw = trunc_exp'(raw), which is sigma itself (clamped alike).
                d_density[l] = self.d_sigma[s as usize] * self.sigma[s as usize];
            }
            let grad = density_grad;
            let g = &mut *self.mlp_grads;
            backward_layer(
                p,
                g,
                layer(DENSITY_OUT),
                act.hidden,
                grad.out,
                Some(grad.hidden),
                self.lane_major,
            );
            field::relu_backward(act.hidden, grad.hidden);
            backward_layer(
                p,
                g,
                layer(DENSITY_HIDDEN),
                act.feats,
                grad.hidden,
                Some(grad.feats),
                self.lane_major,
            );
            laps.lap(Stage::DensityBackward, &mut self.times);

            // Each lane's feature gradients side by side (the lookup's backward takes them).
            fused::to_lane_major(grad.feats, features, self.lane_major);
            let mut d_feat = [0.0f32; 4 * 64];
            for (l, &s) in kept.iter().enumerate() {
                let s = s as usize;
                let lane = &self.lane_major[l * features..(l + 1) * features];
                for ((d, g), w) in d_feat.iter_mut().zip(lane).zip(&weights) {
                    *d = g * w;
                }
                let x = Vec3::from_array(self.positions[s]);
                let u = shared.aabb.normalise(x);
                let d_u = field::planes_backward(
                    shared.planes,
                    shared.geometry,
                    u,
                    &self.plane_values[s * values_len..(s + 1) * values_len],
                    &d_feat[..features],
                    &mut sink,
                    pose,
                );
                if pose {
                    // x = o + t d: d loss / d o = d loss / d x, d loss / d d = t d loss / d x
                    // (the view encoding's share came with the colour layer).
                    let r = self.sample_ray[s] as usize;
                    let (o, d) = Self::ray(shared, r);
                    let d_x = Vec3::from_array(d_u) / extent;
                    let d_d = d_x * (x - o).dot(d);
                    let at = (r - self.first_ray) * RAY_GRAD_FLOATS;
                    let g = &mut self.ray_grads[at..at + 6];
                    for a in 0..3 {
                        g[a] += d_x[a];
                        g[3 + a] += d_d[a];
                    }
                }
            }
            laps.lap(Stage::PlaneBackward, &mut self.times);
        }
    }
}

/// Backward of one MLP layer: its slices of the parameters and of the chunk's gradients,
/// then `field::layer_backward`.
fn backward_layer(
    params: &[f32],
    grads: &mut [f32],
    l: crate::config::Layer,
    x: &[Row],
    dy: &[Row],
    dx: Option<&mut [Row]>,
    lane_major: &mut [f32],
) {
    let (dw, db) = grads[l.weights..l.biases + l.outputs].split_at_mut(l.biases - l.weights);
    field::layer_backward(&params[l.weights..l.biases], x, dy, dx, dw, db, lane_major);
}

/// d loss / d pose parameters `[u, v]` of one ray from `g`, its d loss / d origin (0..3)
/// and d loss / d direction (3..6): the direction is the label's `label` turned by the
/// correction, and with a pivot the origin is `p + R arm + u * length_unit` (`arm` = the
/// label's centre minus the pivot), so the rotation moves it too.
pub(super) fn pose_parameter_gradient(
    correction: &PoseCorrection,
    label: Vec3,
    arm: Option<Vec3>,
    g: &[f32],
    length_unit: f32,
) -> [f32; POSE_PARAMS] {
    let d_origin = Vec3::new(g[0], g[1], g[2]);
    let mut d_v = correction.rotation_vjp(label, Vec3::new(g[3], g[4], g[5]));
    if let Some(arm) = arm {
        d_v += correction.rotation_vjp(arm, d_origin);
    }
    let d_u = d_origin * length_unit;
    [d_u.x, d_u.y, d_u.z, d_v.x, d_v.y, d_v.z]
}

/// Residuals beyond this (colour units) count linearly in a pose refinement (Huber's
/// loss): a glint or a part the field has wrong pulls the pose less than its square would.
const ROBUST_SCALE: f32 = 0.1;

/// A target channel at or above this is saturated (a clipped glint): its true brightness is
/// unknown, so it carries no weight in a pose refinement.
const SATURATED: f32 = 254.0 / 255.0;

/// The robust weight of residual `e` of a pixel whose target colour is `target` (Huber's,
/// 0 on a saturated pixel), and its Huber cost.
pub(super) fn robust_residual(e: f32, target: [f32; 3]) -> (f32, f32) {
    if target.iter().any(|&t| t >= SATURATED) || !e.is_finite() {
        return (0.0, 0.0);
    }
    let a = e.abs();
    if a <= ROBUST_SCALE {
        (1.0, 0.5 * e * e)
    } else {
        (ROBUST_SCALE / a, ROBUST_SCALE * (a - 0.5 * ROBUST_SCALE))
    }
}
