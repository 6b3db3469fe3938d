//! Fused multiply-add, `a * b + c` rounded once, with the same bits on every target.
//!
//! x86-64 with FMA (the host build's `x86-64-v3`) runs the MLP kernels' lane loops as AVX
//! `vfmadd` eight lanes at a time, hard-float 32-bit ARM (Cortex-M4F) as `vfma.f32` four
//! lanes at a time, and every other target calls `libm::fmaf`, which is correctly rounded (a
//! hardware `fmadd` on aarch64, exact software elsewhere). A fused operation is correctly
//! rounded by definition, so all give the same bits, whatever the vector width.
//! One fused operation instead of a multiply and an add halves the MLPs' arithmetic, which
//! on CPUs without separate add pipes (Intel's) is what bounds them.

#[cfg(all(target_arch = "x86_64", target_feature = "fma", target_feature = "avx"))]
use core::arch::x86_64::{__m256, _mm256_fmadd_ps, _mm256_set1_ps, _mm256_setzero_ps};

/// `acc[i] = s * x[i] + acc[i]` (rounded once) for `i < min(acc.len(), x.len())`.
#[inline(always)]
pub fn axpy(acc: &mut [f32], s: f32, x: &[f32]) {
    #[cfg(all(target_arch = "x86_64", target_feature = "fma", target_feature = "avx"))]
    {
        let (acc8, acc) = acc.as_chunks_mut::<8>();
        let (x8, x) = x.as_chunks::<8>();
        #[allow(unsafe_code)] // The intrinsics are `unsafe` only for the CPU features they need.
        // SAFETY: this block is compiled only when AVX and FMA are enabled for the whole
        // build; the values move in and out by `bytemuck::cast`, no pointers.
        unsafe {
            let sv = _mm256_set1_ps(s);
            for (a, xv) in acc8.iter_mut().zip(x8) {
                let fused: __m256 = _mm256_fmadd_ps(sv, bytemuck::cast(*xv), bytemuck::cast(*a));
                *a = bytemuck::cast(fused);
            }
        }
        portable_axpy(acc, s, x);
    }
    #[cfg(all(target_arch = "arm", target_abi = "eabihf"))]
    {
        let (acc4, acc) = acc.as_chunks_mut::<4>();
        let (x4, x) = x.as_chunks::<4>();
        for (a, xv) in acc4.iter_mut().zip(x4) {
            #[allow(unsafe_code)] // FPU loads, four `vfma.f32` and a store.
            // SAFETY: both pointers come from references to four f32 each, the only memory
            // the block reads (`x`) and writes (`a`); s0-s8 are declared clobbered. The
            // operands travel as addresses and bits because rustc's asm check does not see
            // the target's single-precision FPU (`sreg` wants `vfp2`). Four lanes per block
            // keep the moves between core and FPU registers to one per four operations.
            unsafe {
                core::arch::asm!(
                    "vmov s8, {s}",
                    "vldmia {x}, {{s0-s3}}",
                    "vldmia {a}, {{s4-s7}}",
                    "vfma.f32 s4, s8, s0",
                    "vfma.f32 s5, s8, s1",
                    "vfma.f32 s6, s8, s2",
                    "vfma.f32 s7, s8, s3",
                    "vstmia {a}, {{s4-s7}}",
                    s = in(reg) s.to_bits(),
                    x = in(reg) xv.as_ptr(),
                    a = in(reg) a.as_mut_ptr(),
                    out("s0") _,
                    out("s1") _,
                    out("s2") _,
                    out("s3") _,
                    out("s4") _,
                    out("s5") _,
                    out("s6") _,
                    out("s7") _,
                    out("s8") _,
                    options(nostack, preserves_flags),
                );
            }
        }
        portable_axpy(acc, s, x);
    }
    #[cfg(not(any(
        all(target_arch = "x86_64", target_feature = "fma", target_feature = "avx"),
        all(target_arch = "arm", target_abi = "eabihf")
    )))]
    portable_axpy(acc, s, x);
}

/// [`axpy`] one element at a time through `libm::fmaf`: the twin every target can run (on
/// ARM only for lengths that are not a multiple of four, which the MLPs never have).
#[inline(always)]
fn portable_axpy(acc: &mut [f32], s: f32, x: &[f32]) {
    for (a, xv) in acc.iter_mut().zip(x) {
        *a = libm::fmaf(s, *xv, *a);
    }
}

