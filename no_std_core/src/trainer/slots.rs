//! Frame slots: putting frames in (directly or through the replacement policy) and their
//! learnable parameters.

use super::*;

impl<'a> Trainer<'a> {
    /// The learnable parameters of a frame slot: appearance embedding, then pose correction.
    pub fn frame_parameters(&self, slot: usize) -> Option<&[f32]> {
        let n = self.config.frame_params();
        self.frame_params.get(slot * n..(slot + 1) * n)
    }

    /// The pose correction a frame slot has learned, in world units (the identity when pose
    /// correction is off).
    pub fn pose_correction(&self, slot: usize) -> Option<PoseCorrection> {
        let params = self.frame_parameters(slot)?;
        Some(if self.config.pose_correction {
            let pose = params
                .get(self.config.embedding_dim as usize..)
                .unwrap_or(&[]);
            PoseCorrection::from_params(pose, self.length_unit)
        } else {
            PoseCorrection::default()
        })
    }

    /// Mean appearance embedding of the occupied frames (zeros without frames).
    pub fn mean_embedding(&self, out: &mut [f32]) {
        let n = self.config.frame_params();
        out.fill(0.0);
        let count = self.frames.len();
        for i in 0..count {
            let Some(slot) = self.frames.occupied_slot(i) else {
                continue;
            };
            for (o, v) in out.iter_mut().zip(&self.frame_params[slot * n..]) {
                *o += v / count as f32;
            }
        }
    }

    /// Put a frame into `slot`. Its embedding starts at the mean of the other frames'
    /// embeddings, its pose correction at zero, and its optimizer moments are cleared. With a
    /// ray reservoir the frame's pixels are offered to it (its runs replacing those of the
    /// frame the slot held before). With `Config::loss_weighted_frames` its running loss
    /// starts at the largest of the others', so it is drawn as often as the worst-fitted one
    /// until its own rays say otherwise.
    pub fn set_frame(
        &mut self,
        slot: usize,
        camera: Camera,
        pose: Pose,
        pixels: &[u8],
        mask: Option<&[u8]>,
    ) -> Result<(), Error> {
        self.require_training()?;
        let largest_loss = self.largest_frame_loss();
        self.frames.set(slot, camera, pose, pixels, mask)?;
        if let Some(meta) = self.frames.meta.get_mut(slot) {
            meta.loss = largest_loss;
        }
        self.frames
            .offer_rays(slot, pixels, mask, self.config.seed, &mut self.state.rays);
        let n = self.config.frame_params();
        let dim = self.config.embedding_dim as usize;
        let mut mean = [0.0f32; 128];
        let mut others = 0;
        for i in 0..self.frames.len() {
            let Some(s) = self.frames.occupied_slot(i).filter(|&s| s != slot) else {
                continue;
            };
            for (m, v) in mean.iter_mut().zip(&self.frame_params[s * n..s * n + dim]) {
                *m += v;
            }
            others += 1;
        }
        let params = &mut self.frame_params[slot * n..(slot + 1) * n];
        params.fill(0.0);
        if others > 0 {
            for (p, m) in params.iter_mut().zip(&mean[..dim]) {
                *p = m / others as f32;
            }
        }
        self.frame_m[slot * n..(slot + 1) * n].fill(0.0);
        self.frame_v[slot * n..(slot + 1) * n].fill(0.0);
        Ok(())
    }

    /// Empty frame slot `slot` (no-op if it is already empty or out of range), with its
    /// entries in the ray reservoir.
    pub fn clear_frame(&mut self, slot: usize) {
        self.frames.clear(slot, &mut self.state.rays);
    }

    /// Stream a frame into the store. `arrival` counts the frames offered before it (it keys
    /// the policy's randomness and is kept with the slot). The frame is checked as `set_frame`
    /// checks it and refused if all black or all saturated; then the config's replacement
    /// policy (`replacement.rs`) picks its slot or turns it away. A stored frame's per-frame state
    /// is reset as `set_frame` does.
    pub fn ingest_frame(
        &mut self,
        arrival: u32,
        camera: Camera,
        pose: Pose,
        pixels: &[u8],
        mask: Option<&[u8]>,
    ) -> Result<Ingested, Error> {
        self.require_training()?;
        self.frames.check(&camera, &pose, pixels, mask)?;
        replacement::check_exposure(pixels)?;
        let incoming = Descriptor::new(&self.config, &pose, mean_brightness(pixels));
        let Some(slot) = replacement::choose_slot(&self.config, &self.frames, &incoming, arrival)
        else {
            return Ok(Ingested::Rejected);
        };
        self.set_frame(slot, camera, pose, pixels, mask)?;
        self.frames.set_arrival(slot, arrival);
        Ok(Ingested::Stored { slot })
    }
}
