//! Fused multiply-add, `a * b + c` rounded once, with the same bits on every target.
//!
//! x86-64 with FMA (the host build's `x86-64-v3`) runs the MLP kernels' lane loops as AVX
//! `vfmadd` eight lanes at a time, or sixteen when the CPU has AVX-512 (detected at run
//! time, [`wide_vectors`]); hard-float 32-bit ARM (Cortex-M4F) as `vfma.f32` four lanes at
//! a time, and every other target calls `libm::fmaf`, which is correctly rounded (a hardware
//! `fmadd` on aarch64, exact software elsewhere). A fused operation is correctly rounded by
//! definition and every output sums its terms in the same order on every path, so all give
//! the same bits, whatever the vector width.
//! One fused operation instead of a multiply and an add halves the MLPs' arithmetic, which
//! on CPUs without separate add pipes (Intel's) is what bounds them.

use crate::config::LANES;

/// One lane-row: the `LANES` values of one feature across the samples of a mini-batch.
pub type Row = [f32; LANES];

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

/// `out[n] += sum_j coef(n, j) * inputs[j]` for every row `n` of `out`, one fused operation
/// per term in order of `j`: a layer's forward pass (`coef(n, j)` the weight from input `j`
/// to output `n`, `out` holding the biases) or its input gradient (the weight from `n` to `j`).
#[inline(always)]
pub fn combine_rows(out: &mut [Row], inputs: &[Row], coef: impl Fn(usize, usize) -> f32) {
    #[cfg(all(target_arch = "x86_64", target_feature = "fma", target_feature = "avx"))]
    if wide_vectors() {
        #[allow(unsafe_code)]
        // SAFETY: `wide_vectors` found AVX-512F on this CPU, with its registers enabled by
        // the OS.
        unsafe {
            avx512::combine_rows(out, inputs, coef)
        };
        return;
    }
    combine_rows_narrow(out, inputs, coef);
}

/// [`combine_rows`] a row at a time through [`axpy`].
#[inline(always)]
fn combine_rows_narrow(out: &mut [Row], inputs: &[Row], coef: impl Fn(usize, usize) -> f32) {
    for (n, on) in out.iter_mut().enumerate() {
        let mut acc = *on;
        for (j, xj) in inputs.iter().enumerate() {
            axpy(&mut acc, coef(n, j), xj);
        }
        *on = acc;
    }
}

/// `dst[k * outputs + n] += sum_l coefs[k][l] * dyt[l * stride + n]` for every `k` and
/// `n < outputs`: each sum fused over the lanes `l` in order from zero, then added to `dst`.
/// A layer's weight gradient: `coefs` are its input rows, `dyt` its output gradients
/// lane-major in rows of `stride` floats (`outputs` padded to a multiple of 8).
#[inline(always)]
pub fn outer_products(coefs: &[Row], dyt: &[f32], stride: usize, outputs: usize, dst: &mut [f32]) {
    #[cfg(all(target_arch = "x86_64", target_feature = "fma", target_feature = "avx"))]
    if wide_vectors() {
        #[allow(unsafe_code)]
        // SAFETY: as in `combine_rows`.
        unsafe {
            avx512::outer_products(coefs, dyt, stride, outputs, dst)
        };
        return;
    }
    outer_products_narrow(coefs, dyt, stride, outputs, dst);
}

/// [`outer_products`] through [`axpy`]: 64 columns of one input at a time, then 32 of two,
/// 16 of four and 8 of eight, always eight AVX accumulator registers, enough to keep both FMA
/// pipes busy.
#[inline(always)]
fn outer_products_narrow(
    coefs: &[Row],
    dyt: &[f32],
    stride: usize,
    outputs: usize,
    dst: &mut [f32],
) {
    let mut col = 0;
    while col + 64 <= stride {
        narrow_tiles::<1, 64>(coefs, dyt, stride, outputs, col, dst);
        col += 64;
    }
    while col + 32 <= stride {
        narrow_tiles::<2, 32>(coefs, dyt, stride, outputs, col, dst);
        col += 32;
    }
    while col + 16 <= stride {
        narrow_tiles::<4, 16>(coefs, dyt, stride, outputs, col, dst);
        col += 16;
    }
    while col < stride {
        narrow_tiles::<8, 8>(coefs, dyt, stride, outputs, col, dst);
        col += 8;
    }
}

/// The `W` columns from `col` for every input, `K` inputs at a time (the rest one by one):
/// `K * W / 8` independent accumulators, so that narrow layers (a few outputs) are not bound
/// by the latency of one chain of fused operations.
#[inline(always)]
fn narrow_tiles<const K: usize, const W: usize>(
    coefs: &[Row],
    dyt: &[f32],
    stride: usize,
    outputs: usize,
    col: usize,
    dst: &mut [f32],
) {
    let mut k = 0;
    while k + K <= coefs.len() {
        narrow_tile::<K, W>(&coefs[k..k + K], k, dyt, stride, outputs, col, dst);
        k += K;
    }
    while k < coefs.len() {
        narrow_tile::<1, W>(&coefs[k..k + 1], k, dyt, stride, outputs, col, dst);
        k += 1;
    }
}

