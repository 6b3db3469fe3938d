//! The radiance field's building blocks, each with its hand-written backward pass:
//! multi-scale tri-plane lookup (f16 texels, bilinear, product across planes, concatenation
//! across scales), the spherical-harmonics view encoding, MLP layers over `LANES` samples in
//! structure-of-arrays layout, and the activations.
//!
//! Arithmetic is plain f32 multiply and add (no fused multiply-add, no fast-math), so every
//! target computes the same bits.

use crate::config::{Config, LANES, MAX_SCALES};
use crate::fused;
pub use crate::fused::Row;
use half::f16;

/// The two world axes spanned by each of the three planes of a scale: xy, xz, yz.
pub const PLANE_AXES: [(usize, usize); 3] = [(0, 1), (0, 2), (1, 2)];

/// Where each scale's planes live in the texel array.
#[derive(Clone, Copy, Debug)]
pub struct PlaneGeometry {
    pub scales: usize,
    pub features: usize,
    pub resolution: [usize; MAX_SCALES],
    /// Texel index of the first texel of scale `s`'s xy plane; its xz and yz planes follow.
    pub first_texel: [usize; MAX_SCALES],
}

impl PlaneGeometry {
    pub fn new(c: &Config) -> Self {
        let mut resolution = [0; MAX_SCALES];
        let mut first_texel = [0; MAX_SCALES];
        let mut at = 0;
        for s in 0..c.scales as usize {
            let r = c.resolutions[s] as usize;
            resolution[s] = r;
            first_texel[s] = at;
            at += 3 * r * r;
        }
        PlaneGeometry {
            scales: c.scales as usize,
            features: c.features as usize,
            resolution,
            first_texel,
        }
    }
}

/// One bilinear footprint: the texel indices of the four corners and their weights, plus the
/// fractional position (for the spatial gradient).
#[derive(Clone, Copy, Debug)]
struct Footprint {
    texels: [usize; 4],
    weights: [f32; 4],
    frac: [f32; 2],
}

#[inline(always)]
fn footprint(first: usize, res: usize, a: f32, b: f32) -> Footprint {
    // align_corners: coordinate 0 is texel 0's centre and 1 is texel (res - 1)'s centre.
    let scale = (res - 1) as f32;
    let x = (a * scale).clamp(0.0, scale);
    let y = (b * scale).clamp(0.0, scale);
    // Saturating casts keep a NaN at texel 0 instead of panicking.
    let x0 = (x as usize).min(res - 2);
    let y0 = (y as usize).min(res - 2);
    let fx = x - x0 as f32;
    let fy = y - y0 as f32;
    let t00 = first + y0 * res + x0;
    Footprint {
        texels: [t00, t00 + 1, t00 + res, t00 + res + 1],
        weights: [
            (1.0 - fx) * (1.0 - fy),
            fx * (1.0 - fy),
            (1.0 - fx) * fy,
            fx * fy,
        ],
        frac: [fx, fy],
    }
}

/// The `F` features of one texel as f32 (zeros if the index is out of range, which a
/// footprint never produces).
#[inline(always)]
fn load_texel<const F: usize>(planes: &[f16], texel: usize) -> [f32; F] {
    let mut out = [0.0f32; F];
    let Some(src) = planes.get(texel * F..texel * F + F) else {
        return out;
    };
    #[cfg(all(
        target_arch = "x86_64",
        target_feature = "f16c",
        target_feature = "avx"
    ))]
    #[allow(unsafe_code)] // The f16c conversion intrinsics (the others: `fused::axpy`).
    {
        use core::arch::x86_64::{__m128i, _mm_loadu_si128, _mm256_cvtph_ps, _mm256_storeu_ps};
        // F is a multiple of 8 (validated config). The conversion is exact, so this path
        // gives the same bits as the portable one.
        for i in (0..F).step_by(8) {
            // SAFETY: `src` and `out` both hold F >= i + 8 values.
            unsafe {
                let v = _mm_loadu_si128(src.as_ptr().add(i) as *const __m128i);
                _mm256_storeu_ps(out.as_mut_ptr().add(i), _mm256_cvtph_ps(v));
            }
        }
    }
    #[cfg(not(all(
        target_arch = "x86_64",
        target_feature = "f16c",
        target_feature = "avx"
    )))]
    for (o, h) in out.iter_mut().zip(src) {
        *o = h.to_f32();
    }
    out
}

#[inline(always)]
fn bilinear<const F: usize>(planes: &[f16], fp: &Footprint) -> [f32; F] {
    let c = fp.texels.map(|t| load_texel::<F>(planes, t));
    let [w0, w1, w2, w3] = fp.weights;
    let mut out = [0.0f32; F];
    for f in 0..F {
        out[f] = w0 * c[0][f] + w1 * c[1][f] + w2 * c[2][f] + w3 * c[3][f];
    }
    out
}

/// Plane features at normalised position `u` in [0,1]^3: for each scale, the product of the
/// three planes' bilinear values; scales concatenated into `feats` (`scales * features`).
/// The per-plane values go to `values` (`3 * scales * features`) for the backward pass.
pub fn planes_forward(
    planes: &[f16],
    geo: &PlaneGeometry,
    u: [f32; 3],
    feats: &mut [f32],
    values: &mut [f32],
) {
    #[cfg(all(target_arch = "x86_64", target_feature = "fma", target_feature = "avx"))]
    if fused::wide_vectors() {
        #[allow(unsafe_code)]
        // SAFETY: `wide_vectors` found AVX-512F on this CPU, with its registers enabled.
        unsafe {
            match geo.features {
                16 => return wide::planes_forward::<16>(planes, geo, u, feats, values),
                32 => return wide::planes_forward::<32>(planes, geo, u, feats, values),
                64 => return wide::planes_forward::<64>(planes, geo, u, feats, values),
                _ => {}
            }
        }
    }
    match geo.features {
        8 => planes_forward_n::<8>(planes, geo, u, feats, values),
        16 => planes_forward_n::<16>(planes, geo, u, feats, values),
        32 => planes_forward_n::<32>(planes, geo, u, feats, values),
        _ => planes_forward_n::<64>(planes, geo, u, feats, values),
    }
}

