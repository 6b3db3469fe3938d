//! A chunk's training pass: forward, loss and the hand-written backward pass.

use super::chunk::{ChunkReport, density_forward, split_rows};
use super::*;

impl Chunk<'_> {
    /// Forward, loss and backward for this chunk's rays of the batch.
    pub(super) fn train(&mut self, shared: &Shared<'_>) {
        let c = shared.config;
        self.report = ChunkReport::default();
        let (first, end) = (self.first_ray, self.first_ray + self.ray_count);
        let mut laps = shared.timer.laps();
        let rays = self.march_rays(shared, first, end);
        laps.lap(Stage::Marching, &mut self.times);
        let marched = self.ray_start[rays] as usize;
        self.density_pass(shared, marched);
        laps.lap(Stage::DensityForward, &mut self.times);
        let n = self.keep_visible(shared, rays);
        laps.lap(Stage::EarlyStop, &mut self.times);
        self.colour_pass(shared, n);
        laps.lap(Stage::ColourForward, &mut self.times);

        // Loss: sum of squared errors over the batch, normalised by the batch capacity so the
        // gradient scale does not depend on how many rays fit.
        let norm = 1.0 / (3.0 * c.rays_per_batch as f32);
        let mut squared_error = 0.0f32;
        for r in 0..rays {
            let (start, end) = (self.ray_start[r] as usize, self.ray_start[r + 1] as usize);
            let ray = &shared.rays[first + r];
            let (colour, _) = render::composite_forward(
                &self.sigma[start..end],
                &self.rgb[start..end],
                shared.optical_step,
                ray.background,
            );
            let target = ray.target;
            let mut d_colour = [0.0f32; 3];
            for ch in 0..3 {
                let e = colour[ch] - target[ch];
                squared_error += e * e;
                d_colour[ch] = 2.0 * e * norm;
            }
            render::composite_backward(
                &self.sigma[start..end],
                &self.rgb[start..end],
                shared.optical_step,
                colour,
                d_colour,
                &mut self.d_sigma[start..end],
                &mut self.d_rgb[start..end],
            );
        }
        if shared.pose_gradients {
            self.ray_grads.fill(0.0);
        }
        laps.lap(Stage::Compositing, &mut self.times);
        self.backward(shared, n, &mut laps);
        if shared.pose_gradients {
            self.fold_ray_gradients(shared, rays);
        }
        laps.lap(Stage::PlaneBackward, &mut self.times);
        self.report = ChunkReport {
            squared_error,
            rays: rays as u32,
            samples: n as u32,
            marched: marched as u32,
            dropped: (self.ray_count - rays) as u32,
        };
    }

    /// Move each ray's origin and direction gradients to its frame's pose correction.
    fn fold_ray_gradients(&mut self, shared: &Shared<'_>, rays: usize) {
        let c = shared.config;
        let n = c.frame_params();
        let dim = c.embedding_dim as usize;
        let Embedding::PerFrame(params) = shared.embedding else {
            return;
        };
        let pivot = c.pose_pivot_point();
        for r in 0..rays {
            let ray = self.first_ray + r;
            let slot = shared.ray_frames[ray] as usize;
            let g = &self.ray_grads[r * 6..r * 6 + 6];
            let correction = PoseCorrection::from_params(
                &params[slot * n + dim..(slot + 1) * n],
                shared.length_unit,
            );
            let label = Vec3::from_array(shared.rays[ray].label_direction);
            let mut d_v = correction.rotation_vjp(label, Vec3::new(g[3], g[4], g[5]));
            // With a pivot the origin is p + R (c - p) + u: the rotation also moves it.
            if let (Some(p), Some(meta)) = (pivot, shared.frame_meta.get(slot)) {
                let arm = Vec3::from_array(meta.center) - p;
                d_v += correction.rotation_vjp(arm, Vec3::new(g[0], g[1], g[2]));
            }
            let dst = &mut self.frame_grads[slot * n + dim..(slot + 1) * n];
            for a in 0..3 {
                // The parameter is u, with dt = u * length_unit.
                dst[a] += g[a] * shared.length_unit;
                dst[3 + a] += d_v[a];
            }
        }
    }

    /// Recompute the field for samples `0..n` mini-batch by mini-batch and push the
    /// compositing gradients back to the MLPs, the planes and the embeddings.
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
        for base in (0..n).step_by(LANES) {
            let lanes = LANES.min(n - base);
            let mut act = split_rows(c, self.activations);
            let grad = split_rows(c, self.gradients);
            density_forward(
                shared,
                &self.positions[base..base + lanes],
                &mut act,
                self.plane_values,
            );
            Self::colour_forward(self.sample_ray, self.geo, shared, base, lanes, &mut act);
            laps.lap(Stage::BackwardRecompute, &mut self.times);

            // Output gradients; unused lanes stay zero and so contribute nothing.
            for row in grad.rgb.iter_mut().chain(grad.density_out.iter_mut()) {
                row.fill(0.0);
            }
            for l in 0..lanes {
                let s = base + l;
                for ch in 0..3 {
                    grad.rgb[ch][l] = self.d_rgb[s][ch] * field::sigmoid_grad(act.rgb[ch][l]);
                }
                // d sigma / d raw = trunc_exp'(raw), which is sigma itself below the clamp.
                grad.density_out[0][l] =
                    self.d_sigma[s] * field::trunc_exp_grad(act.density_out[0][l]);
            }
            let g = &mut *self.mlp_grads;
            let p = shared.mlp;
            let layer = |i: usize| layout.layers[i];
            let (l_out, l2, l1) = (
                layer(COLOUR_OUT),
                layer(COLOUR_HIDDEN2),
                layer(COLOUR_HIDDEN1),
            );
            backward_layer(
                p,
                g,
                l_out,
                act.colour2,
                grad.rgb,
                Some(grad.colour2),
                self.lane_major,
            );
            field::relu_backward(act.colour2, grad.colour2);
            backward_layer(
                p,
                g,
                l2,
                act.colour1,
                grad.colour2,
                Some(grad.colour1),
                self.lane_major,
            );
            field::relu_backward(act.colour1, grad.colour1);
            backward_layer(
                p,
                g,
                l1,
                act.colour_in,
                grad.colour1,
                Some(grad.colour_in),
                self.lane_major,
            );
            laps.lap(Stage::ColourBackward, &mut self.times);
            for gi in 0..geo_len {
                grad.density_out[1 + gi] = grad.colour_in[sh_len + gi];
            }
            if shared.fit_embedding {
                for (k, d) in self.frame_grads[..dim].iter_mut().enumerate() {
                    for l in 0..lanes {
                        *d += grad.colour_in[sh_len + geo_len + k][l];
                    }
                }
                continue;
            }
            if dim > 0 && matches!(shared.embedding, Embedding::PerFrame(_)) {
                for l in 0..lanes {
                    let slot = shared.ray_frames[self.sample_ray[base + l] as usize] as usize;
                    let dst = &mut self.frame_grads[slot * frame_params..slot * frame_params + dim];
                    for (k, d) in dst.iter_mut().enumerate() {
                        *d += grad.colour_in[sh_len + geo_len + k][l];
                    }
                }
            }
            backward_layer(
                p,
                g,
                layout.layers[DENSITY_OUT],
                act.hidden,
                grad.density_out,
                Some(grad.hidden),
                self.lane_major,
            );
            field::relu_backward(act.hidden, grad.hidden);
            backward_layer(
                p,
                g,
                layout.layers[DENSITY_HIDDEN],
                act.feats,
                grad.hidden,
                Some(grad.feats),
                self.lane_major,
            );
            laps.lap(Stage::DensityBackward, &mut self.times);

            let mut sink = PlaneGrads {
                grads: self.plane_grads,
                touched: self.touched,
            };
            let mut d_feat = [0.0f32; 4 * 64];
            let pose = shared.pose_gradients;
            let extent = shared.aabb.max - shared.aabb.min;
            let per_scale = c.features as usize;
            for l in 0..lanes {
                for k in 0..features {
                    d_feat[k] = grad.feats[k][l] * shared.scale_weights[k / per_scale];
                }
                let x = Vec3::from_array(self.positions[base + l]);
                let u = shared.aabb.normalise(x);
                let values = &self.plane_values[l * 3 * features..(l + 1) * 3 * features];
                let d_u = field::planes_backward(
                    shared.planes,
                    shared.geometry,
                    u,
                    values,
                    &d_feat[..features],
                    &mut sink,
                    pose,
                );
                if pose {
                    // x = o + t d: d loss / d o = d loss / d x, d loss / d d = t d loss / d x,
                    // plus the view encoding's gradient.
                    let r = self.sample_ray[base + l] as usize;
                    let (o, d) = Self::ray(shared, r);
                    let d_x = Vec3::from_array(d_u) / extent;
                    let mut d_sh = [0.0f32; 16];
                    for k in 0..sh_len {
                        d_sh[k] = grad.colour_in[k][l];
                    }
                    let d_view = Vec3::from_array(field::sh_backward(
                        c.sh_bands as usize,
                        d.to_array(),
                        &d_sh[..sh_len],
                    ));
                    let d_d = d_x * (x - o).dot(d) + d_view;
                    let g =
                        &mut self.ray_grads[(r - self.first_ray) * 6..(r - self.first_ray) * 6 + 6];
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