/// Inputs `k0 .. k0 + K` (`coefs`), the `W` columns from `col`.
#[inline(always)]
fn narrow_tile<const K: usize, const W: usize>(
    coefs: &[Row],
    k0: usize,
    dyt: &[f32],
    stride: usize,
    outputs: usize,
    col: usize,
    dst: &mut [f32],
) {
    let mut acc = [[0.0f32; W]; K];
    for l in 0..LANES {
        let start = l * stride + col;
        let row = &dyt[start..start + W];
        for (a, coef) in acc.iter_mut().zip(coefs) {
            axpy(a, coef[l], row);
        }
    }
    for (t, a) in acc.iter().enumerate() {
        add_columns(a, k0 + t, outputs, col, dst);
    }
}

/// Adds a tile's column sums to input `k`'s row of `dst`, dropping the padding columns.
#[inline(always)]
fn add_columns(sums: &[f32], k: usize, outputs: usize, col: usize, dst: &mut [f32]) {
    let row = &mut dst[k * outputs..(k + 1) * outputs];
    for (o, s) in row.iter_mut().skip(col).zip(sums) {
        *o += s;
    }
}

/// Layers with up to this many outputs (a colour MLP's RGB) take their weight gradient from
/// [`few_outputs_products`] where the CPU has AVX-512.
pub const FEW_OUTPUTS: usize = 4;

/// [`outer_products`] of `coefs` with a layer's output gradients `dy` (rows, not lane-major)
/// for a layer of at most [`FEW_OUTPUTS`] outputs, with AVX-512. A lane-row of so few outputs
/// fills a fraction of a register, so the inputs go lane-major instead (into `scratch`,
/// `LANES` rows of `coefs.len()` rounded up to 16) and the registers run along the inputs.
/// Every sum still fuses its lanes in order from zero before it is added to `dst`: the bits
/// of [`outer_products`]. Returns `false`, having done nothing, where it does not apply (no
/// AVX-512, more outputs, a smaller `scratch` or `dst`).
pub fn few_outputs_products(
    coefs: &[Row],
    dy: &[Row],
    scratch: &mut [f32],
    dst: &mut [f32],
) -> bool {
    #[cfg(all(target_arch = "x86_64", target_feature = "fma", target_feature = "avx"))]
    if wide_vectors() {
        #[allow(unsafe_code)]
        // SAFETY: as in `combine_rows`.
        return unsafe { avx512::few_outputs_products(coefs, dy, scratch, dst) };
    }
    let _ = (coefs, dy, scratch, dst);
    false
}

/// `dst[l * stride + n] = rows[n][l]` for every lane `l` and `n < stride` (zero for
/// `n >= rows.len()`): rows of `LANES` values into lane-major rows of `stride` values. Moves
/// only, the same bits on every path.
#[inline]
pub fn to_lane_major(rows: &[Row], stride: usize, dst: &mut [f32]) {
    let dst = &mut dst[..LANES * stride];
    #[cfg(all(target_arch = "x86_64", target_feature = "fma", target_feature = "avx"))]
    if wide_vectors() && rows.len() <= stride {
        #[allow(unsafe_code)]
        // SAFETY: as in `combine_rows`.
        unsafe {
            avx512::to_lane_major(rows, stride, dst)
        };
        return;
    }
    to_lane_major_portable(rows, stride, dst);
}

fn to_lane_major_portable(rows: &[Row], stride: usize, dst: &mut [f32]) {
    for (l, row) in dst.chunks_exact_mut(stride.max(1)).enumerate() {
        for (n, v) in row.iter_mut().enumerate() {
            *v = rows.get(n).map_or(0.0, |r| r[l]);
        }
    }
}

/// Moves the kept lanes of `batches` mini-batches to the front, in order: `store` holds
/// mini-batches of `batch_rows` rows each, `kept(b)` marks batch `b`'s kept lanes (bit `l`
/// for lane `l`; called once per batch, in order), and afterwards the `j`-th kept lane
/// (counting batch by batch) sits in batch `j / LANES`, lane `j % LANES`, in each row.
/// Places after the last kept lane keep stale values.
/// Moves only, the same bits on every path. Does nothing if `store` holds fewer batches.
pub fn compact_lanes(
    store: &mut [Row],
    batch_rows: usize,
    batches: usize,
    kept: impl FnMut(usize) -> u64,
) {
    const _: () = assert!(LANES == 64, "one u64 mask per mini-batch");
    if store.len() < batches * batch_rows {
        return;
    }
    #[cfg(all(target_arch = "x86_64", target_feature = "fma", target_feature = "avx"))]
    if wide_vectors() {
        let wide = |store: &mut [Row], batch: usize, mask: u64, first: usize| {
            #[allow(unsafe_code)]
            // SAFETY: as in `combine_rows`.
            unsafe {
                avx512::move_kept(store, batch_rows, batch, mask, first)
            }
        };
        compact_lanes_with(store, batches, kept, wide);
        return;
    }
    let portable = |store: &mut [Row], batch: usize, mask: u64, first: usize| {
        move_kept_portable(store, batch_rows, batch, mask, first)
    };
    compact_lanes_with(store, batches, kept, portable);
}

