//! Pose errors: rotation (split about and across the view axis) and translation, per frame
//! and summarised.

use super::mean;
use glam::DVec3;
use orbit_nerf_core::PoseFit;
use orbit_nerf_core::camera::Pose;

/// Angle in degrees, in [0, 180], of the relative rotation `R_a^T R_b`.
///
/// Computed in `f64` as `atan2(|v|, trace - 1)`, where `v` is the axial vector of the
/// relative rotation (`|v| = 2 sin θ`, `trace - 1 = 2 cos θ`). Unlike `acos((trace - 1) / 2)`,
/// whose slope is infinite at 0° and 180°, this stays accurate at both ends: identical poses
/// give exactly 0, and f32 rounding in the matrices does not show up as a spurious 0.03°. It
/// needs no clamping either, and is insensitive to a uniform scale error in the matrices.
pub fn rotation_error_deg(a: &Pose, b: &Pose) -> f64 {
    relative_rotation(a, b).1.to_degrees()
}

/// The rotation error of `rotation_error_deg` split by its axis in camera `a`'s frame, in
/// degrees: the part about the optical axis (the image turns in its own plane, which every
/// edge of the target shows) and the part across it (the camera turns about the target, which
/// only the target's relief shows). The two add up in quadrature to the whole angle, except at
/// exactly 180 degrees, whose axis this does not recover (it gives 0 and 0).
pub fn rotation_error_split_deg(a: &Pose, b: &Pose) -> (f64, f64) {
    let (axis, angle) = relative_rotation(a, b);
    (
        (angle * axis.z.abs()).to_degrees(),
        (angle * axis.truncate().length()).to_degrees(),
    )
}

/// Unit axis (zero for no rotation) and angle in [0, pi] of `R_a^T R_b`.
fn relative_rotation(a: &Pose, b: &Pose) -> (DVec3, f64) {
    let relative = a.rotation.as_dmat3().transpose() * b.rotation.as_dmat3();
    let (x, y, z) = (relative.x_axis, relative.y_axis, relative.z_axis);
    // Column-major: m(row, col) is `<col>_axis.<row>`.
    let axial = DVec3::new(y.z - z.y, z.x - x.z, x.y - y.x);
    let twice_cos = x.x + y.y + z.z - 1.0;
    (axial.normalize_or_zero(), axial.length().atan2(twice_cos))
}

/// Distance between the two camera centres, in the dataset's units (metres for SPEED+/SHIRT).
///
/// ```
/// use orbit_nerf_core::Pose;
/// use orbit_nerf_core::glam::{Mat3, Vec3};
/// use orbit_nerf_host::report::{rotation_error_deg, rotation_error_split_deg, translation_error};
///
/// let a = Pose { rotation: Mat3::IDENTITY, center: Vec3::ZERO };
/// // Turned 10 degrees about its optical axis (+z) and moved 3 m right, 4 m forward.
/// let b = Pose {
///     rotation: Mat3::from_rotation_z(10f32.to_radians()),
///     center: Vec3::new(3.0, 0.0, 4.0),
/// };
/// assert!((translation_error(&a, &b) - 5.0).abs() < 1e-9);
/// assert!((rotation_error_deg(&a, &b) - 10.0).abs() < 1e-4);
/// let (about, across) = rotation_error_split_deg(&a, &b);
/// assert!((about - 10.0).abs() < 1e-4 && across.abs() < 1e-4);
/// assert_eq!(rotation_error_deg(&a, &a), 0.0);
/// ```
pub fn translation_error(a: &Pose, b: &Pose) -> f64 {
    a.center.as_dvec3().distance(b.center.as_dvec3())
}