#[inline(always)]
fn planes_forward_n<const F: usize>(
    planes: &[f16],
    geo: &PlaneGeometry,
    u: [f32; 3],
    feats: &mut [f32],
    values: &mut [f32],
) {
    for s in 0..geo.scales {
        let res = geo.resolution[s];
        let mut product = [1.0f32; F];
        for (p, &(a, b)) in PLANE_AXES.iter().enumerate() {
            let fp = footprint(geo.first_texel[s] + p * res * res, res, u[a], u[b]);
            let v = bilinear::<F>(planes, &fp);
            for f in 0..F {
                product[f] *= v[f];
            }
            if let Some(dst) = values.get_mut((3 * s + p) * F..(3 * s + p + 1) * F) {
                dst.copy_from_slice(&v);
            }
        }
        if let Some(dst) = feats.get_mut(s * F..(s + 1) * F) {
            dst.copy_from_slice(&product);
        }
    }
}

/// Where the backward pass of the plane lookup writes: a dense f32 gradient per plane
/// parameter and a bitmap of the texels touched (so the optimizer visits only those).
pub struct PlaneGrads<'a> {
    pub grads: &'a mut [f32],
    pub touched: &'a mut [u64],
}

/// Backward of `planes_forward` given its per-plane `values`: accumulates `d_feats`
/// (d loss / d features) into the texel gradients. With `want_spatial` it also returns
/// d loss / d u (the spatial gradient, for pose correction; this reloads the texels),
/// otherwise zeros.
pub fn planes_backward(
    planes: &[f16],
    geo: &PlaneGeometry,
    u: [f32; 3],
    values: &[f32],
    d_feats: &[f32],
    sink: &mut PlaneGrads<'_>,
    want_spatial: bool,
) -> [f32; 3] {
    #[cfg(all(target_arch = "x86_64", target_feature = "fma", target_feature = "avx"))]
    if fused::wide_vectors() {
        #[allow(unsafe_code)]
        // SAFETY: as in `planes_forward`.
        unsafe {
            match geo.features {
                16 => {
                    return wide::planes_backward::<16>(
                        planes,
                        geo,
                        u,
                        values,
                        d_feats,
                        sink,
                        want_spatial,
                    );
                }
                32 => {
                    return wide::planes_backward::<32>(
                        planes,
                        geo,
                        u,
                        values,
                        d_feats,
                        sink,
                        want_spatial,
                    );
                }
                64 => {
                    return wide::planes_backward::<64>(
                        planes,
                        geo,
                        u,
                        values,
                        d_feats,
                        sink,
                        want_spatial,
                    );
                }
                _ => {}
            }
        }
    }
    match geo.features {
        8 => planes_backward_n::<8>(planes, geo, u, values, d_feats, sink, want_spatial),
        16 => planes_backward_n::<16>(planes, geo, u, values, d_feats, sink, want_spatial),
        32 => planes_backward_n::<32>(planes, geo, u, values, d_feats, sink, want_spatial),
        _ => planes_backward_n::<64>(planes, geo, u, values, d_feats, sink, want_spatial),
    }
}

#[inline(always)]
fn planes_backward_n<const F: usize>(
    planes: &[f16],
    geo: &PlaneGeometry,
    u: [f32; 3],
    values: &[f32],
    d_feats: &[f32],
    sink: &mut PlaneGrads<'_>,
    want_spatial: bool,
) -> [f32; 3] {
    let mut spatial = [0.0f32; 3];
    let row = |i: usize| -> [f32; F] {
        values
            .get(i * F..(i + 1) * F)
            .and_then(|v| v.try_into().ok())
            .unwrap_or([0.0; F])
    };
    for s in 0..geo.scales {
        let res = geo.resolution[s];
        let d_feat: [f32; F] = d_feats
            .get(s * F..(s + 1) * F)
            .and_then(|v| v.try_into().ok())
            .unwrap_or([0.0; F]);
        let v = [row(3 * s), row(3 * s + 1), row(3 * s + 2)];
        for (p, &(a, b)) in PLANE_AXES.iter().enumerate() {
            let (q, r) = match p {
                0 => (1, 2),
                1 => (0, 2),
                _ => (0, 1),
            };
            // d loss / d (this plane's value) = upstream * the other two planes' values.
            let mut d_value = [0.0f32; F];
            for i in 0..F {
                d_value[i] = d_feat[i] * v[q][i] * v[r][i];
            }
            let fp = footprint(geo.first_texel[s] + p * res * res, res, u[a], u[b]);
            for (&texel, &w) in fp.texels.iter().zip(&fp.weights) {
                if let Some(g) = sink.grads.get_mut(texel * F..texel * F + F) {
                    for (gi, dv) in g.iter_mut().zip(&d_value) {
                        *gi += w * dv;
                    }
                }
                if let Some(word) = sink.touched.get_mut(texel / 64) {
                    *word |= 1 << (texel % 64);
                }
            }
            if want_spatial {
                add_spatial::<F>(planes, &fp, &d_value, u, (a, b), res, &mut spatial);
            }
        }
    }
    spatial
}

