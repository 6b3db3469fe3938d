//! The scene box of an unknown target, found from the data: a visual hull carved on a voxel
//! grid from each frame's foreground (its mask, or the bright target against the black sky)
//! and its labelled pose, then the hull's bounds plus a margin. And the rule that picks a
//! dataset's box ([`choose_scene_box`]): a box the user states (a flag, then a config file
//! that sets one) wins over the data's own (a truth file), which wins over one found here.
//!
//! Why a hull and not the cameras alone: the cameras tell where the target is (their axes
//! converge on it) but not how big it is; the silhouettes do. A voxel is judged by its whole
//! footprint in each view, not its centre, so a boom thinner than a voxel is kept. Label noise
//! moves a silhouette by a few pixels in some views, so a voxel is removed only when more than
//! a small share of the views that see it see only sky there (dilating the silhouettes instead
//! inflated thin targets by the dilation in every view: measured on boxes seen from 80 views
//! with 0-1 degree label noise).

use crate::dataset::{Dataset, Frame, SceneBoxOrigin};
use crate::error::{HostError, Result as HostResult};
use glam::{DMat3, DVec3, Vec3};
use rayon::prelude::*;
use std::fmt;

/// Voxels per side of the coarse pass (over the cameras' common view) and of the fine pass
/// (over the coarse hull).
const COARSE: usize = 48;
const FINE: usize = 96;
/// A voxel must be inside at least this share of the frames to be judged at all.
const MIN_VIEW_SHARE: f64 = 0.5;

/// How carving judges a voxel, and how much is added around the hull.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Carving {
    /// A voxel is sky once more than this share of the views that see it see sky there
    /// (absorbs label noise and the odd bad mask).
    pub sky_vote_tolerance: f64,
    /// Added on every side, as a share of the hull's extent along that axis.
    pub margin_share: f32,
}

impl Default for Carving {
    fn default() -> Self {
        Carving {
            sky_vote_tolerance: 0.03,
            margin_share: 0.03,
        }
    }
}
/// Without masks, a pixel is target when its Rec.601 luma is above this (8-bit).
pub const SKY_LUMA: u8 = 24;
/// How many times the search volume may double when the hull touches its border.
const MAX_GROWTH: usize = 4;

/// Where a frame's foreground came from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Silhouettes {
    /// Every frame has a mask.
    Masks,
    /// No frame has a mask: pixels brighter than the sky ([`SKY_LUMA`]).
    BrightTarget,
    /// Masks where present, brightness elsewhere.
    Mixed,
}

/// A box found from the data, with what it was found from.
#[derive(Clone, Debug, PartialEq)]
pub struct FoundBox {
    /// Lower corner, world units (the poses' units), margin included.
    pub min: [f32; 3],
    /// Upper corner, world units, margin included.
    pub max: [f32; 3],
    /// Frames carved from (those with a valid camera, pose and pixels).
    pub frames: usize,
    /// Where the frames' foreground came from.
    pub silhouettes: Silhouettes,
    /// Voxels per side of the final carving pass.
    pub grid: usize,
    /// Margin added on every side, as a share of the hull's extent along that axis.
    pub margin_share: f32,
}

impl fmt::Display for FoundBox {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let source = match self.silhouettes {
            Silhouettes::Masks => "the masks".to_string(),
            Silhouettes::BrightTarget => {
                format!("the bright target against the sky (luma > {SKY_LUMA}, no masks)")
            }
            Silhouettes::Mixed => "the masks (brightness where a frame has none)".to_string(),
        };
        write!(
            f,
            "scene box [{:.3}, {:.3}, {:.3}] .. [{:.3}, {:.3}, {:.3}], found from {source} and the \
             labelled poses of {} frames (visual hull on a {}^3 grid, {:.0}% margin per side)",
            self.min[0],
            self.min[1],
            self.min[2],
            self.max[0],
            self.max[1],
            self.max[2],
            self.frames,
            self.grid,
            self.margin_share * 100.0
        )
    }
}

