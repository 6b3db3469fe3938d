//! Pinhole cameras and camera-to-world poses (OpenCV axes: x right, y down, z forward).

use glam::{Mat3, Quat, Vec3};

/// Pinhole intrinsics in pixels. Pixel `(i, j)` has its centre at `(i + 0.5, j + 0.5)`.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Camera {
    /// Image width in pixels.
    pub width: u16,
    /// Image height in pixels.
    pub height: u16,
    /// Horizontal focal length in pixels.
    pub fx: f32,
    /// Vertical focal length in pixels.
    pub fy: f32,
    /// Principal point, x coordinate in pixels from the left image edge.
    pub cx: f32,
    /// Principal point, y coordinate in pixels from the top image edge.
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

    /// Number of pixels in the image, `width * height`.
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
    /// Camera-to-world rotation; its columns are the camera's x, y, z axes in world axes.
    pub rotation: Mat3,
    /// Camera centre in world coordinates.
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
    /// The camera at the world origin, looking along world +z.
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

/// A learned per-frame pose correction, as in the paper: `dt` is added to the ray origins,
/// and ray directions are rotated (in the world frame; the origin is not rotated) by the unit
/// quaternion with vector part `v` and scalar part `sqrt(1 - |v|²)`.
///
/// Guard: `|v|` is capped at 1 (beyond it `v` is scaled back to unit length, a 180° rotation),
/// and the derivative of the scalar part, `-v / w`, uses `max(w, MIN_SCALAR)`, so values and
/// gradients stay finite however far an update pushes `v`.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PoseCorrection {
    /// Translation added to the ray origins, in world units.
    pub dt: Vec3,
    /// Vector part of the rotation quaternion applied to the ray directions (`|v| <= 1`).
    pub v: Vec3,
}

impl PoseCorrection {
    /// Smallest scalar part used in the gradient of `sqrt(1 - |v|²)`.
    pub const MIN_SCALAR: f32 = 1e-3;

    /// From the six parameters `[u.x, u.y, u.z, v.x, v.y, v.z]` (zeros if fewer), where the
    /// learned translation `u` is in units of `length_unit` (`Config::length_unit`), so it
    /// learns alike at every scene scale: `dt = u * length_unit`.
    pub fn from_params(p: &[f32], length_unit: f32) -> Self {
        match p {
            [a, b, c, d, e, f, ..] => PoseCorrection {
                dt: Vec3::new(*a, *b, *c) * length_unit,
                v: Vec3::new(*d, *e, *f),
            },
            _ => PoseCorrection::default(),
        }
    }

    /// The vector part actually used (capped at unit length) and the scalar part; the
    /// identity for a non-finite `v` (an infinite component would give inf x 0 = NaN).
    fn quaternion(&self) -> (Vec3, f32) {
        if !self.v.is_finite() {
            return (Vec3::ZERO, 1.0);
        }
        // Scaled down first, so that |v|² cannot overflow for a huge finite `v`.
        let largest = self.v.abs().max_element();
        let v = if largest > 1.0 {
            self.v * (1.0 / largest)
        } else {
            self.v
        };
        let n2 = v.length_squared();
        if n2 > 1.0 {
            (v * (1.0 / libm::sqrtf(n2)), 0.0)
        } else {
            (v, libm::sqrtf(1.0 - n2))
        }
    }

    /// The corrected ray origin of a camera at `center`: `center + dt`, and with a pivot `p`
    /// also turned about it, `p + R (center - p) + dt` (see [`crate::PosePivot`]).
    pub fn origin(&self, center: Vec3, pivot: Option<Vec3>) -> Vec3 {
        match pivot {
            Some(p) => p + self.rotate(center - p) + self.dt,
            None => center + self.dt,
        }
    }

    /// The pose a label becomes with this correction: rays start at the corrected origin
    /// ([`PoseCorrection::origin`]) and their directions are rotated in the world frame, so
    /// a camera at the result sends every pixel's ray where the trainer sends it.
    pub fn apply(&self, label: &Pose, pivot: Option<Vec3>) -> Pose {
        let rotation = Mat3::from_cols(
            self.rotate(Vec3::X),
            self.rotate(Vec3::Y),
            self.rotate(Vec3::Z),
        );
        Pose {
            rotation: rotation * label.rotation,
            center: self.origin(label.center, pivot),
        }
    }

    /// Rotate a vector: `d + 2w (v × d) + 2 v × (v × d)`.
    pub fn rotate(&self, d: Vec3) -> Vec3 {
        let (v, w) = self.quaternion();
        let vxd = v.cross(d);
        d + vxd * (2.0 * w) + v.cross(vxd) * 2.0
    }

