//! The target spacecraft: a triangle mesh with one material per part, in a BVH (the `bvh`
//! crate) for closest-hit and shadow rays. Built either procedurally (TANGO sized by the
//! SPEED+ landmarks) or from an OBJ file (`tobj`).

use super::scene::{MaterialSpec, Scene, TargetSpec};
use crate::error::{HostError, Result};
use bvh::aabb::{Aabb, Bounded};
use bvh::bounding_hierarchy::BHShape;
use bvh::bvh::{Bvh, BvhNode};
use nalgebra::{Point3, Vector3};
use orbit_nerf_core::glam::Vec3;
use std::path::Path;

/// Thickness of the procedural TANGO solar panel (metres): the landmarks give its corners only.
const PANEL_THICKNESS: f32 = 0.02;
/// Half-width of the square procedural antenna rods (metres).
const ANTENNA_HALF_WIDTH: f32 = 0.008;
/// Margin added around the target's bounding box for the dataset's scene box.
const SCENE_BOX_MARGIN: f32 = 0.10;

/// Reflectance of one part, in linear units.
#[derive(Clone, Debug, PartialEq)]
pub struct Material {
    pub diffuse: Vec3,
    pub specular: Vec3,
    pub shininess: f32,
    grid_pitch: f32,
    grid_contrast: f32,
}

impl Material {
    fn new(spec: &MaterialSpec) -> Material {
        Material {
            diffuse: Vec3::from(spec.diffuse),
            specular: Vec3::from(spec.specular),
            shininess: spec.shininess,
            grid_pitch: spec.grid_pitch_m,
            grid_contrast: spec.grid_contrast,
        }
    }

    /// Diffuse albedo at body-frame point `p` on a surface with normal `n`: the grid lines (cell
    /// busbars, MLI seams) lie on the two body axes across the normal's dominant axis.
    pub fn diffuse_at(&self, p: Vec3, n: Vec3) -> Vec3 {
        if self.grid_pitch <= 0.0 {
            return self.diffuse;
        }
        let a = n.abs();
        let (u, v) = if a.x >= a.y && a.x >= a.z {
            (p.y, p.z)
        } else if a.y >= a.z {
            (p.x, p.z)
        } else {
            (p.x, p.y)
        };
        let line_fraction = 0.08;
        let on_line = |c: f32| (c / self.grid_pitch).rem_euclid(1.0) < line_fraction;
        if on_line(u) || on_line(v) {
            (self.diffuse * (1.0 + self.grid_contrast)).min(Vec3::ONE)
        } else {
            self.diffuse
        }
    }
}

/// A triangle as the ray test wants it: one vertex, two edges, the unit geometric normal.
#[derive(Clone, Debug)]
struct Triangle {
    v0: Vec3,
    e1: Vec3,
    e2: Vec3,
    normal: Vec3,
    material: u16,
    bvh_node: usize,
}

impl Bounded<f32, 3> for Triangle {
    fn aabb(&self) -> Aabb<f32, 3> {
        let (a, b, c) = (self.v0, self.v0 + self.e1, self.v0 + self.e2);
        let (lo, hi) = (a.min(b).min(c), a.max(b).max(c));
        Aabb::with_bounds(Point3::new(lo.x, lo.y, lo.z), Point3::new(hi.x, hi.y, hi.z))
    }
}

impl BHShape<f32, 3> for Triangle {
    fn set_bh_node_index(&mut self, index: usize) {
        self.bvh_node = index;
    }
    fn bh_node_index(&self) -> usize {
        self.bvh_node
    }
}

impl Triangle {
    /// Two-sided Möller-Trumbore: distance along the unit direction, if hit beyond `t_min`.
    #[inline]
    fn intersect(&self, origin: Vec3, dir: Vec3, t_min: f32) -> Option<f32> {
        let p = dir.cross(self.e2);
        let inv_det = 1.0 / self.e1.dot(p);
        let s = origin - self.v0;
        let u = s.dot(p) * inv_det;
        if !(0.0..=1.0).contains(&u) {
            return None;
        }
        let q = s.cross(self.e1);
        let v = dir.dot(q) * inv_det;
        if !(v >= 0.0 && u + v <= 1.0) {
            return None;
        }
        let t = self.e2.dot(q) * inv_det;
        (t > t_min).then_some(t)
    }
}

/// What a ray hit.
#[derive(Clone, Copy, Debug)]
pub struct Hit {
    pub distance: f32,
    /// Unit geometric normal (either side).
    pub normal: Vec3,
    pub material: u16,
}

/// Reusable traversal stack (node index, entry distance), one per thread.
pub type TraversalStack = Vec<(usize, f32)>;