/// [`compact_lanes`]'s walk over the batches, `move_kept(store, b, mask, first)` moving
/// batch `b`'s kept lanes to places `first ..` of the compacted order. In each row, kept lane
/// `j` comes from a place at or after its own in the sequence of that row's lanes over the
/// batches, so moving the batches in order never reads a value already overwritten.
fn compact_lanes_with(
    store: &mut [Row],
    batches: usize,
    mut kept: impl FnMut(usize) -> u64,
    mut move_kept: impl FnMut(&mut [Row], usize, u64, usize),
) {
    let mut first = 0usize;
    for b in 0..batches {
        let mask = kept(b);
        // A batch with no lane cut before it that keeps a prefix of its own lanes is in
        // place already: the common case of a pass in which no ray is cut, or none yet.
        let in_place = first == b * LANES && mask & mask.wrapping_add(1) == 0;
        if !in_place {
            move_kept(store, b, mask, first);
        }
        first += mask.count_ones() as usize;
    }
}

/// Batch `b`'s kept lanes (`mask`) to places `first ..` of the compacted order, one value at
/// a time.
fn move_kept_portable(store: &mut [Row], batch_rows: usize, b: usize, mask: u64, first: usize) {
    for r in 0..batch_rows {
        let (mut m, mut j) = (mask, first);
        while m != 0 {
            let l = m.trailing_zeros() as usize;
            m &= m - 1;
            let v = store[b * batch_rows + r][l];
            store[j / LANES * batch_rows + r][j % LANES] = v;
            j += 1;
        }
    }
}

#[cfg(all(target_arch = "x86_64", target_feature = "fma", target_feature = "avx"))]
mod detect {
    use core::sync::atomic::{AtomicBool, AtomicU8, Ordering::Relaxed};

    static ALLOWED: AtomicBool = AtomicBool::new(true);
    /// 0: not looked yet, 1: no AVX-512F, 2: AVX-512F.
    static FOUND: AtomicU8 = AtomicU8::new(0);

    pub fn wide_vectors() -> bool {
        if !ALLOWED.load(Relaxed) {
            return false;
        }
        match FOUND.load(Relaxed) {
            0 => {
                let found = avx512f();
                FOUND.store(if found { 2 } else { 1 }, Relaxed);
                found
            }
            state => state == 2,
        }
    }

    pub fn allow_wide_vectors(allow: bool) {
        ALLOWED.store(allow, Relaxed);
    }

    /// AVX-512F in the CPU (CPUID leaf 7) and its state saved by the OS (XCR0: SSE, AVX,
    /// opmask, upper halves of ZMM0-15, ZMM16-31), as the Intel SDM asks software to check.
    fn avx512f() -> bool {
        use core::arch::x86_64::{__cpuid, __cpuid_count, _xgetbv};
        #[allow(unsafe_code)]
        // SAFETY: CPUID exists on every x86-64 CPU; XGETBV runs only once CPUID has said the
        // OS enabled it (OSXSAVE).
        unsafe {
            if __cpuid(0).eax < 7 || __cpuid(1).ecx & (1 << 27) == 0 {
                return false;
            }
            _xgetbv(0) & 0xE6 == 0xE6 && __cpuid_count(7, 0).ebx & (1 << 16) != 0
        }
    }
}

/// Whether the MLP kernels run sixteen lanes per instruction: an x86-64 CPU with AVX-512F
/// (detected once, at the first call) unless [`allow_wide_vectors`] turned it off. The results
/// are the same bits either way; only the speed differs.
pub fn wide_vectors() -> bool {
    #[cfg(all(target_arch = "x86_64", target_feature = "fma", target_feature = "avx"))]
    return detect::wide_vectors();
    #[cfg(not(all(target_arch = "x86_64", target_feature = "fma", target_feature = "avx")))]
    false
}

/// Lets the MLP kernels use AVX-512 where the CPU has it (the default), or keeps them to
/// eight lanes: for benchmarks that compare the two and tests that prove them equal. Takes
/// effect for every thread from their next kernel call.
pub fn allow_wide_vectors(allow: bool) {
    #[cfg(all(target_arch = "x86_64", target_feature = "fma", target_feature = "avx"))]
    detect::allow_wide_vectors(allow);
    #[cfg(not(all(target_arch = "x86_64", target_feature = "fma", target_feature = "avx")))]
    let _ = allow;
}