/// Summary of per-frame pose errors against ground truth.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PoseErrors {
    /// Mean rotation error, degrees.
    pub rotation_deg_mean: f64,
    /// Median rotation error, degrees.
    pub rotation_deg_median: f64,
    /// Mean camera-centre distance, dataset units (metres for SPEED+/SHIRT).
    pub translation_mean: f64,
    /// Median camera-centre distance, dataset units.
    pub translation_median: f64,
    /// Mean of the rotation error's parts about and across the optical axis
    /// (`rotation_error_split_deg`), degrees: this one about the axis.
    pub about_view_axis_deg_mean: f64,
    /// Mean of the rotation error's part across the optical axis, degrees.
    pub across_view_axis_deg_mean: f64,
    /// Number of frames compared.
    pub frames: usize,
}

/// Rotation and translation errors of `estimated` against `truth`, frame by frame.
///
/// When the slices differ in length only the common prefix is compared (`frames` says how many);
/// empty input gives all zeros with `frames == 0`. Never panics; a non-finite pose gives NaN
/// errors, which propagate into the mean, and sort last for the median.
pub fn pose_errors(estimated: &[Pose], truth: &[Pose]) -> PoseErrors {
    let pairs = estimated.iter().zip(truth);
    let rotations: Vec<f64> = pairs
        .clone()
        .map(|(e, t)| rotation_error_deg(e, t))
        .collect();
    let (about, across): (Vec<f64>, Vec<f64>) = pairs
        .clone()
        .map(|(e, t)| rotation_error_split_deg(t, e))
        .unzip();
    let translations: Vec<f64> = pairs.map(|(e, t)| translation_error(e, t)).collect();
    if rotations.is_empty() {
        return PoseErrors::default();
    }
    PoseErrors {
        rotation_deg_mean: mean(&rotations),
        rotation_deg_median: median(&rotations),
        translation_mean: mean(&translations),
        translation_median: median(&translations),
        about_view_axis_deg_mean: mean(&about),
        across_view_axis_deg_mean: mean(&across),
        frames: rotations.len(),
    }
}

/// One training frame's refined pose: its 1-sigma uncertainty from the refinement and,
/// where the exact pose is known, its true error (`metrics.json`, the ablation report).
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct FramePose {
    /// The frame's image file name.
    pub name: String,
    /// 1-sigma attitude uncertainty, degrees; `None` (JSON null) where the view does not
    /// constrain the pose (no finite sigma).
    pub rotation_sigma_deg: Option<f64>,
    /// 1-sigma position uncertainty, dataset units; `None` as for `rotation_sigma_deg`.
    pub position_sigma: Option<f64>,
    /// Rotation error of the refined pose against the exact one, degrees; `None` without
    /// exact poses.
    pub rotation_error_deg: Option<f64>,
    /// Camera-centre distance of the refined pose from the exact one, dataset units; `None`
    /// without exact poses.
    pub position_error: Option<f64>,
}

/// Each frame's [`FramePose`]: `fits`, `corrected` and `names` in the same order, `exact`
/// too when the data has exact poses.
pub fn frame_poses(
    names: &[String],
    fits: &[PoseFit],
    corrected: &[Pose],
    exact: Option<&[Pose]>,
) -> Vec<FramePose> {
    let finite = |v: f32| v.is_finite().then_some(v as f64);
    (names.iter().zip(fits).zip(corrected).enumerate())
        .map(|(i, ((name, fit), pose))| {
            let truth = exact.and_then(|e| e.get(i));
            FramePose {
                name: name.clone(),
                rotation_sigma_deg: finite(fit.rotation_sigma_deg),
                position_sigma: finite(fit.position_sigma),
                rotation_error_deg: truth.map(|t| rotation_error_deg(pose, t)),
                position_error: truth.map(|t| translation_error(pose, t)),
            }
        })
        .collect()
}

