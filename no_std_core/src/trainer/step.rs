//! One training step: the chunks' forward and backward passes, the reduction of their
//! gradients in chunk order, and Adam.

use super::*;

impl<'a> Trainer<'a> {
    /// One training step. Returns what it did; a step whose loss or gradients are not finite
    /// is counted and skipped, leaving the parameters untouched.
    pub fn step<E: Executor>(&mut self, executor: &E) -> Result<StepReport, Error> {
        self.step_or_stop(executor, &|| false)
            .map(Option::unwrap_or_default)
    }

    /// [`Trainer::step`] that gives up when `stop` says so: `stop` is asked before the step
    /// and between the passes of every chunk (each pass at most `samples_per_chunk`
    /// samples), so a stop request waits for one pass, not for a whole step of
    /// `rays_per_batch` rays. A step given up returns `Ok(None)` and leaves no trace: no
    /// update, and the step counter, the random draws (keyed by the step), the optimiser's
    /// moments and the chunks' gradient buffers (zeroed again) are as before it, so a
    /// checkpoint taken then resumes to the bits of a run never stopped. Only the profile's
    /// stage times keep the time it took. `stop` may be called from any of the executor's
    /// threads, any number of times.
    pub fn step_or_stop<E: Executor>(
        &mut self,
        executor: &E,
        stop: &(dyn Fn() -> bool + Sync),
    ) -> Result<Option<StepReport>, Error> {
        self.require_training()?;
        if stop() {
            return Ok(None);
        }
        if !self.forward_backward(executor, stop)? {
            let features = self.config.features as usize;
            executor.for_each(&mut self.chunks, |chunk| chunk.clear_gradients(features));
            return Ok(None);
        }
        let report = self.reduce_and_apply(executor);
        self.state.step += 1;
        if self.state.step.is_multiple_of(self.config.occupancy_every) {
            self.refresh_occupancy(executor);
        }
        Ok(Some(report))
    }

    /// Sample this step's batch and run every chunk's forward and backward pass, leaving the
    /// gradients in the chunks' buffers. Returns `false` when a chunk heard `stop` before it
    /// had trained all its rays (the gradients are then partial).
    pub(super) fn forward_backward<E: Executor>(
        &mut self,
        executor: &E,
        stop: &(dyn Fn() -> bool + Sync),
    ) -> Result<bool, Error> {
        let mut laps = self.profile.laps();
        self.sample_rays(executor)?;
        self.profile
            .serial(&mut laps, Bucket::Train, Stage::RaySampling);
        let rays = self.config.rays_per_batch as usize;
        self.with_chunks(Pass::Train { stop }, rays, |shared, chunks| {
            executor.for_each(chunks, |chunk| chunk.train(shared))
        });
        let times = self.chunks.iter_mut().map(|chunk| &mut chunk.times);
        self.profile.parallel(&mut laps, Bucket::Train, times, None);
        Ok(!self.chunks.iter().any(|chunk| chunk.report.stopped))
    }