    /// d loss / d v given d loss / d (rotated vector) `g`, for the vector `d` that was
    /// rotated.
    pub fn rotation_vjp(&self, d: Vec3, g: Vec3) -> Vec3 {
        let (v, w) = self.quaternion();
        let d_w = -v / w.max(Self::MIN_SCALAR);
        // Term 2w (v × d): through w and through v. Term 2 v × (v × d) = 2 (v (v·d) - d |v|²).
        d_w * (2.0 * g.dot(v.cross(d)))
            + d.cross(g) * (2.0 * w)
            + (g * v.dot(d) + d * g.dot(v) - v * (2.0 * g.dot(d))) * 2.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn applying_a_correction_moves_the_label_in_the_world_frame() {
        let label = Pose {
            rotation: Mat3::from_rotation_x(0.3),
            center: Vec3::new(1.0, 2.0, 3.0),
        };
        let correction = PoseCorrection {
            dt: Vec3::new(0.1, 0.0, -0.2),
            v: Vec3::new(0.0, 0.05, 0.0),
        };
        let pose = correction.apply(&label, None);
        let d_cam = Vec3::new(0.2, -0.1, 1.0);
        // The corrected pose sends a camera ray where the trainer sends it.
        let expected = correction.rotate(label.rotation * d_cam);
        assert!((pose.rotation * d_cam - expected).length() < 1e-6);
        assert!((pose.center - Vec3::new(1.1, 2.0, 2.8)).length() < 1e-6);
        // About a pivot the rotation also turns the centre: it keeps its distance to the
        // pivot, and a pure rotation moves it along the sphere about the pivot.
        let pivot = Vec3::new(0.5, 0.0, 0.0);
        let turn = PoseCorrection {
            dt: Vec3::ZERO,
            v: Vec3::new(0.0, 0.0, 0.1),
        };
        let pose = turn.apply(&label, Some(pivot));
        assert!((pose.center.distance(pivot) - label.center.distance(pivot)).abs() < 1e-5);
        assert!((pose.center - (pivot + turn.rotate(label.center - pivot))).length() < 1e-6);
        assert!((pose.rotation * d_cam - turn.rotate(label.rotation * d_cam)).length() < 1e-6);
        // A zero correction leaves the label as it is.
        let same = PoseCorrection::default().apply(&label, None);
        assert!((same.rotation - label.rotation).abs_diff_eq(Mat3::ZERO, 1e-7));
    }

    #[test]
    fn pose_correction_rotation_is_a_rotation_and_its_gradient_matches_finite_differences() {
        let d = Vec3::new(0.3, -0.5, 0.81).normalize();
        let g = Vec3::new(0.7, 0.2, -0.4);
        for v in [
            Vec3::new(0.01, -0.02, 0.03),
            Vec3::new(0.3, 0.4, -0.5),
            Vec3::ZERO,
        ] {
            let pc = PoseCorrection { dt: Vec3::ZERO, v };
            assert!((pc.rotate(d).length() - 1.0).abs() < 1e-5);
            let analytic = pc.rotation_vjp(d, g);
            for i in 0..3 {
                let h = 1e-3;
                let (mut p, mut m) = (pc, pc);
                p.v[i] += h;
                m.v[i] -= h;
                let numeric = (g.dot(p.rotate(d)) - g.dot(m.rotate(d))) / (2.0 * h);
                assert!(
                    (analytic[i] - numeric).abs() < 2e-3,
                    "v {v}: {} vs {numeric}",
                    analytic[i]
                );
            }
        }
        // The quaternion with vector part v is the rotation by 2 asin(|v|) about v.
        let v = Vec3::new(0.0, 0.0, libm::sinf(0.25));
        let rotated = PoseCorrection { dt: Vec3::ZERO, v }.rotate(Vec3::X);
        assert!((rotated - Vec3::new(libm::cosf(0.5), libm::sinf(0.5), 0.0)).length() < 1e-6);
    }

    #[test]
    fn pose_correction_stays_finite_at_and_beyond_unit_vector_part() {
        let d = Vec3::new(0.0, 0.6, 0.8);
        let g = Vec3::ONE;
        for v in [
            Vec3::new(1.0, 0.0, 0.0),
            Vec3::new(0.6, 0.8, 1e-4),
            Vec3::splat(3.0),
            Vec3::new(1e30, -2e38, 0.0),
            Vec3::new(f32::INFINITY, 0.0, 0.0),
            Vec3::splat(f32::NEG_INFINITY),
            Vec3::splat(f32::NAN),
        ] {
            let pc = PoseCorrection { dt: Vec3::ZERO, v };
            let r = pc.rotate(d);
            assert!(
                r.is_finite() && (r.length() - 1.0).abs() < 1e-4,
                "{v} -> {r}"
            );
            assert!(pc.rotation_vjp(d, g).is_finite() || !v.is_finite(), "{v}");
        }
    }
}
