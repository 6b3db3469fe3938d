//! The training state as named byte sections, for checkpoints.

use super::*;

/// The checkpoint's sections in file order: each name and the trainer field that holds it.
/// `sections` (save) and `restore_section` both expand this one table through `$expand`.
macro_rules! with_section_table {
    ($expand:ident, $trainer:ident) => {
        $expand!($trainer;
            "state" => state,
            "planes" => planes,
            "plane_master" => plane_master,
            "plane_m" => plane_m,
            "plane_v" => plane_v,
            "mlp" => mlp,
            "mlp_m" => mlp_m,
            "mlp_v" => mlp_v,
            "occupancy_bits" => occupancy_bits,
            "occupancy_density" => occupancy_density,
            "frame_meta" => frames.meta,
            "frame_pixels" => frames.pixels,
            "frame_masks" => frames.masks,
            "frame_params" => frame_params,
            "frame_m" => frame_m,
            "frame_v" => frame_v,
        )
    };
}

/// A section's bytes, as stored in a checkpoint.
trait SectionBytes {
    fn bytes(&self) -> &[u8];
    fn bytes_mut(&mut self) -> &mut [u8];
}

impl<T: Pod> SectionBytes for [T] {
    fn bytes(&self) -> &[u8] {
        bytemuck::cast_slice(self)
    }
    fn bytes_mut(&mut self) -> &mut [u8] {
        bytemuck::cast_slice_mut(self)
    }
}

impl SectionBytes for TrainState {
    fn bytes(&self) -> &[u8] {
        bytemuck::bytes_of(self)
    }
    fn bytes_mut(&mut self) -> &mut [u8] {
        bytemuck::bytes_of_mut(self)
    }
}

