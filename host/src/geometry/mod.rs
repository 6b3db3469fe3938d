//! Geometry out of a trained field and scored against the truth: the surface of the density
//! field as a coloured triangle mesh (`extract`), written as PLY or OBJ (`files`), and the
//! Chamfer distance between two surfaces (`chamfer`), the one definition every command reports.

pub mod chamfer;
pub mod extract;
pub mod files;
pub mod preview;

pub use chamfer::{Chamfer, chamfer_distance};
pub use extract::{SurfaceOptions, extract_surface};

/// A triangle mesh with a unit normal and an RGB8 colour per vertex (world frame).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Mesh {
    /// Vertex positions, world units.
    pub positions: Vec<[f32; 3]>,
    /// Unit outward normals (towards lower density).
    pub normals: Vec<[f32; 3]>,
    /// Vertex colours, RGB8.
    pub colours: Vec<[u8; 3]>,
    /// Vertex indices, three per triangle.
    pub triangles: Vec<[u32; 3]>,
}

/// A triangle as its three corners.
pub type Triangle = [[f32; 3]; 3];

impl Mesh {
    /// The triangles as corner positions.
    pub fn triangle_corners(&self) -> Vec<Triangle> {
        self.triangles
            .iter()
            .map(|t| t.map(|i| self.positions[i as usize]))
            .collect()
    }
}