/// One plane's share of d loss / d u given d loss / d its bilinear value (`d_value`), added
/// to `spatial`: the footprint's texels reloaded, the sums over the features in order.
#[inline(always)]
fn add_spatial<const F: usize>(
    planes: &[f16],
    fp: &Footprint,
    d_value: &[f32; F],
    u: [f32; 3],
    (a, b): (usize, usize),
    res: usize,
    spatial: &mut [f32; 3],
) {
    let c = fp.texels.map(|t| load_texel::<F>(planes, t));
    let [fx, fy] = fp.frac;
    let (mut dx, mut dy) = (0.0f32, 0.0f32);
    for i in 0..F {
        let ddx = (1.0 - fy) * (c[1][i] - c[0][i]) + fy * (c[3][i] - c[2][i]);
        let ddy = (1.0 - fx) * (c[2][i] - c[0][i]) + fx * (c[3][i] - c[1][i]);
        dx += d_value[i] * ddx;
        dy += d_value[i] * ddy;
    }
    // Inside the clamp the texel coordinate is u * (res - 1); outside it is flat.
    let scale = (res - 1) as f32;
    if (0.0..=1.0).contains(&u[a]) {
        spatial[a] += dx * scale;
    }
    if (0.0..=1.0).contains(&u[b]) {
        spatial[b] += dy * scale;
    }
}

/// The plane lookup and its backward pass with AVX-512F: sixteen features per register
/// instead of eight, the same multiplies and adds in the same order (no fused operations, as
/// in the portable code), so the same bits; the spatial gradient is the portable code's.
#[cfg(all(target_arch = "x86_64", target_feature = "fma", target_feature = "avx"))]
#[allow(unsafe_code)] // Loads and stores of whole texels and feature rows, within their slices.
mod wide {
    use super::{Footprint, PLANE_AXES, PlaneGeometry, PlaneGrads, add_spatial, f16, footprint};
    use core::arch::x86_64::{
        __m256i, __m512, _mm256_loadu_si256, _mm512_add_ps, _mm512_cvtph_ps, _mm512_loadu_ps,
        _mm512_mul_ps, _mm512_set1_ps, _mm512_setzero_ps, _mm512_storeu_ps,
    };

    /// Registers `0 .. F / 16` of one texel's features, or zeros if the texel is out of range
    /// (as `load_texel`).
    #[target_feature(enable = "avx512f")]
    #[inline]
    fn load_texel<const F: usize>(planes: &[f16], texel: usize) -> [__m512; 4] {
        let mut out = [_mm512_setzero_ps(); 4];
        if let Some(src) = planes.get(texel * F..texel * F + F) {
            for (i, o) in out.iter_mut().enumerate().take(F / 16) {
                // SAFETY: `src` holds F >= 16 i + 16 values.
                *o = _mm512_cvtph_ps(unsafe {
                    _mm256_loadu_si256(src.as_ptr().add(16 * i) as *const __m256i)
                });
            }
        }
        out
    }

    /// Registers `0 .. F / 16` of `row[at .. at + F]`, or zeros if out of range.
    #[target_feature(enable = "avx512f")]
    #[inline]
    fn load_row<const F: usize>(row: &[f32], at: usize) -> [__m512; 4] {
        let mut out = [_mm512_setzero_ps(); 4];
        if let Some(src) = row.get(at..at + F) {
            for (i, o) in out.iter_mut().enumerate().take(F / 16) {
                // SAFETY: `src` holds F >= 16 i + 16 values.
                *o = unsafe { _mm512_loadu_ps(src.as_ptr().add(16 * i)) };
            }
        }
        out
    }

    /// Stores registers `0 .. F / 16` to `row[at .. at + F]` if it is in range.
    #[target_feature(enable = "avx512f")]
    #[inline]
    fn store_row<const F: usize>(row: &mut [f32], at: usize, v: &[__m512; 4]) {
        if let Some(dst) = row.get_mut(at..at + F) {
            for (i, vi) in v.iter().enumerate().take(F / 16) {
                // SAFETY: `dst` holds F >= 16 i + 16 values.
                unsafe { _mm512_storeu_ps(dst.as_mut_ptr().add(16 * i), *vi) };
            }
        }
    }

    /// `super::planes_forward` for `F` a multiple of 16.
    #[target_feature(enable = "avx512f")]
    pub(super) fn planes_forward<const F: usize>(
        planes: &[f16],
        geo: &PlaneGeometry,
        u: [f32; 3],
        feats: &mut [f32],
        values: &mut [f32],
    ) {
        for s in 0..geo.scales {
            let res = geo.resolution[s];
            let mut product = [_mm512_set1_ps(1.0); 4];
            for (p, &(a, b)) in PLANE_AXES.iter().enumerate() {
                let fp = footprint(geo.first_texel[s] + p * res * res, res, u[a], u[b]);
                let v = bilinear::<F>(planes, &fp);
                for i in 0..F / 16 {
                    product[i] = _mm512_mul_ps(product[i], v[i]);
                }
                store_row::<F>(values, (3 * s + p) * F, &v);
            }
            store_row::<F>(feats, s * F, &product);
        }
    }

    /// `w0 c0 + w1 c1 + w2 c2 + w3 c3`, summed left to right as the portable `bilinear`.
    #[target_feature(enable = "avx512f")]
    #[inline]
    fn bilinear<const F: usize>(planes: &[f16], fp: &Footprint) -> [__m512; 4] {
        let c = fp.texels.map(|t| load_texel::<F>(planes, t));
        let w = fp.weights.map(|w| _mm512_set1_ps(w));
        let mut out = [_mm512_setzero_ps(); 4];
        for (i, o) in out.iter_mut().enumerate().take(F / 16) {
            let mut sum = _mm512_mul_ps(w[0], c[0][i]);
            for t in 1..4 {
                sum = _mm512_add_ps(sum, _mm512_mul_ps(w[t], c[t][i]));
            }
            *o = sum;
        }
        out
    }

