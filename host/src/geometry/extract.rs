//! The surface of a trained field: densities on a regular grid over the scene box (the core's
//! `density_at`), Naive Surface Nets (`fast-surface-nets`) at a density threshold, and vertex
//! colours rendered by the field along each vertex's normal.

use super::Mesh;
use crate::error::{HostError, Result};
use crate::memory::{self, Part};
use crate::train::to_rgb8;
use fast_surface_nets::ndshape::{RuntimeShape, Shape};
use fast_surface_nets::{SurfaceNetsBuffer, surface_nets};
use orbit_nerf_core::{Config, Executor, MemoryPlan, Trainer};
use std::path::Path;

/// Grid samples along the box's longest side that `export` and the reports use by default.
pub const DEFAULT_RESOLUTION: u32 = 128;
/// Most grid samples along the longest side a user may ask for (2048^3 points is 32 GiB of
/// grid; the memory check refuses what does not fit below that).
pub const MAX_RESOLUTION: u32 = 2048;

/// How the surface is extracted.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfaceOptions {
    /// Grid samples along the longest side of the scene box (cubic voxels, so the shorter
    /// sides get proportionally fewer); from 8 to [`MAX_RESOLUTION`].
    pub resolution: u32,
    /// The density (`sigma`, per length unit, see `Config::length_unit`) the surface passes
    /// through; `None`: [`default_threshold`].
    pub threshold: Option<f32>,
}

impl Default for SurfaceOptions {
    fn default() -> Self {
        SurfaceOptions {
            resolution: DEFAULT_RESOLUTION,
            threshold: None,
        }
    }
}

/// The default surface lies where a segment of 1/`DEFAULT_SEGMENTS` of the box diagonal is
/// half opaque.
const DEFAULT_SEGMENTS: f32 = 128.0;

/// The density at which a segment of 1/128 of the scene box's diagonal is half opaque:
/// `ln 2 * 128 / diagonal`, the diagonal in length units. It depends on the box's
/// shape only, not its size (length units) nor the model's `march_steps`, so one default
/// serves every scene and every training setup (17.1 on any cubic box).
pub fn default_threshold(config: &Config) -> f32 {
    let diagonal = (0..3)
        .map(|a| (config.aabb_max[a] - config.aabb_min[a]) / config.length_unit())
        .map(|side| side * side)
        .sum::<f32>()
        .sqrt();
    std::f32::consts::LN_2 * DEFAULT_SEGMENTS / diagonal
}

/// The density threshold `options` stand for with the model of `trainer`.
pub fn threshold(trainer: &Trainer<'_>, options: &SurfaceOptions) -> f32 {
    options
        .threshold
        .unwrap_or_else(|| default_threshold(trainer.config()))
}

/// The regular grid over the scene box: its sample spacing and counts per axis, with one
/// extra layer outside the box on every side (kept empty, so the surface closes at the box).
struct Grid {
    min: [f32; 3],
    spacing: f32,
    /// Samples per axis including the two outer layers.
    counts: [u32; 3],
}

impl Grid {
    fn new(min: [f32; 3], max: [f32; 3], resolution: u32) -> Grid {
        let longest = (0..3).map(|a| max[a] - min[a]).fold(0.0f32, f32::max);
        let spacing = longest / (resolution - 1) as f32;
        let counts = [0, 1, 2].map(|a| ((max[a] - min[a]) / spacing).floor() as u32 + 1 + 2);
        Grid {
            min,
            spacing,
            counts,
        }
    }

    fn points(&self) -> u64 {
        self.counts.iter().map(|&c| c as u64).product()
    }

    /// World position of grid sample (x, y, z), fractional for vertices; the outer layer is
    /// at index 0.
    fn world(&self, p: [f32; 3]) -> [f32; 3] {
        [0, 1, 2].map(|a| self.min[a] + (p[a] - 1.0) * self.spacing)
    }

    /// A vertex's world position, within the box `min`..`max`: where the surface closes
    /// against the empty outer layer it is cut at the box's faces.
    fn vertex(&self, p: [f32; 3], max: [f32; 3]) -> [f32; 3] {
        let w = self.world(p);
        [0, 1, 2].map(|a| w[a].clamp(self.min[a], max[a]))
    }
}

