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
    /// Diffuse albedo, RGB in [0, 1].
    pub diffuse: Vec3,
    /// Specular reflectance, RGB.
    pub specular: Vec3,
    /// Blinn-Phong exponent: higher is a sharper highlight.
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
    /// Distance along the ray's unit direction, metres.
    pub distance: f32,
    /// Unit geometric normal (either side).
    pub normal: Vec3,
    /// Index of the hit triangle's material in [`Target::materials`].
    pub material: u16,
}

/// Reusable traversal stack (node index, entry distance), one per thread.
pub type TraversalStack = Vec<(usize, f32)>;

/// The target's triangles (body frame, metres) in a BVH, with their materials.
pub struct Target {
    triangles: Vec<Triangle>,
    bvh: Bvh<f32, 3>,
    /// The distinct materials of the parts; a hit's `material` indexes this.
    pub materials: Vec<Material>,
    /// Lower corner of the tight bounding box, body frame, metres.
    pub box_min: Vec3,
    /// Upper corner of the tight bounding box, body frame, metres.
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
                let points = parse_landmarks(&data.origin(), &data.text()?)?;
                let points: &[Vec3; TANGO_LANDMARKS] =
                    points.as_slice().try_into().map_err(|_| {
                        HostError::invalid(
                            data.origin(),
                            format!(
                                "TANGO needs exactly {TANGO_LANDMARKS} landmarks (4 solar-panel corners, 4 body corners, 3 antenna tips), the file has {}",
                                points.len()
                            ),
                        )
                    })?;
                tango_parts(points)
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

    /// Triangles in the mesh.
    pub fn triangle_count(&self) -> usize {
        self.triangles.len()
    }