/// The kernels with AVX-512F, sixteen lanes per instruction. A 64-lane row is only four
/// registers, so each tile computes several outputs (or inputs) at once: at least eight
/// independent accumulators keep both FMA pipes busy (four cycles of latency, two per cycle;
/// sixteen measured 2 to 4 % faster), and each loaded row is shared among them. Every output
/// still sums its terms in the order of the narrow kernels, so the bits are theirs.
#[cfg(all(target_arch = "x86_64", target_feature = "fma", target_feature = "avx"))]
#[allow(unsafe_code)] // Pointer loads and stores of the rows, within their slices.
mod avx512 {
    use super::{LANES, Row, add_columns};
    use core::arch::x86_64::{
        __m256, __m512, __mmask16, _mm256_fmadd_ps, _mm256_loadu_ps, _mm256_set1_ps,
        _mm256_setzero_ps, _mm256_storeu_ps, _mm512_castpd_ps, _mm512_castps_pd, _mm512_fmadd_ps,
        _mm512_loadu_ps, _mm512_mask_storeu_ps, _mm512_maskz_compress_ps, _mm512_set1_ps,
        _mm512_setzero_ps, _mm512_shuffle_f32x4, _mm512_storeu_ps, _mm512_unpackhi_pd,
        _mm512_unpackhi_ps, _mm512_unpacklo_pd, _mm512_unpacklo_ps,
    };

    /// Registers per lane-row.
    const Z: usize = LANES / 16;
    const _: () = assert!(LANES.is_multiple_of(16));

    #[target_feature(enable = "avx512f")]
    #[inline]
    fn load_row(row: &Row) -> [__m512; Z] {
        // SAFETY: register `i` reads floats 16 i .. 16 i + 16 of the row's LANES.
        core::array::from_fn(|i| unsafe { _mm512_loadu_ps(row.as_ptr().add(16 * i)) })
    }

    #[target_feature(enable = "avx512f")]
    #[inline]
    fn store_row(row: &mut Row, v: [__m512; Z]) {
        for (i, vi) in v.into_iter().enumerate() {
            // SAFETY: register `i` writes floats 16 i .. 16 i + 16 of the row's LANES.
            unsafe { _mm512_storeu_ps(row.as_mut_ptr().add(16 * i), vi) };
        }
    }

    /// The 16 x 16 transpose of `r` (sixteen rows of sixteen floats).
    #[target_feature(enable = "avx512f")]
    #[inline]
    fn transpose16(r: [__m512; 16]) -> [__m512; 16] {
        // Pairs of floats, then pairs of pairs, then 128-bit quarters twice.
        let t: [__m512; 16] = core::array::from_fn(|i| {
            let (a, b) = (r[i / 2 * 2], r[i / 2 * 2 + 1]);
            if i % 2 == 0 {
                _mm512_unpacklo_ps(a, b)
            } else {
                _mm512_unpackhi_ps(a, b)
            }
        });
        let u: [__m512; 16] = core::array::from_fn(|i| {
            let g = i / 4 * 4;
            let (a, b) = (
                _mm512_castps_pd(t[g + (i % 4) / 2]),
                _mm512_castps_pd(t[g + 2 + (i % 4) / 2]),
            );
            _mm512_castpd_ps(if i % 2 == 0 {
                _mm512_unpacklo_pd(a, b)
            } else {
                _mm512_unpackhi_pd(a, b)
            })
        });
        let v: [__m512; 16] = core::array::from_fn(|i| {
            let g = i / 8 * 8;
            let (a, b) = (u[g + i % 4], u[g + 4 + i % 4]);
            if i % 8 < 4 {
                _mm512_shuffle_f32x4::<0x88>(a, b)
            } else {
                _mm512_shuffle_f32x4::<0xdd>(a, b)
            }
        });
        core::array::from_fn(|i| {
            let (a, b) = (v[i % 8], v[8 + i % 8]);
            if i < 8 {
                _mm512_shuffle_f32x4::<0x88>(a, b)
            } else {
                _mm512_shuffle_f32x4::<0xdd>(a, b)
            }
        })
    }

    /// [`super::to_lane_major`] in blocks of 16 rows by 16 lanes.
    #[target_feature(enable = "avx512f")]
    pub(super) fn to_lane_major(rows: &[Row], stride: usize, dst: &mut [f32]) {
        for n0 in (0..stride).step_by(16) {
            let width = (stride - n0).min(16);
            let mask: __mmask16 = ((1u32 << width) - 1) as __mmask16;
            for l0 in (0..LANES).step_by(16) {
                let block = core::array::from_fn(|i| match rows.get(n0 + i) {
                    // SAFETY: lanes l0 .. l0 + 16 <= LANES of the row.
                    Some(row) => unsafe { _mm512_loadu_ps(row.as_ptr().add(l0)) },
                    None => _mm512_setzero_ps(),
                });
                for (i, v) in transpose16(block).into_iter().enumerate() {
                    let at = (l0 + i) * stride + n0;
                    let out = &mut dst[at..at + width];
                    // SAFETY: the mask writes the `width` floats of `out`.
                    unsafe { _mm512_mask_storeu_ps(out.as_mut_ptr(), mask, v) };
                }
            }
        }
    }