    /// `super::planes_backward` for `F` a multiple of 16.
    #[target_feature(enable = "avx512f")]
    pub(super) fn planes_backward<const F: usize>(
        planes: &[f16],
        geo: &PlaneGeometry,
        u: [f32; 3],
        values: &[f32],
        d_feats: &[f32],
        sink: &mut PlaneGrads<'_>,
        want_spatial: bool,
    ) -> [f32; 3] {
        let mut spatial = [0.0f32; 3];
        for s in 0..geo.scales {
            let res = geo.resolution[s];
            let d_feat = load_row::<F>(d_feats, s * F);
            let v = [0, 1, 2].map(|p| load_row::<F>(values, (3 * s + p) * F));
            for (p, &(a, b)) in PLANE_AXES.iter().enumerate() {
                let (q, r) = match p {
                    0 => (1, 2),
                    1 => (0, 2),
                    _ => (0, 1),
                };
                let mut d_value = [_mm512_setzero_ps(); 4];
                for i in 0..F / 16 {
                    d_value[i] = _mm512_mul_ps(_mm512_mul_ps(d_feat[i], v[q][i]), v[r][i]);
                }
                let fp = footprint(geo.first_texel[s] + p * res * res, res, u[a], u[b]);
                for (&texel, &w) in fp.texels.iter().zip(&fp.weights) {
                    let w = _mm512_set1_ps(w);
                    let mut g = load_row::<F>(sink.grads, texel * F);
                    for i in 0..F / 16 {
                        g[i] = _mm512_add_ps(g[i], _mm512_mul_ps(w, d_value[i]));
                    }
                    store_row::<F>(sink.grads, texel * F, &g);
                    if let Some(word) = sink.touched.get_mut(texel / 64) {
                        *word |= 1 << (texel % 64);
                    }
                }
                if want_spatial {
                    let mut d = [0.0f32; F];
                    store_row::<F>(&mut d, 0, &d_value);
                    add_spatial::<F>(planes, &fp, &d, u, (a, b), res, &mut spatial);
                }
            }
        }
        spatial
    }
}

/// Adds to `grad` (one texel's `features` values) the gradient with respect to texel
/// `texel` of K-Planes' plane total variation times `weight`: per plane of side `r`, twice
/// the mean squared difference of vertically and of horizontally neighbouring values (each
/// mean over `features * r * (r - 1)` pairs), summed over every plane of every scale. A
/// texel index past the planes adds nothing.
pub fn plane_tv_gradient(
    planes: &[f16],
    geo: &PlaneGeometry,
    weight: f32,
    texel: usize,
    grad: &mut [f32],
) {
    let f = geo.features;
    for s in 0..geo.scales {
        let r = geo.resolution[s];
        let first = geo.first_texel[s];
        if texel < first || texel >= first + 3 * r * r {
            continue;
        }
        let local = (texel - first) % (r * r);
        let (x, y) = (local % r, local / r);
        // d/dt of 2 (t - n)² / pairs, for each neighbour n.
        let coefficient = 4.0 * weight / (f * r * (r - 1)) as f32;
        let neighbours = [
            (x > 0).then(|| texel - 1),
            (x + 1 < r).then(|| texel + 1),
            (y > 0).then(|| texel - r),
            (y + 1 < r).then(|| texel + r),
        ];
        let (Some(own), Some(grad)) = (planes.get(texel * f..(texel + 1) * f), grad.get_mut(..f))
        else {
            return;
        };
        for n in neighbours.into_iter().flatten() {
            let Some(other) = planes.get(n * f..(n + 1) * f) else {
                continue;
            };
            for ((g, a), b) in grad.iter_mut().zip(own).zip(other) {
                *g += coefficient * (a.to_f32() - b.to_f32());
            }
        }
        return;
    }
}

/// K-Planes' plane total variation (unweighted) of every plane of every scale, in f64: the
/// loss whose gradient `plane_tv_gradient` computes.
#[cfg(test)]
pub(crate) fn plane_tv(planes: &[f16], geo: &PlaneGeometry) -> f64 {
    let f = geo.features;
    let mut total = 0.0f64;
    for s in 0..geo.scales {
        let r = geo.resolution[s];
        let pairs = (f * r * (r - 1)) as f64;
        for p in 0..3 {
            let at = |x: usize, y: usize, k: usize| {
                planes[(geo.first_texel[s] + p * r * r + y * r + x) * f + k].to_f64()
            };
            let (mut vertical, mut horizontal) = (0.0, 0.0);
            for y in 0..r {
                for x in 0..r {
                    for k in 0..f {
                        if x + 1 < r {
                            horizontal += (at(x + 1, y, k) - at(x, y, k)).powi(2);
                        }
                        if y + 1 < r {
                            vertical += (at(x, y + 1, k) - at(x, y, k)).powi(2);
                        }
                    }
                }
            }
            total += 2.0 * (vertical / pairs + horizontal / pairs);
        }
    }
    total
}

const SH_C0: f32 = 0.282_094_8;
const SH_C1: f32 = 0.488_602_5;
const SH_C2: [f32; 5] = [
    1.092_548_4,
    -1.092_548_4,
    0.315_391_57,
    -1.092_548_4,
    0.546_274_2,
];
const SH_C3: [f32; 7] = [
    -0.590_043_6,
    2.890_611_4,
    -0.457_045_8,
    0.373_176_34,
    -0.457_045_8,
    1.445_305_7,
    -0.590_043_6,
];