/// Why no box could be found.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum BoxError {
    /// Fewer than 2 frames have a valid camera, pose and pixels; holds how many do.
    #[error(
        "cannot find a scene box: {0} usable frames (need at least 2 with a valid camera and pose)"
    )]
    TooFewFrames(usize),
    /// The optical axes are (nearly) parallel, or meet behind most of the cameras.
    #[error(
        "cannot find a scene box: the camera axes do not converge on a point in front of the cameras"
    )]
    NoFocus,
    /// No frame shows a single foreground pixel.
    #[error("cannot find a scene box: no frame shows any target pixel (every silhouette is empty)")]
    EmptySilhouettes,
    /// Every voxel was carved away: the silhouettes and poses do not agree on any point.
    #[error(
        "cannot find a scene box: the silhouettes disagree, no point in space is target in the views that see it"
    )]
    EmptyHull,
    /// The hull still touched the border after the search volume grew to its limit; holds
    /// the search volume's width in world units.
    #[error(
        "cannot find a scene box: the target fills the views out to the edge of a search volume {0:.3e} wide"
    )]
    Unbounded(f64),
}

/// One frame reduced to what carving needs: world-to-camera transform, intrinsics and its
/// foreground as a pyramid of bitmaps (level 0 the pixels, each next level the OR of 2x2
/// cells), so a voxel's whole footprint is tested in a few lookups.
struct View {
    rotation: DMat3,
    translation: DVec3,
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    foreground: Vec<Bitmap>,
}

/// One pyramid level.
struct Bitmap {
    width: usize,
    height: usize,
    cells: Vec<bool>,
}

impl Bitmap {
    /// The next pyramid level: each cell is set when any of its (up to) 2x2 cells is.
    fn coarser(&self) -> Bitmap {
        let (width, height) = (self.width.div_ceil(2), self.height.div_ceil(2));
        let mut cells = vec![false; width * height];
        for y in 0..self.height {
            for x in 0..self.width {
                if self.cells[y * self.width + x] {
                    cells[(y / 2) * width + x / 2] = true;
                }
            }
        }
        Bitmap {
            width,
            height,
            cells,
        }
    }
}

impl View {
    /// Whether the box `[lo, hi]` (a voxel) projects onto target: `Some(true)` when any pixel
    /// its footprint (the bounding rectangle of its projected corners) covers is foreground,
    /// `Some(false)` when the footprint lies in the image and is all sky, `None` when this view
    /// cannot tell (a corner behind the camera, or the footprint leaves the image without
    /// touching target there). Testing the footprint, not the centre, keeps structures thinner
    /// than a voxel (a boom, a panel edge-on) that a centre sample would miss.
    fn sees(&self, lo: DVec3, hi: DVec3) -> Option<bool> {
        let (mut u0, mut v0) = (f64::INFINITY, f64::INFINITY);
        let (mut u1, mut v1) = (f64::NEG_INFINITY, f64::NEG_INFINITY);
        for corner in 0..8 {
            let pick = |axis: usize, low: f64, high: f64| {
                if corner >> axis & 1 == 1 { high } else { low }
            };
            let p = DVec3::new(
                pick(0, lo.x, hi.x),
                pick(1, lo.y, hi.y),
                pick(2, lo.z, hi.z),
            );
            let q = self.rotation * p + self.translation;
            if q.z <= 1e-9 {
                return None;
            }
            let (u, v) = (self.fx * q.x / q.z + self.cx, self.fy * q.y / q.z + self.cy);
            (u0, u1, v0, v1) = (u0.min(u), u1.max(u), v0.min(v), v1.max(v));
        }
        let base = &self.foreground[0];
        let (w, h) = (base.width as f64, base.height as f64);
        if !(u1 >= 0.0 && v1 >= 0.0 && u0 < w && v0 < h) {
            return None;
        }
        let leaves_image = u0 < 0.0 || v0 < 0.0 || u1 >= w || v1 >= h;
        let x0 = u0.max(0.0) as usize;
        let y0 = v0.max(0.0) as usize;
        let x1 = (u1.min(w - 1.0)) as usize;
        let y1 = (v1.min(h - 1.0)) as usize;
        // The finest level where the footprint spans at most 8x8 cells: the pixels themselves
        // for a small footprint, else a superset at most one cell (an eighth of it) wider.
        let level = (0..self.foreground.len())
            .find(|&l| (x1 >> l) - (x0 >> l) < 8 && (y1 >> l) - (y0 >> l) < 8)
            .unwrap_or(self.foreground.len() - 1);
        let map = &self.foreground[level];
        let target = ((y0 >> level)..=(y1 >> level).min(map.height - 1)).any(|y| {
            ((x0 >> level)..=(x1 >> level).min(map.width - 1)).any(|x| map.cells[y * map.width + x])
        });
        if target {
            Some(true)
        } else if leaves_image {
            None
        } else {
            Some(false)
        }
    }
}

