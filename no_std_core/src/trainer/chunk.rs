//! One chunk's buffers and its forward kernels: marching, the density and colour passes,
//! rendering and the occupancy cells.

use super::*;

/// The density MLP's activation rows of one mini-batch of `LANES` samples (or their
/// gradients).
pub(super) struct DensityRows<'r> {
    pub(super) feats: &'r mut [Row],
    pub(super) hidden: &'r mut [Row],
    pub(super) out: &'r mut [Row],
}

/// The colour MLP's activation rows of one mini-batch (or their gradients).
pub(super) struct ColourRows<'r> {
    /// The per-sample inputs: the geometry features.
    pub(super) geo: &'r mut [Row],
    pub(super) hidden1: &'r mut [Row],
    pub(super) hidden2: &'r mut [Row],
    pub(super) rgb: &'r mut [Row],
}

/// One mini-batch's density rows laid out in `rows` (`density_activation_rows` of them).
pub(super) fn density_rows_of<'r>(c: &Config, rows: &'r mut [Row]) -> DensityRows<'r> {
    let (feats, rest) = rows.split_at_mut(c.density_inputs());
    let (hidden, out) = rest.split_at_mut(c.density_hidden as usize);
    DensityRows { feats, hidden, out }
}

/// One mini-batch's colour rows laid out in `rows` (`colour_activation_rows` of them).
pub(super) fn colour_rows_of<'r>(c: &Config, rows: &'r mut [Row]) -> ColourRows<'r> {
    let (geo, rest) = rows.split_at_mut(c.geo_features as usize);
    let (hidden1, rest) = rest.split_at_mut(c.colour_hidden as usize);
    let (hidden2, rgb) = rest.split_at_mut(c.colour_hidden as usize);
    ColourRows {
        geo,
        hidden1,
        hidden2,
        rgb,
    }
}

/// The scratch rows of one mini-batch: the density part, then the colour part.
pub(super) fn split_rows<'r>(c: &Config, rows: &'r mut [Row]) -> (DensityRows<'r>, ColourRows<'r>) {
    let (density, colour) = rows.split_at_mut(density_activation_rows(c));
    (density_rows_of(c, density), colour_rows_of(c, colour))
}

/// One chunk's private buffers. Per-sample buffers are in marching order (a ray's samples
/// are consecutive); the samples a ray keeps after the early stop are a prefix of its own.
pub(super) struct Chunk<'a> {
    pub(super) plane_grads: &'a mut [f32],
    pub(super) touched: &'a mut [u64],
    pub(super) mlp_grads: &'a mut [f32],
    pub(super) frame_grads: &'a mut [f32],
    pub(super) positions: &'a mut [[f32; 3]],
    pub(super) sigma: &'a mut [f32],
    pub(super) geo: &'a mut [f32],
    pub(super) rgb: &'a mut [[f32; 3]],
    pub(super) d_sigma: &'a mut [f32],
    pub(super) d_rgb: &'a mut [[f32; 3]],
    pub(super) sample_ray: &'a mut [u32],
    /// Index of each kept sample (the colour MLP's mini-batches run over these).
    pub(super) kept_index: &'a mut [u32],
    /// Where each ray of the pass starts, and where its kept samples end.
    pub(super) ray_start: &'a mut [u32],
    pub(super) kept_end: &'a mut [u32],
    /// Scratch rows of one mini-batch (forward-only passes), and their gradients.
    pub(super) activations: &'a mut [Row],
    pub(super) gradients: &'a mut [Row],
    /// The training pass's activations, kept for its backward pass instead of recomputed:
    /// the density rows of every mini-batch of samples, the colour rows of every mini-batch
    /// of kept samples, and each sample's per-plane bilinear values (lane-major).
    pub(super) density_store: &'a mut [Row],
    pub(super) colour_store: &'a mut [Row],
    pub(super) plane_values: &'a mut [f32],
    /// d loss / d origin and d loss / d direction of each of the chunk's rays (pose correction).
    pub(super) ray_grads: &'a mut [f32],
    /// Each of the chunk's rays' squared colour error over its channels, for the frames'
    /// running losses (empty unless `Config::loss_weighted_frames`).
    pub(super) ray_loss: &'a mut [f32],
    /// Output gradients of one layer in lane-major order (the weight-gradient kernel's input).
    pub(super) lane_major: &'a mut [f32],
    /// First ray of the batch this chunk works on, and how many.
    pub(super) first_ray: usize,
    pub(super) ray_count: usize,
    pub(super) report: ChunkReport,
    /// A pose refinement's normal equations over this chunk's rays (Jacobian passes).
    pub(super) pose_system: PoseSystem,
    /// Time this chunk spent per stage since the trainer last collected it (profiling).
    pub(super) times: StageTimes,
}

