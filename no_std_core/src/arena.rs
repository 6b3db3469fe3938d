//! Carving typed slices out of the caller's byte arena.

use crate::Error;
use crate::config::PART_ALIGN;
use bytemuck::Pod;

pub(crate) struct Carver<'a> {
    rest: &'a mut [u8],
    used: usize,
}

impl<'a> Carver<'a> {
    /// Skip to the first `PART_ALIGN` boundary of `arena`.
    pub fn new(arena: &'a mut [u8], needed: usize) -> Result<Self, Error> {
        let skip = arena.as_ptr().align_offset(PART_ALIGN);
        if arena.len() < needed || skip > arena.len() {
            return Err(Error::ArenaTooSmall {
                needed,
                got: arena.len(),
            });
        }
        let (_, rest) = arena.split_at_mut(skip);
        Ok(Carver { rest, used: 0 })
    }

    /// Bytes handed out so far (including padding to `PART_ALIGN`).
    pub fn used(&self) -> usize {
        self.used
    }

    /// `count` zeroed values of `T`, starting on a `PART_ALIGN` boundary.
    pub fn take<T: Pod>(&mut self, count: usize) -> Result<&'a mut [T], Error> {
        let bytes = count * core::mem::size_of::<T>();
        let padded = bytes.div_ceil(PART_ALIGN) * PART_ALIGN;
        if padded > self.rest.len() {
            return Err(Error::ArenaTooSmall {
                needed: self.used + padded,
                got: self.used + self.rest.len(),
            });
        }
        let rest = core::mem::take(&mut self.rest);
        let (part, rest) = rest.split_at_mut(padded);
        self.rest = rest;
        self.used += padded;
        let part = &mut part[..bytes];
        part.fill(0);
        bytemuck::try_cast_slice_mut(part).map_err(|_| Error::Misaligned {
            part_align: PART_ALIGN,
            type_align: core::mem::align_of::<T>(),
        })
    }
}