pub struct Target {
    triangles: Vec<Triangle>,
    bvh: Bvh<f32, 3>,
    pub materials: Vec<Material>,
    /// Tight bounding box, body frame, metres.
    pub box_min: Vec3,
    pub box_max: Vec3,
}

/// One named part of the target and its triangles (metres, body frame).
struct Part {
    name: String,
    triangles: Vec<[Vec3; 3]>,
}

impl Target {
    /// Build the scene's target with its per-part materials.
    pub fn build(scene: &Scene) -> Result<Target> {
        let parts = match &scene.spec.target {
            TargetSpec::Tango { landmarks, .. } => {
                let data = scene.resolve_data("target.landmarks", landmarks)?;
                tango_parts(&parse_landmarks(&data.origin(), &data.text()?)?)
            }
            TargetSpec::Mesh { path, scale, .. } => {
                let file = scene.resolve_path("target.path", path)?;
                obj_parts(&file, *scale)?
            }
        };
        for part in scene.spec.target.materials().keys() {
            if part != "default" && !parts.iter().any(|p| &p.name == part) {
                let names: Vec<_> = parts.iter().map(|p| p.name.as_str()).collect();
                return Err(HostError::field(
                    &scene.origin,
                    format!("target.materials.{part}"),
                    format!(
                        "the target has no part `{part}` (parts: {})",
                        names.join(", ")
                    ),
                ));
            }
        }
        let mut materials = Vec::new();
        let mut triangles = Vec::new();
        for part in &parts {
            let material = Material::new(&scene.material(&part.name)?);
            let index = materials
                .iter()
                .position(|m| *m == material)
                .unwrap_or_else(|| {
                    materials.push(material);
                    materials.len() - 1
                });
            triangles.extend(part.triangles.iter().filter_map(|&[a, b, c]| {
                let normal = (b - a).cross(c - a).normalize_or_zero();
                (normal != Vec3::ZERO).then_some(Triangle {
                    v0: a,
                    e1: b - a,
                    e2: c - a,
                    normal,
                    material: index as u16,
                    bvh_node: 0,
                })
            }));
        }
        if triangles.is_empty() {
            return Err(HostError::field(
                &scene.origin,
                "target",
                "the target has no triangles",
            ));
        }
        let (box_min, box_max) =
            triangles
                .iter()
                .fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(lo, hi), t| {
                    let (a, b, c) = (t.v0, t.v0 + t.e1, t.v0 + t.e2);
                    (lo.min(a).min(b).min(c), hi.max(a).max(b).max(c))
                });
        let bvh = Bvh::build(&mut triangles);
        Ok(Target {
            triangles,
            bvh,
            materials,
            box_min,
            box_max,
        })
    }

    /// The target's surface: every triangle's corners (metres, body frame: the frame the
    /// simulated datasets' poses, and so a field trained on them, use).
    pub fn surface(&self) -> Vec<[[f32; 3]; 3]> {
        self.triangles
            .iter()
            .map(|t| [t.v0, t.v0 + t.e1, t.v0 + t.e2].map(|p| p.to_array()))
            .collect()
    }

    pub fn triangle_count(&self) -> usize {
        self.triangles.len()
    }

    pub fn center(&self) -> Vec3 {
        0.5 * (self.box_min + self.box_max)
    }

    /// Radius of the sphere around [`Target::center`] that holds the target.
    pub fn radius(&self) -> f32 {
        0.5 * (self.box_max - self.box_min).length()
    }

    /// The bounding box grown by 10 % of its size on every side (the dataset's scene box).
    pub fn scene_box(&self) -> ([f32; 3], [f32; 3]) {
        let margin = SCENE_BOX_MARGIN * (self.box_max - self.box_min);
        (
            (self.box_min - margin).to_array(),
            (self.box_max + margin).to_array(),
        )
    }

    /// Closest hit along a unit direction.
    pub fn closest_hit(&self, origin: Vec3, dir: Vec3, stack: &mut TraversalStack) -> Option<Hit> {
        let mut best: Option<(f32, usize)> = None;
        self.traverse(origin, dir, stack, |triangle_index, t_best| {
            if let Some(t) = self.triangles[triangle_index].intersect(origin, dir, 0.0)
                && t < t_best
            {
                best = Some((t, triangle_index));
                return Some(t);
            }
            None
        });
        best.map(|(distance, index)| {
            let triangle = &self.triangles[index];
            Hit {
                distance,
                normal: triangle.normal,
                material: triangle.material,
            }
        })
    }

    /// Whether anything lies along the ray beyond `t_min` (shadow rays).
    pub fn occluded(
        &self,
        origin: Vec3,
        dir: Vec3,
        t_min: f32,
        stack: &mut TraversalStack,
    ) -> bool {
        let mut hit = false;
        self.traverse(origin, dir, stack, |triangle_index, _| {
            hit = self.triangles[triangle_index]
                .intersect(origin, dir, t_min)
                .is_some();
            // Any hit ends the search: report a distance closer than every box.
            hit.then_some(f32::NEG_INFINITY)
        });
        hit
    }

    /// Visit the triangles whose BVH boxes the ray enters before the closest hit so far, nearest
    /// box first. `visit(triangle, closest)` returns the new closest distance when it found one.
    fn traverse(
        &self,
        origin: Vec3,
        dir: Vec3,
        stack: &mut TraversalStack,
        mut visit: impl FnMut(usize, f32) -> Option<f32>,
    ) {
        let ray = bvh::ray::Ray::new(
            Point3::new(origin.x, origin.y, origin.z),
            Vector3::new(dir.x, dir.y, dir.z),
        );
        let nodes = &self.bvh.nodes;
        let mut closest = f32::INFINITY;
        stack.clear();
        stack.push((0, 0.0));
        while let Some((node, entry)) = stack.pop() {
            if entry > closest {
                continue;
            }
            match &nodes[node] {
                BvhNode::Leaf { shape_index, .. } => {
                    if let Some(t) = visit(*shape_index, closest) {
                        closest = t;
                    }
                }
                BvhNode::Node {
                    child_l_index,
                    child_l_aabb,
                    child_r_index,
                    child_r_aabb,
                    ..
                } => {
                    let enter = |aabb| {
                        ray.intersection_slice_for_aabb(aabb)
                            .map(|(t, _)| t)
                            .filter(|&t| t <= closest)
                    };
                    match (enter(child_l_aabb), enter(child_r_aabb)) {
                        (Some(l), Some(r)) if l <= r => {
                            stack.extend([(*child_r_index, r), (*child_l_index, l)])
                        }
                        (Some(l), Some(r)) => {
                            stack.extend([(*child_l_index, l), (*child_r_index, r)])
                        }
                        (Some(l), None) => stack.push((*child_l_index, l)),
                        (None, Some(r)) => stack.push((*child_r_index, r)),
                        (None, None) => {}
                    }
                }
            }
        }
    }
}