#[derive(Clone, Copy, Default)]
pub(super) struct ChunkReport {
    pub(super) squared_error: f32,
    pub(super) rays: u32,
    pub(super) samples: u32,
    pub(super) marched: u32,
    /// Huber cost of a Jacobian pass's channel residuals (`backward::robust_residual`).
    pub(super) robust_cost: f32,
    /// The pass's stop request was heard before all the chunk's rays were trained: its
    /// gradients are partial (`Trainer::step_or_stop` throws them away).
    pub(super) stopped: bool,
}

impl Chunk<'_> {
    /// Origin and direction of ray `r` of the batch.
    pub(super) fn ray(shared: &Shared<'_>, r: usize) -> (Vec3, Vec3) {
        let ray = &shared.rays[r];
        (
            Vec3::from_array(ray.origin),
            Vec3::from_array(ray.direction),
        )
    }

    /// March rays `first..end` of the batch into the sample buffers, as many whole rays as
    /// fit (at least one: the config keeps `max_samples_per_ray <= samples_per_chunk`).
    /// Returns the number of rays marched.
    pub(super) fn march_rays(&mut self, shared: &Shared<'_>, first: usize, end: usize) -> usize {
        let c = shared.config;
        let capacity = self.sample_ray.len();
        let mut n = 0usize;
        self.ray_start[0] = 0;
        for r in first..end {
            let (o, d) = Self::ray(shared, r);
            let jitter = if shared.jitter {
                rng::unit_f32(rng::hash(
                    c.seed,
                    domain::RAY_JITTER,
                    shared.draw_counter as u64,
                    r as u64,
                ))
            } else {
                0.5
            };
            let mut full = false;
            render::march(
                &shared.occupancy,
                o,
                d,
                shared.step_size,
                jitter,
                c.max_samples_per_ray as usize,
                |t| {
                    if n == capacity {
                        full = true;
                        return false;
                    }
                    self.positions[n] = (o + d * t).to_array();
                    self.sample_ray[n] = r as u32;
                    n += 1;
                    true
                },
            );
            if full && r > first {
                // This ray goes to the next pass, marched again from its start.
                return r - first;
            }
            self.ray_start[r - first + 1] = n as u32;
        }
        end - first
    }

    /// Density of samples `0..n`. With `store`, every mini-batch's activations and plane
    /// values stay in the stores (for the colour pass and the backward pass); without, the
    /// geometry features go to `geo` for the colour pass.
    pub(super) fn density_pass(&mut self, shared: &Shared<'_>, n: usize, store: bool) {
        let c = shared.config;
        let geo_len = c.geo_features as usize;
        let rows = density_activation_rows(c);
        let values_len = 3 * c.density_inputs() * LANES;
        for base in (0..n).step_by(LANES) {
            let lanes = LANES.min(n - base);
            let (mut act, values) = if store {
                let b = base / LANES;
                (
                    density_rows_of(c, &mut self.density_store[b * rows..(b + 1) * rows]),
                    &mut self.plane_values[b * values_len..(b + 1) * values_len],
                )
            } else {
                // Only the density: no backward pass reads this pass's plane values.
                (split_rows(c, self.activations).0, &mut [][..])
            };
            density_forward(
                shared,
                &self.positions[base..base + lanes],
                &mut act,
                values,
                Outputs::All,
            );
            for l in 0..lanes {
                self.sigma[base + l] = field::trunc_exp(act.out[0][l]);
            }
            if !store {
                for l in 0..lanes {
                    for g in 0..geo_len {
                        self.geo[(base + l) * geo_len + g] = act.out[1 + g][l];
                    }
                }
            }
        }
    }

    /// Moves the stored density rows of the kept samples (`n` of the `marched`) to the front,
    /// so that mini-batch `b` of them holds kept samples `64 b ..` like the colour rows: the
    /// colour pass reads its geometry features there, and the backward pass spends nothing on
    /// the samples cut off.
    pub(super) fn compact_density_rows(&mut self, shared: &Shared<'_>, marched: usize, n: usize) {
        let rows = density_activation_rows(shared.config);
        let kept = &self.kept_index[..n];
        let mut next = 0;
        fused::compact_lanes(self.density_store, rows, marched.div_ceil(LANES), |b| {
            // `kept_index` is in marching order: batch b's kept samples come next.
            let mut mask = 0u64;
            while let Some(&s) = kept.get(next).filter(|&&s| (s as usize) < (b + 1) * LANES) {
                mask |= 1 << (s as usize - b * LANES);
                next += 1;
            }
            mask
        });
    }

    /// Cut each of the pass's `rays` after the sample where its transmittance runs out:
    /// records where its kept samples end and lists them in `kept_index`. Returns the
    /// number kept.
    pub(super) fn keep_visible(&mut self, shared: &Shared<'_>, rays: usize) -> usize {
        let c = shared.config;
        let mut n = 0usize;
        for r in 0..rays {
            let (start, end) = (self.ray_start[r] as usize, self.ray_start[r + 1] as usize);
            let kept = render::kept_samples(
                &self.sigma[start..end],
                shared.optical_step,
                c.min_transmittance,
            );
            self.kept_end[r] = (start + kept) as u32;
            for (slot, s) in self.kept_index[n..n + kept].iter_mut().zip(start as u32..) {
                *slot = s;
            }
            n += kept;
        }
        n
    }

    /// Colours of the kept samples (`n` of them). With `store`, every mini-batch's colour
    /// rows stay in the store for the backward pass, and the geometry features come from
    /// the compacted density rows ([`Self::compact_density_rows`]).
    pub(super) fn colour_pass(&mut self, shared: &Shared<'_>, n: usize, store: bool) {
        let c = shared.config;
        let (rows, density_rows) = (colour_activation_rows(c), density_activation_rows(c));
        let geo_len = c.geo_features as usize;
        for base in (0..n).step_by(LANES) {
            let lanes = LANES.min(n - base);
            let b = base / LANES;
            let kept = &self.kept_index[base..base + lanes];
            let mut act = if store {
                let act = colour_rows_of(c, &mut self.colour_store[b * rows..(b + 1) * rows]);
                let stored = &self.density_store[b * density_rows..(b + 1) * density_rows];
                let geo = &stored[density_rows - geo_len..];
                for (row, from) in act.geo.iter_mut().zip(geo) {
                    row[..lanes].copy_from_slice(&from[..lanes]);
                    row[lanes..].fill(0.0);
                }
                act
            } else {
                let act = split_rows(c, self.activations).1;
                for (g, row) in act.geo.iter_mut().enumerate() {
                    row.fill(0.0);
                    for (v, &s) in row.iter_mut().zip(kept) {
                        *v = self.geo[s as usize * geo_len + g];
                    }
                }
                act
            };
            Self::colour_forward(kept, self.sample_ray, shared, &mut act);
            for (l, &s) in kept.iter().enumerate() {
                self.rgb[s as usize] = [act.rgb[0][l], act.rgb[1][l], act.rgb[2][l]];
            }
        }
    }

    /// The colour MLP on the samples `kept` (at most `LANES`; their geometry features in
    /// `rows.geo`, zero in the unused lanes) into `rows.rgb`. The view encoding and the
    /// appearance embedding are the same for every sample of a ray, so their part of the
    /// first layer ([`ray_term`]) is computed once per run of a ray's samples; only the
    /// geometry features go through that layer per sample.
    pub(super) fn colour_forward(
        kept: &[u32],
        sample_ray: &[u32],
        shared: &Shared<'_>,
        rows: &mut ColourRows<'_>,
    ) {
        let c = shared.config;
        let (sh_len, geo_len) = (c.sh_values(), c.geo_features as usize);
        let first = shared.layout.layers[COLOUR_HIDDEN1];
        let hidden = first.outputs;
        let lanes = kept.len();
        let rays = lane_rays(kept, sample_ray);
        let mut term = [0.0f32; MAX_COLOUR_HIDDEN];
        let term = &mut term[..hidden];
        for (start, end) in ray_runs(&rays[..lanes]) {
            ray_term(shared, rays[start] as usize, term);
            for (row, t) in rows.hidden1.iter_mut().zip(term.iter()) {
                row[start..end].fill(*t);
            }
        }
        // Unused lanes (their geometry rows are zero) get the bias alone.
        let p = shared.mlp;
        let bias = &p[first.biases..first.biases + hidden];
        for (row, b) in rows.hidden1.iter_mut().zip(bias) {
            row[lanes..].fill(*b);
        }
        let weights = &p[first.weights..first.biases];
        field::layer_forward_onto(
            &weights[sh_len * hidden..(sh_len + geo_len) * hidden],
            rows.geo,
            rows.hidden1,
        );
        colour_mlp(shared, rows.hidden1, rows.hidden2, rows.rgb);
    }

    /// The forward part of one pass over rays from `first` (before `end`): march as many
    /// whole rays as fit, their densities, the early stop and the kept samples' colours (with
    /// `store`, keeping the activations for the backward pass). Returns the rays, the
    /// samples marched and the samples kept.
    pub(super) fn forward_pass(
        &mut self,
        shared: &Shared<'_>,
        first: usize,
        end: usize,
        store: bool,
        laps: &mut Laps,
    ) -> (usize, usize, usize) {
        let rays = self.march_rays(shared, first, end);
        laps.lap(Stage::Marching, &mut self.times);
        let marched = self.ray_start[rays] as usize;
        self.density_pass(shared, marched, store);
        laps.lap(Stage::DensityForward, &mut self.times);
        let n = self.keep_visible(shared, rays);
        if store {
            self.compact_density_rows(shared, marched, n);
        }
        laps.lap(Stage::EarlyStop, &mut self.times);
        self.colour_pass(shared, n, store);
        laps.lap(Stage::ColourForward, &mut self.times);
        (rays, marched, n)
    }

    /// Render this chunk's rays (all of them, in as many passes as the sample capacity
    /// needs) into `out` (RGB per ray).
    pub(super) fn render(&mut self, shared: &Shared<'_>, out: &mut [f32]) {
        let c = shared.config;
        self.report = ChunkReport::default();
        let (mut first, end) = (self.first_ray, self.first_ray + self.ray_count);
        while first < end {
            let mut laps = shared.timer.laps();
            let (rays, _, n) = self.forward_pass(shared, first, end, false, &mut laps);
            for r in 0..rays {
                let kept = self.ray_start[r] as usize..self.kept_end[r] as usize;
                let (colour, _) = render::composite_forward(
                    &self.sigma[kept.clone()],
                    &self.rgb[kept],
                    shared.optical_step,
                    c.background,
                );
                let o = (first - self.first_ray + r) * 3;
                out[o..o + 3].copy_from_slice(&colour);
            }
            laps.lap(Stage::Compositing, &mut self.times);
            self.report.samples += n as u32;
            first += rays;
        }
    }

    /// Zero the gradients a training pass left in this chunk (the texels its touched bits
    /// name, the MLP's and the frames'), as the step's reduction leaves them: what an
    /// abandoned step does instead of reducing and applying them.
    pub(super) fn clear_gradients(&mut self, features: usize) {
        for texel in set_bits(self.touched) {
            let range = texel * features..(texel + 1) * features;
            if let Some(grads) = self.plane_grads.get_mut(range) {
                grads.fill(0.0);
            }
        }
        self.touched.fill(0);
        self.mlp_grads.fill(0.0);
        self.frame_grads.fill(0.0);
    }

    /// Density of each of `points` into `sigma` (the same field as the density pass).
    pub(super) fn densities(
        &mut self,
        shared: &Shared<'_>,
        points: &[[f32; 3]],
        sigma: &mut [f32],
    ) {
        for (points, sigma) in points.chunks(LANES).zip(sigma.chunks_mut(LANES)) {
            let (mut rows, _) = split_rows(shared.config, self.activations);
            density_forward(shared, points, &mut rows, &mut [], Outputs::DensityOnly);
            for (l, s) in sigma.iter_mut().enumerate() {
                *s = field::trunc_exp(rows.out[0][l]);
            }
        }
    }

    /// Update the running density of `cells` (starting at cell index `first_cell`).
    pub(super) fn refresh_cells(
        &mut self,
        shared: &Shared<'_>,
        first_cell: usize,
        cells: &mut [f32],
    ) {
        let mut laps = shared.timer.laps();
        let c = shared.config;
        let res = c.occupancy_res as usize;
        let size = (shared.aabb.max - shared.aabb.min) / res as f32;
        for base in (0..cells.len()).step_by(LANES) {
            let lanes = LANES.min(cells.len() - base);
            let mut positions = [[0.0f32; 3]; LANES];
            for (l, p) in positions.iter_mut().enumerate().take(lanes) {
                let i = first_cell + base + l;
                let cell = Vec3::new(
                    (i % res) as f32,
                    ((i / res) % res) as f32,
                    (i / (res * res)) as f32,
                );
                let bits = rng::hash(
                    c.seed,
                    domain::OCCUPANCY,
                    shared.draw_counter as u64,
                    i as u64,
                );
                let jitter = Vec3::new(
                    rng::unit_f32(bits),
                    rng::unit_f32(bits << 24),
                    rng::unit_f32(bits << 48),
                );
                *p = (shared.aabb.min + (cell + jitter) * size).to_array();
            }
            let (mut rows, _) = split_rows(c, self.activations);
            density_forward(
                shared,
                &positions[..lanes],
                &mut rows,
                &mut [],
                Outputs::DensityOnly,
            );
            for l in 0..lanes {
                let d = &mut cells[base + l];
                let sigma = field::trunc_exp(rows.out[0][l]);
                *d = (*d * c.occupancy_decay).max(sigma);
            }
        }
        laps.lap(Stage::Occupancy, &mut self.times);
    }
}

