//! Volume rendering: ray/box clipping, the occupancy bitfield that lets marching skip empty
//! space, and compositing onto the background (forward and backward).

use glam::Vec3;

/// The scene's axis-aligned box.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Aabb {
    pub min: Vec3,
    pub max: Vec3,
}

impl Aabb {
    /// Entry and exit distances of the ray, or `None` if it misses the box (or is not finite).
    pub fn clip(&self, origin: Vec3, dir: Vec3) -> Option<(f32, f32)> {
        let mut t0 = 0.0f32;
        let mut t1 = f32::INFINITY;
        for a in 0..3 {
            let d = dir[a];
            // A zero component never crosses its slabs: keep it only if the origin is inside.
            if d.abs() < 1e-12 {
                if !(self.min[a] <= origin[a] && origin[a] <= self.max[a]) {
                    return None;
                }
                continue;
            }
            let inv = 1.0 / d;
            let (mut near, mut far) = (
                (self.min[a] - origin[a]) * inv,
                (self.max[a] - origin[a]) * inv,
            );
            if near > far {
                core::mem::swap(&mut near, &mut far);
            }
            t0 = t0.max(near);
            t1 = t1.min(far);
        }
        // Comparisons with NaN are false, so a NaN ray is rejected here too.
        if t0 < t1 && t1.is_finite() {
            Some((t0, t1))
        } else {
            None
        }
    }

    /// Position mapped to [0,1]^3 over the box.
    #[inline]
    pub fn normalise(&self, p: Vec3) -> [f32; 3] {
        ((p - self.min) / (self.max - self.min)).to_array()
    }

    pub fn diagonal(&self) -> f32 {
        (self.max - self.min).length()
    }
}

/// Read-only view of the occupancy bitfield: `res³` cells over the box, bit set = occupied.
#[derive(Clone, Copy)]
pub struct OccupancyView<'a> {
    pub bits: &'a [u64],
    pub res: usize,
    pub aabb: Aabb,
}

impl OccupancyView<'_> {
    #[inline]
    fn occupied(&self, c: [usize; 3]) -> bool {
        let i = (c[2] * self.res + c[1]) * self.res + c[0];
        self.bits
            .get(i / 64)
            .is_some_and(|w| w >> (i % 64) & 1 == 1)
    }
}

/// Sample distances along a ray: the lattice `t_near + (k + jitter) * step` inside the box,
/// restricted to occupied cells. Calls `emit(t)` for each until it returns false or
/// `max_samples` were emitted; returns how many were emitted.
///
/// The ray walks the grid cell by cell (Amanatides and Woo's traversal: per cell a minimum
/// of three exit distances and one bit test, no division), emitting the lattice points that
/// fall inside each occupied cell and stepping over the rest.
pub fn march(
    occupancy: &OccupancyView<'_>,
    origin: Vec3,
    dir: Vec3,
    step: f32,
    jitter: f32,
    max_samples: usize,
    mut emit: impl FnMut(f32) -> bool,
) -> usize {
    let Some((t_near, t_far)) = occupancy.aabb.clip(origin, dir) else {
        return 0;
    };
    let res = occupancy.res;
    // The ray in grid units: cell coordinates of o + d t are og + t dg.
    let scale = res as f32 / (occupancy.aabb.max - occupancy.aabb.min);
    let og = (origin - occupancy.aabb.min) * scale;
    let dg = dir * scale;
    let entry = og + dg * t_near;
    let mut cell = [0usize; 3];
    let mut t_exit = [f32::INFINITY; 3];
    let mut t_delta = [f32::INFINITY; 3];
    let mut forward = [true; 3];
    for a in 0..3 {
        // Saturating float-to-int casts keep rounding outside the box in range.
        cell[a] = (entry[a] as usize).min(res - 1);
        if dg[a].abs() >= 1e-12 {
            forward[a] = dg[a] > 0.0;
            let bound = cell[a] as f32 + if forward[a] { 1.0 } else { 0.0 };
            t_exit[a] = (bound - og[a]) / dg[a];
            t_delta[a] = 1.0 / dg[a].abs();
        }
    }
    let mut k = 0.0f32;
    let mut count = 0;
    let mut t_enter = t_near;
    // Each iteration leaves one cell, so this ends within 3 * res iterations.
    loop {
        let a = if t_exit[0] <= t_exit[1] && t_exit[0] <= t_exit[2] {
            0
        } else if t_exit[1] <= t_exit[2] {
            1
        } else {
            2
        };
        let leave = t_exit[a].min(t_far);
        if occupancy.occupied(cell) {
            // The first lattice point at or past the cell's entry.
            let first = libm::ceilf((t_enter - t_near) / step - jitter);
            if first > k {
                k = first;
            }
            loop {
                let t = t_near + (k + jitter) * step;
                if t >= leave {
                    break;
                }
                if count >= max_samples || !emit(t) {
                    return count;
                }
                count += 1;
                k += 1.0;
            }
        }
        // (Whatever the distances, each iteration moves one cell, so the walk ends at the
        // grid's edge at the latest.)
        if t_exit[a] >= t_far {
            return count;
        }
        t_enter = t_exit[a];
        if forward[a] {
            cell[a] += 1;
            if cell[a] == res {
                return count;
            }
        } else {
            if cell[a] == 0 {
                return count;
            }
            cell[a] -= 1;
        }
        t_exit[a] += t_delta[a];
    }
}