/// What [`extract_surface`] holds beside the model before the surface is known, for `options`
/// over the scene box of `config`: the signed density grid and the surface-net index map (4
/// bytes each per grid point).
pub fn grid_parts(config: &Config, options: &SurfaceOptions) -> [Part; 2] {
    let grid = Grid::new(
        config.aabb_min,
        config.aabb_max,
        options.resolution.clamp(8, MAX_RESOLUTION),
    );
    let points = grid.points().saturating_mul(4);
    [("density grid", points), ("surface-net index map", points)]
}

/// Bytes per surface vertex of the mesh and its working buffers, an upper bound: surface
/// nets' position, normal, grid point and stride (40) and up to 18 indices (72); the mesh's
/// position, normal and colour, the colour rays' origin, direction and RGB (63); up to six
/// triangles (72).
pub const BYTES_PER_SURFACE_VERTEX: u64 = 256;

/// The surface where the field's density crosses the threshold, inside the trainer's scene
/// box, with unit outward normals and colours: each vertex's colour is what the field renders
/// (appearance `embedding`) on a ray that starts two grid steps outside the surface along the
/// normal and looks back along it, i.e. the surface seen head-on from outside. `file` names
/// the checkpoint in errors; `limit` is the memory limit the model, the grid and then the mesh
/// (its size known from the sampled densities) are checked against before they are built.
/// The surface is closed at the box: where the field is dense at a face, it is cut there.
/// Fails when no surface crosses the threshold, saying what the densities were.
pub fn extract_surface<E: Executor>(
    trainer: &mut Trainer<'_>,
    executor: &E,
    embedding: &[f32],
    options: &SurfaceOptions,
    file: &Path,
    limit: Option<u64>,
) -> Result<Mesh> {
    if !(8..=MAX_RESOLUTION).contains(&options.resolution) {
        return Err(HostError::field(
            file,
            "resolution",
            format!("{} is not from 8 to {MAX_RESOLUTION}", options.resolution),
        ));
    }
    let threshold = threshold(trainer, options);
    if !(threshold.is_finite() && threshold > 0.0) {
        return Err(HostError::field(
            file,
            "threshold",
            format!("{threshold} is not a positive density"),
        ));
    }
    let c = *trainer.config();
    let grid = Grid::new(c.aabb_min, c.aabb_max, options.resolution);
    let [nx, ny, nz] = grid.counts;
    let mut parts = memory::with_arena(&grid_parts(&c, options), &MemoryPlan::new(&c));
    memory::check_plan(file, &parts, limit)?;
    let shape = RuntimeShape::<u32, 3>::new([nx, ny, nz]);
    // Signed values: ln(threshold) - ln(sigma), negative inside. The log keeps the linear
    // interpolation along grid edges meaningful across the densities' orders of magnitude.
    let mut signed = vec![1.0f32; grid.points() as usize];
    let slice = (nx as usize - 2) * (ny as usize - 2);
    let mut positions = vec![[0.0f32; 3]; slice];
    let mut sigma = vec![0.0f32; slice];
    let (mut lowest, mut highest) = (f32::INFINITY, 0.0f32);
    let log_threshold = threshold.ln();
    for z in 1..nz - 1 {
        let mut k = 0;
        for y in 1..ny - 1 {
            for x in 1..nx - 1 {
                positions[k] = grid.world([x as f32, y as f32, z as f32]);
                k += 1;
            }
        }
        trainer
            .density_at(executor, &positions, &mut sigma)
            .map_err(|e| HostError::invalid(file, e.to_string()))?;
        let mut k = 0;
        for y in 1..ny - 1 {
            for x in 1..nx - 1 {
                let s = sigma[k];
                if !s.is_finite() {
                    return Err(HostError::invalid(
                        file,
                        "the field's density is not finite: the checkpoint is broken",
                    ));
                }
                (lowest, highest) = (lowest.min(s), highest.max(s));
                signed[shape.linearize([x, y, z]) as usize] =
                    log_threshold - s.max(f32::MIN_POSITIVE).ln();
                k += 1;
            }
        }
    }
    // One vertex per cell the surface crosses: the mesh's size is known before it is built.
    let surface_cells = surface_cells(&signed, grid.counts);
    parts.push((
        "mesh and its buffers",
        surface_cells.saturating_mul(BYTES_PER_SURFACE_VERTEX),
    ));
    memory::check_plan(file, &parts, limit).map_err(|e| {
        HostError::invalid(
            file,
            format!("{e} (the surface crosses {surface_cells} grid cells: lower --resolution)"),
        )
    })?;
    let mut nets = SurfaceNetsBuffer::default();
    surface_nets(&signed, &shape, [0; 3], [nx - 1, ny - 1, nz - 1], &mut nets);
    drop(signed);
    if nets.indices.is_empty() {
        return Err(HostError::invalid(
            file,
            format!(
                "no surface at density {threshold}: the field's densities in the box run from \
                 {lowest:.3e} to {highest:.3e}; choose a threshold between them (--threshold)"
            ),
        ));
    }
    let normals: Vec<[f32; 3]> = nets
        .normals
        .iter()
        .map(|n| {
            let length = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
            if length > 0.0 && length.is_finite() {
                n.map(|v| v / length)
            } else {
                [0.0, 0.0, 1.0]
            }
        })
        .collect();
    let positions: Vec<[f32; 3]> = (nets.positions.iter())
        .map(|&p| grid.vertex(p, c.aabb_max))
        .collect();
    let colours = vertex_colours(
        trainer,
        executor,
        embedding,
        &positions,
        &normals,
        grid.spacing,
    )
    .map_err(|e| HostError::invalid(file, e.to_string()))?;
    Ok(Mesh {
        positions,
        normals,
        colours,
        triangles: nets
            .indices
            .chunks_exact(3)
            .map(|t| [t[0], t[1], t[2]])
            .collect(),
    })
}