/// Find the scene box of the target the frames show.
pub fn find_scene_box(frames: &[Frame]) -> Result<FoundBox, BoxError> {
    find_scene_box_with(frames, &Carving::default())
}

/// [`find_scene_box`] with chosen carving parameters.
pub fn find_scene_box_with(frames: &[Frame], carving: &Carving) -> Result<FoundBox, BoxError> {
    let usable: Vec<&Frame> = frames
        .iter()
        .filter(|f| {
            f.camera.is_valid()
                && f.pose.is_finite()
                && f.pixels.len() == f.camera.pixel_count() * 3
        })
        .collect();
    if usable.len() < 2 {
        return Err(BoxError::TooFewFrames(usable.len()));
    }
    let masked = usable.iter().filter(|f| f.mask.is_some()).count();
    let silhouettes = match masked {
        0 => Silhouettes::BrightTarget,
        m if m == usable.len() => Silhouettes::Masks,
        _ => Silhouettes::Mixed,
    };
    let views: Vec<View> = usable.par_iter().map(|f| view_of(f)).collect();
    if views.iter().all(|v| !v.foreground[0].cells.contains(&true)) {
        return Err(BoxError::EmptySilhouettes);
    }

    let (focus, mut half) = search_volume(&usable)?;
    let mut growth = 0;
    let (coarse, lo, hi) = loop {
        let (lo, hi) = (focus - DVec3::splat(half), focus + DVec3::splat(half));
        let hull =
            carve(&views, lo, hi, COARSE, carving.sky_vote_tolerance).ok_or(BoxError::EmptyHull)?;
        if !hull.touches_border {
            break (hull, lo, hi);
        }
        if growth == MAX_GROWTH {
            return Err(BoxError::Unbounded(2.0 * half));
        }
        growth += 1;
        half *= 2.0;
    };
    // The fine pass covers the coarse hull with one coarse voxel to spare on every side.
    let coarse_voxel = (hi - lo) / COARSE as f64;
    let fine = carve(
        &views,
        coarse.min - coarse_voxel,
        coarse.max + coarse_voxel,
        FINE,
        carving.sky_vote_tolerance,
    )
    .ok_or(BoxError::EmptyHull)?;
    let extent = (fine.max - fine.min).max(DVec3::splat(1e-9));
    // A flat target (a panel seen edge-on) still gets a box with some depth.
    let extent = extent.max(DVec3::splat(extent.max_element() * 0.05));
    let centre = 0.5 * (fine.min + fine.max);
    let half = 0.5 * extent * (1.0 + 2.0 * carving.margin_share as f64);
    Ok(FoundBox {
        min: (centre - half).as_vec3().to_array(),
        max: (centre + half).as_vec3().to_array(),
        frames: views.len(),
        silhouettes,
        grid: FINE,
        margin_share: carving.margin_share,
    })
}

/// A box the user stated, with what stated it (`--scene-box`, a config file).
#[derive(Clone, Debug, PartialEq)]
pub struct StatedBox {
    /// Lower corner, world units.
    pub min: [f32; 3],
    /// Upper corner, world units.
    pub max: [f32; 3],
    /// What stated it, for messages (e.g. `--scene-box`, a config file's path).
    pub by: String,
}

/// Set `dataset`'s scene box by the rule: `stated` (the user's) if given, else the data's own,
/// else found from the frames `frames` (the training views, so held-out views play no part).
/// Returns one line saying the box and why.
pub fn choose_scene_box(
    dataset: &mut Dataset,
    stated: Option<StatedBox>,
    frames: &[usize],
) -> HostResult<String> {
    if let Some(stated) = stated {
        dataset.scene_min = stated.min;
        dataset.scene_max = stated.max;
        dataset.scene_box = SceneBoxOrigin::Stated(stated.by);
    }
    let why = match &dataset.scene_box {
        SceneBoxOrigin::Data(what) => format!("from {what}"),
        SceneBoxOrigin::Stated(by) => format!("given by {by}"),
        SceneBoxOrigin::Found(account) => account.clone(),
        SceneBoxOrigin::Unknown => {
            let views: Vec<Frame> = frames
                .iter()
                .filter_map(|&i| dataset.frames.get(i).cloned())
                .collect();
            let found = find_scene_box(&views).map_err(|e| {
                HostError::invalid(
                    &dataset.source,
                    format!(
                        "{e}; the data gives no scene box (no truth.json): state one with \
                         --scene-box xmin,ymin,zmin,xmax,ymax,zmax"
                    ),
                )
            })?;
            dataset.scene_min = found.min;
            dataset.scene_max = found.max;
            dataset.scene_box = SceneBoxOrigin::Found(found.to_string());
            found.to_string()
        }
    };
    let account = match &dataset.scene_box {
        SceneBoxOrigin::Found(_) => why.clone(),
        _ => format!(
            "scene box {}, {why}",
            box_text(dataset.scene_min, dataset.scene_max)
        ),
    };
    if dataset.target_centred {
        let (min, max) = (Vec3::from(dataset.scene_min), Vec3::from(dataset.scene_max));
        let inside = frames
            .iter()
            .filter_map(|&i| dataset.frames.get(i))
            .find(|frame| {
                let c = frame.pose.center;
                c.cmpge(min).all() && c.cmple(max).all()
            });
        if let Some(frame) = inside {
            let c = frame.pose.center;
            return Err(HostError::invalid(
                &dataset.source,
                format!(
                    "frame `{}`: its label puts the camera at [{:.3}, {:.3}, {:.3}], inside \
                     the target's {account}: a camera cannot be inside its target (check the \
                     label or the box)",
                    frame.name, c.x, c.y, c.z
                ),
            ));
        }
    }
    Ok(account)
}

