//! Seeded randomness. Everything random in training is a pure function of
//! (seed, domain, counter), so results never depend on how work is split across threads.

/// splitmix64's finaliser: a bijective 64-bit mix.
#[inline]
const fn mix(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// Random 64 bits for `(seed, domain, a, b)`.
#[inline]
pub const fn hash(seed: u64, domain: u64, a: u64, b: u64) -> u64 {
    let h = mix(seed ^ domain.wrapping_mul(0x9e37_79b9_7f4a_7c15));
    let h = mix(h ^ a.wrapping_mul(0xd6e8_feb8_6659_fd93));
    mix(h ^ b.wrapping_mul(0xa076_1d64_78bd_642f))
}

/// Uniform in [0, 1) from the top 24 bits of `bits` (exact in f32).
#[inline]
pub fn unit_f32(bits: u64) -> f32 {
    (bits >> 40) as f32 * (1.0 / (1u64 << 24) as f32)
}

/// Uniform integer in [0, n) (multiply-shift; bias below 2^-32 for n < 2^32).
#[inline]
pub fn below(bits: u64, n: u32) -> u32 {
    (((bits >> 32) * n as u64) >> 32) as u32
}

/// Domains of `hash`, one per use, so that no two uses share draws.
pub mod domain {
    /// Which frame and pixel each training ray comes from.
    pub const RAY_PICK: u64 = 1;
    /// Offset of each ray's first sample along the ray.
    pub const RAY_JITTER: u64 = 2;
    /// Where in each occupancy cell the density is probed at a refresh.
    pub const OCCUPANCY: u64 = 3;
    /// Stochastic rounding of updated texels to f16.
    pub const ROUNDING: u64 = 4;
    /// Initial values of the planes and MLP weights.
    pub const INIT: u64 = 5;
    /// Pixels picked for the rays of an appearance-embedding fit.
    pub const FIT: u64 = 6;
    /// The replacement policy's choices when a frame streams in.
    pub const ADMIT: u64 = 7;
    /// Pixels picked for the rays of a pose refinement.
    pub const REFINE: u64 = 8;
    /// Which pixels a frame offers the ray reservoir and which offers it keeps.
    pub const RESERVOIR: u64 = 9;
}

/// A small sequential generator for initialisation and tests.
#[derive(Clone, Copy, Debug)]
pub struct Rng {
    state: u64,
}

impl Rng {
    /// A generator whose draws are fixed by `seed`.
    pub const fn new(seed: u64) -> Self {
        Rng { state: seed }
    }
    /// The next 64 random bits.
    #[inline]
    pub fn next_u64(&mut self) -> u64 {
        self.state = self.state.wrapping_add(0x9e37_79b9_7f4a_7c15);
        mix(self.state)
    }
    /// The next value, uniform in [0, 1).
    #[inline]
    pub fn uniform(&mut self) -> f32 {
        unit_f32(self.next_u64())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn uniform_is_in_range_and_roughly_flat() {
        let mut rng = Rng::new(7);
        let mut bins = [0u32; 10];
        for _ in 0..100_000 {
            let u = rng.uniform();
            assert!((0.0..1.0).contains(&u));
            bins[(u * 10.0) as usize] += 1;
        }
        assert!(
            bins.iter().all(|&b| (9_000..11_000).contains(&b)),
            "{bins:?}"
        );
        for n in [1, 3, 1000] {
            assert!((0..1000).all(|i| below(hash(1, 2, i, 0), n) < n));
        }
    }

    #[test]
    fn hash_depends_on_every_input() {
        let base = hash(1, 2, 3, 4);
        assert_ne!(base, hash(0, 2, 3, 4));
        assert_ne!(base, hash(1, 0, 3, 4));
        assert_ne!(base, hash(1, 2, 0, 4));
        assert_ne!(base, hash(1, 2, 3, 0));
        assert_eq!(base, hash(1, 2, 3, 4));
    }
}
