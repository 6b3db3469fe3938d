//! Using the trained field: rendering an image, and fitting an appearance embedding to a
//! held-out image with the field frozen.

use super::*;

/// One chunk's share of a density query: its points, their outputs and the chunk.
type DensityJob<'q, 'a> = (&'q [[f32; 3]], &'q mut [f32], &'q mut Chunk<'a>);

/// Adam learning rate of `fit_view`'s embedding (only a few dozen steps, on one vector); its
/// pose correction learns at this times `Config::pose_lr_factor`, as in training.
const FIT_LEARNING_RATE: f32 = 0.05;

impl<'a> Trainer<'a> {
    /// Fit a held-out view's frame parameters to its image with the field frozen: its
    /// appearance embedding (the paper's and K-Planes' evaluation), `steps` Adam steps, each
    /// on a batch of rays through the pixels in columns `columns.0..columns.1` (the left
    /// half, in the paper), and with `align_pose` its pose correction too (test-time
    /// alignment: the view is then scored at its corrected label, not at the label's noise):
    /// Adam steps on it with the embedding's (at the embedding's rate times
    /// `pose_lr_factor`, about `pose_pivot`, as in training), then the refinement training
    /// frames get ([`Trainer::refine_pose`], on the same columns). `params` (`frame_params()`
    /// values: the embedding, then the correction) holds the starting point (the mean
    /// training embedding, no correction) and receives the result; the corrected pose is
    /// `PoseCorrection::from_params(&params[embedding_dim..], length_unit)` applied to
    /// `pose`. Returns the last step's mean squared error.
    #[allow(clippy::too_many_arguments)]
    pub fn fit_view<E: Executor>(
        &mut self,
        executor: &E,
        camera: &Camera,
        pose: &Pose,
        pixels: &[u8],
        columns: (u32, u32),
        steps: u32,
        align_pose: bool,
        params: &mut [f32],
    ) -> Result<f32, Error> {
        self.require_training()?;
        let c = self.config;
        let (dim, n) = (c.embedding_dim as usize, c.frame_params());
        if params.len() != n {
            return Err(Error::BufferSize {
                what: "frame parameters",
                expected: n,
                got: params.len(),
            });
        }
        if !camera.is_valid() || !pose.is_finite() {
            return Err(Error::InvalidFrame { field: "camera" });
        }
        if pixels.len() != camera.pixel_count() * 3 {
            return Err(Error::BufferSize {
                what: "pixels",
                expected: camera.pixel_count() * 3,
                got: pixels.len(),
            });
        }
        let (x0, x1) = (
            columns.0.min(camera.width as u32),
            columns.1.min(camera.width as u32),
        );
        if x0 >= x1 {
            return Err(Error::InvalidFrame { field: "columns" });
        }
        let mut laps = self.profile.laps();
        const MOST: usize = 128 + POSE_PARAMS;
        let (mut m, mut v) = ([0.0f32; MOST], [0.0f32; MOST]);
        let mut mse = 0.0;
        // With alignment, the pose follows the loss's gradient with the embedding (Adam's
        // small steps reach poses a Gauss-Newton step from the label would overshoot); the
        // refinement, where the config asks for its steps, finishes it.
        for step in 0..steps {
            let mut grad = [0.0f32; MOST];
            let squared_error = self.fit_pass(
                executor,
                (camera, pose, pixels),
                (x0, x1),
                (step, align_pose),
                params,
                &mut grad[..n],
                &mut laps,
            );
            mse = squared_error;
            if !(mse.is_finite() && grad[..n].iter().all(|g| g.is_finite())) {
                continue;
            }
            let adam = AdamStep::new(&c, FIT_LEARNING_RATE, step + 1);
            adam.apply(
                &mut params[..dim],
                &grad[..dim],
                &mut m[..dim],
                &mut v[..dim],
            );
            if align_pose {
                let adam = AdamStep::new(&c, FIT_LEARNING_RATE * c.pose_lr_factor, step + 1);
                adam.apply(
                    &mut params[dim..n],
                    &grad[dim..n],
                    &mut m[dim..n],
                    &mut v[dim..n],
                );
            }
        }
        if align_pose && c.pose_refine_iterations > 0 {
            let view = (camera, pose, pixels);
            let iterations = c.pose_refine_iterations;
            self.refine_image_pose(executor, view, (x0, x1), params, iterations);
        }
        self.profile
            .serial(&mut laps, Bucket::Render, Stage::FitEmbedding);
        Ok(mse)
    }