/// Real spherical harmonics of direction `d` (unit length expected) in `bands` bands
/// (degrees 0..bands), `bands²` values.
pub fn sh_forward(bands: usize, d: [f32; 3], out: &mut [f32]) {
    let [x, y, z] = d;
    out[0] = SH_C0;
    if bands > 1 {
        out[1] = -SH_C1 * y;
        out[2] = SH_C1 * z;
        out[3] = -SH_C1 * x;
    }
    if bands > 2 {
        let (xx, yy, zz) = (x * x, y * y, z * z);
        out[4] = SH_C2[0] * x * y;
        out[5] = SH_C2[1] * y * z;
        out[6] = SH_C2[2] * (2.0 * zz - xx - yy);
        out[7] = SH_C2[3] * x * z;
        out[8] = SH_C2[4] * (xx - yy);
        if bands > 3 {
            out[9] = SH_C3[0] * y * (3.0 * xx - yy);
            out[10] = SH_C3[1] * x * y * z;
            out[11] = SH_C3[2] * y * (4.0 * zz - xx - yy);
            out[12] = SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy);
            out[13] = SH_C3[4] * x * (4.0 * zz - xx - yy);
            out[14] = SH_C3[5] * z * (xx - yy);
            out[15] = SH_C3[6] * x * (xx - 3.0 * yy);
        }
    }
}

/// Backward of `sh_forward`: d loss / d d, given d loss / d (each SH value).
pub fn sh_backward(bands: usize, d: [f32; 3], d_out: &[f32]) -> [f32; 3] {
    let [x, y, z] = d;
    let mut g = [0.0f32; 3];
    if bands > 1 {
        g[1] -= SH_C1 * d_out[1];
        g[2] += SH_C1 * d_out[2];
        g[0] -= SH_C1 * d_out[3];
    }
    if bands > 2 {
        g[0] += SH_C2[0] * y * d_out[4];
        g[1] += SH_C2[0] * x * d_out[4];
        g[1] += SH_C2[1] * z * d_out[5];
        g[2] += SH_C2[1] * y * d_out[5];
        g[0] += SH_C2[2] * -2.0 * x * d_out[6];
        g[1] += SH_C2[2] * -2.0 * y * d_out[6];
        g[2] += SH_C2[2] * 4.0 * z * d_out[6];
        g[0] += SH_C2[3] * z * d_out[7];
        g[2] += SH_C2[3] * x * d_out[7];
        g[0] += SH_C2[4] * 2.0 * x * d_out[8];
        g[1] += SH_C2[4] * -2.0 * y * d_out[8];
        if bands > 3 {
            let (xx, yy, zz) = (x * x, y * y, z * z);
            g[0] += SH_C3[0] * 6.0 * x * y * d_out[9];
            g[1] += SH_C3[0] * (3.0 * xx - 3.0 * yy) * d_out[9];
            g[0] += SH_C3[1] * y * z * d_out[10];
            g[1] += SH_C3[1] * x * z * d_out[10];
            g[2] += SH_C3[1] * x * y * d_out[10];
            g[0] += SH_C3[2] * -2.0 * x * y * d_out[11];
            g[1] += SH_C3[2] * (4.0 * zz - xx - 3.0 * yy) * d_out[11];
            g[2] += SH_C3[2] * 8.0 * y * z * d_out[11];
            g[0] += SH_C3[3] * -6.0 * x * z * d_out[12];
            g[1] += SH_C3[3] * -6.0 * y * z * d_out[12];
            g[2] += SH_C3[3] * (6.0 * zz - 3.0 * xx - 3.0 * yy) * d_out[12];
            g[0] += SH_C3[4] * (4.0 * zz - 3.0 * xx - yy) * d_out[13];
            g[1] += SH_C3[4] * -2.0 * x * y * d_out[13];
            g[2] += SH_C3[4] * 8.0 * x * z * d_out[13];
            g[0] += SH_C3[5] * 2.0 * x * z * d_out[14];
            g[1] += SH_C3[5] * -2.0 * y * z * d_out[14];
            g[2] += SH_C3[5] * (xx - yy) * d_out[14];
            g[0] += SH_C3[6] * (3.0 * xx - 3.0 * yy) * d_out[15];
            g[1] += SH_C3[6] * -6.0 * x * y * d_out[15];
        }
    }
    g
}

/// `y[n] = b[n] + sum_k w[k * outputs + n] * x[k]` for all lanes, one fused multiply-add per
/// term in order of `k`. `x` has `inputs` rows and `y` has `outputs` rows.
pub fn layer_forward(w: &[f32], b: &[f32], x: &[Row], y: &mut [Row]) {
    for (yn, bn) in y.iter_mut().zip(b) {
        *yn = [*bn; LANES];
    }
    layer_forward_onto(w, x, y);
}

/// `y[n] += sum_k w[k * outputs + n] * x[k]` for all lanes, fused, in order of `k`: a layer
/// whose bias (and the terms of any inputs summed elsewhere) `y` already holds.
pub fn layer_forward_onto(w: &[f32], x: &[Row], y: &mut [Row]) {
    let outputs = y.len();
    fused::combine_rows(y, x, |n, k| w[k * outputs + n]);
}