    /// [`super::combine_rows`], `T` outputs at a time (the last one to three together).
    #[target_feature(enable = "avx512f")]
    pub(super) fn combine_rows(
        out: &mut [Row],
        inputs: &[Row],
        coef: impl Fn(usize, usize) -> f32,
    ) {
        const T: usize = 4;
        let (tiles, rest) = out.as_chunks_mut::<T>();
        for (t, tile) in tiles.iter_mut().enumerate() {
            combine_tile(tile, T * t, inputs, &coef);
        }
        let n0 = T * tiles.len();
        match rest {
            [a, b, c] => {
                let mut tile = [*a, *b, *c];
                combine_tile(&mut tile, n0, inputs, &coef);
                [*a, *b, *c] = tile;
            }
            [a, b] => {
                let mut tile = [*a, *b];
                combine_tile(&mut tile, n0, inputs, &coef);
                [*a, *b] = tile;
            }
            [a] => combine_tile(core::array::from_mut(a), n0, inputs, &coef),
            _ => {}
        }
    }

    /// Outputs `n0 .. n0 + K` (`out`): `K` times [`Z`] accumulators, each input row loaded
    /// once for all of them.
    #[target_feature(enable = "avx512f")]
    #[inline]
    fn combine_tile<const K: usize>(
        out: &mut [Row; K],
        n0: usize,
        inputs: &[Row],
        coef: &impl Fn(usize, usize) -> f32,
    ) {
        let mut acc: [[__m512; Z]; K] = core::array::from_fn(|t| load_row(&out[t]));
        for (j, xj) in inputs.iter().enumerate() {
            let x = load_row(xj);
            for (t, a) in acc.iter_mut().enumerate() {
                let c = _mm512_set1_ps(coef(n0 + t, j));
                for i in 0..Z {
                    a[i] = _mm512_fmadd_ps(c, x[i], a[i]);
                }
            }
        }
        for (o, a) in out.iter_mut().zip(acc) {
            store_row(o, a);
        }
    }

    /// [`super::move_kept_portable`] sixteen lanes per compress: each row of the batch is
    /// loaded whole before its kept lanes are written to the same or earlier places of that
    /// row's sequence (the end of one batch's row continues at the start of the next batch's).
    #[target_feature(enable = "avx512f")]
    pub(super) fn move_kept(
        store: &mut [Row],
        batch_rows: usize,
        b: usize,
        mask: u64,
        first: usize,
    ) {
        for r in 0..batch_rows {
            let v = load_row(&store[b * batch_rows + r]);
            let mut j = first;
            for (i, vi) in v.into_iter().enumerate() {
                let m = (mask >> (16 * i)) as __mmask16;
                let count = m.count_ones() as usize;
                let packed = _mm512_maskz_compress_ps(m, vi);
                let (batch, lane) = (j / LANES, j % LANES);
                let here = count.min(LANES - lane);
                let row = &mut store[batch * batch_rows + r];
                // SAFETY: the mask writes lanes `lane .. lane + here <= LANES` of the row.
                unsafe {
                    _mm512_mask_storeu_ps(row.as_mut_ptr().add(lane), low_lanes(here), packed)
                };
                if count > here {
                    // The rest starts the next batch's row (it exists: j + count lanes never
                    // pass the end of batch b).
                    let rest = _mm512_maskz_compress_ps(!low_lanes(here), packed);
                    let row = &mut store[(batch + 1) * batch_rows + r];
                    // SAFETY: the mask writes lanes `0 .. count - here < 16` of the row.
                    unsafe {
                        _mm512_mask_storeu_ps(row.as_mut_ptr(), low_lanes(count - here), rest)
                    };
                }
                j += count;
            }
        }
    }

    /// The mask of the lowest `n <= 16` lanes.
    #[inline]
    fn low_lanes(n: usize) -> __mmask16 {
        ((1u32 << n) - 1) as __mmask16
    }

    /// [`super::few_outputs_products`].
    #[target_feature(enable = "avx512f")]
    pub(super) fn few_outputs_products(
        coefs: &[Row],
        dy: &[Row],
        scratch: &mut [f32],
        dst: &mut [f32],
    ) -> bool {
        let (inputs, outputs) = (coefs.len(), dy.len());
        let stride = inputs.next_multiple_of(16);
        let Some(xt) = scratch.get_mut(..LANES * stride) else {
            return false;
        };
        let Some(dst) = dst.get_mut(..inputs * outputs) else {
            return false;
        };
        match dy {
            [a] => few_outputs::<1>(inputs, xt, coefs, &[a], dst),
            [a, b] => few_outputs::<2>(inputs, xt, coefs, &[a, b], dst),
            [a, b, c] => few_outputs::<3>(inputs, xt, coefs, &[a, b, c], dst),
            [a, b, c, d] => few_outputs::<4>(inputs, xt, coefs, &[a, b, c, d], dst),
            _ => return false,
        }
        true
    }

    /// The inputs lane-major into `xt`, then 64 inputs at a time (16 at a time for the rest).
    #[target_feature(enable = "avx512f")]
    #[inline]
    fn few_outputs<const N: usize>(
        inputs: usize,
        xt: &mut [f32],
        coefs: &[Row],
        dy: &[&Row; N],
        dst: &mut [f32],
    ) {
        let stride = xt.len() / LANES;
        to_lane_major(coefs, stride, xt);
        let mut k = 0;
        while k + 64 <= stride {
            few_outputs_tile::<N, 4>(inputs, xt, stride, k, dy, dst);
            k += 64;
        }
        while k < stride {
            few_outputs_tile::<N, 1>(inputs, xt, stride, k, dy, dst);
            k += 16;
        }
    }