/// Number of leading samples a ray keeps: marching stops after the sample that takes the
/// transmittance below `min_transmittance`.
pub fn kept_samples(sigma: &[f32], step: f32, min_transmittance: f32) -> usize {
    let mut optical_depth = 0.0f32;
    let limit = -libm::logf(min_transmittance.max(f32::MIN_POSITIVE));
    for (i, s) in sigma.iter().enumerate() {
        optical_depth += s * step;
        if optical_depth > limit {
            return i + 1;
        }
    }
    sigma.len()
}

/// The opacity `1 - exp(-x)` of a sample of optical depth `x`, as `-expm1(-x)` (exact to
/// the last bit for small `x`, where `1 - exp(-x)` cancels), and the transmittance it keeps.
#[inline(always)]
fn opacity_and_keep(depth: f32) -> (f32, f32) {
    let opacity = -libm::expm1f(-depth);
    (opacity, 1.0 - opacity)
}

/// Composite samples front to back onto `background`. Returns the colour and the final
/// transmittance.
pub fn composite_forward(
    sigma: &[f32],
    rgb: &[[f32; 3]],
    step: f32,
    background: [f32; 3],
) -> ([f32; 3], f32) {
    let mut transmittance = 1.0f32;
    let mut colour = [0.0f32; 3];
    for (s, c) in sigma.iter().zip(rgb) {
        let (opacity, keep) = opacity_and_keep(*s * step);
        let weight = transmittance * opacity;
        for ch in 0..3 {
            colour[ch] += weight * c[ch];
        }
        transmittance *= keep;
    }
    for ch in 0..3 {
        colour[ch] += transmittance * background[ch];
    }
    (colour, transmittance)
}