/// Backward of `layer_forward`: accumulates d w and d b from `dy`, and (if `dx` is given)
/// writes d x. Lanes whose `dy` is zero contribute nothing, which is how partial
/// mini-batches are masked. Returns whether it left `dy` lane-major in `dy_lane_major`
/// (rows of `dy.len()` rounded up to 8), which every layer of more than
/// `fused::FEW_OUTPUTS` outputs does.
pub fn layer_backward(
    w: &[f32],
    x: &[Row],
    dy: &[Row],
    dx: Option<&mut [Row]>,
    dw: &mut [f32],
    db: &mut [f32],
    dy_lane_major: &mut [f32],
) -> bool {
    let outputs = dy.len();
    let few =
        outputs <= fused::FEW_OUTPUTS && fused::few_outputs_products(x, dy, dy_lane_major, dw);
    if few {
        // The bias gradient as `outer_products` sums a row of ones: each output's lanes in
        // order from zero (a fused 1 * y + a is the rounded y + a).
        for (d, row) in db.iter_mut().zip(dy) {
            *d += row.iter().fold(0.0f32, |a, y| a + y);
        }
    } else {
        // Transpose dy to lane-major rows padded to a multiple of 8, so the weight gradient
        // is a sum of outer products with accumulators held in registers (no horizontal
        // sums).
        let stride = outputs.div_ceil(8) * 8;
        let dyt = &mut dy_lane_major[..LANES * stride];
        fused::to_lane_major(dy, stride, dyt);
        fused::outer_products(&[ONES], dyt, stride, outputs, db);
        fused::outer_products(x, dyt, stride, outputs, dw);
    }
    if let Some(dx) = dx {
        dx.fill([0.0; LANES]);
        fused::combine_rows(dx, dy, |k, n| w[k * outputs + n]);
    }
    !few
}

const ONES: Row = [1.0; LANES];

pub fn relu_forward(y: &mut [Row]) {
    for row in y {
        for v in row.iter_mut() {
            *v = v.max(0.0);
        }
    }
}

/// Backward of ReLU given its output `y`.
pub fn relu_backward(y: &[Row], dy: &mut [Row]) {
    for (yr, dr) in y.iter().zip(dy) {
        for l in 0..LANES {
            if yr[l] <= 0.0 {
                dr[l] = 0.0;
            }
        }
    }
}

/// Raw densities above this saturate (exp(15) = 3.3e6): the forward value stays finite and
/// the backward pass uses the clamped exponential as its gradient (instant-ngp's trunc_exp).
pub const TRUNC_EXP_LIMIT: f32 = 15.0;

#[inline]
pub fn trunc_exp(x: f32) -> f32 {
    libm::expf(x.min(TRUNC_EXP_LIMIT))
}

#[inline]
pub fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + libm::expf(-x))
}