    /// Inputs `k0 .. k0 + 16 V` for all `N` outputs: `N V` accumulators.
    #[target_feature(enable = "avx512f")]
    #[inline]
    fn few_outputs_tile<const N: usize, const V: usize>(
        inputs: usize,
        xt: &[f32],
        stride: usize,
        k0: usize,
        dy: &[&Row; N],
        dst: &mut [f32],
    ) {
        let mut acc = [[_mm512_setzero_ps(); V]; N];
        for l in 0..LANES {
            let row = &xt[l * stride + k0..l * stride + k0 + 16 * V];
            // SAFETY: register `i` reads floats 16 i .. 16 i + 16 of `row`.
            let x: [__m512; V] =
                core::array::from_fn(|i| unsafe { _mm512_loadu_ps(row.as_ptr().add(16 * i)) });
            for (a, dy) in acc.iter_mut().zip(dy) {
                let d = _mm512_set1_ps(dy[l]);
                for i in 0..V {
                    a[i] = _mm512_fmadd_ps(x[i], d, a[i]);
                }
            }
        }
        for (n, a) in acc.into_iter().enumerate() {
            for (i, ai) in a.into_iter().enumerate() {
                let mut sums = [0.0f32; 16];
                // SAFETY: writes the 16 floats of `sums`.
                unsafe { _mm512_storeu_ps(sums.as_mut_ptr(), ai) };
                let first = k0 + 16 * i;
                for (k, s) in (first..inputs).zip(sums) {
                    dst[k * N + n] += s;
                }
            }
        }
    }

    /// [`super::outer_products`]: 64 columns for four inputs at a time, then 32 for eight, 16
    /// for sixteen, and the last 8 columns (AVX registers) for sixteen: 16 accumulators each.
    /// The twin of `outer_products_narrow`'s loop, with tiles twice as deep.
    #[target_feature(enable = "avx512f")]
    pub(super) fn outer_products(
        coefs: &[Row],
        dyt: &[f32],
        stride: usize,
        outputs: usize,
        dst: &mut [f32],
    ) {
        let mut col = 0;
        while col + 64 <= stride {
            wide_tiles::<4, 4>(coefs, dyt, stride, outputs, col, dst);
            col += 64;
        }
        while col + 32 <= stride {
            wide_tiles::<8, 2>(coefs, dyt, stride, outputs, col, dst);
            col += 32;
        }
        while col + 16 <= stride {
            wide_tiles::<16, 1>(coefs, dyt, stride, outputs, col, dst);
            col += 16;
        }
        while col < stride {
            let mut k = 0;
            while k + 16 <= coefs.len() {
                eight_column_tile::<16>(coefs, k, dyt, stride, outputs, col, dst);
                k += 16;
            }
            while k < coefs.len() {
                eight_column_tile::<1>(coefs, k, dyt, stride, outputs, col, dst);
                k += 1;
            }
            col += 8;
        }
    }

    /// The `16 V` columns from `col` for every input, `K` inputs at a time (the rest one by
    /// one).
    #[target_feature(enable = "avx512f")]
    #[inline]
    fn wide_tiles<const K: usize, const V: usize>(
        coefs: &[Row],
        dyt: &[f32],
        stride: usize,
        outputs: usize,
        col: usize,
        dst: &mut [f32],
    ) {
        let mut k = 0;
        while k + K <= coefs.len() {
            wide_tile::<K, V>(coefs, k, dyt, stride, outputs, col, dst);
            k += K;
        }
        while k < coefs.len() {
            wide_tile::<1, V>(coefs, k, dyt, stride, outputs, col, dst);
            k += 1;
        }
    }

    /// Inputs `k0 .. k0 + K`, the `16 V` columns from `col`.
    #[target_feature(enable = "avx512f")]
    #[inline]
    fn wide_tile<const K: usize, const V: usize>(
        coefs: &[Row],
        k0: usize,
        dyt: &[f32],
        stride: usize,
        outputs: usize,
        col: usize,
        dst: &mut [f32],
    ) {
        let coefs = &coefs[k0..k0 + K];
        let mut acc = [[_mm512_setzero_ps(); V]; K];
        for l in 0..LANES {
            let start = l * stride + col;
            let row = &dyt[start..start + 16 * V];
            // SAFETY: register `i` reads floats 16 i .. 16 i + 16 of `row`.
            let y: [__m512; V] =
                core::array::from_fn(|i| unsafe { _mm512_loadu_ps(row.as_ptr().add(16 * i)) });
            for (a, coef) in acc.iter_mut().zip(coefs) {
                let c = _mm512_set1_ps(coef[l]);
                for i in 0..V {
                    a[i] = _mm512_fmadd_ps(c, y[i], a[i]);
                }
            }
        }
        for (t, a) in acc.into_iter().enumerate() {
            let mut sums = [0.0f32; 64];
            for (i, ai) in a.into_iter().enumerate() {
                // SAFETY: register `i` writes floats 16 i .. 16 i + 16 < 64 of `sums`.
                unsafe { _mm512_storeu_ps(sums.as_mut_ptr().add(16 * i), ai) };
            }
            add_columns(&sums[..16 * V], k0 + t, outputs, col, dst);
        }
    }