    /// Centre of the bounding box, body frame, metres.
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

/// [`read_landmarks`] on the text of the file `path` names. Every field of every landmark line
/// must be a finite number, no farther from the origin than a mesh's vertices may be.
pub fn parse_landmarks(path: &Path, text: &str) -> Result<Vec<Vec3>> {
    let mut lines = text.lines().enumerate();
    // A first line that is a landmark would be lost as the header.
    if let Some((_, header)) = lines.next()
        && parse_landmark(path, 1, header).is_ok()
    {
        return Err(HostError::field(
            path,
            "line 1",
            "the first line is the header `x,y,z`, not a landmark",
        ));
    }
    lines
        .filter(|(_, line)| !line.trim().is_empty())
        .map(|(line_index, line)| parse_landmark(path, line_index + 1, line))
        .collect()
}

/// One `x,y,z` line (line number `line_number`, from 1) of the landmarks file `path`.
fn parse_landmark(path: &Path, line_number: usize, line: &str) -> Result<Vec3> {
    let fields: Vec<&str> = line.split(',').collect();
    let [x, y, z] = fields[..] else {
        return Err(HostError::field(
            path,
            format!("line {line_number}"),
            format!(
                "expected three numbers x,y,z, found {} fields",
                fields.len()
            ),
        ));
    };
    let coordinate = |name: &str, field: &str| {
        let field = field.trim();
        match field.parse::<f32>() {
            Ok(v) if !v.is_finite() => Err(format!("`{field}` is not a finite number")),
            Ok(v) if v.abs() > MAX_VERTEX_M => Err(format!(
                "{field} m is farther than {MAX_VERTEX_M:e} m from the origin"
            )),
            Ok(v) => Ok(v),
            Err(_) => Err(format!("`{field}` is not a number")),
        }
        .map_err(|reason| HostError::field(path, format!("line {line_number}, {name}"), reason))
    };
    Ok(Vec3::new(
        coordinate("x", x)?,
        coordinate("y", y)?,
        coordinate("z", z)?,
    ))
}

/// Landmarks of TANGO in the SPEED+ devkit.
const TANGO_LANDMARKS: usize = 11;

/// TANGO from its 11 landmarks (SPEED+ devkit order): 4 solar-panel corners (top), 4 body
/// corners (bottom), 3 antenna tips. The body box spans the bottom corners up to the panel,
/// the panel spans the top corners, and each antenna is a rod from the nearest point of the
/// body to its tip.
fn tango_parts(landmarks: &[Vec3; TANGO_LANDMARKS]) -> Vec<Part> {
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

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::PathBuf;

    const BUILTIN_LANDMARKS: &str = include_str!("../../../scenes/tango-landmarks.csv");

    /// The synthetic preset with its landmarks read from a file holding `text`.
    fn build_with_landmarks(dir: &Path, text: &str) -> (PathBuf, Result<Target>) {
        let file = dir.join("landmarks.csv");
        std::fs::write(&file, text).unwrap();
        let mut scene = Scene::load("synthetic").unwrap();
        let TargetSpec::Tango { landmarks, .. } = &mut scene.spec.target else {
            panic!("the synthetic preset is not TANGO");
        };
        *landmarks = file.to_str().unwrap().to_owned();
        let target = Target::build(&scene);
        (file, target)
    }

    /// The `(file, field, reason)` of a field error, or a panic naming what came instead.
    fn field_error(result: Result<Vec<Vec3>>) -> (PathBuf, String, String) {
        match result {
            Err(HostError::Field {
                file,
                field,
                reason,
            }) => (file, field, reason),
            other => panic!("expected a field error, got {other:?}"),
        }
    }

    #[test]
    fn a_landmarks_file_without_exactly_eleven_points_is_refused_naming_both_counts() {
        let dir = tempfile::tempdir().unwrap();
        let lines: Vec<&str> = BUILTIN_LANDMARKS.lines().collect();
        let (_, target) = build_with_landmarks(dir.path(), BUILTIN_LANDMARKS);
        assert!(target.is_ok(), "{:?}", target.err());
        let extra = format!("{BUILTIN_LANDMARKS}0.1,0.2,0.3\n");
        for (text, count) in [
            (lines[..9].join("\n"), 8),
            (lines[..11].join("\n"), 10),
            (lines[..1].join("\n"), 0),
            (extra, 12),
        ] {
            let (file, target) = build_with_landmarks(dir.path(), &text);
            let message = target
                .err()
                .expect("a wrong count must be refused")
                .to_string();
            assert!(
                message.starts_with(&file.display().to_string())
                    && message.contains("exactly 11 landmarks")
                    && message.contains(&format!("the file has {count}")),
                "{message}"
            );
        }
    }

    #[test]
    fn every_landmark_field_must_be_a_finite_number_in_range() {
        let path = Path::new("landmarks.csv");
        assert_eq!(
            parse_landmarks(path, "x,y,z\n1,2,3\n\n-4.5, 0 ,6e-1\n").unwrap(),
            vec![Vec3::new(1.0, 2.0, 3.0), Vec3::new(-4.5, 0.0, 0.6)]
        );
        for (line, field, said) in [
            ("1,abc,3", "line 3, y", "`abc` is not a number"),
            ("1,2,", "line 3, z", "`` is not a number"),
            ("inf,2,3", "line 3, x", "`inf` is not a finite number"),
            ("1,NaN,3", "line 3, y", "`NaN` is not a finite number"),
            ("1,2,1e30", "line 3, z", "farther than"),
            ("1,abc,2,3", "line 3", "found 4 fields"),
            ("1,2", "line 3", "found 2 fields"),
        ] {
            let text = format!("x,y,z\n0,0,0\n{line}\n");
            let (file, got_field, reason) = field_error(parse_landmarks(path, &text));
            assert_eq!(
                (file.as_path(), got_field.as_str()),
                (path, field),
                "{line}"
            );
            assert!(reason.contains(said), "{line}: {reason}");
        }
        // Without the header, the first landmark would be lost.
        let (_, field, reason) = field_error(parse_landmarks(path, "1,2,3\n4,5,6\n"));
        assert_eq!(field, "line 1");
        assert!(reason.contains("header"), "{reason}");
    }
}
