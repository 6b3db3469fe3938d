//! A picture of a mesh: an orthographic z-buffer rasteriser with the vertex colours shaded by
//! how squarely each surface faces the viewer, for the README and a quick look at an export.

use super::Mesh;
use orbit_nerf_core::glam::Vec3;

/// RGB8 picture (`size` x `size` pixels, white background) of `mesh` seen from direction `from`
/// (towards the mesh's centre) with `up` upwards, the mesh filling the frame.
pub fn preview(mesh: &Mesh, size: u32, from: Vec3, up: Vec3) -> Vec<u8> {
    let size = size.max(1) as usize;
    let mut rgb = vec![255u8; size * size * 3];
    let forward = (-from).try_normalize().unwrap_or(Vec3::NEG_Z);
    let right = forward.cross(up).try_normalize().unwrap_or(Vec3::X);
    let screen_up = right.cross(forward);
    let project = |p: &[f32; 3]| {
        let p = Vec3::from_array(*p);
        Vec3::new(p.dot(right), p.dot(screen_up), p.dot(forward))
    };
    let projected: Vec<Vec3> = mesh.positions.iter().map(project).collect();
    let (lo, hi) = projected
        .iter()
        .fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(lo, hi), p| {
            (lo.min(*p), hi.max(*p))
        });
    let extent = (hi.x - lo.x).max(hi.y - lo.y);
    if !(extent.is_finite() && extent > 0.0) {
        return rgb;
    }
    // 5 % margin on every side.
    let scale = 0.9 * size as f32 / extent;
    let centre = (lo + hi) * 0.5;
    let pixel = |p: Vec3| {
        Vec3::new(
            size as f32 * 0.5 + (p.x - centre.x) * scale,
            size as f32 * 0.5 - (p.y - centre.y) * scale,
            p.z,
        )
    };
    let shade = |i: usize| {
        let facing = Vec3::from_array(mesh.normals[i]).dot(-forward).abs();
        Vec3::from_array(mesh.colours[i].map(f32::from)) * (0.3 + 0.7 * facing)
    };
    let mut depth = vec![f32::INFINITY; size * size];
    for t in &mesh.triangles {
        let [a, b, c] = t.map(|i| pixel(projected[i as usize]));
        let area = (b.x - a.x) * (c.y - a.y) - (b.y - a.y) * (c.x - a.x);
        if area.abs() < 1e-12 {
            continue;
        }
        let x0 = a.x.min(b.x).min(c.x).floor().max(0.0) as usize;
        let x1 = (a.x.max(b.x).max(c.x).ceil() as usize).min(size - 1);
        let y0 = a.y.min(b.y).min(c.y).floor().max(0.0) as usize;
        let y1 = (a.y.max(b.y).max(c.y).ceil() as usize).min(size - 1);
        let colours = t.map(|i| shade(i as usize));
        for y in y0..=y1 {
            for x in x0..=x1 {
                let (px, py) = (x as f32 + 0.5, y as f32 + 0.5);
                let wa = ((b.x - px) * (c.y - py) - (b.y - py) * (c.x - px)) / area;
                let wb = ((c.x - px) * (a.y - py) - (c.y - py) * (a.x - px)) / area;
                let wc = 1.0 - wa - wb;
                if wa < 0.0 || wb < 0.0 || wc < 0.0 {
                    continue;
                }
                let z = wa * a.z + wb * b.z + wc * c.z;
                let k = y * size + x;
                if z < depth[k] {
                    depth[k] = z;
                    let colour = colours[0] * wa + colours[1] * wb + colours[2] * wc;
                    for (ch, v) in colour.to_array().iter().enumerate() {
                        rgb[k * 3 + ch] = v.clamp(0.0, 255.0) as u8;
                    }
                }
            }
        }
    }
    rgb
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_triangle_facing_the_viewer_covers_its_part_of_the_picture_in_its_colour() {
        let mesh = Mesh {
            positions: vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
            normals: vec![[0.0, 0.0, 1.0]; 3],
            colours: vec![[200, 100, 50]; 3],
            triangles: vec![[0, 1, 2]],
        };
        let rgb = preview(&mesh, 20, Vec3::Z, Vec3::Y);
        let at = |x: usize, y: usize| &rgb[(y * 20 + x) * 3..(y * 20 + x) * 3 + 3];
        // Lower left is inside the triangle (facing the viewer: full colour), upper right not.
        assert_eq!(at(3, 16), &[200, 100, 50]);
        assert_eq!(at(16, 3), &[255, 255, 255]);
    }
}