/// Cells of the grid of `counts` samples (values `signed`, x fastest) whose corners are not
/// all on one side of zero: where surface nets places a vertex.
fn surface_cells(signed: &[f32], counts: [u32; 3]) -> u64 {
    let [nx, ny, nz] = counts.map(|c| c as usize);
    let at = |x: usize, y: usize, z: usize| signed[x + nx * (y + ny * z)] < 0.0;
    let mut cells = 0u64;
    for z in 0..nz - 1 {
        for y in 0..ny - 1 {
            for x in 0..nx - 1 {
                let inside = [(0, 0, 0), (1, 0, 0), (0, 1, 0), (1, 1, 0)]
                    .iter()
                    .flat_map(|&(dx, dy, _)| [at(x + dx, y + dy, z), at(x + dx, y + dy, z + 1)])
                    .filter(|&inside| inside)
                    .count();
                cells += u64::from(inside != 0 && inside != 8);
            }
        }
    }
    cells
}

/// The field's colour seen head-on from outside each vertex.
fn vertex_colours<E: Executor>(
    trainer: &mut Trainer<'_>,
    executor: &E,
    embedding: &[f32],
    positions: &[[f32; 3]],
    normals: &[[f32; 3]],
    spacing: f32,
) -> std::result::Result<Vec<[u8; 3]>, orbit_nerf_core::Error> {
    let origins: Vec<[f32; 3]> = positions
        .iter()
        .zip(normals)
        .map(|(p, n)| [0, 1, 2].map(|a| p[a] + 2.0 * spacing * n[a]))
        .collect();
    let directions: Vec<[f32; 3]> = normals.iter().map(|n| n.map(|v| -v)).collect();
    let mut rgb = vec![0.0f32; positions.len() * 3];
    trainer.render_rays(executor, &origins, &directions, embedding, &mut rgb)?;
    Ok(to_rgb8(&rgb)
        .chunks_exact(3)
        .map(|c| [c[0], c[1], c[2]])
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_default_threshold_depends_on_the_box_shape_only() {
        let boxed = |min: [f32; 3], max: [f32; 3]| {
            default_threshold(&Config {
                aabb_min: min,
                aabb_max: max,
                ..Config::DEFAULT
            })
        };
        let cube = boxed([-1.5; 3], [1.5; 3]);
        // ln 2 * 128 / (3 * sqrt 3): the diagonal of a cube of half-side 1.5 units.
        assert!((cube - 17.075).abs() < 1e-3, "{cube}");
        for scale in [1e-3, 0.4, 1e3] {
            let scaled = boxed([-scale; 3], [scale; 3]);
            assert!((scaled - cube).abs() <= 1e-5 * cube, "{scale}: {scaled}");
        }
        let march_steps = default_threshold(&Config {
            march_steps: 64,
            ..Config::DEFAULT
        });
        assert_eq!(march_steps, default_threshold(&Config::DEFAULT));
        // A flat box: the same longest side, a shorter diagonal, a higher threshold.
        assert!(boxed([-1.5, -1.5, -0.1], [1.5, 1.5, 0.1]) > cube);
    }
}