    /// Sum the chunks' gradients in chunk order, check them, and apply Adam. The planes'
    /// part runs in parallel over ranges of texels (each texel's sums and update are its own,
    /// so the ranges change no bit).
    fn reduce_and_apply<E: Executor>(&mut self, executor: &E) -> StepReport {
        let mut laps = self.profile.laps();
        let mut report = StepReport::default();
        let mut squared_error = 0.0f32;
        for chunk in self.chunks.iter() {
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
        let Some((first, rest)) = self.chunks.split_first_mut() else {
            return report;
        };
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
        let tv_weight = self.config.plane_tv_weight;
        let (planes, geometry) = (&*self.planes, &self.geometry);
        let parts_count = self.chunks.len();
        let mut sums = texel_sums(&mut self.chunks, self.touched_union, f, parts_count);
        executor.for_each(&mut sums, |part| {
            part.finite = part.reduce(f, |texel, grad| {
                if tv_weight > 0.0 {
                    field::plane_tv_gradient(planes, geometry, tv_weight, texel, grad);
                }
            });
        });
        finite &= sums.iter().all(|part| part.finite);
        drop(sums);
        self.profile
            .serial(&mut laps, Bucket::Train, Stage::Reduction);

        let config = self.config;
        let c = &config;
        let lr = optim::learning_rate(c, self.state.step);
        let adam = if finite {
            self.state.updates += 1;
            Some(AdamStep::new(c, lr, self.state.updates))
        } else {
            self.state.skipped += 1;
            report.skipped = true;
            None
        };
        if adam.is_some() && c.loss_weighted_frames {
            self.update_frame_losses();
        }
        let pose_learns = adam.is_some() && c.pose_learns_at(self.state.step);
        if pose_learns {
            self.state.pose_updates += 1;
            self.add_pose_prior_gradients(report.mse);
        }
        let Some(first) = self.chunks.first_mut() else {
            return report;
        };
        if let Some(adam) = &adam {
            adam.apply(self.mlp, first.mlp_grads, self.mlp_m, self.mlp_v);
            let n = c.frame_params();
            let dim = c.embedding_dim as usize;
            // The pose block's own schedule and time step: its moments start at zero when it
            // starts learning, so its bias correction counts from there.
            let pose_lr = optim::pose_learning_rate(c, self.state.step);
            let pose_adam = AdamStep::new(c, pose_lr, self.state.pose_updates);
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
                if pose_learns {
                    pose_adam.apply(
                        &mut self.frame_params[pose.clone()],
                        &first.frame_grads[pose.clone()],
                        &mut self.frame_m[pose.clone()],
                        &mut self.frame_v[pose],
                    );
                }
            }
        }
        first.mlp_grads.fill(0.0);
        first.frame_grads.fill(0.0);
        let mut updates = TexelUpdate::parts(
            first.plane_grads,
            self.touched_union,
            self.planes,
            self.plane_master,
            self.plane_m,
            self.plane_v,
            f,
            parts_count,
        );
        let (seed, step) = (c.seed, self.state.step);
        executor.for_each(&mut updates, |part| {
            part.apply(adam.as_ref(), f, seed, step)
        });
        drop(updates);
        if pose_learns {
            self.fix_pose_gauge();
        }
        self.profile.serial(&mut laps, Bucket::Train, Stage::Adam);
        report
    }

    /// Move each frame's running loss towards its rays' squared errors of this step, a ray at
    /// a time in batch order (each ray by `1 / FRAME_LOSS_RAYS` of the way, so a frame's loss
    /// follows its last few hundred rays).
    fn update_frame_losses(&mut self) {
        for chunk in self.chunks.iter() {
            for (k, &error) in chunk.ray_loss.iter().enumerate() {
                let slot = self
                    .ray_frames
                    .get(chunk.first_ray + k)
                    .copied()
                    .unwrap_or(0);
                if let Some(meta) = self.frames.meta.get_mut(slot as usize) {
                    let mse = error * (1.0 / 3.0);
                    meta.loss += (mse - meta.loss) * (1.0 / FRAME_LOSS_RAYS);
                }
            }
        }
    }
}

/// A frame's running loss moves this many rays' worth towards each new ray's error.
const FRAME_LOSS_RAYS: f32 = 64.0;

/// Texels `first_texel ..` (whole bitmap words): each chunk's gradients and touched bits of
/// them, to be summed into the first chunk's.
struct TexelSum<'p> {
    first_texel: usize,
    union: &'p mut [u64],
    grads: heapless::Vec<&'p mut [f32], MAX_CHUNKS>,
    touched: heapless::Vec<&'p mut [u64], MAX_CHUNKS>,
    finite: bool,
}

/// The texels split into `parts` ranges of whole bitmap words.
fn texel_sums<'p>(
    chunks: &'p mut [Chunk<'_>],
    union: &'p mut [u64],
    f: usize,
    parts: usize,
) -> heapless::Vec<TexelSum<'p>, MAX_CHUNKS> {
    let words = union.len().div_ceil(parts.max(1)).max(1);
    let mut out: heapless::Vec<TexelSum<'p>, MAX_CHUNKS> = heapless::Vec::new();
    for (i, union) in union.chunks_mut(words).enumerate() {
        let _ = out.push(TexelSum {
            first_texel: i * words * 64,
            union,
            grads: heapless::Vec::new(),
            touched: heapless::Vec::new(),
            finite: true,
        });
    }
    for chunk in chunks.iter_mut() {
        let mut grads = &mut *chunk.plane_grads;
        let mut touched = &mut *chunk.touched;
        for part in out.iter_mut() {
            let (g, g_rest) = grads.split_at_mut((part.union.len() * 64 * f).min(grads.len()));
            let (t, t_rest) = touched.split_at_mut(part.union.len().min(touched.len()));
            let _ = part.grads.push(g);
            let _ = part.touched.push(t);
            (grads, touched) = (g_rest, t_rest);
        }
    }
    out
}

