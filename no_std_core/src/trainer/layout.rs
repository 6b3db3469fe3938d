//! Carving the arena into the trainer's buffers, and the seeded initial parameters.

use super::chunk::ChunkReport;
use super::*;

impl<'a> Trainer<'a> {
    /// Validate `config`, lay out `arena` and initialise the parameters from the seed.
    pub fn new(config: Config, arena: &'a mut [u8]) -> Result<Self, Error> {
        Self::carve(config, arena, true)
    }

    /// A trainer that can only render: `arena` holds [`MemoryPlan::render_only`] (planes, MLP
    /// weights, occupancy bits, rays, forward buffers), to be filled with
    /// [`Trainer::restore_section`] ("planes", "mlp", "occupancy_bits"). Training, embedding
    /// fits, occupancy refreshes and frames are refused with [`Error::RenderOnly`].
    pub fn new_render_only(config: Config, arena: &'a mut [u8]) -> Result<Self, Error> {
        Self::carve(config, arena, false)
    }

    /// Lay out the whole plan (`training`) or the render-only one: the parts the latter
    /// leaves out are carved with length zero.
    fn carve(config: Config, arena: &'a mut [u8], training: bool) -> Result<Self, Error> {
        config.validate()?;
        let plan = if training {
            MemoryPlan::new(&config)
        } else {
            MemoryPlan::render_only(&config)
        };
        let mut carver = Carver::new(arena, plan.total)?;
        let t = |len: usize| if training { len } else { 0 };
        let c = &config;
        let params = c.plane_params();
        let words = c.texels().div_ceil(64);
        let mlp_len = c.mlp().total;
        let frames = t(c.max_frames as usize);
        let frame_params = c.frame_params();
        let chunks = c.chunks as usize;
        let samples = c.samples_per_chunk as usize;
        let chunk_rays = c.rays_per_chunk();
        let mut used = MemoryPlan { total: 0, ..plan };
        let mut mark = 0;
        let mut tally = |carver: &Carver, part: &mut usize| {
            *part = carver.used() - mark;
            mark = carver.used();
        };

        let planes = carver.take::<f16>(params)?;
        tally(&carver, &mut used.planes);
        let master_len = if training && c.texel_update == TexelUpdate::MasterCopy {
            params
        } else {
            0
        };
        let plane_master = carver.take::<f32>(master_len)?;
        tally(&carver, &mut used.plane_master);
        let plane_m = carver.take::<f32>(t(params))?;
        let plane_v = carver.take::<f32>(t(params))?;
        tally(&carver, &mut used.plane_moments);
        let mut plane_grad_parts: heapless::Vec<(&mut [f32], &mut [u64]), MAX_CHUNKS> =
            heapless::Vec::new();
        for _ in 0..chunks {
            let grads = carver.take::<f32>(t(params))?;
            let touched = carver.take::<u64>(t(words))?;
            let _ = plane_grad_parts.push((grads, touched));
        }
        let touched_union = carver.take::<u64>(t(words))?;
        tally(&carver, &mut used.plane_grads);
        let mlp = carver.take::<f32>(mlp_len)?;
        let mlp_m = carver.take::<f32>(t(mlp_len))?;
        let mlp_v = carver.take::<f32>(t(mlp_len))?;
        let mut mlp_grad_parts: heapless::Vec<&mut [f32], MAX_CHUNKS> = heapless::Vec::new();
        for _ in 0..chunks {
            let _ = mlp_grad_parts.push(carver.take::<f32>(t(mlp_len))?);
        }
        tally(&carver, &mut used.mlp);
        let occupancy_bits = carver.take::<u64>(c.occupancy_cells().div_ceil(64))?;
        let occupancy_density = carver.take::<f32>(t(c.occupancy_cells()))?;
        tally(&carver, &mut used.occupancy);
        let (pixel_bytes, mask_bytes) = c.frame_pixel_bytes();
        let pixels = carver.take::<u8>(t(pixel_bytes))?;
        let masks = carver.take::<u8>(t(mask_bytes))?;
        let meta = carver.take::<FrameMeta>(frames)?;
        let occupied = carver.take::<u16>(frames)?;
        let frame_param_slice = carver.take::<f32>(frames * frame_params)?;
        let frame_m = carver.take::<f32>(frames * frame_params)?;
        let frame_v = carver.take::<f32>(frames * frame_params)?;
        let mut frame_grad_parts: heapless::Vec<&mut [f32], MAX_CHUNKS> = heapless::Vec::new();
        for _ in 0..chunks {
            let _ = frame_grad_parts.push(carver.take::<f32>(frames * frame_params)?);
        }
        tally(&carver, &mut used.frames);
        let rays = carver.take::<BatchRay>(c.rays_per_batch as usize)?;
        let ray_frames = carver.take::<u32>(t(c.rays_per_batch as usize))?;
        tally(&carver, &mut used.ray_batch);
        let mut chunk_list = heapless::Vec::new();
        let rows = activation_floats(c);
        let density_rows = density_activation_rows(c);
        let (geo_len, inputs) = (c.geo_features as usize, c.density_inputs());
        // Whole mini-batches: the stored activations are kept per mini-batch of LANES.
        let samples = samples.div_ceil(LANES) * LANES;
        for (i, ((plane_grads, touched), (mlp_grads, frame_grads))) in plane_grad_parts
            .into_iter()
            .zip(mlp_grad_parts.into_iter().zip(frame_grad_parts))
            .enumerate()
        {
            let block = carver.take::<f32>(if training {
                samples * sample_floats(c)
            } else {
                samples * forward_sample_floats(c)
            })?;
            let (positions, block) = block.split_at_mut(3 * samples);
            let (sigma, block) = block.split_at_mut(samples);
            let (geo, block) = block.split_at_mut(geo_len * samples);
            let (rgb, block) = block.split_at_mut(3 * samples);
            let (d_sigma, block) = block.split_at_mut(t(samples));
            let (d_rgb, block) = block.split_at_mut(t(3 * samples));
            let (plane_values, block) = block.split_at_mut(t(3 * inputs * samples));
            let (density_store, colour_store) = block.split_at_mut(t(density_rows * samples));
            let sample_ray = carver.take::<u32>(samples)?;
            let kept_index = carver.take::<u32>(samples)?;
            let ray_start = carver.take::<u32>(chunk_rays + 1)?;
            let kept_end = carver.take::<u32>(chunk_rays)?;
            let act = carver.take::<Row>(rows + t(rows))?;
            let (activations, gradients) = act.split_at_mut(rows);
            let lane_major = carver.take::<f32>(t(LANES * widest_layer(c)))?;
            let ray_grads = carver.take::<f32>(t(chunk_rays * RAY_GRAD_FLOATS))?;
            let ray_loss = carver.take::<f32>(t(chunk_rays * c.loss_weighted_frames as usize))?;
            let chunk = Chunk {
                plane_grads,
                touched,
                mlp_grads,
                frame_grads,
                positions: bytemuck::cast_slice_mut(positions),
                sigma,
                geo,
                rgb: bytemuck::cast_slice_mut(rgb),
                d_sigma,
                d_rgb: bytemuck::cast_slice_mut(d_rgb),
                sample_ray,
                kept_index,
                ray_start,
                kept_end,
                activations,
                gradients,
                density_store: bytemuck::cast_slice_mut(density_store),
                colour_store: bytemuck::cast_slice_mut(colour_store),
                plane_values,
                lane_major,
                ray_grads,
                ray_loss,
                first_ray: i * chunk_rays,
                ray_count: chunk_rays,
                report: ChunkReport::default(),
                pose_system: PoseSystem::default(),
                times: StageTimes::default(),
            };
            if chunk_list.push(chunk).is_err() {
                return Err(Error::InvalidConfig { field: "chunks" });
            }
        }
        tally(&carver, &mut used.samples);
        used.total = carver.used();

        let aabb = Aabb {
            min: Vec3::from_array(c.aabb_min),
            max: Vec3::from_array(c.aabb_max),
        };
        let step_size = aabb.diagonal() / config.march_steps as f32;
        let length_unit = config.length_unit();
        let mut trainer = Trainer {
            config,
            geometry: PlaneGeometry::new(&config),
            layout: config.mlp(),
            aabb,
            step_size,
            optical_step: step_size / length_unit,
            length_unit,
            planes,
            plane_master,
            plane_m,
            plane_v,
            touched_union,
            mlp,
            mlp_m,
            mlp_v,
            occupancy_bits,
            occupancy_density,
            frames: FrameStore {
                meta,
                pixels,
                masks,
                occupied,
                len: 0,
                max_pixels: t(c.max_pixels_per_frame as usize),
                foreground_rays: c.foreground_rays(),
                keep_rays: c.ray_store > 0,
            },
            frame_params: frame_param_slice,
            frame_m,
            frame_v,
            rays,
            ray_frames,
            chunks: chunk_list,
            state: TrainState::default(),
            profile: Profiler::default(),
            used,
            training,
        };
        trainer.initialise();
        Ok(trainer)
    }

    /// Seeded initial parameters: planes uniform in [init_low, init_high], MLP weights
    /// uniform in ±sqrt(6 / fan_in) (He), zero biases; every occupancy cell occupied.
    fn initialise(&mut self) {
        let c = &self.config;
        let mut rng = rng::Rng::new(rng::hash(c.seed, domain::INIT, 0, 0));
        for (i, t) in self.planes.iter_mut().enumerate() {
            let v = c.init_low + (c.init_high - c.init_low) * rng.uniform();
            *t = f16::from_f32(v);
            if let Some(m) = self.plane_master.get_mut(i) {
                *m = t.to_f32();
            }
        }
        for layer in &self.layout.layers {
            let bound = libm::sqrtf(6.0 / layer.inputs as f32);
            for w in &mut self.mlp[layer.weights..layer.biases] {
                *w = bound * (2.0 * rng.uniform() - 1.0);
            }
        }
        self.occupancy_bits.fill(u64::MAX);
    }
}
