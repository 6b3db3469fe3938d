//! Mesh and point-cloud files: binary little-endian PLY (`ply-rs-bw`; vertices with normals
//! and RGB8 colours, and triangles unless it is a point cloud) and Wavefront OBJ (text: `v x y
//! z r g b` with colours in 0..1 as MeshLab and Blender read them, `vn`, and `f a//a b//b
//! c//c`). Written atomically.

use super::Mesh;
use crate::error::{HostError, Result};
use ply_rs_bw::ply::{
    Addable, DefaultElement, ElementDef, Encoding, Ply, Property, PropertyDef, PropertyType,
    ScalarType,
};
use ply_rs_bw::writer::Writer;
use std::fmt::Write as _;
use std::path::Path;

/// A mesh file's format, told from its name's extension.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum MeshFormat {
    /// Binary PLY (`.ply`): a mesh or a point cloud.
    Ply,
    /// Wavefront OBJ (`.obj`): a mesh only.
    Obj,
}

impl MeshFormat {
    /// The format of the file `out` by its extension (case ignored); a point cloud
    /// (`points`) must be PLY.
    pub fn of(out: &Path, points: bool) -> Result<MeshFormat> {
        let extension = (out.extension().and_then(|e| e.to_str())).map(str::to_ascii_lowercase);
        match extension.as_deref() {
            Some("ply") => Ok(MeshFormat::Ply),
            Some("obj") if !points => Ok(MeshFormat::Obj),
            _ => Err(HostError::invalid(
                out,
                format!(
                    "--out must end in {}",
                    if points { ".ply" } else { ".ply or .obj" }
                ),
            )),
        }
    }

    /// Write `mesh` to `out` in this format (its vertices alone when `points`), atomically.
    pub fn write(self, out: &Path, mesh: &Mesh, points: bool) -> Result<()> {
        match self {
            MeshFormat::Ply => write_ply(out, mesh, !points),
            MeshFormat::Obj => write_obj(out, mesh),
        }
    }
}

/// Write `mesh` as binary PLY: vertices (x, y, z, nx, ny, nz, red, green, blue) and, when
/// `with_faces`, its triangles (`vertex_indices`); without them it is a point cloud.
pub fn write_ply(path: &Path, mesh: &Mesh, with_faces: bool) -> Result<()> {
    let mut ply = Ply::<DefaultElement>::new();
    ply.header.encoding = Encoding::BinaryLittleEndian;
    ply.header
        .comments
        .push("orbit-nerf: surface of a trained density field".into());
    let mut vertex = ElementDef::new("vertex".into());
    for name in ["x", "y", "z", "nx", "ny", "nz"] {
        let float = PropertyType::Scalar(ScalarType::Float);
        vertex.properties.add(PropertyDef::new(name.into(), float));
    }
    for name in ["red", "green", "blue"] {
        let byte = PropertyType::Scalar(ScalarType::UChar);
        vertex.properties.add(PropertyDef::new(name.into(), byte));
    }
    ply.header.elements.add(vertex);
    let vertices = (mesh.positions.iter().zip(&mesh.normals).zip(&mesh.colours))
        .map(|((p, n), c)| {
            let mut v = DefaultElement::new();
            for (name, value) in ["x", "y", "z", "nx", "ny", "nz"]
                .iter()
                .zip(p.iter().chain(n))
            {
                v.insert(name.to_string(), Property::Float(*value));
            }
            for (name, value) in ["red", "green", "blue"].iter().zip(c) {
                v.insert(name.to_string(), Property::UChar(*value));
            }
            v
        })
        .collect();
    ply.payload.insert("vertex".into(), vertices);
    if with_faces {
        let mut face = ElementDef::new("face".into());
        let list = PropertyType::List(ScalarType::UChar, ScalarType::UInt);
        face.properties
            .add(PropertyDef::new("vertex_indices".into(), list));
        ply.header.elements.add(face);
        let faces = mesh
            .triangles
            .iter()
            .map(|t| {
                let mut f = DefaultElement::new();
                f.insert("vertex_indices".into(), Property::ListUInt(t.to_vec()));
                f
            })
            .collect();
        ply.payload.insert("face".into(), faces);
    }
    let mut bytes = Vec::new();
    Writer::new()
        .write_ply(&mut bytes, &mut ply)
        .map_err(|e| HostError::invalid(path, format!("PLY encoding failed: {e}")))?;
    crate::io::write_atomic(path, &bytes)
}

/// Write `mesh` as Wavefront OBJ with per-vertex colours and normals.
pub fn write_obj(path: &Path, mesh: &Mesh) -> Result<()> {
    let mut text = String::from("# orbit-nerf: surface of a trained density field\n");
    for (p, c) in mesh.positions.iter().zip(&mesh.colours) {
        let [r, g, b] = c.map(|v| v as f32 / 255.0);
        let _ = writeln!(text, "v {} {} {} {r:.4} {g:.4} {b:.4}", p[0], p[1], p[2]);
    }
    for n in &mesh.normals {
        let _ = writeln!(text, "vn {:.5} {:.5} {:.5}", n[0], n[1], n[2]);
    }
    for t in &mesh.triangles {
        let [a, b, c] = t.map(|i| i + 1);
        let _ = writeln!(text, "f {a}//{a} {b}//{b} {c}//{c}");
    }
    crate::io::write_atomic(path, text.as_bytes())
}