/// The ray of each of the samples `kept` (at most `LANES`).
pub(super) fn lane_rays(kept: &[u32], sample_ray: &[u32]) -> [u32; LANES] {
    let mut rays = [0u32; LANES];
    for (r, &s) in rays.iter_mut().zip(kept) {
        *r = sample_ray[s as usize];
    }
    rays
}

/// The runs of equal rays in `sample_ray` (a ray's samples are consecutive): `(start, end)`
/// lane ranges.
pub(super) fn ray_runs(sample_ray: &[u32]) -> impl Iterator<Item = (usize, usize)> + '_ {
    let mut start = 0;
    core::iter::from_fn(move || {
        let ray = *sample_ray.get(start)?;
        let len = sample_ray[start..]
            .iter()
            .take_while(|&&r| r == ray)
            .count();
        let run = (start, start + len);
        start += len;
        Some(run)
    })
}

/// The colour MLP's first layer on ray `r`'s own inputs into `term` (`colour_hidden`
/// values): the bias, plus the view encoding's and the appearance embedding's weights times
/// their values, each row fused in order (encoding, then embedding).
pub(super) fn ray_term(shared: &Shared<'_>, r: usize, term: &mut [f32]) {
    let c = shared.config;
    let (sh_len, geo_len) = (c.sh_values(), c.geo_features as usize);
    let first = shared.layout.layers[COLOUR_HIDDEN1];
    let hidden = first.outputs;
    let p = shared.mlp;
    let weights = &p[first.weights..first.biases];
    term.copy_from_slice(&p[first.biases..first.biases + hidden]);
    let mut sh = [0.0f32; 16];
    let (_, d) = Chunk::ray(shared, r);
    field::sh_forward(c.sh_bands as usize, d.to_array(), &mut sh);
    for (k, v) in sh.iter().enumerate().take(sh_len) {
        fused::axpy(term, *v, &weights[k * hidden..(k + 1) * hidden]);
    }
    let embedding = embedding_of(shared, r);
    for (k, v) in embedding.iter().enumerate().take(c.embedding_dim as usize) {
        let row = sh_len + geo_len + k;
        fused::axpy(term, *v, &weights[row * hidden..(row + 1) * hidden]);
    }
}