/// Read the SPEED+ landmarks file: a header line, then one `x,y,z` line (metres) per landmark.
pub fn read_landmarks(path: &Path) -> Result<Vec<Vec3>> {
    let text = std::fs::read_to_string(path).map_err(|e| HostError::io(path, e))?;
    parse_landmarks(path, &text)
}

/// [`read_landmarks`] on the text of the file `path` names.
pub fn parse_landmarks(path: &Path, text: &str) -> Result<Vec<Vec3>> {
    text.lines()
        .enumerate()
        .skip(1)
        .filter(|(_, line)| !line.trim().is_empty())
        .map(|(line_index, line)| {
            let values: Vec<f32> = line
                .split(',')
                .filter_map(|v| v.trim().parse().ok())
                .collect();
            match values[..] {
                [x, y, z] if x.is_finite() && y.is_finite() && z.is_finite() => {
                    Ok(Vec3::new(x, y, z))
                }
                _ => Err(HostError::field(
                    path,
                    format!("line {}", line_index + 1),
                    "expected three numbers x,y,z",
                )),
            }
        })
        .collect()
}

/// TANGO from its 11 landmarks (SPEED+ devkit order): 4 solar-panel corners (top), 4 body
/// corners (bottom), 3 antenna tips. The body box spans the bottom corners up to the panel,
/// the panel spans the top corners, and each antenna is a rod from the nearest point of the
/// body to its tip.
fn tango_parts(landmarks: &[Vec3]) -> Vec<Part> {
    let extent = |points: &[Vec3]| {
        points
            .iter()
            .fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(lo, hi), &p| {
                (lo.min(p), hi.max(p))
            })
    };
    let (panel_lo, panel_hi) = extent(&landmarks[0..4]);
    let (body_lo, body_hi) = extent(&landmarks[4..8]);
    let panel_top = panel_hi.z;
    let panel = (
        Vec3::new(panel_lo.x, panel_lo.y, panel_top - PANEL_THICKNESS),
        Vec3::new(panel_hi.x, panel_hi.y, panel_top),
    );
    let body = (
        Vec3::new(body_lo.x, body_lo.y, body_lo.z),
        Vec3::new(body_hi.x, body_hi.y, panel_top - PANEL_THICKNESS),
    );
    let antennas = landmarks[8..11]
        .iter()
        .flat_map(|&tip| {
            let base = tip.clamp(body.0, body.1);
            // Start the rod a little inside the body so no gap shows at the root.
            let axis = (tip - base).normalize_or_zero();
            rod(base - axis * 2.0 * ANTENNA_HALF_WIDTH, tip)
        })
        .collect();
    vec![
        Part {
            name: "body".into(),
            triangles: cuboid(body.0, body.1),
        },
        Part {
            name: "panel".into(),
            triangles: cuboid(panel.0, panel.1),
        },
        Part {
            name: "antenna".into(),
            triangles: antennas,
        },
    ]
}