/// A box as `[xmin, ymin, zmin] .. [xmax, ymax, zmax]`, three decimals (millimetres when the
/// units are metres).
///
/// ```
/// use orbit_nerf_host::scene_box::{box_text, parse_box};
///
/// let (min, max) = parse_box("-1.5, -1.5, -1, 1.5, 1.5, 2").unwrap();
/// assert_eq!((min, max), ([-1.5, -1.5, -1.0], [1.5, 1.5, 2.0]));
/// assert_eq!(box_text(min, max), "[-1.500, -1.500, -1.000] .. [1.500, 1.500, 2.000]");
/// ```
pub fn box_text(min: [f32; 3], max: [f32; 3]) -> String {
    format!(
        "[{:.3}, {:.3}, {:.3}] .. [{:.3}, {:.3}, {:.3}]",
        min[0], min[1], min[2], max[0], max[1], max[2]
    )
}

/// Parse a box typed as `xmin,ymin,zmin,xmax,ymax,zmax`: six finite numbers, each min below
/// its max. The error is a message for the user.
///
/// ```
/// use orbit_nerf_host::scene_box::parse_box;
///
/// assert!(parse_box("0,0,0,1,1,1").is_ok());
/// assert!(parse_box("0,0,0,1,1").is_err()); // five numbers
/// assert!(parse_box("0,0,2,1,1,1").is_err()); // z min above z max
/// assert!(parse_box("0,0,0,1,1,inf").is_err());
/// ```
pub fn parse_box(text: &str) -> std::result::Result<([f32; 3], [f32; 3]), String> {
    let values: Vec<f32> = text
        .split(',')
        .map(|v| {
            v.trim()
                .parse::<f32>()
                .map_err(|_| format!("`{}` is not a number", v.trim()))
        })
        .collect::<std::result::Result<_, _>>()?;
    let [x0, y0, z0, x1, y1, z1] = values[..] else {
        return Err(format!(
            "expected six numbers xmin,ymin,zmin,xmax,ymax,zmax, found {}",
            values.len()
        ));
    };
    let (min, max) = ([x0, y0, z0], [x1, y1, z1]);
    for axis in 0..3 {
        if !(min[axis].is_finite() && max[axis].is_finite()) {
            return Err("every number must be finite".into());
        }
        if min[axis] >= max[axis] {
            return Err(format!(
                "{} min {} is not below its max {}",
                ["x", "y", "z"][axis],
                min[axis],
                max[axis]
            ));
        }
    }
    Ok((min, max))
}

fn view_of(frame: &Frame) -> View {
    let (rotation, translation) = frame.pose.world_to_camera();
    let c = frame.camera;
    let (width, height) = (c.width as usize, c.height as usize);
    let foreground: Vec<bool> = match &frame.mask {
        Some(mask) if mask.len() == width * height => mask.iter().map(|&m| m >= 128).collect(),
        _ => frame
            .pixels
            .chunks_exact(3)
            .map(|p| {
                let luma = 0.299 * p[0] as f32 + 0.587 * p[1] as f32 + 0.114 * p[2] as f32;
                luma > SKY_LUMA as f32
            })
            .collect(),
    };
    let mut pyramid = vec![Bitmap {
        width,
        height,
        cells: foreground,
    }];
    while let Some(last) = pyramid.last().filter(|b| b.width > 1 || b.height > 1) {
        let next = last.coarser();
        pyramid.push(next);
    }
    View {
        rotation: rotation.as_dmat3(),
        translation: translation.as_dvec3(),
        fx: c.fx as f64,
        fy: c.fy as f64,
        cx: c.cx as f64,
        cy: c.cy as f64,
        foreground: pyramid,
    }
}