    /// One step of [`Trainer::fit_view`] without the update: a batch of rays through the
    /// view's pixels in `columns` (drawn by `step`), through the pose corrected by `params`,
    /// their loss and its gradient with respect to the embedding (and with `align_pose` the
    /// pose correction) into `grad`.
    /// Returns the mean squared error. `laps` charges the chunks' work to the profile.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn fit_pass<E: Executor>(
        &mut self,
        executor: &E,
        (camera, pose, pixels): (&Camera, &Pose, &[u8]),
        (x0, x1): (u32, u32),
        (step, align_pose): (u32, bool),
        params: &[f32],
        grad: &mut [f32],
        laps: &mut Laps,
    ) -> f32 {
        let c = self.config;
        let dim = c.embedding_dim as usize;
        let correction =
            PoseCorrection::from_params(params.get(dim..).unwrap_or(&[]), self.length_unit);
        let pivot = c.pose_pivot_point();
        for r in 0..c.rays_per_batch as usize {
            let bits = rng::hash(c.seed, domain::FIT, step as u64, r as u64);
            let i = x0 + rng::below(bits, x1 - x0);
            let j = rng::below(bits.rotate_right(32), camera.height as u32);
            let (o, d) = Self::pixel_ray(camera, pose, i, j);
            let p = (j as usize * camera.width as usize + i as usize) * 3;
            self.rays[r] = BatchRay {
                origin: correction.origin(o, pivot).to_array(),
                direction: correction.rotate(d).to_array(),
                target: core::array::from_fn(|ch| pixels[p + ch] as f32 * (1.0 / 255.0)),
                label_direction: d.to_array(),
                background: c.background,
            };
        }
        let pass = Pass::FitView {
            params,
            center: pose.center.to_array(),
            step,
            align_pose,
        };
        self.with_chunks(pass, c.rays_per_batch as usize, |shared, chunks| {
            executor.for_each(chunks, |chunk| chunk.train(shared))
        });
        let times = self.chunks.iter_mut().map(|chunk| &mut chunk.times);
        let only = Some(Stage::FitEmbedding);
        self.profile.parallel(laps, Bucket::Render, times, only);
        grad.fill(0.0);
        let (mut squared_error, mut rays) = (0.0f32, 0u32);
        for chunk in self.chunks.iter_mut() {
            let n = grad.len();
            for (g, d) in grad.iter_mut().zip(chunk.frame_grads[..n].iter_mut()) {
                *g += *d;
                *d = 0.0;
            }
            chunk.mlp_grads.fill(0.0);
            squared_error += chunk.report.squared_error;
            rays += chunk.report.rays;
        }
        squared_error / (3 * rays.max(1)) as f32
    }

    /// Render the image of `camera` at `pose` with a given appearance embedding (length
    /// `embedding_dim`) into `out` (RGB f32, row-major). Returns the mean samples per ray.
    pub fn render<E: Executor>(
        &mut self,
        executor: &E,
        camera: &Camera,
        pose: &Pose,
        embedding: &[f32],
        out: &mut [f32],
    ) -> Result<f32, Error> {
        if !camera.is_valid() || !pose.is_finite() {
            return Err(Error::InvalidFrame { field: "camera" });
        }
        let width = camera.width as u32;
        self.render_with(executor, camera.pixel_count(), embedding, out, |p| {
            Self::pixel_ray(camera, pose, p as u32 % width, p as u32 / width)
        })
    }

    /// Render arbitrary rays (world frame) with a given appearance embedding into `out` (RGB
    /// f32, one triple per ray): the same marching and compositing as [`Trainer::render`].
    /// Directions are normalised here; a ray with a zero or non-finite direction or origin
    /// misses the box and gets the background colour. Returns the mean samples per ray.
    pub fn render_rays<E: Executor>(
        &mut self,
        executor: &E,
        origins: &[[f32; 3]],
        directions: &[[f32; 3]],
        embedding: &[f32],
        out: &mut [f32],
    ) -> Result<f32, Error> {
        if directions.len() != origins.len() {
            return Err(Error::BufferSize {
                what: "directions",
                expected: origins.len(),
                got: directions.len(),
            });
        }
        self.render_with(executor, origins.len(), embedding, out, |r| {
            let d = Vec3::from_array(directions[r]);
            let length = libm::sqrtf(d.length_squared());
            let d = if length > 0.0 && length.is_finite() {
                d * (1.0 / length)
            } else {
                Vec3::splat(f32::NAN)
            };
            (Vec3::from_array(origins[r]), d)
        })
    }

    /// Density (the field's `sigma`, per world unit of length, as the renderer composites it)
    /// at each of `positions` (world frame) into `out`: no marching, no occupancy grid, no
    /// colour. Points outside the scene box read the box's edge texels; a non-finite point
    /// reads texels inside the box. Allocation-free; the chunks share the points out.
    pub fn density_at<E: Executor>(
        &mut self,
        executor: &E,
        positions: &[[f32; 3]],
        out: &mut [f32],
    ) -> Result<(), Error> {
        if out.len() != positions.len() {
            return Err(Error::BufferSize {
                what: "out",
                expected: positions.len(),
                got: out.len(),
            });
        }
        let pass = Pass::Render { embedding: &[] };
        self.with_chunks(pass, 0, |shared, chunks| {
            let per_chunk = positions.len().div_ceil(chunks.len()).max(1);
            let mut jobs: heapless::Vec<DensityJob<'_, 'a>, MAX_CHUNKS> = heapless::Vec::new();
            for ((points, sigma), chunk) in positions
                .chunks(per_chunk)
                .zip(out.chunks_mut(per_chunk))
                .zip(chunks.iter_mut())
            {
                let _ = jobs.push((points, sigma, chunk));
            }
            executor.for_each(&mut jobs, |(points, sigma, chunk)| {
                chunk.densities(shared, points, sigma)
            });
        });
        Ok(())
    }

    /// Render `count` rays, ray `r` given by `ray(r)` (origin, unit direction), into `out`.
    fn render_with<E: Executor>(
        &mut self,
        executor: &E,
        count_all: usize,
        embedding: &[f32],
        out: &mut [f32],
        ray: impl Fn(usize) -> (Vec3, Vec3),
    ) -> Result<f32, Error> {
        let c = self.config;
        if embedding.len() != c.embedding_dim as usize {
            return Err(Error::BufferSize {
                what: "embedding",
                expected: c.embedding_dim as usize,
                got: embedding.len(),
            });
        }
        if out.len() != count_all * 3 {
            return Err(Error::BufferSize {
                what: "out",
                expected: count_all * 3,
                got: out.len(),
            });
        }
        let batch = c.rays_per_batch as usize;
        let mut samples = 0u64;
        for first in (0..count_all).step_by(batch) {
            let mut laps = self.profile.laps();
            let count = batch.min(count_all - first);
            for r in 0..count {
                let (o, d) = ray(first + r);
                self.rays[r].origin = o.to_array();
                self.rays[r].direction = d.to_array();
            }
            self.profile
                .serial(&mut laps, Bucket::Render, Stage::RaySampling);
            let out_batch = &mut out[first * 3..(first + count) * 3];
            samples += self.with_chunks(Pass::Render { embedding }, count, |shared, chunks| {
                let mut jobs: heapless::Vec<(&mut Chunk<'a>, &mut [f32]), MAX_CHUNKS> =
                    heapless::Vec::new();
                let mut rest = out_batch;
                for chunk in chunks.iter_mut() {
                    let (mine, tail) = rest.split_at_mut(chunk.ray_count * 3);
                    rest = tail;
                    let _ = jobs.push((chunk, mine));
                }
                executor.for_each(&mut jobs, |(chunk, out)| chunk.render(shared, out));
                jobs.iter()
                    .map(|(chunk, _)| chunk.report.samples as u64)
                    .sum::<u64>()
            });
            let times = self.chunks.iter_mut().map(|chunk| &mut chunk.times);
            self.profile
                .parallel(&mut laps, Bucket::Render, times, None);
        }
        Ok(samples as f32 / count_all.max(1) as f32)
    }
}