/// `sum_i a[i] * b[i]` over `i < min(a.len(), b.len())`, in one fixed order on every target:
/// eight running sums (term `i` fused into sum `i % 8`), then added pairwise,
/// `((s0 + s1) + (s2 + s3)) + ((s4 + s5) + (s6 + s7))`.
#[inline(always)]
pub fn dot(a: &[f32], b: &[f32]) -> f32 {
    let len = a.len().min(b.len());
    let (a8, a_tail) = a[..len].as_chunks::<8>();
    let (b8, b_tail) = b[..len].as_chunks::<8>();
    #[cfg(all(target_arch = "x86_64", target_feature = "fma", target_feature = "avx"))]
    #[allow(unsafe_code)] // The intrinsics are `unsafe` only for the CPU features they need.
    // SAFETY: compiled only when AVX and FMA are enabled for the whole build; the values move
    // in and out by `bytemuck::cast`, no pointers.
    let mut sums: [f32; 8] = unsafe {
        let mut acc = _mm256_setzero_ps();
        for (av, bv) in a8.iter().zip(b8) {
            acc = _mm256_fmadd_ps(bytemuck::cast(*av), bytemuck::cast(*bv), acc);
        }
        bytemuck::cast(acc)
    };
    #[cfg(not(all(target_arch = "x86_64", target_feature = "fma", target_feature = "avx")))]
    let mut sums = {
        let mut sums = [0.0f32; 8];
        for (av, bv) in a8.iter().zip(b8) {
            for i in 0..8 {
                sums[i] = libm::fmaf(av[i], bv[i], sums[i]);
            }
        }
        sums
    };
    for (i, (x, y)) in a_tail.iter().zip(b_tail).enumerate() {
        sums[i] = libm::fmaf(*x, *y, sums[i]);
    }
    ((sums[0] + sums[1]) + (sums[2] + sums[3])) + ((sums[4] + sums[5]) + (sums[6] + sums[7]))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    /// Values that stress the single rounding: products that cancel against the addend,
    /// subnormals, huge and tiny magnitudes, infinities and NaN.
    fn awkward(rng: &mut Rng) -> f32 {
        const SPECIAL: [f32; 10] = [
            0.0,
            -0.0,
            1.0e-40,
            -3.0e-39,
            f32::MAX,
            f32::MIN_POSITIVE,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
            1.0 + f32::EPSILON,
        ];
        let pick = rng.next_u64() as u32;
        if pick.is_multiple_of(8) {
            SPECIAL[(pick / 8) as usize % SPECIAL.len()]
        } else {
            let scale = [1.0e-20, 1.0e-3, 1.0, 1.0e3, 1.0e20][(pick / 8) as usize % 5];
            (rng.uniform() * 2.0 - 1.0) * scale
        }
    }

    #[test]
    fn the_vector_path_gives_the_bits_of_the_correctly_rounded_scalar_one() {
        let mut rng = Rng::new(7);
        for len in [0, 1, 7, 8, 9, 32, 64, 67] {
            for _ in 0..200 {
                let s = awkward(&mut rng);
                let x: [f32; 67] = core::array::from_fn(|_| awkward(&mut rng));
                let start: [f32; 67] = core::array::from_fn(|_| awkward(&mut rng));
                let mut vector = start;
                axpy(&mut vector[..len], s, &x[..len]);
                let mut scalar = start;
                portable_axpy(&mut scalar[..len], s, &x[..len]);
                for i in 0..67 {
                    assert_eq!(vector[i].to_bits(), scalar[i].to_bits(), "{len} {i}");
                }
            }
        }
    }

    #[test]
    fn fused_rounds_once() {
        // (1 + e)(1 - e) - 1 = -e^2: lost entirely by a multiply then an add.
        let e = f32::EPSILON;
        assert_eq!(libm::fmaf(1.0 + e, 1.0 - e, -1.0), -e * e);
        assert_eq!((1.0 + e) * (1.0 - e) - 1.0, 0.0);
        let mut acc = [-1.0f32; 9];
        axpy(&mut acc, 1.0 + e, &[1.0 - e; 9]);
        assert!(acc.iter().all(|&a| a == -e * e));
    }

    #[test]
    fn the_vector_dot_gives_the_bits_of_the_portable_order() {
        let mut rng = Rng::new(11);
        for len in [0, 1, 7, 8, 9, 16, 63, 64, 67] {
            for _ in 0..200 {
                let a: [f32; 67] = core::array::from_fn(|_| awkward(&mut rng));
                let b: [f32; 67] = core::array::from_fn(|_| awkward(&mut rng));
                let mut sums = [0.0f32; 8];
                for i in 0..len {
                    sums[i % 8] = libm::fmaf(a[i], b[i], sums[i % 8]);
                }
                let expected = ((sums[0] + sums[1]) + (sums[2] + sums[3]))
                    + ((sums[4] + sums[5]) + (sums[6] + sums[7]));
                let got = dot(&a[..len], &b[..len]);
                assert!(
                    got.to_bits() == expected.to_bits() || (got.is_nan() && expected.is_nan()),
                    "{len}: {got} != {expected}"
                );
            }
        }
    }
}
