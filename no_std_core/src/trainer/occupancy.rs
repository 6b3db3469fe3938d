//! The occupancy grid: its refresh from the field's densities.

use super::*;

impl<'a> Trainer<'a> {
    /// Fraction of occupancy cells marked occupied.
    pub fn occupancy_fraction(&self) -> f32 {
        let ones: u32 = self.occupancy_bits.iter().map(|w| w.count_ones()).sum();
        ones as f32 / self.config.occupancy_cells() as f32
    }

    /// Re-estimate every occupancy cell's density at a seeded point inside it, keep the
    /// decayed maximum, and mark cells whose opacity over one marching step exceeds the
    /// threshold as occupied.
    pub fn refresh_occupancy<E: Executor>(&mut self, executor: &E) {
        // A render-only trainer has no running densities to refresh.
        if !self.training {
            return;
        }
        let mut laps = self.profile.laps();
        let c = self.config;
        let cells = c.occupancy_cells();
        let density = core::mem::take(&mut self.occupancy_density);
        self.with_chunks(Pass::Occupancy, 0, |shared, chunks| {
            let per_chunk = cells.div_ceil(chunks.len());
            let mut jobs: heapless::Vec<(usize, &mut [f32], &mut Chunk<'a>), MAX_CHUNKS> =
                heapless::Vec::new();
            for (i, (part, chunk)) in density
                .chunks_mut(per_chunk)
                .zip(chunks.iter_mut())
                .enumerate()
            {
                let _ = jobs.push((i * per_chunk, part, chunk));
            }
            executor.for_each(&mut jobs, |(first_cell, part, chunk)| {
                chunk.refresh_cells(shared, *first_cell, part)
            });
        });
        self.occupancy_density = density;
        let times = self.chunks.iter_mut().map(|chunk| &mut chunk.times);
        self.profile.parallel(&mut laps, Bucket::Train, times, None);
        // As in nerfacc, the threshold never exceeds the mean cell opacity, so a field whose
        // densities are all still low (early training) is not culled to nothing.
        let sum = self
            .occupancy_density
            .iter()
            .fold(0.0f64, |a, d| a + *d as f64);
        let mean = (sum / cells as f64) as f32 * self.optical_step;
        let threshold = c.occupancy_threshold.min(mean);
        for (w, word) in self.occupancy_bits.iter_mut().enumerate() {
            let mut bits = 0u64;
            for (b, d) in self
                .occupancy_density
                .iter()
                .skip(w * 64)
                .take(64)
                .enumerate()
            {
                bits |= ((*d * self.optical_step > threshold) as u64) << b;
            }
            *word = bits;
        }
        // A grid with no occupied cell samples nothing, so nothing could ever learn again
        // (all densities underflowed, or all equal to their mean): re-open every cell and
        // let the next refresh cull from what training has learned by then.
        if self.occupancy_bits.iter().all(|word| *word == 0) {
            self.occupancy_bits.fill(u64::MAX);
        }
        self.state.refreshes += 1;
        self.profile
            .serial(&mut laps, Bucket::Train, Stage::Occupancy);
    }
}