/// d sigmoid / d x from the sigmoid's output.
#[inline]
pub fn sigmoid_grad(y: f32) -> f32 {
    y * (1.0 - y)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    fn random_planes(geo: &PlaneGeometry, texels: usize, seed: u64) -> [f16; 4096] {
        let mut p = [f16::ZERO; 4096];
        let mut rng = Rng::new(seed);
        for v in p.iter_mut().take(texels * geo.features) {
            *v = f16::from_f32(0.2 + 0.6 * rng.uniform());
        }
        p
    }

    fn small_geometry() -> (PlaneGeometry, usize) {
        let mut c = Config::DEFAULT;
        c.scales = 2;
        c.resolutions = [4, 6, 0, 0];
        c.features = 8;
        (PlaneGeometry::new(&c), c.texels())
    }

    /// Relative agreement of an analytic and a central-difference derivative.
    fn assert_close(analytic: f32, numeric: f32, tol: f32, what: &str) {
        let scale = analytic.abs().max(numeric.abs()).max(1e-2);
        assert!(
            (analytic - numeric).abs() / scale < tol,
            "{what}: analytic {analytic} vs numeric {numeric}"
        );
    }

    #[test]
    fn plane_tv_gradient_matches_finite_differences() {
        let (geo, texels) = small_geometry();
        // Values on a 1/64 grid, so the perturbed values below are exact in f16.
        let planes = random_planes(&geo, texels, 3)
            .map(|v| f16::from_f32((v.to_f32() * 64.0).round() / 64.0));
        let f = geo.features;
        let weight = 0.5f32;
        let loss = |planes: &[f16]| weight as f64 * plane_tv(planes, &geo);
        for t in 0..texels {
            let mut grad = [0.0f32; 8];
            plane_tv_gradient(&planes, &geo, weight, t, &mut grad);
            for k in 0..f {
                let i = t * f + k;
                let h = 0.0625f32;
                let mut plus = planes;
                let mut minus = planes;
                plus[i] = f16::from_f32(planes[i].to_f32() + h);
                minus[i] = f16::from_f32(planes[i].to_f32() - h);
                let numeric = ((loss(&plus) - loss(&minus)) / (2.0 * h as f64)) as f32;
                assert_close(grad[k], numeric, 1e-4, "plane TV");
            }
        }
        // Past the planes: nothing added.
        let mut grad = [0.0f32; 8];
        plane_tv_gradient(&planes, &geo, weight, texels, &mut grad);
        assert_eq!(grad, [0.0; 8]);
    }

    #[test]
    fn plane_lookup_gradients_match_finite_differences() {
        let (geo, texels) = small_geometry();
        let planes = random_planes(&geo, texels, 1);
        let n = 2 * geo.features;
        let u = [0.37, 0.61, 0.18];
        let mut d_out = [0.0f32; 16];
        let mut rng = Rng::new(2);
        for v in d_out.iter_mut().take(n) {
            *v = rng.uniform() - 0.5;
        }
        let loss = |planes: &[f16], u: [f32; 3]| {
            let mut out = [0.0f32; 16];
            planes_forward(planes, &geo, u, &mut out[..n], &mut [0.0; 48]);
            (0..n).map(|i| (out[i] * d_out[i]) as f64).sum::<f64>()
        };
        let mut grads = [0.0f32; 4096];
        let mut touched = [0u64; 8];
        let mut values = [0.0f32; 48];
        planes_forward(&planes, &geo, u, &mut [0.0; 16], &mut values);
        let spatial = planes_backward(
            &planes,
            &geo,
            u,
            &values,
            &d_out[..n],
            &mut PlaneGrads {
                grads: &mut grads,
                touched: &mut touched,
            },
            true,
        );
        // Texel gradients: perturb in f32 through a shadow copy (the lookup is linear in
        // each texel, so the difference is exact up to f16 storage of the base value).
        let mut checked = 0;
        for t in 0..texels {
            let is_touched = touched[t / 64] >> (t % 64) & 1 == 1;
            for f in 0..geo.features {
                let i = t * geo.features + f;
                if !is_touched {
                    assert_eq!(grads[i], 0.0);
                    continue;
                }
                let h = 0.0625f32; // exact in f16 around values in [0.2, 0.8]
                let mut plus = planes;
                let mut minus = planes;
                plus[i] = f16::from_f32(planes[i].to_f32() + h);
                minus[i] = f16::from_f32(planes[i].to_f32() - h);
                let numeric = ((loss(&plus, u) - loss(&minus, u)) / (2.0 * h as f64)) as f32;
                assert_close(grads[i], numeric, 2e-3, "texel");
                checked += 1;
            }
        }
        assert_eq!(checked, 2 * 3 * 4 * geo.features);
        for a in 0..3 {
            let h = 1e-3f32;
            let (mut up, mut um) = (u, u);
            up[a] += h;
            um[a] -= h;
            let numeric = ((loss(&planes, up) - loss(&planes, um)) / (2.0 * h as f64)) as f32;
            assert_close(spatial[a], numeric, 1e-2, "position");
        }
    }

    #[test]
    fn the_wide_plane_lookup_gives_the_bits_of_the_portable_one() {
        #[cfg(all(target_arch = "x86_64", target_feature = "fma", target_feature = "avx"))]
        if fused::wide_vectors() {
            wide_lookup_matches::<16>();
            wide_lookup_matches::<32>();
            wide_lookup_matches::<64>();
        }
    }

    /// `F` features, two scales (4 and 6 texels a side): lookups and their backward passes
    /// at random positions, outside the box and at NaN, by both paths.
    #[cfg(all(target_arch = "x86_64", target_feature = "fma", target_feature = "avx"))]
    fn wide_lookup_matches<const F: usize>() {
        use crate::fused::tests::same_bits;
        let mut c = Config::DEFAULT;
        c.scales = 2;
        c.resolutions = [4, 6, 0, 0];
        c.features = F as u16;
        let geo = PlaneGeometry::new(&c);
        let len = c.texels() * F;
        let mut rng = Rng::new(F as u64);
        let mut planes = [f16::ZERO; 156 * 64];
        for v in planes.iter_mut().take(len) {
            *v = f16::from_f32(2.0 * rng.uniform() - 0.5);
        }
        let mut grads = [[0.0f32; 156 * 64]; 2];
        let mut touched = [[0u64; 3]; 2];
        for i in 0..40 {
            let u = match i {
                0 => [-5.0, 2.0, 0.5],
                1 => [f32::NAN, 0.5, f32::INFINITY],
                2 => [1.0, 1.0, 0.0],
                _ => [rng.uniform(), rng.uniform(), rng.uniform()],
            };
            let mut feats = [[0.0f32; 2 * 64]; 2];
            let mut values = [[0.0f32; 6 * 64]; 2];
            planes_forward_n::<F>(&planes, &geo, u, &mut feats[0], &mut values[0]);
            #[allow(unsafe_code)]
            // SAFETY: `wide_vectors` said the CPU runs AVX-512F.
            unsafe {
                wide::planes_forward::<F>(&planes, &geo, u, &mut feats[1], &mut values[1])
            };
            assert!(same_bits(&feats[0], &feats[1]), "feats {F} {i}");
            assert!(same_bits(&values[0], &values[1]), "values {F} {i}");
            let d_feats: [f32; 2 * 64] = core::array::from_fn(|_| rng.uniform() - 0.5);
            let [g0, g1] = &mut grads;
            let [t0, t1] = &mut touched;
            let spatial = [
                planes_backward_n::<F>(
                    &planes,
                    &geo,
                    u,
                    &values[0],
                    &d_feats,
                    &mut PlaneGrads {
                        grads: &mut g0[..len],
                        touched: t0,
                    },
                    i % 2 == 0,
                ),
                #[allow(unsafe_code)]
                // SAFETY: as above.
                unsafe {
                    wide::planes_backward::<F>(
                        &planes,
                        &geo,
                        u,
                        &values[1],
                        &d_feats,
                        &mut PlaneGrads {
                            grads: &mut g1[..len],
                            touched: t1,
                        },
                        i % 2 == 0,
                    )
                },
            ];
            assert!(same_bits(&spatial[0], &spatial[1]), "spatial {F} {i}");
        }
        assert!(same_bits(&grads[0], &grads[1]), "grads {F}");
        assert_eq!(touched[0], touched[1]);
        assert_ne!(touched[0], [0; 3]);
    }

    #[test]
    fn plane_lookup_outside_the_box_and_nan_stay_in_bounds() {
        let (geo, texels) = small_geometry();
        let planes = random_planes(&geo, texels, 3);
        let mut out = [0.0f32; 16];
        for u in [
            [-5.0, 2.0, 0.5],
            [f32::NAN, 0.5, f32::INFINITY],
            [1.0, 1.0, 1.0],
        ] {
            planes_forward(&planes, &geo, u, &mut out, &mut [0.0; 48]);
            assert!(
                out.iter()
                    .all(|v| v.is_finite() || u.iter().any(|x| x.is_nan()))
            );
        }
    }

    #[test]
    fn sh_gradients_match_finite_differences() {
        let d = [0.3f32, -0.5, 0.8];
        let mut d_out = [0.0f32; 16];
        let mut rng = Rng::new(4);
        for v in &mut d_out {
            *v = rng.uniform() - 0.5;
        }
        for bands in 1..=4 {
            let n = bands * bands;
            let loss = |d: [f32; 3]| {
                let mut out = [0.0f32; 16];
                sh_forward(bands, d, &mut out);
                (0..n).map(|i| (out[i] * d_out[i]) as f64).sum::<f64>()
            };
            let g = sh_backward(bands, d, &d_out[..n]);
            for a in 0..3 {
                let h = 1e-3f32;
                let (mut p, mut m) = (d, d);
                p[a] += h;
                m[a] -= h;
                let numeric = ((loss(p) - loss(m)) / (2.0 * h as f64)) as f32;
                assert_close(g[a], numeric, 1e-2, "sh");
            }
        }
    }

    #[test]
    fn sh_on_the_z_axis_keeps_only_the_constant_and_z_terms() {
        // Values on +z: only the constant and the z-aligned terms are non-zero.
        let mut out = [0.0f32; 16];
        sh_forward(4, [0.0, 0.0, 1.0], &mut out);
        assert!((out[0] - SH_C0).abs() < 1e-7 && (out[2] - SH_C1).abs() < 1e-7);
        assert_eq!(out[1], 0.0);
        assert_eq!(out[3], 0.0);
    }

    #[test]
    fn layer_gradients_match_finite_differences() {
        const K: usize = 5;
        const N: usize = 4;
        let mut rng = Rng::new(5);
        let mut w = [0.0f32; K * N];
        let mut b = [0.0f32; N];
        let mut x = [[0.0f32; LANES]; K];
        let mut upstream = [[0.0f32; LANES]; N];
        w.iter_mut()
            .chain(b.iter_mut())
            .for_each(|v| *v = rng.uniform() - 0.5);
        x.iter_mut()
            .flatten()
            .for_each(|v| *v = rng.uniform() - 0.5);
        upstream
            .iter_mut()
            .flatten()
            .for_each(|v| *v = rng.uniform() - 0.5);
        // Loss = sum over lanes of upstream * relu(layer(x)).
        let loss = |w: &[f32], b: &[f32], x: &[Row]| {
            let mut y = [[0.0f32; LANES]; N];
            layer_forward(w, b, x, &mut y);
            relu_forward(&mut y);
            y.iter()
                .zip(&upstream)
                .flat_map(|(a, u)| a.iter().zip(u))
                .map(|(a, u)| (a * u) as f64)
                .sum::<f64>()
        };
        let mut y = [[0.0f32; LANES]; N];
        layer_forward(&w, &b, &x, &mut y);
        relu_forward(&mut y);
        let mut dy = upstream;
        relu_backward(&y, &mut dy);
        let (mut dw, mut db, mut dx) = ([0.0f32; K * N], [0.0f32; N], [[0.0f32; LANES]; K]);
        layer_backward(
            &w,
            &x,
            &dy,
            Some(&mut dx),
            &mut dw,
            &mut db,
            &mut [0.0; LANES * 8],
        );
        let h = 1e-3f32;
        for i in 0..K * N {
            let (mut p, mut m) = (w, w);
            p[i] += h;
            m[i] -= h;
            let numeric = ((loss(&p, &b, &x) - loss(&m, &b, &x)) / (2.0 * h as f64)) as f32;
            assert_close(dw[i], numeric, 1e-2, "weight");
        }
        for i in 0..N {
            let (mut p, mut m) = (b, b);
            p[i] += h;
            m[i] -= h;
            let numeric = ((loss(&w, &p, &x) - loss(&w, &m, &x)) / (2.0 * h as f64)) as f32;
            assert_close(db[i], numeric, 1e-2, "bias");
        }
        for (k, l) in [(0, 0), (2, 17), (4, 63)] {
            let (mut p, mut m) = (x, x);
            p[k][l] += h;
            m[k][l] -= h;
            let numeric = ((loss(&w, &b, &p) - loss(&w, &b, &m)) / (2.0 * h as f64)) as f32;
            assert_close(dx[k][l], numeric, 1e-2, "input");
        }
    }

    #[test]
    fn activations_match_finite_differences() {
        let h = 1e-3f32;
        for x in [-3.0f32, -0.2, 0.0, 0.7, 4.0] {
            let numeric = (sigmoid(x + h) - sigmoid(x - h)) / (2.0 * h);
            assert_close(sigmoid_grad(sigmoid(x)), numeric, 1e-2, "sigmoid");
            // The backward pass uses the value itself as the derivative (clamped alike).
            let numeric = (trunc_exp(x + h) - trunc_exp(x - h)) / (2.0 * h);
            assert_close(trunc_exp(x), numeric, 1e-2, "trunc_exp");
        }
        // Saturated: finite value (and so a finite, clamped gradient).
        assert!(trunc_exp(1e30).is_finite() && trunc_exp(f32::INFINITY).is_finite());
        assert_eq!(trunc_exp(100.0), trunc_exp(TRUNC_EXP_LIMIT));
    }
}