/// The appearance embedding of the frame ray `r` was drawn from (or the fixed one).
pub(super) fn embedding_of<'s>(shared: &Shared<'s>, r: usize) -> &'s [f32] {
    let c = shared.config;
    match shared.embedding {
        Embedding::Fixed(e) => e,
        Embedding::PerFrame(all) => {
            let slot = shared.ray_frames.get(r).copied().unwrap_or(0) as usize;
            let n = c.frame_params();
            all.get(slot * n..slot * n + c.embedding_dim as usize)
                .unwrap_or(&[])
        }
    }
}

/// What [`density_forward`] computes of the density MLP's outputs.
#[derive(Clone, Copy, PartialEq)]
pub(super) enum Outputs {
    /// The density and the geometry features.
    All,
    /// The density alone (`rows.out[0]`; the other rows keep what they held): the occupancy
    /// refresh and point queries, which read nothing else.
    DensityOnly,
}

/// The density MLP on up to `LANES` positions: their plane features into `rows.feats`, then
/// the hidden layer and `rows.out` (all of it, or the density row alone).
pub(super) fn density_forward(
    shared: &Shared<'_>,
    positions: &[[f32; 3]],
    rows: &mut DensityRows<'_>,
    values: &mut [f32],
    outputs: Outputs,
) {
    load_features(shared, positions, rows.feats, values);
    let out = match outputs {
        Outputs::All => &mut rows.out[..],
        Outputs::DensityOnly => &mut rows.out[..1],
    };
    density_mlp(shared, rows.feats, rows.hidden, out);
}