fn quad(a: Vec3, b: Vec3, c: Vec3, d: Vec3) -> [[Vec3; 3]; 2] {
    [[a, b, c], [a, c, d]]
}

/// The 12 triangles of an axis-aligned box, wound outwards.
fn cuboid(lo: Vec3, hi: Vec3) -> Vec<[Vec3; 3]> {
    let corner = |x: bool, y: bool, z: bool| {
        Vec3::new(
            if x { hi.x } else { lo.x },
            if y { hi.y } else { lo.y },
            if z { hi.z } else { lo.z },
        )
    };
    let c = |i: u8| corner(i & 1 != 0, i & 2 != 0, i & 4 != 0);
    [
        quad(c(0), c(2), c(3), c(1)), // z-
        quad(c(4), c(5), c(7), c(6)), // z+
        quad(c(0), c(1), c(5), c(4)), // y-
        quad(c(2), c(6), c(7), c(3)), // y+
        quad(c(0), c(4), c(6), c(2)), // x-
        quad(c(1), c(3), c(7), c(5)), // x+
    ]
    .into_iter()
    .flatten()
    .collect()
}

/// A square rod from `start` to `end` with a cap at `end`.
fn rod(start: Vec3, end: Vec3) -> Vec<[Vec3; 3]> {
    let axis = (end - start).normalize_or_zero();
    let (side, up) = axis.any_orthonormal_pair();
    let (side, up) = (side * ANTENNA_HALF_WIDTH, up * ANTENNA_HALF_WIDTH);
    let ring = |centre: Vec3| {
        [
            centre + side + up,
            centre - side + up,
            centre - side - up,
            centre + side - up,
        ]
    };
    let (a, b) = (ring(start), ring(end));
    let mut triangles: Vec<[Vec3; 3]> = (0..4)
        .flat_map(|i| quad(a[i], a[(i + 1) % 4], b[(i + 1) % 4], b[i]))
        .collect();
    triangles.extend(quad(b[0], b[1], b[2], b[3]));
    triangles
}

/// Largest vertex coordinate of a target mesh, metres (a spacecraft is metres to a few
/// hundred metres across).
const MAX_VERTEX_M: f32 = 1e5;

/// The objects/groups of an OBJ file as parts (triangulated, scaled to metres).
fn obj_parts(path: &Path, scale: f32) -> Result<Vec<Part>> {
    let options = tobj::LoadOptions {
        triangulate: true,
        ..Default::default()
    };
    // Materials come from the scene, so a missing or broken .mtl file does not matter.
    let (models, _materials) = tobj::load_obj(path, &options)
        .map_err(|e| HostError::invalid(path, format!("cannot read OBJ mesh: {e}")))?;
    let mut parts: Vec<Part> = Vec::new();
    for model in models {
        let mesh = &model.mesh;
        let vertex = |i: u32| {
            let i = i as usize * 3;
            scale
                * Vec3::new(
                    mesh.positions[i],
                    mesh.positions[i + 1],
                    mesh.positions[i + 2],
                )
        };
        let triangles = mesh
            .indices
            .chunks_exact(3)
            .map(|t| [vertex(t[0]), vertex(t[1]), vertex(t[2])]);
        // tobj splits an object at each material change: merge pieces that share a name.
        match parts.iter_mut().find(|p| p.name == model.name) {
            Some(part) => part.triangles.extend(triangles),
            None => parts.push(Part {
                name: model.name.clone(),
                triangles: triangles.collect(),
            }),
        }
    }
    let corners = parts.iter().flat_map(|p| &p.triangles).flatten();
    if let Some(v) = corners.clone().find(|v| !v.is_finite()) {
        return Err(HostError::invalid(
            path,
            format!("the mesh has a non-finite vertex ({v})"),
        ));
    }
    // Farther than this, a triangle's edges overflow f32 products and it silently vanishes.
    if let Some(v) = corners
        .clone()
        .find(|v| v.abs().max_element() > MAX_VERTEX_M)
    {
        return Err(HostError::invalid(
            path,
            format!(
                "the mesh has a vertex at {v} m (after the scale), farther than {MAX_VERTEX_M:e} m from its origin"
            ),
        ));
    }
    Ok(parts)
}
