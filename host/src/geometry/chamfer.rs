//! The Chamfer distance between two surfaces: points drawn uniformly by area on each (seeded,
//! so the same surfaces give the same number), each point's distance to the nearest point
//! drawn on the other surface (a k-d tree, `kiddo`), both directions pooled.

use super::Triangle;
use kiddo::{KdTree, SquaredEuclidean};
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;

/// Points drawn on each surface by default: at 100 000 points on a 1 m TANGO the spacing
/// (a few mm) adds well under a millimetre to the mean.
pub const DEFAULT_SAMPLES: usize = 100_000;
/// Seed of the surface samples.
pub const SEED: u64 = 0x0c4a_3f3e;

/// A symmetric Chamfer distance, in the surfaces' units (metres for the simulator's scenes).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Chamfer {
    /// Mean over both directions: (mean of A -> B + mean of B -> A) / 2.
    pub mean: f64,
    /// 95th percentile of the pooled distances of both directions.
    pub p95: f64,
    /// Points drawn on each surface.
    pub samples: usize,
}

/// The symmetric Chamfer distance between surfaces `a` and `b` with `samples` points drawn
/// uniformly by area on each. `None` when either has no area (or a non-finite corner).
pub fn chamfer_distance(a: &[Triangle], b: &[Triangle], samples: usize) -> Option<Chamfer> {
    let samples = samples.max(1);
    let points_a = sample_surface(a, samples, SEED)?;
    let points_b = sample_surface(b, samples, SEED ^ 1)?;
    let a_to_b = nearest_distances(&points_a, &points_b);
    let b_to_a = nearest_distances(&points_b, &points_a);
    let mean = |d: &[f64]| d.iter().sum::<f64>() / d.len() as f64;
    let mut pooled: Vec<f64> = a_to_b.iter().chain(&b_to_a).copied().collect();
    pooled.sort_by(f64::total_cmp);
    let rank = ((pooled.len() as f64 * 0.95).ceil() as usize).clamp(1, pooled.len()) - 1;
    Some(Chamfer {
        mean: 0.5 * (mean(&a_to_b) + mean(&b_to_a)),
        p95: pooled[rank],
        samples,
    })
}

/// `count` points uniformly distributed by area over `triangles` (seeded). `None` when the
/// total area is zero or not finite.
pub fn sample_surface(triangles: &[Triangle], count: usize, seed: u64) -> Option<Vec<[f32; 3]>> {
    let mut cumulative = Vec::with_capacity(triangles.len());
    let mut total = 0.0f64;
    for t in triangles {
        total += area(t);
        cumulative.push(total);
    }
    if !(total.is_finite() && total > 0.0) {
        return None;
    }
    let mut rng = Pcg64::seed_from_u64(seed);
    let points = (0..count)
        .map(|_| {
            let pick = rng.random::<f64>() * total;
            let i = cumulative
                .partition_point(|&c| c <= pick)
                .min(triangles.len() - 1);
            let [a, b, c] = triangles[i].map(|p| p.map(f64::from));
            // Uniform on the triangle: the square root keeps the density even.
            let (r1, r2) = (rng.random::<f64>().sqrt(), rng.random::<f64>());
            let (wa, wb, wc) = (1.0 - r1, r1 * (1.0 - r2), r1 * r2);
            [0, 1, 2].map(|k| (wa * a[k] + wb * b[k] + wc * c[k]) as f32)
        })
        .collect();
    Some(points)
}