impl TexelSum<'_> {
    /// The union of the touched bits (clearing the chunks'), the sums in chunk order into
    /// the first chunk's gradients (clearing the others'), `extra` on each touched texel's
    /// sum. Returns whether every sum is finite.
    fn reduce(&mut self, f: usize, extra: impl Fn(usize, &mut [f32])) -> bool {
        let mut finite = true;
        for (w, union) in self.union.iter_mut().enumerate() {
            let mut bits = 0;
            for touched in self.touched.iter_mut() {
                if let Some(word) = touched.get_mut(w) {
                    bits |= *word;
                    *word = 0;
                }
            }
            *union = bits;
        }
        let Some((first, rest)) = self.grads.split_first_mut() else {
            return finite;
        };
        for local in set_bits(self.union) {
            let range = local * f..(local + 1) * f;
            for other in rest.iter_mut() {
                for (a, b) in first[range.clone()]
                    .iter_mut()
                    .zip(&mut other[range.clone()])
                {
                    *a += *b;
                    *b = 0.0;
                }
            }
            extra(self.first_texel + local, &mut first[range.clone()]);
            finite &= first[range].iter().all(|g| g.is_finite());
        }
        finite
    }
}

/// Texels `first_texel ..` (whole bitmap words): their summed gradients, touched bits and
/// parameters, for Adam.
struct TexelUpdate<'p> {
    first_texel: usize,
    union: &'p [u64],
    grads: &'p mut [f32],
    planes: &'p mut [f16],
    master: &'p mut [f32],
    m: &'p mut [f32],
    v: &'p mut [f32],
}

impl<'p> TexelUpdate<'p> {
    /// The texels split into `parts` ranges of whole bitmap words (`master` may be empty).
    #[allow(clippy::too_many_arguments)]
    fn parts(
        mut grads: &'p mut [f32],
        union: &'p [u64],
        mut planes: &'p mut [f16],
        mut master: &'p mut [f32],
        mut m: &'p mut [f32],
        mut v: &'p mut [f32],
        f: usize,
        parts: usize,
    ) -> heapless::Vec<TexelUpdate<'p>, MAX_CHUNKS> {
        let words = union.len().div_ceil(parts.max(1)).max(1);
        let mut out = heapless::Vec::new();
        for (i, union) in union.chunks(words).enumerate() {
            let len = union.len() * 64 * f;
            let take = |s: &mut &'p mut [f32]| {
                let whole = core::mem::take(s);
                let (head, tail) = whole.split_at_mut(len.min(whole.len()));
                *s = tail;
                head
            };
            let (g, mm, vv, ms) = (
                take(&mut grads),
                take(&mut m),
                take(&mut v),
                take(&mut master),
            );
            let whole = core::mem::take(&mut planes);
            let (p, p_rest) = whole.split_at_mut(len.min(whole.len()));
            planes = p_rest;
            let _ = out.push(TexelUpdate {
                first_texel: i * words * 64,
                union,
                grads: g,
                planes: p,
                master: ms,
                m: mm,
                v: vv,
            });
        }
        out
    }

    /// Adam on every touched texel (none without `adam`, a skipped step), then their
    /// gradients cleared.
    fn apply(&mut self, adam: Option<&AdamStep>, f: usize, seed: u64, step: u32) {
        let first = self.first_texel * f;
        for local in set_bits(self.union) {
            let range = local * f..(local + 1) * f;
            if let Some(adam) = adam {
                for i in range.clone() {
                    let delta = adam.delta(self.grads[i], &mut self.m[i], &mut self.v[i]);
                    optim::store_texel(
                        &mut self.planes[i],
                        self.master.get_mut(i),
                        delta,
                        seed,
                        step,
                        first + i,
                    );
                }
            }
            self.grads[range].fill(0.0);
        }
    }
}
