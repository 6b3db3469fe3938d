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

    /// Restore one section written by `sections` for the same config. The size must match.
    pub fn restore_section(&mut self, name: &str, data: &[u8]) -> Result<(), Error> {
        macro_rules! find {
            ($trainer:ident; $($name:literal => $($field:ident).+,)*) => {
                match name {
                    $($name => ($name, $trainer.$($field).+.bytes_mut()),)*
                    _ => {
                        return Err(Error::BadSection {
                            name: "unknown",
                            expected: 0,
                            got: data.len(),
                        });
                    }
                }
            };
        }
        let (name, target): (&'static str, &mut [u8]) = with_section_table!(find, self);
        if target.len() != data.len() {
            return Err(Error::BadSection {
                name,
                expected: target.len(),
                got: data.len(),
            });
        }
        if name == "frame_meta" {
            // Slot sizes index the pixel store: reject any that would not fit.
            let size = core::mem::size_of::<FrameMeta>();
            for raw in data.chunks_exact(size) {
                let meta: FrameMeta = bytemuck::pod_read_unaligned(raw);
                let pixels = meta.width as usize * meta.height as usize;
                if meta.occupied != 0
                    && (!meta.camera().is_valid()
                        || pixels > self.frames.max_pixels
                        || meta.width > u16::MAX as u32
                        || meta.height > u16::MAX as u32)
                {
                    return Err(Error::BadSection {
                        name,
                        expected: 0,
                        got: data.len(),
                    });
                }
            }
        }
        target.copy_from_slice(data);
        if name == "frame_meta" {
            self.frames.rebuild_occupied();
        }
        Ok(())
    }
}