/// Plane features of up to `LANES` positions into `feats` (unused lanes zero), and each
/// lane's per-plane values into `values` (lane-major; empty when no backward pass follows).
fn load_features(
    shared: &Shared<'_>,
    positions: &[[f32; 3]],
    feats: &mut [Row],
    values: &mut [f32],
) {
    let n = feats.len();
    let mut out = [0.0f32; 4 * 64];
    for row in feats.iter_mut() {
        row.fill(0.0);
    }
    let weights = row_scale_weights(shared);
    for (l, p) in positions.iter().enumerate() {
        let values = values
            .get_mut(l * 3 * n..(l + 1) * 3 * n)
            .unwrap_or_default();
        let u = shared.aabb.normalise(Vec3::from_array(*p));
        field::planes_forward(shared.planes, shared.geometry, u, &mut out[..n], values);
        for k in 0..n {
            feats[k][l] = out[k] * weights[k];
        }
    }
}

/// Each feature row's scale weight (coarse to fine), looked up once per chunk instead of
/// dividing the row index per sample.
pub(super) fn row_scale_weights(shared: &Shared<'_>) -> [f32; 4 * 64] {
    let per_scale = shared.geometry.features.max(1);
    core::array::from_fn(|k| {
        shared
            .scale_weights
            .get(k / per_scale)
            .copied()
            .unwrap_or(0.0)
    })
}