/// The point nearest to every optical axis (least squares), and half the side of a cube
/// around it that every camera's view would hold at that distance (the median camera's).
pub fn search_volume(frames: &[&Frame]) -> Result<(DVec3, f64), BoxError> {
    let axes: Vec<(DVec3, DVec3)> = frames
        .iter()
        .map(|f| {
            (
                f.pose.center.as_dvec3(),
                (f.pose.rotation * Vec3::Z).as_dvec3().normalize(),
            )
        })
        .collect();
    let focus = focus_of_axes(&axes).ok_or(BoxError::NoFocus)?;
    let mut view_half: Vec<f64> = frames
        .iter()
        .zip(&axes)
        .map(|(f, (origin, _))| {
            let c = f.camera;
            let spread = (c.width as f64 / c.fx as f64).max(c.height as f64 / c.fy as f64);
            0.5 * spread * origin.distance(focus)
        })
        .collect();
    view_half.sort_by(f64::total_cmp);
    let half = view_half[view_half.len() / 2];
    if !(half.is_finite() && half > 0.0) {
        return Err(BoxError::NoFocus);
    }
    Ok((focus, half))
}

/// Least-squares point nearest to every axis `(origin, unit direction)`:
/// `sum (I - d d^T) (p - o) = 0`. `None` when the axes are (nearly) parallel or the point is
/// behind most of them.
pub fn focus_of_axes(axes: &[(DVec3, DVec3)]) -> Option<DVec3> {
    let mut normal = DMat3::ZERO;
    let mut rhs = DVec3::ZERO;
    for &(origin, d) in axes {
        let projector = DMat3::IDENTITY - DMat3::from_cols(d * d.x, d * d.y, d * d.z);
        normal += projector;
        rhs += projector * origin;
    }
    let n = axes.len() as f64;
    // det(normal) / n^3 is the product of the normalised eigenvalues; near zero when every
    // axis is (nearly) parallel to one direction.
    if axes.is_empty() || normal.determinant() / (n * n * n) < 1e-4 {
        return None;
    }
    let focus = normal.inverse() * rhs;
    let in_front = axes
        .iter()
        .filter(|(o, d)| (focus - *o).dot(*d) > 0.0)
        .count();
    (focus.is_finite() && in_front * 2 >= axes.len()).then_some(focus)
}

/// Bounds of the voxels that survive carving.
struct Hull {
    min: DVec3,
    max: DVec3,
    touches_border: bool,
}