fn area(t: &Triangle) -> f64 {
    let [a, b, c] = t.map(|p| p.map(f64::from));
    let (u, v) = (
        [b[0] - a[0], b[1] - a[1], b[2] - a[2]],
        [c[0] - a[0], c[1] - a[1], c[2] - a[2]],
    );
    let n = [
        u[1] * v[2] - u[2] * v[1],
        u[2] * v[0] - u[0] * v[2],
        u[0] * v[1] - u[1] * v[0],
    ];
    0.5 * (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt()
}

/// For each of `from`, the distance to the nearest of `to`.
fn nearest_distances(from: &[[f32; 3]], to: &[[f32; 3]]) -> Vec<f64> {
    let mut tree: KdTree<f32, 3> = KdTree::with_capacity(to.len());
    for (i, p) in to.iter().enumerate() {
        tree.add(p, i as u64);
    }
    from.iter()
        .map(|p| (tree.nearest_one::<SquaredEuclidean>(p).distance as f64).sqrt())
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f32::consts::PI;

    /// A UV sphere of `radius` about `centre`, fine enough that its facets sit within 0.1 %
    /// of the radius of the true sphere.
    fn sphere(radius: f32, centre: [f32; 3]) -> Vec<Triangle> {
        let (rings, segments) = (96, 192);
        let point = |i: usize, j: usize| {
            let (theta, phi) = (
                PI * i as f32 / rings as f32,
                2.0 * PI * j as f32 / segments as f32,
            );
            [
                centre[0] + radius * theta.sin() * phi.cos(),
                centre[1] + radius * theta.sin() * phi.sin(),
                centre[2] + radius * theta.cos(),
            ]
        };
        let mut triangles = Vec::new();
        for i in 0..rings {
            for j in 0..segments {
                let (a, b, c, d) = (
                    point(i, j),
                    point(i + 1, j),
                    point(i + 1, j + 1),
                    point(i, j + 1),
                );
                triangles.push([a, b, c]);
                triangles.push([a, c, d]);
            }
        }
        triangles
    }

    /// The 12 triangles of the axis-aligned cube [lo, lo + 1]^3.
    fn cube(lo: [f32; 3]) -> Vec<Triangle> {
        let corner =
            |x: usize, y: usize, z: usize| [lo[0] + x as f32, lo[1] + y as f32, lo[2] + z as f32];
        let mut triangles = Vec::new();
        for axis in 0..3 {
            for side in 0..2 {
                let at = |u: usize, v: usize| {
                    let mut c = [0; 3];
                    c[axis] = side;
                    c[(axis + 1) % 3] = u;
                    c[(axis + 2) % 3] = v;
                    corner(c[0], c[1], c[2])
                };
                triangles.push([at(0, 0), at(1, 0), at(1, 1)]);
                triangles.push([at(0, 0), at(1, 1), at(0, 1)]);
            }
        }
        triangles
    }

    #[test]
    fn concentric_spheres_are_their_radial_gap_apart() {
        let (inner, outer) = (sphere(1.0, [0.2, -0.1, 0.3]), sphere(1.1, [0.2, -0.1, 0.3]));
        let c = chamfer_distance(&inner, &outer, 50_000).unwrap();
        // Every point is 0.1 from the other sphere; the nearest drawn point is a little
        // further (the spacing of 50 000 points on the spheres is about 0.016).
        assert!((0.099..0.103).contains(&c.mean), "{c:?}");
        assert!((0.099..0.106).contains(&c.p95), "{c:?}");
        // Symmetric up to the draws, and the same draws give the same number.
        let swapped = chamfer_distance(&outer, &inner, 50_000).unwrap();
        assert!((swapped.mean - c.mean).abs() < 1e-3, "{swapped:?} {c:?}");
        assert_eq!(chamfer_distance(&inner, &outer, 50_000), Some(c));
    }

    #[test]
    fn a_surface_is_at_zero_from_itself_and_offset_cubes_are_not() {
        let a = cube([0.0; 3]);
        let same = chamfer_distance(&a, &a, 20_000).unwrap();
        // Only the sampling spacing remains: the mean nearest-neighbour distance of 20 000
        // points on 6 unit faces is about 0.5 * sqrt(6 / 20 000) = 0.009.
        assert!(same.mean < 0.012, "{same:?}");
        // Shifted by 0.3 along x. From A: the face x = 0 is 0.3 from B (area 1); the face
        // x = 1, inside B, is min(0.3, distance to the square's edge) from B's sides and end,
        // mean (1 - 0.4^3) / 6 = 0.156; a strip 0.3 wide of each side face is 0.3 - x from B,
        // mean 0.15 over area 0.3; the rest of the side faces lie on B. So
        // (0.3 + 0.156 + 4 * 0.3 * 0.15) / 6 = 0.106 each way, plus the sampling spacing on
        // the shared faces; a sixth of the points are 0.3 away, so that is the 95th percentile.
        let b = cube([0.3, 0.0, 0.0]);
        let shifted = chamfer_distance(&a, &b, 20_000).unwrap();
        assert!((0.104..0.115).contains(&shifted.mean), "{shifted:?}");
        assert!((0.295..0.305).contains(&shifted.p95), "{shifted:?}");
        assert_eq!(chamfer_distance(&a, &[], 10), None);
    }
}