    /// Inputs `k0 .. k0 + K`, the 8 columns from `col`, in AVX registers.
    #[target_feature(enable = "avx512f")]
    #[inline]
    fn eight_column_tile<const K: usize>(
        coefs: &[Row],
        k0: usize,
        dyt: &[f32],
        stride: usize,
        outputs: usize,
        col: usize,
        dst: &mut [f32],
    ) {
        let coefs = &coefs[k0..k0 + K];
        let mut acc = [_mm256_setzero_ps(); K];
        for l in 0..LANES {
            let start = l * stride + col;
            let row = &dyt[start..start + 8];
            // SAFETY: reads the 8 floats of `row`.
            let y: __m256 = unsafe { _mm256_loadu_ps(row.as_ptr()) };
            for (a, coef) in acc.iter_mut().zip(coefs) {
                *a = _mm256_fmadd_ps(_mm256_set1_ps(coef[l]), y, *a);
            }
        }
        for (t, a) in acc.into_iter().enumerate() {
            let mut sums = [0.0f32; 8];
            // SAFETY: writes the 8 floats of `sums`.
            unsafe { _mm256_storeu_ps(sums.as_mut_ptr(), a) };
            add_columns(&sums, k0 + t, outputs, col, dst);
        }
    }
}

#[cfg(test)]
pub(crate) mod tests {
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

    /// Random rows of awkward values, for the kernels' wide-against-narrow tests.
    fn awkward_rows<const N: usize>(rng: &mut Rng) -> [Row; N] {
        core::array::from_fn(|_| core::array::from_fn(|_| awkward(rng)))
    }

    /// Equal bits, any NaN equal to any NaN (the kernels' twins may carry different payloads).
    pub(crate) fn same_bits(a: &[f32], b: &[f32]) -> bool {
        a.iter()
            .zip(b)
            .all(|(x, y)| x.to_bits() == y.to_bits() || (x.is_nan() && y.is_nan()))
    }