/// Backward of `composite_forward` given the forward colour and d loss / d colour: writes
/// d loss / d sigma and d loss / d rgb per sample.
pub fn composite_backward(
    sigma: &[f32],
    rgb: &[[f32; 3]],
    step: f32,
    colour: [f32; 3],
    d_colour: [f32; 3],
    d_sigma: &mut [f32],
    d_rgb: &mut [[f32; 3]],
) {
    let mut transmittance = 1.0f32;
    // Colour accumulated up to and including the current sample.
    let mut accumulated = [0.0f32; 3];
    for i in 0..sigma.len() {
        let (opacity, keep) = opacity_and_keep(sigma[i] * step);
        let weight = transmittance * opacity;
        let after = transmittance * keep;
        let mut d = 0.0f32;
        for ch in 0..3 {
            accumulated[ch] += weight * rgb[i][ch];
            // d colour / d sigma_i = step * (T_{i+1} c_i - (colour - accumulated_i))
            d += d_colour[ch] * (after * rgb[i][ch] - (colour[ch] - accumulated[ch]));
            d_rgb[i][ch] = d_colour[ch] * weight;
        }
        d_sigma[i] = d * step;
        transmittance = after;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    #[test]
    fn compositing_gradients_match_finite_differences() {
        let mut rng = Rng::new(9);
        let n = 7;
        let mut sigma = [0.0f32; 7];
        let mut rgb = [[0.0f32; 3]; 7];
        for i in 0..n {
            sigma[i] = 20.0 * rng.uniform();
            rgb[i] = [rng.uniform(), rng.uniform(), rng.uniform()];
        }
        let step = 0.05;
        let bg = [1.0, 0.5, 0.2];
        let d_colour = [0.3, -0.7, 0.4];
        let loss = |sigma: &[f32], rgb: &[[f32; 3]]| {
            let (c, _) = composite_forward(sigma, rgb, step, bg);
            (0..3).map(|ch| (c[ch] * d_colour[ch]) as f64).sum::<f64>()
        };
        let (colour, _) = composite_forward(&sigma, &rgb, step, bg);
        let mut d_sigma = [0.0f32; 7];
        let mut d_rgb = [[0.0f32; 3]; 7];
        composite_backward(
            &sigma,
            &rgb,
            step,
            colour,
            d_colour,
            &mut d_sigma,
            &mut d_rgb,
        );
        let h = 1e-2f32;
        for i in 0..n {
            let (mut p, mut m) = (sigma, sigma);
            p[i] += h;
            m[i] -= h;
            let numeric = ((loss(&p, &rgb) - loss(&m, &rgb)) / (2.0 * h as f64)) as f32;
            assert!(
                (d_sigma[i] - numeric).abs() < 1e-3 + 1e-2 * numeric.abs(),
                "sigma {i}: {} vs {numeric}",
                d_sigma[i]
            );
            for ch in 0..3 {
                let (mut p, mut m) = (rgb, rgb);
                p[i][ch] += h;
                m[i][ch] -= h;
                let numeric = ((loss(&sigma, &p) - loss(&sigma, &m)) / (2.0 * h as f64)) as f32;
                assert!((d_rgb[i][ch] - numeric).abs() < 1e-4 + 1e-2 * numeric.abs());
            }
        }
    }

    #[test]
    fn thin_samples_keep_their_opacity_to_the_last_bit() {
        // 1 - exp(-1e-9) is 0 in f32; the opacity is 1e-9 to within rounding.
        let (opacity, keep) = opacity_and_keep(1e-9);
        assert!((opacity - 1e-9).abs() < 1e-15, "{opacity}");
        assert_eq!(keep, 1.0);
        let (c, t) = composite_forward(&[1e-6], &[[1.0, 1.0, 1.0]], 1e-3, [0.0; 3]);
        assert!((c[0] - 1e-9).abs() < 1e-15 && t == 1.0, "{c:?}");
    }

    #[test]
    fn empty_ray_shows_the_background_and_opaque_ray_hides_it() {
        let bg = [0.2, 0.4, 0.6];
        assert_eq!(composite_forward(&[], &[], 0.1, bg), (bg, 1.0));
        let (c, t) = composite_forward(&[1e6], &[[0.9, 0.1, 0.0]], 0.1, bg);
        assert!(t < 1e-6 && (c[0] - 0.9).abs() < 1e-5);
        assert_eq!(kept_samples(&[1e6, 1.0, 1.0], 0.1, 1e-4), 1);
        assert_eq!(kept_samples(&[0.0, 0.0], 0.1, 1e-4), 2);
    }

    #[test]
    fn clipping_handles_axis_aligned_nan_and_missing_rays() {
        let aabb = Aabb {
            min: Vec3::splat(-1.0),
            max: Vec3::splat(1.0),
        };
        let (t0, t1) = aabb.clip(Vec3::new(0.0, 0.0, -3.0), Vec3::Z).unwrap();
        assert!((t0 - 2.0).abs() < 1e-6 && (t1 - 4.0).abs() < 1e-6);
        assert!(aabb.clip(Vec3::new(2.0, 0.0, -3.0), Vec3::Z).is_none());
        assert!(aabb.clip(Vec3::new(0.0, 0.0, -3.0), -Vec3::Z).is_none());
        assert!(aabb.clip(Vec3::splat(f32::NAN), Vec3::Z).is_none());
        assert!(aabb.clip(Vec3::ZERO, Vec3::ZERO).is_none());
    }

    /// The lattice points in occupied cells, point by point (what `march` must emit).
    fn march_reference(
        occ: &OccupancyView<'_>,
        o: Vec3,
        d: Vec3,
        step: f32,
        jitter: f32,
    ) -> heapless::Vec<f32, 512> {
        let mut out = heapless::Vec::new();
        let Some((t_near, t_far)) = occ.aabb.clip(o, d) else {
            return out;
        };
        let mut k = 0.0f32;
        loop {
            let t = t_near + (k + jitter) * step;
            if t >= t_far {
                return out;
            }
            let u = occ.aabb.normalise(o + d * t);
            let cell = u.map(|v| ((v * occ.res as f32) as usize).min(occ.res - 1));
            if occ.occupied(cell) {
                out.push(t).unwrap();
            }
            k += 1.0;
        }
    }

    #[test]
    fn marching_emits_the_lattice_points_in_occupied_cells() {
        let aabb = Aabb {
            min: Vec3::new(-1.0, -0.5, -2.0),
            max: Vec3::new(1.0, 1.5, 0.5),
        };
        let res = 8;
        let mut rng = crate::rng::Rng::new(7);
        let (mut checked, mut borderline) = (0, 0);
        for case in 0..400 {
            let mut bits = [0u64; 8];
            for w in &mut bits {
                *w = rng.next_u64() & rng.next_u64();
            }
            let occ = OccupancyView {
                bits: &bits,
                res,
                aabb,
            };
            let o = Vec3::new(rng.uniform(), rng.uniform(), rng.uniform()) * 6.0 - 3.0;
            // Aimed at a point of the box (most rays hit it).
            let aim = aabb.min
                + (aabb.max - aabb.min) * Vec3::new(rng.uniform(), rng.uniform(), rng.uniform());
            let mut d = aim - o;
            // Every fourth ray runs along an axis or in a coordinate plane.
            if case % 4 == 0 {
                d[case / 4 % 3] = 0.0;
            }
            if case % 8 == 0 {
                d[(case / 4 + 1) % 3] = 0.0;
            }
            let d = d.normalize_or(Vec3::X);
            let (step, jitter) = (0.005 + 0.05 * rng.uniform(), rng.uniform());
            let expected = march_reference(&occ, o, d, step, jitter);
            let mut got: heapless::Vec<f32, 512> = heapless::Vec::new();
            let count = march(&occ, o, d, step, jitter, 512, |t| {
                got.push(t).unwrap();
                true
            });
            assert_eq!(count, got.len());
            // A point a rounding error from a cell face may land on either side of it.
            let on_face = |t: f32| {
                let g = (aabb.normalise(o + d * t)).map(|v| v * res as f32);
                g.iter().any(|v| (v - libm::roundf(*v)).abs() < 1e-3)
            };
            for t in got.iter().filter(|t| !expected.contains(t)) {
                assert!(on_face(*t), "case {case}: extra sample at {t}");
                borderline += 1;
            }
            for t in expected.iter().filter(|t| !got.contains(t)) {
                assert!(on_face(*t), "case {case}: missing sample at {t}");
                borderline += 1;
            }
            assert!(
                got.windows(2).all(|w| w[0] < w[1]),
                "case {case}: out of order"
            );
            checked += expected.len();
        }
        assert!(
            checked > 2000 && borderline * 100 < checked,
            "{checked} {borderline}"
        );
    }

    #[test]
    fn marching_skips_empty_cells_and_stays_on_the_lattice() {
        let aabb = Aabb {
            min: Vec3::splat(0.0),
            max: Vec3::splat(4.0),
        };
        // 4^3 cells; only cell (2, 0, 0) is occupied.
        let mut bits = [0u64; 1];
        bits[0] |= 1 << 2;
        let occ = OccupancyView {
            bits: &bits,
            res: 4,
            aabb,
        };
        let origin = Vec3::new(-1.0, 0.5, 0.5);
        let mut ts = [0.0f32; 64];
        let mut n = 0;
        let count = march(&occ, origin, Vec3::X, 0.25, 0.5, 64, |t| {
            ts[n] = t;
            n += 1;
            true
        });
        assert_eq!(count, 4);
        for (i, t) in ts[..n].iter().enumerate() {
            let x = origin.x + t;
            assert!((2.0..3.0).contains(&x), "sample at x = {x}");
            assert!((t - (1.0 + (8.0 + i as f32 + 0.5) * 0.25)).abs() < 1e-5);
        }
        // Capacity: emit refuses after two samples.
        let mut m = 0;
        assert_eq!(
            march(&occ, origin, Vec3::X, 0.25, 0.5, 64, |_| {
                m += 1;
                m <= 2
            }),
            2
        );
    }
}
