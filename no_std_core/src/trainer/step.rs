//! One training step: the chunks' forward and backward passes, the reduction of their
//! gradients in chunk order, and Adam.

use super::*;

impl<'a> Trainer<'a> {
    /// One training step. Returns what it did; a step whose loss or gradients are not finite
    /// is counted and skipped, leaving the parameters untouched.
    pub fn step<E: Executor>(&mut self, executor: &E) -> Result<StepReport, Error> {
        self.require_training()?;
        self.forward_backward(executor)?;
        let report = self.reduce_and_apply();
        self.state.step += 1;
        if self.state.step.is_multiple_of(self.config.occupancy_every) {
            self.refresh_occupancy(executor);
        }
        Ok(report)
    }

    /// Sample this step's batch and run every chunk's forward and backward pass, leaving the
    /// gradients in the chunks' buffers.
    pub(super) fn forward_backward<E: Executor>(&mut self, executor: &E) -> Result<(), Error> {
        let mut laps = self.profile.laps();
        self.sample_rays()?;
        self.profile
            .serial(&mut laps, Bucket::Train, Stage::RaySampling);
        let rays = self.config.rays_per_batch as usize;
        self.with_chunks(Pass::Train, rays, |shared, chunks| {
            executor.for_each(chunks, |chunk| chunk.train(shared))
        });
        let times = self.chunks.iter_mut().map(|chunk| &mut chunk.times);
        self.profile.parallel(&mut laps, Bucket::Train, times, None);
        Ok(())
    }

    /// Sum the chunks' gradients in chunk order, check them, and apply Adam.
    fn reduce_and_apply(&mut self) -> StepReport {
        let mut laps = self.profile.laps();
        let (first, rest) = match self.chunks.split_first_mut() {
            Some(split) => split,
            None => return StepReport::default(),
        };
        let mut report = StepReport::default();
        let mut squared_error = 0.0f32;
        for chunk in core::iter::once(&*first).chain(rest.iter()) {
            squared_error += chunk.report.squared_error;
            report.rays += chunk.report.rays;
            report.samples += chunk.report.samples;
            report.samples_marched += chunk.report.marched;
        }
        report.mse = if report.rays > 0 {
            squared_error / (3 * report.rays) as f32
        } else {
            0.0
        };
        let mut finite = squared_error.is_finite();

        for other in rest.iter_mut() {
            for (a, b) in first.mlp_grads.iter_mut().zip(other.mlp_grads.iter_mut()) {
                *a += *b;
                *b = 0.0;
            }
            for (a, b) in first
                .frame_grads
                .iter_mut()
                .zip(other.frame_grads.iter_mut())
            {
                *a += *b;
                *b = 0.0;
            }
        }
        finite &= first
            .mlp_grads
            .iter()
            .chain(first.frame_grads.iter())
            .all(|g| g.is_finite());
        let f = self.config.features as usize;
        for (w, union) in self.touched_union.iter_mut().enumerate() {
            let mut bits = first.touched[w];
            first.touched[w] = 0;
            for other in rest.iter_mut() {
                bits |= other.touched[w];
                other.touched[w] = 0;
            }
            *union = bits;
        }
        let tv_weight = self.config.plane_tv_weight;
        for texel in set_bits(self.touched_union) {
            let range = texel * f..(texel + 1) * f;
            for other in rest.iter_mut() {
                for (a, b) in first.plane_grads[range.clone()]
                    .iter_mut()
                    .zip(&mut other.plane_grads[range.clone()])
                {
                    *a += *b;
                    *b = 0.0;
                }
            }
            if tv_weight > 0.0 {
                field::plane_tv_gradient(
                    self.planes,
                    &self.geometry,
                    tv_weight,
                    texel,
                    &mut first.plane_grads[range.clone()],
                );
            }
            finite &= first.plane_grads[range].iter().all(|g| g.is_finite());
        }

        self.profile
            .serial(&mut laps, Bucket::Train, Stage::Reduction);
        let c = &self.config;
        if finite {
            self.state.updates += 1;
            let lr = optim::learning_rate(c, self.state.step);
            let adam = AdamStep::new(c, lr, self.state.updates);
            adam.apply(self.mlp, first.mlp_grads, self.mlp_m, self.mlp_v);
            let n = c.frame_params();
            let dim = c.embedding_dim as usize;
            let pose_adam = AdamStep::new(c, lr * c.pose_lr_factor, self.state.updates);
            for i in 0..self.frames.len() {
                let Some(slot) = self.frames.occupied_slot(i) else {
                    continue;
                };
                let range = slot * n..(slot + 1) * n;
                let (emb, pose) = (range.start..range.start + dim, range.start + dim..range.end);
                adam.apply(
                    &mut self.frame_params[emb.clone()],
                    &first.frame_grads[emb.clone()],
                    &mut self.frame_m[emb.clone()],
                    &mut self.frame_v[emb],
                );
                if c.pose_learns_at(self.state.step) {
                    pose_adam.apply(
                        &mut self.frame_params[pose.clone()],
                        &first.frame_grads[pose.clone()],
                        &mut self.frame_m[pose.clone()],
                        &mut self.frame_v[pose],
                    );
                }
            }
            let master = !self.plane_master.is_empty();
            for texel in set_bits(self.touched_union) {
                for i in texel * f..(texel + 1) * f {
                    let delta = adam.delta(
                        first.plane_grads[i],
                        &mut self.plane_m[i],
                        &mut self.plane_v[i],
                    );
                    let master = if master {
                        self.plane_master.get_mut(i)
                    } else {
                        None
                    };
                    optim::store_texel(
                        &mut self.planes[i],
                        master,
                        delta,
                        c.seed,
                        self.state.step,
                        i,
                    );
                }
            }
        } else {
            self.state.skipped += 1;
            report.skipped = true;
        }
        first.mlp_grads.fill(0.0);
        first.frame_grads.fill(0.0);
        for texel in set_bits(self.touched_union) {
            first.plane_grads[texel * f..(texel + 1) * f].fill(0.0);
        }
        self.profile.serial(&mut laps, Bucket::Train, Stage::Adam);
        report
    }
}