    #[test]
    fn the_lane_major_transpose_moves_every_value_to_its_place() {
        let mut rng = Rng::new(17);
        let rows: [Row; 40] = awkward_rows(&mut rng);
        for (used, stride) in [
            (0, 8),
            (3, 8),
            (15, 16),
            (16, 16),
            (17, 24),
            (40, 40),
            (33, 64),
        ] {
            for wide in [false, true] {
                let mut lane_major = [f32::NAN; LANES * 64];
                let dst = &mut lane_major[..LANES * stride];
                match wide {
                    false => to_lane_major_portable(&rows[..used], stride, dst),
                    #[cfg(all(
                        target_arch = "x86_64",
                        target_feature = "fma",
                        target_feature = "avx"
                    ))]
                    #[allow(unsafe_code)]
                    // SAFETY: `wide_vectors` said the CPU runs AVX-512F.
                    true if wide_vectors() => unsafe {
                        avx512::to_lane_major(&rows[..used], stride, dst)
                    },
                    true => continue,
                }
                for l in 0..LANES {
                    for n in 0..stride {
                        let expected = if n < used { rows[n][l] } else { 0.0 };
                        let got = lane_major[l * stride + n];
                        assert!(same_bits(&[got], &[expected]), "{used} {stride} {l} {n}");
                    }
                }
                assert!(lane_major[LANES * stride..].iter().all(|v| v.is_nan()));
            }
        }
    }

    #[test]
    fn the_wide_kernels_give_the_bits_of_the_narrow_ones() {
        if !wide_vectors() {
            return; // Nothing to compare on a CPU without AVX-512.
        }
        let mut rng = Rng::new(13);
        let inputs: [Row; 19] = awkward_rows(&mut rng);
        let weights: [f32; 19 * 19] = core::array::from_fn(|_| awkward(&mut rng));
        for (outputs, used) in [(1, 19), (2, 3), (3, 19), (16, 19), (19, 1), (19, 19)] {
            let coef = |n: usize, j: usize| weights[j * outputs + n];
            let start: [Row; 19] = awkward_rows(&mut rng);
            let mut wide = start;
            #[allow(unsafe_code)]
            // SAFETY: `wide_vectors` said the CPU runs AVX-512F.
            unsafe {
                avx512::combine_rows(&mut wide[..outputs], &inputs[..used], coef)
            };
            let mut narrow = start;
            combine_rows_narrow(&mut narrow[..outputs], &inputs[..used], coef);
            assert!(
                same_bits(wide.as_flattened(), narrow.as_flattened()),
                "{outputs} {used}"
            );
        }
        // Strides that reach every tile: 64, 32, 16 and 8 columns, and 8 inputs at a time.
        for (outputs, used) in [
            (3, 19),
            (8, 9),
            (16, 17),
            (24, 2),
            (40, 19),
            (64, 1),
            (120, 3),
            (128, 19),
        ] {
            let stride = usize::div_ceil(outputs, 8) * 8;
            let mut dyt = [0.0f32; LANES * 128];
            for v in dyt[..LANES * stride].iter_mut() {
                *v = awkward(&mut rng);
            }
            let start: [f32; 19 * 128] = core::array::from_fn(|_| awkward(&mut rng));
            let mut wide = start;
            #[allow(unsafe_code)]
            // SAFETY: as above.
            unsafe {
                avx512::outer_products(&inputs[..used], &dyt, stride, outputs, &mut wide)
            };
            let mut narrow = start;
            outer_products_narrow(&inputs[..used], &dyt, stride, outputs, &mut narrow);
            assert!(same_bits(&wide, &narrow), "{outputs} {used}");
        }
    }

    #[test]
    fn compacting_lanes_moves_the_kept_ones_to_the_front_in_order() {
        const BATCH_ROWS: usize = 3;
        let mut rng = Rng::new(23);
        for batches in [1usize, 2, 3, 5] {
            for _ in 0..40 {
                let kept: [u64; 5] = core::array::from_fn(|_| match rng.next_u64() % 5 {
                    0 => 0,
                    1 => u64::MAX,
                    // A prefix, as a ray's kept samples are; a suffix.
                    2 => (1u64 << (rng.next_u64() % 64)) - 1,
                    3 => !((1u64 << (rng.next_u64() % 64)) - 1),
                    _ => rng.next_u64(),
                });
                let kept = &kept[..batches];
                let original: [Row; 5 * BATCH_ROWS] = awkward_rows(&mut rng);
                let mut expected = original;
                for r in 0..BATCH_ROWS {
                    let mut j = 0;
                    for (b, mask) in kept.iter().enumerate() {
                        for l in (0..LANES).filter(|l| mask >> l & 1 == 1) {
                            expected[j / LANES * BATCH_ROWS + r][j % LANES] =
                                original[b * BATCH_ROWS + r][l];
                            j += 1;
                        }
                    }
                }
                for wide in [false, true] {
                    let mut store = original;
                    match wide {
                        false => compact_lanes_with(
                            &mut store,
                            batches,
                            |b| kept[b],
                            |s, b, mask, first| move_kept_portable(s, BATCH_ROWS, b, mask, first),
                        ),
                        #[cfg(all(
                            target_arch = "x86_64",
                            target_feature = "fma",
                            target_feature = "avx"
                        ))]
                        true if wide_vectors() => compact_lanes_with(
                            &mut store,
                            batches,
                            |b| kept[b],
                            #[allow(unsafe_code)]
                            // SAFETY: `wide_vectors` said the CPU runs AVX-512F.
                            |s, b, mask, first| unsafe {
                                avx512::move_kept(s, BATCH_ROWS, b, mask, first)
                            },
                        ),
                        true => continue,
                    }
                    assert!(
                        same_bits(store.as_flattened(), expected.as_flattened()),
                        "{batches} {kept:x?} wide {wide}"
                    );
                }
            }
        }
        // A store shorter than the masks say is left alone.
        let original: [Row; 2] = awkward_rows(&mut rng);
        let mut store = original;
        compact_lanes(&mut store, 1, 3, |_| 1 << 5);
        assert!(same_bits(store.as_flattened(), original.as_flattened()));
    }

    #[test]
    fn the_few_outputs_products_give_the_bits_of_the_outer_products() {
        if !wide_vectors() {
            return; // Nothing to compare on a CPU without AVX-512.
        }
        let mut rng = Rng::new(19);
        let inputs: [Row; 70] = awkward_rows(&mut rng);
        let dy: [Row; FEW_OUTPUTS] = awkward_rows(&mut rng);
        // Every tile: 64 inputs at a time, 16 at a time, a part-filled last 16.
        for used in [1, 15, 16, 17, 64, 70] {
            for outputs in 1..=FEW_OUTPUTS {
                let start: [f32; 70 * FEW_OUTPUTS] = core::array::from_fn(|_| awkward(&mut rng));
                let mut scratch = [f32::NAN; LANES * 80];
                let mut few = start;
                assert!(few_outputs_products(
                    &inputs[..used],
                    &dy[..outputs],
                    &mut scratch,
                    &mut few
                ));
                let mut dyt = [0.0f32; LANES * 8];
                to_lane_major_portable(&dy[..outputs], 8, &mut dyt);
                let mut reference = start;
                outer_products_narrow(&inputs[..used], &dyt, 8, outputs, &mut reference);
                assert!(same_bits(&few, &reference), "{outputs} {used}");
            }
        }
        // Where it does not apply it leaves everything as it was.
        let mut dst = [1.0f32; 70 * 8];
        let mut scratch = [0.0f32; LANES * 80];
        assert!(!few_outputs_products(
            &inputs,
            &[dy[0]; 5],
            &mut scratch,
            &mut dst
        ));
        assert!(!few_outputs_products(
            &inputs,
            &dy,
            &mut scratch[..LANES * 64],
            &mut dst
        ));
        assert!(!few_outputs_products(
            &inputs,
            &dy,
            &mut scratch,
            &mut dst[..69]
        ));
        assert!(dst.iter().all(|&v| v == 1.0));
    }
}