/// The density MLP from the plane features: the hidden layer, then the first `out.len()`
/// output rows.
fn density_mlp(shared: &Shared<'_>, feats: &[Row], hidden: &mut [Row], out: &mut [Row]) {
    let (l1, l2) = (
        shared.layout.layers[DENSITY_HIDDEN],
        shared.layout.layers[DENSITY_OUT],
    );
    let p = shared.mlp;
    field::layer_forward(
        &p[l1.weights..l1.biases],
        &p[l1.biases..l1.biases + l1.outputs],
        feats,
        hidden,
    );
    field::relu_forward(hidden);
    // Each output row sums its own terms, so computing the first rows alone gives their bits.
    let w2 = &p[l2.weights..l2.biases];
    for (row, b) in out.iter_mut().zip(&p[l2.biases..l2.biases + l2.outputs]) {
        *row = [*b; LANES];
    }
    fused::combine_rows(out, hidden, |n, k| w2[k * l2.outputs + n]);
}

/// The colour MLP from its first layer's output `h1` (before the ReLU) to `rgb`.
fn colour_mlp(shared: &Shared<'_>, h1: &mut [Row], h2: &mut [Row], rgb: &mut [Row]) {
    let layers = &shared.layout.layers;
    let p = shared.mlp;
    let wb = |i: usize| {
        let l = layers[i];
        (&p[l.weights..l.biases], &p[l.biases..l.biases + l.outputs])
    };
    field::relu_forward(h1);
    let (w, b) = wb(COLOUR_HIDDEN2);
    field::layer_forward(w, b, h1, h2);
    field::relu_forward(h2);
    let (w, b) = wb(COLOUR_OUT);
    field::layer_forward(w, b, h2, rgb);
    for row in rgb.iter_mut() {
        for v in row.iter_mut() {
            *v = field::sigmoid(*v);
        }
    }
}
