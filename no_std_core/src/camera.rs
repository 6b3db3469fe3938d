//! Pinhole cameras and camera-to-world poses (OpenCV axes: x right, y down, z forward).

use glam::{Mat3, Quat, Vec3};

/// Pinhole intrinsics in pixels. Pixel `(i, j)` has its centre at `(i + 0.5, j + 0.5)`.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Camera {
    pub width: u16,
    pub height: u16,
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
}

impl Camera {
    /// Direction of the ray through pixel `(i, j)` in camera axes (not normalised, z = 1).
    #[inline]
    pub fn pixel_direction(&self, i: u32, j: u32) -> Vec3 {
        Vec3::new(
            (i as f32 + 0.5 - self.cx) / self.fx,
            (j as f32 + 0.5 - self.cy) / self.fy,
            1.0,
        )
    }

    pub fn pixel_count(&self) -> usize {
        self.width as usize * self.height as usize
    }

    /// Finite, positive focal lengths and a non-empty image.
    pub fn is_valid(&self) -> bool {
        self.width > 0
            && self.height > 0
            && self.fx.is_finite()
            && self.fy.is_finite()
            && self.fx > 0.0
            && self.fy > 0.0
            && self.cx.is_finite()
            && self.cy.is_finite()
    }
}

/// Camera-to-world pose: `p_world = rotation * p_cam + center`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Pose {
    pub rotation: Mat3,
    pub center: Vec3,
}

#[cfg(feature = "defmt")]
impl defmt::Format for Pose {
    fn format(&self, f: defmt::Formatter) {
        defmt::write!(
            f,
            "Pose(center=[{}, {}, {}])",
            self.center.x,
            self.center.y,
            self.center.z
        )
    }
}

impl Pose {
    pub const IDENTITY: Pose = Pose {
        rotation: Mat3::IDENTITY,
        center: Vec3::ZERO,
    };

    /// From a world-to-camera rotation quaternion and translation (`p_cam = q * p_world + t`),
    /// as in SPEED+ labels. Returns `None` for a zero or non-finite quaternion; the quaternion
    /// is normalised otherwise.
    pub fn from_world_to_camera(q: Quat, t: Vec3) -> Option<Pose> {
        let n2 = q.length_squared();
        if !n2.is_finite() || n2 < 1e-12 || !t.is_finite() {
            return None;
        }
        let q = q * (1.0 / libm::sqrtf(n2));
        let r_w2c = Mat3::from_quat(q);
        let rotation = r_w2c.transpose();
        Some(Pose {
            rotation,
            center: -(rotation * t),
        })
    }

    /// The inverse view: world-to-camera rotation and translation.
    pub fn world_to_camera(&self) -> (Mat3, Vec3) {
        let r = self.rotation.transpose();
        (r, -(r * self.center))
    }

    /// All nine rotation entries and the centre are finite.
    pub fn is_finite(&self) -> bool {
        self.rotation.is_finite() && self.center.is_finite()
    }
}