impl<'a> Trainer<'a> {
    /// The whole training state as named byte sections (for checkpoints): parameters,
    /// optimizer moments, occupancy, frames and counters.
    pub fn sections(&self) -> [(&'static str, &[u8]); 16] {
        macro_rules! save {
            ($trainer:ident; $($name:literal => $($field:ident).+,)*) => {
                [$(($name, $trainer.$($field).+.bytes())),*]
            };
        }
        with_section_table!(save, self)
    }

    /// The first section holding a non-finite parameter, moment or density, with the
    /// element's index: a diverged model that must not be saved or scored.
    pub fn first_non_finite_section(&self) -> Option<(&'static str, usize)> {
        self.sections()
            .into_iter()
            .find_map(|(name, data)| first_non_finite(name, data).map(|index| (name, index)))
    }

    /// Restore one section written by `sections` for the same config. The size must match.
    pub fn restore_section(&mut self, name: &str, data: &[u8]) -> Result<(), Error> {
        self.restore_section_with(name, data.len(), |target| {
            target.copy_from_slice(data);
            true
        })
    }

    /// [`restore_section`](Self::restore_section) of a section of `len` bytes that `fill`
    /// writes straight into the trainer's own storage (from a file, say), so that restoring
    /// takes no copy of the model. `fill` returns whether it filled the whole slice. A section
    /// that was not filled, or that fails the checks, is left zeroed (no parameters, no
    /// occupied frame slot), never half-restored.
    pub fn restore_section_with(
        &mut self,
        name: &str,
        len: usize,
        fill: impl FnOnce(&mut [u8]) -> bool,
    ) -> Result<(), Error> {
        macro_rules! find {
            ($trainer:ident; $($name:literal => $($field:ident).+,)*) => {
                match name {
                    $($name => ($name, $trainer.$($field).+.bytes_mut()),)*
                    _ => return Err(Error::UnknownSection),
                }
            };
        }
        let max_pixels = self.frames.max_pixels;
        let (name, target): (&'static str, &mut [u8]) = with_section_table!(find, self);
        if target.len() != len {
            return Err(Error::BadSection {
                name,
                expected: target.len(),
                got: len,
            });
        }
        let checked = if !fill(target) {
            Err(Error::SectionNotRead { name })
        } else if let Some(index) = first_non_finite(name, target) {
            Err(Error::NonFiniteSection { name, index })
        } else if name == "frame_meta" {
            check_frame_slots(target, max_pixels)
        } else {
            Ok(())
        };
        if checked.is_err() {
            target.fill(0);
        }
        if name == "frame_meta" {
            self.frames.rebuild_occupied();
        }
        checked
    }
}

/// Refuse frame slots whose camera is invalid or whose sizes would not index a pixel store of
/// `max_pixels` per slot.
fn check_frame_slots(meta: &[u8], max_pixels: usize) -> Result<(), Error> {
    let size = core::mem::size_of::<FrameMeta>();
    for (slot, raw) in meta.chunks_exact(size).enumerate() {
        let meta: FrameMeta = bytemuck::pod_read_unaligned(raw);
        let pixels = meta.width as usize * meta.height as usize;
        if meta.occupied != 0
            && (!meta.camera().is_valid()
                || pixels > max_pixels
                || meta.width > u16::MAX as u32
                || meta.height > u16::MAX as u32)
        {
            return Err(Error::BadFrameSlot { slot });
        }
    }
    Ok(())
}

/// The first non-finite element of a section of parameters, moments or densities (f16
/// planes, f32 otherwise); `None` for finite data and for sections of other kinds.
fn first_non_finite(name: &str, data: &[u8]) -> Option<usize> {
    match name {
        "planes" => data
            .chunks_exact(2)
            .position(|b| !f16::from_ne_bytes([b[0], b[1]]).is_finite()),
        "plane_master" | "plane_m" | "plane_v" | "mlp" | "mlp_m" | "mlp_v"
        | "occupancy_density" | "frame_params" | "frame_m" | "frame_v" => data
            .chunks_exact(4)
            .position(|b| !f32::from_ne_bytes([b[0], b[1], b[2], b[3]]).is_finite()),
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::super::tests::{put_test_frame, small_config};
    use super::*;

    /// Two trainers of the small config in `arena`: one holding a test frame, one fresh.
    fn trainer_with_a_frame_and_a_fresh_one(arena: &mut [u8]) -> (Trainer<'_>, Trainer<'_>) {
        let config = small_config();
        let plan = MemoryPlan::new(&config);
        let (first, second) = arena.split_at_mut(arena.len() / 2);
        let mut trainer = Trainer::new(config, &mut first[..plan.total]).unwrap();
        put_test_frame(&mut trainer);
        (
            trainer,
            Trainer::new(config, &mut second[..plan.total]).unwrap(),
        )
    }

    /// Every section restores into a fresh trainer; a frame slot larger than a slot holds, or
    /// an unknown section, is refused with an error that says which.
    #[test]
    fn sections_round_trip_and_bad_frame_slots_are_named() {
        let mut arena = [0u8; 1 << 20];
        let (trainer, mut copy) = trainer_with_a_frame_and_a_fresh_one(&mut arena);
        for (name, bytes) in trainer.sections() {
            copy.restore_section(name, bytes).unwrap();
        }
        assert_eq!(copy.sections(), trainer.sections());

        let mut meta = trainer.frames.meta[0];
        meta.width = 1000;
        let mut bytes = [0u8; 2 * core::mem::size_of::<FrameMeta>()];
        bytes[core::mem::size_of::<FrameMeta>()..].copy_from_slice(bytemuck::bytes_of(&meta));
        assert_eq!(
            copy.restore_section("frame_meta", &bytes),
            Err(Error::BadFrameSlot { slot: 1 })
        );
        assert_eq!(
            copy.restore_section("frame_metadata", &bytes),
            Err(Error::UnknownSection)
        );
        // The refused slot table is left empty, not half-restored: no slot is occupied.
        assert!(copy.frames.meta.iter().all(|m| m.occupied == 0));
    }

    /// A section filled in place is the section restored from a slice; one whose filler
    /// fails, or that holds a NaN, is refused naming it and left zeroed.
    #[test]
    fn a_section_filled_in_place_restores_or_is_left_zeroed() {
        let mut arena = [0u8; 1 << 20];
        let (trainer, mut copy) = trainer_with_a_frame_and_a_fresh_one(&mut arena);
        let mlp = trainer.sections()[5];
        assert_eq!(mlp.0, "mlp");
        let len = mlp.1.len();
        copy.restore_section_with("mlp", len, |target| {
            target.copy_from_slice(mlp.1);
            true
        })
        .unwrap();
        assert_eq!(copy.sections()[5], mlp);
        let fill_half = |target: &mut [u8]| {
            target[..len / 2].fill(1);
            false
        };
        assert_eq!(
            copy.restore_section_with("mlp", len, fill_half),
            Err(Error::SectionNotRead { name: "mlp" })
        );
        assert!(copy.sections()[5].1.iter().all(|&b| b == 0));
        let nan = |target: &mut [u8]| {
            target.copy_from_slice(mlp.1);
            target[4..8].copy_from_slice(&f32::NAN.to_ne_bytes());
            true
        };
        assert_eq!(
            copy.restore_section_with("mlp", len, nan),
            Err(Error::NonFiniteSection {
                name: "mlp",
                index: 1
            })
        );
        assert!(copy.sections()[5].1.iter().all(|&b| b == 0));
    }
}