/// The refined poses' uncertainty over the frames: the mean 1-sigma attitude and position
/// uncertainties (over the frames with a finite one) and, where the exact poses are known,
/// the fraction of frames whose true error lies within 3 sigma (a frame without a finite
/// sigma counts as inside).
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct PoseUncertainty {
    /// Mean 1-sigma attitude uncertainty, degrees; `None` when no frame has a finite one.
    pub rotation_sigma_deg_mean: Option<f64>,
    /// Mean 1-sigma position uncertainty, dataset units; `None` when no frame has a finite one.
    pub position_sigma_mean: Option<f64>,
    /// Fraction (0 to 1) of frames whose true rotation error is within 3 sigma; `None`
    /// without exact poses.
    pub rotation_within_3_sigma: Option<f64>,
    /// Fraction (0 to 1) of frames whose true position error is within 3 sigma; `None`
    /// without exact poses.
    pub position_within_3_sigma: Option<f64>,
    /// Number of frames summarised.
    pub frames: usize,
}

/// [`PoseUncertainty`] of `frames`.
pub fn pose_uncertainty(frames: &[FramePose]) -> PoseUncertainty {
    let finite_mean = |f: fn(&FramePose) -> Option<f64>| {
        let values: Vec<f64> = frames.iter().filter_map(f).collect();
        (!values.is_empty()).then(|| mean(&values))
    };
    let within = |error: fn(&FramePose) -> Option<f64>, sigma: fn(&FramePose) -> Option<f64>| {
        let inside: Vec<bool> = frames
            .iter()
            .filter_map(|f| {
                let e = error(f)?;
                Some(sigma(f).is_none_or(|s| e <= 3.0 * s))
            })
            .collect();
        (!inside.is_empty())
            .then(|| inside.iter().filter(|&&b| b).count() as f64 / inside.len() as f64)
    };
    PoseUncertainty {
        rotation_sigma_deg_mean: finite_mean(|f| f.rotation_sigma_deg),
        position_sigma_mean: finite_mean(|f| f.position_sigma),
        rotation_within_3_sigma: within(|f| f.rotation_error_deg, |f| f.rotation_sigma_deg),
        position_within_3_sigma: within(|f| f.position_error, |f| f.position_sigma),
        frames: frames.len(),
    }
}