/// Carve an `n`^3 grid over `[lo, hi]`: a voxel stays when at least [`MIN_VIEW_SHARE`] of the
/// views can judge it ([`View::sees`]) and at most `tolerance` of those see only sky there. Returns the survivors' bounds (voxel faces), `None` if none survives.
fn carve(views: &[View], lo: DVec3, hi: DVec3, n: usize, tolerance: f64) -> Option<Hull> {
    let voxel = (hi - lo) / n as f64;
    let min_views = ((MIN_VIEW_SHARE * views.len() as f64).ceil() as usize).max(1);
    let keep = |i: usize, j: usize, k: usize| {
        let corner = lo + voxel * DVec3::new(i as f64, j as f64, k as f64);
        let (mut seen, mut sky) = (0usize, 0usize);
        for view in views {
            match view.sees(corner, corner + voxel) {
                Some(true) => seen += 1,
                Some(false) => {
                    seen += 1;
                    sky += 1;
                    // Enough sky votes already: even if every remaining view saw target the
                    // voxel would go.
                    if sky as f64 > tolerance * views.len() as f64 {
                        return false;
                    }
                }
                None => {}
            }
        }
        seen >= min_views && sky as f64 <= tolerance * seen as f64
    };
    // Per z slice: the survivors' index bounds. Slices are independent, so the result does not
    // depend on the thread count.
    let slices: Vec<Option<([usize; 3], [usize; 3])>> = (0..n)
        .into_par_iter()
        .map(|k| {
            let mut bounds: Option<([usize; 3], [usize; 3])> = None;
            for j in 0..n {
                for i in 0..n {
                    if keep(i, j, k) {
                        let b = bounds.get_or_insert(([i, j, k], [i, j, k]));
                        b.0 = [b.0[0].min(i), b.0[1].min(j), k];
                        b.1 = [b.1[0].max(i), b.1[1].max(j), k];
                    }
                }
            }
            bounds
        })
        .collect();
    let (first, last) = slices.into_iter().flatten().reduce(|a, b| {
        (
            [a.0[0].min(b.0[0]), a.0[1].min(b.0[1]), a.0[2].min(b.0[2])],
            [a.1[0].max(b.1[0]), a.1[1].max(b.1[1]), a.1[2].max(b.1[2])],
        )
    })?;
    let at = |idx: [usize; 3]| DVec3::new(idx[0] as f64, idx[1] as f64, idx[2] as f64);
    Some(Hull {
        min: lo + voxel * at(first),
        max: lo + voxel * (at(last) + DVec3::ONE),
        touches_border: first.contains(&0) || last.contains(&(n - 1)),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use orbit_nerf_core::{Camera, Pose};

    /// A camera at `eye` looking at `target` (OpenCV axes: y down).
    fn look_at(eye: Vec3, target: Vec3) -> Pose {
        let z = (target - eye).normalize();
        let up = if z.y.abs() > 0.9 { Vec3::X } else { Vec3::Y };
        let x = up.cross(z).normalize();
        let y = z.cross(x);
        Pose {
            rotation: glam::Mat3::from_cols(x, y, z),
            center: eye,
        }
    }

    /// Frames of an axis-aligned box `[lo, hi]` seen from `count` directions spread over the
    /// sphere (Fibonacci), each looking at `aim`: the box's silhouette as mask (if `masks`)
    /// and as bright pixels on black.
    fn box_frames(
        lo: Vec3,
        hi: Vec3,
        aim: Vec3,
        distance: f32,
        count: usize,
        masks: bool,
    ) -> Vec<Frame> {
        boxes_frames(&[(lo, hi)], aim, distance, count, masks)
    }

    /// [`box_frames`] for a target made of several boxes.
    fn boxes_frames(
        boxes: &[(Vec3, Vec3)],
        aim: Vec3,
        distance: f32,
        count: usize,
        masks: bool,
    ) -> Vec<Frame> {
        let camera = Camera {
            width: 192,
            height: 128,
            fx: 160.0,
            fy: 160.0,
            cx: 96.0,
            cy: 64.0,
        };
        (0..count)
            .map(|n| {
                let t = (n as f32 + 0.5) / count as f32;
                let polar = (1.0 - 2.0 * t).acos();
                let azimuth = n as f32 * 2.399_963;
                let dir = Vec3::new(
                    polar.sin() * azimuth.cos(),
                    polar.sin() * azimuth.sin(),
                    polar.cos(),
                );
                let pose = look_at(aim + dir * distance, aim);
                let mut mask = vec![0u8; camera.pixel_count()];
                for j in 0..camera.height as u32 {
                    for i in 0..camera.width as u32 {
                        let d = pose.rotation * camera.pixel_direction(i, j);
                        let o = pose.center;
                        // Slab test of the pixel's ray against each box.
                        let inv = d.recip();
                        let hit = boxes.iter().any(|&(lo, hi)| {
                            let t0 = (lo - o) * inv;
                            let t1 = (hi - o) * inv;
                            let near = t0.min(t1).max_element();
                            let far = t0.max(t1).min_element();
                            far >= near.max(0.0)
                        });
                        if hit {
                            mask[(j * camera.width as u32 + i) as usize] = 255;
                        }
                    }
                }
                let pixels = mask.iter().flat_map(|&m| [m / 2; 3]).collect();
                Frame {
                    name: format!("view{n}"),
                    camera,
                    pose,
                    pixels,
                    mask: masks.then_some(mask),
                    alpha_composited: false,
                }
            })
            .collect()
    }

    /// `found` holds `[lo, hi]` and is at most `max_ratio` times its extent on every axis.
    fn assert_holds_and_fits(found: &FoundBox, lo: Vec3, hi: Vec3, max_ratio: f32) {
        for axis in 0..3 {
            assert!(
                found.min[axis] <= lo[axis] && found.max[axis] >= hi[axis],
                "axis {axis}: {found} does not hold [{lo}, {hi}]"
            );
            let ratio = (found.max[axis] - found.min[axis]) / (hi[axis] - lo[axis]);
            assert!(
                ratio <= max_ratio,
                "axis {axis}: {ratio:.3}x the true extent ({found})"
            );
        }
    }

    #[test]
    fn an_off_centre_flat_box_is_found_from_masks_and_from_brightness() {
        // A panel-like target, not centred on the origin, with the cameras aimed off it. Its
        // thin side spans about 10 px: the views that could carve just above its faces are the
        // few grazing ones, within the vote tolerance, so that axis may grow up to 1.5x.
        let lo = Vec3::new(-0.9, 0.2, -0.1);
        let hi = Vec3::new(1.1, 0.8, 0.15);
        for masks in [true, false] {
            let frames = box_frames(lo, hi, Vec3::new(0.2, 0.4, 0.0), 4.0, 60, masks);
            let found = find_scene_box(&frames).unwrap();
            assert_eq!(
                found.silhouettes,
                if masks {
                    Silhouettes::Masks
                } else {
                    Silhouettes::BrightTarget
                }
            );
            assert_holds_and_fits(&found, lo, hi, 1.5);
        }
    }

    #[test]
    fn a_boom_thinner_than_a_voxel_is_kept() {
        // A body with a 2 cm boom reaching 0.6 m out along +y: about 1 px wide in the views
        // and less than a fine voxel across, so only footprints, not voxel centres, keep it.
        let body = (Vec3::new(-0.3, -0.2, -0.2), Vec3::new(0.3, 0.2, 0.2));
        let boom = (Vec3::new(-0.01, 0.2, -0.01), Vec3::new(0.01, 0.8, 0.01));
        let frames = boxes_frames(&[body, boom], Vec3::ZERO, 3.0, 60, true);
        let found = find_scene_box(&frames).unwrap();
        assert_holds_and_fits(&found, body.0, boom.1.max(body.1), 1.3);
    }

    /// Turn every label by `degrees` about a seeded random axis, as noisy labels are.
    fn perturb(frames: &mut [Frame], degrees: f32) {
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut uniform = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 40) as f32 / (1u64 << 24) as f32 * 2.0 - 1.0
        };
        for f in frames {
            let axis = Vec3::new(uniform(), uniform(), uniform()).normalize();
            let turn = glam::Mat3::from_axis_angle(axis, degrees.to_radians());
            f.pose.rotation = turn * f.pose.rotation;
        }
    }

    #[test]
    fn label_noise_of_a_degree_keeps_the_true_bounds_inside() {
        // A TDRS-sized target (0.9 x 0.45 x 0.47 m) filling about half of each view.
        let lo = Vec3::new(-0.45, -0.2, -0.25);
        let hi = Vec3::new(0.45, 0.25, 0.22);
        for degrees in [0.5, 1.0] {
            let mut frames = box_frames(lo, hi, Vec3::ZERO, 3.0, 80, true);
            perturb(&mut frames, degrees);
            let found = find_scene_box(&frames).unwrap();
            assert_holds_and_fits(&found, lo, hi, 1.3);
        }
    }

    #[test]
    fn a_target_much_larger_than_the_first_search_volume_is_still_held() {
        // Cameras close to a 1 km target see only parts of it; the hull grows the volume.
        let lo = Vec3::splat(-500.0);
        let hi = Vec3::splat(500.0);
        let frames = box_frames(lo, hi, Vec3::ZERO, 3000.0, 40, true);
        let found = find_scene_box(&frames).unwrap();
        assert_holds_and_fits(&found, lo, hi, 1.3);
    }

    #[test]
    fn degenerate_inputs_give_one_clear_error() {
        let lo = Vec3::splat(-0.5);
        let hi = Vec3::splat(0.5);
        let mut frames = box_frames(lo, hi, Vec3::ZERO, 5.0, 12, true);
        assert_eq!(find_scene_box(&frames[..1]), Err(BoxError::TooFewFrames(1)));
        for f in &mut frames {
            f.mask.as_mut().unwrap().fill(0);
        }
        assert_eq!(find_scene_box(&frames), Err(BoxError::EmptySilhouettes));
        // Every camera on one line looking the same way: no point where the axes meet.
        let mut parallel = box_frames(lo, hi, Vec3::ZERO, 5.0, 12, true);
        for (n, f) in parallel.iter_mut().enumerate() {
            f.pose = look_at(
                Vec3::new(0.0, 0.0, -5.0 - n as f32),
                Vec3::new(0.0, 0.0, 10.0),
            );
        }
        assert_eq!(find_scene_box(&parallel), Err(BoxError::NoFocus));
        let message = BoxError::EmptyHull.to_string();
        assert!(message.starts_with("cannot find a scene box"), "{message}");
    }

    #[test]
    fn an_unbounded_hull_reports_the_width_last_searched() {
        // Cameras on a narrow cone round -z, every pixel target: all of them see the voxels far
        // beyond the origin along +z as target, so the hull outgrows every search volume.
        let mut frames = box_frames(
            Vec3::splat(-0.5),
            Vec3::splat(0.5),
            Vec3::ZERO,
            5.0,
            8,
            true,
        );
        let tilt = 15f32.to_radians();
        for (n, f) in frames.iter_mut().enumerate() {
            let azimuth = n as f32 * std::f32::consts::TAU / 8.0;
            let eye = 5.0
                * Vec3::new(
                    tilt.sin() * azimuth.cos(),
                    tilt.sin() * azimuth.sin(),
                    -tilt.cos(),
                );
            f.pose = look_at(eye, Vec3::ZERO);
            f.mask.as_mut().unwrap().fill(255);
        }
        let usable: Vec<&Frame> = frames.iter().collect();
        let (_, first_half) = search_volume(&usable).unwrap();
        let last_width = 2.0 * first_half * 2f64.powi(MAX_GROWTH as i32);
        assert_eq!(
            find_scene_box(&frames),
            Err(BoxError::Unbounded(last_width))
        );
    }

    #[test]
    fn the_stated_box_wins_then_the_datas_then_the_found_one() {
        let (lo, hi) = (Vec3::new(-0.4, -0.3, -0.2), Vec3::new(0.5, 0.3, 0.25));
        let dataset = |origin: SceneBoxOrigin| Dataset {
            source: "set".into(),
            frames: box_frames(lo, hi, Vec3::ZERO, 4.0, 40, true),
            scene_min: [-1.0; 3],
            scene_max: [1.0; 3],
            scene_box: origin,
            background: [0.0; 3],
            target_centred: false,
        };
        let all: Vec<usize> = (0..40).collect();
        let stated = StatedBox {
            min: [-2.0; 3],
            max: [2.0, 3.0, 4.0],
            by: "--scene-box".into(),
        };
        for origin in [
            SceneBoxOrigin::Unknown,
            SceneBoxOrigin::Data("truth.json".into()),
        ] {
            let mut set = dataset(origin);
            let line = choose_scene_box(&mut set, Some(stated.clone()), &all).unwrap();
            assert_eq!((set.scene_min, set.scene_max), (stated.min, stated.max));
            assert!(line.contains("given by --scene-box"), "{line}");
        }
        let mut known = dataset(SceneBoxOrigin::Data("truth.json".into()));
        let line = choose_scene_box(&mut known, None, &all).unwrap();
        assert_eq!((known.scene_min, known.scene_max), ([-1.0; 3], [1.0; 3]));
        assert!(line.contains("from truth.json"), "{line}");
        let mut unknown = dataset(SceneBoxOrigin::Unknown);
        let line = choose_scene_box(&mut unknown, None, &all).unwrap();
        assert!(line.contains("found from the masks"), "{line}");
        assert!(matches!(unknown.scene_box, SceneBoxOrigin::Found(_)));
        for axis in 0..3 {
            assert!(unknown.scene_min[axis] <= lo[axis] && unknown.scene_max[axis] >= hi[axis]);
        }
        // Nothing to find it from: the error says how to state it.
        let mut empty = dataset(SceneBoxOrigin::Unknown);
        let error = choose_scene_box(&mut empty, None, &[])
            .unwrap_err()
            .to_string();
        assert!(error.contains("--scene-box"), "{error}");
    }

    #[test]
    fn a_typed_box_is_six_finite_numbers_each_min_below_its_max() {
        assert_eq!(
            parse_box("-1,-2,-3,1,2,3.5"),
            Ok(([-1.0, -2.0, -3.0], [1.0, 2.0, 3.5]))
        );
        for (text, reason) in [
            ("1,2,3", "six numbers"),
            ("0,0,0,1,1,x", "`x` is not a number"),
            ("0,0,0,1,inf,1", "finite"),
            ("0,0,NaN,1,1,1", "finite"),
            ("0,0,0,1,0,1", "y min 0 is not below its max 0"),
            ("2,0,0,1,1,1", "x min 2"),
        ] {
            let error = parse_box(text).unwrap_err();
            assert!(error.contains(reason), "{text}: {error}");
        }
    }
}