/// Median of a non-empty slice; the mean of the two middle values for an even count.
fn median(values: &[f64]) -> f64 {
    let mut sorted = values.to_vec();
    sorted.sort_by(f64::total_cmp);
    let middle = sorted.len() / 2;
    if sorted.len() % 2 == 1 {
        sorted[middle]
    } else {
        (sorted[middle - 1] + sorted[middle]) / 2.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::{Mat3, Vec3};

    fn pose(rotation: Mat3, center: Vec3) -> Pose {
        Pose { rotation, center }
    }

    #[test]
    fn rotation_error_splits_about_and_across_the_view_axis() {
        let base = Mat3::from_euler(glam::EulerRot::XYZ, 0.3, -1.1, 2.0);
        let a = pose(base, Vec3::ZERO);
        let deg = |d: f32| d.to_radians();
        // Turning camera a about its own optical axis (+z) is all "about"; about x, all "across".
        let (about, across) = rotation_error_split_deg(
            &a,
            &pose(base * Mat3::from_rotation_z(deg(2.0)), Vec3::ZERO),
        );
        assert!(
            (about - 2.0).abs() < 1e-4 && across.abs() < 1e-4,
            "{about} {across}"
        );
        let (about, across) = rotation_error_split_deg(
            &a,
            &pose(base * Mat3::from_rotation_x(deg(3.0)), Vec3::ZERO),
        );
        assert!(
            about.abs() < 1e-4 && (across - 3.0).abs() < 1e-4,
            "{about} {across}"
        );
        // A mixed axis splits by its components; the parts add up in quadrature to the angle.
        let axis = Vec3::new(3.0, 0.0, 4.0).normalize();
        let mixed = pose(base * Mat3::from_axis_angle(axis, deg(5.0)), Vec3::ZERO);
        let (about, across) = rotation_error_split_deg(&a, &mixed);
        assert!(
            (about - 4.0).abs() < 1e-4 && (across - 3.0).abs() < 1e-4,
            "{about} {across}"
        );
        let whole = rotation_error_deg(&a, &mixed);
        assert!((about.hypot(across) - whole).abs() < 1e-6);
        assert_eq!(rotation_error_split_deg(&a, &a), (0.0, 0.0));
    }

    #[test]
    fn rotation_error_of_known_rotations() {
        let base = Mat3::from_rotation_z(0.7) * Mat3::from_rotation_x(-1.2);
        let a = pose(base, Vec3::ZERO);
        let ten = pose(
            base * Mat3::from_axis_angle(Vec3::new(1.0, 2.0, 3.0).normalize(), 10f32.to_radians()),
            Vec3::ZERO,
        );
        assert!((rotation_error_deg(&a, &ten) - 10.0).abs() < 1e-4);
        assert!((rotation_error_deg(&ten, &a) - 10.0).abs() < 1e-4);

        let identical = rotation_error_deg(&a, &a);
        assert_eq!(identical, 0.0);

        let half_turn = pose(
            base * Mat3::from_rotation_y(std::f32::consts::PI),
            Vec3::ZERO,
        );
        let error = rotation_error_deg(&a, &half_turn);
        assert!(error.is_finite() && (error - 180.0).abs() < 1e-3, "{error}");
        let tiny = pose(
            base * Mat3::from_rotation_x(1e-3f32.to_radians()),
            Vec3::ZERO,
        );
        assert!((rotation_error_deg(&a, &tiny) - 1e-3).abs() < 1e-4);
    }

    #[test]
    fn translation_error_is_the_centre_distance() {
        let a = pose(Mat3::IDENTITY, Vec3::new(1.0, 2.0, 3.0));
        let b = pose(Mat3::from_rotation_z(1.0), Vec3::new(4.0, 6.0, 3.0));
        assert_eq!(translation_error(&a, &b), 5.0);
    }

    #[test]
    fn pose_errors_summarise_frames() {
        let truth: Vec<Pose> = (0..4)
            .map(|i| {
                pose(
                    Mat3::from_rotation_y(i as f32),
                    Vec3::new(i as f32, 0.0, 0.0),
                )
            })
            .collect();
        let offsets_deg = [1.0f32, 2.0, 3.0, 10.0];
        let offsets_m = [0.5f32, 0.25, 1.0, 2.0];
        let estimated: Vec<Pose> = truth
            .iter()
            .zip(offsets_deg.iter().zip(&offsets_m))
            .map(|(t, (&deg, &m))| {
                pose(
                    t.rotation * Mat3::from_rotation_x(deg.to_radians()),
                    t.center + Vec3::new(0.0, 0.0, m),
                )
            })
            .collect();
        let errors = pose_errors(&estimated, &truth);
        assert_eq!(errors.frames, 4);
        assert!((errors.rotation_deg_mean - 4.0).abs() < 1e-4, "{errors:?}");
        // The offsets turn the cameras about their x axes: all across the view axis.
        assert!(errors.about_view_axis_deg_mean.abs() < 1e-4, "{errors:?}");
        assert!(
            (errors.across_view_axis_deg_mean - 4.0).abs() < 1e-4,
            "{errors:?}"
        );
        assert!(
            (errors.rotation_deg_median - 2.5).abs() < 1e-4,
            "{errors:?}"
        );
        assert!(
            (errors.translation_mean - 0.9375).abs() < 1e-6,
            "{errors:?}"
        );
        assert!(
            (errors.translation_median - 0.75).abs() < 1e-6,
            "{errors:?}"
        );

        let prefix = pose_errors(&estimated[..3], &truth);
        assert_eq!(prefix.frames, 3);
        assert!(
            (prefix.rotation_deg_median - 2.0).abs() < 1e-4,
            "{prefix:?}"
        );
        assert!((prefix.translation_median - 0.5).abs() < 1e-6, "{prefix:?}");
        assert_eq!(pose_errors(&[], &truth), PoseErrors::default());
    }
}
