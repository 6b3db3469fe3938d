//! The SPEED+ / SHIRT camera file (`camera.json`) in the layouts real files use, read to one
//! pixel camera (matrix, distortion, optional pixel pitch) and written in the SPEED+ layout.

use super::json::{JsonFile, write_json};
use super::resample::Distortion;
use crate::error::{HostError, Result};
use orbit_nerf_core::Camera;
use serde::Serialize;
use serde_json::Value;
use std::path::Path;

/// The SPEED+ camera file (`camera.json`): image size, the pixel camera matrix, OpenCV
/// distortion `[k1, k2, p1, p2, k3]`, and the pixel pitch when the file gives one.
///
/// Layouts read (they load to the same camera):
/// - SPEED+ / SHIRT: `Nu`, `Nv`, `ppx`/`ppy` (pixel pitch, m), `fx`/`fy` (focal lengths, m),
///   `ccx`/`ccy` (principal point, px), `cameraMatrix`, `distCoeffs`;
/// - `Nu`, `Nv` and `cameraMatrix` alone (plus `distCoeffs`);
/// - `Nu`, `Nv`, `fx`/`fy`/`ccx`/`ccy` in pixels (no pitch, no matrix).
///
/// When a file gives the same quantity twice (matrix and focal lengths), they must agree.
/// Written in the SPEED+ layout (the metre fields only when the pitch is known).
#[derive(Clone, Debug, PartialEq)]
pub struct SpeedCamera {
    /// Image width in pixels (`Nu`), 1 to 65535.
    pub width: u32,
    /// Image height in pixels (`Nv`), 1 to 65535.
    pub height: u32,
    /// Pixel pitch in metres (`ppx`, `ppy`), when the file gives it.
    pub pixel_pitch: Option<[f64; 2]>,
    /// The pinhole matrix `[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`, row-major, in pixels.
    pub camera_matrix: [[f64; 3]; 3],
    /// OpenCV distortion `[k1, k2, p1, p2, k3]`; all zero means none.
    pub dist_coeffs: [f64; 5],
}

/// How far a focal length given twice may disagree (relative), and a principal point (pixels).
const FOCAL_AGREEMENT: f64 = 1e-3;
const CENTRE_AGREEMENT_PX: f64 = 0.5;

/// The fields of view a pinhole camera has, in degrees: from a telescope's (a 2000 px image
/// through a 0.1 degree field has a 1.1e6 px focal length) to a wide-angle lens's.
pub(crate) const FIELD_OF_VIEW_DEG: (f64, f64) = (0.005, 170.0);

/// Why `focal` (pixels) over an image side of `side` pixels is no camera's, if it is not.
pub(crate) fn focal_problem(focal: f64, side: f64) -> Option<String> {
    let degrees = 2.0 * (side / (2.0 * focal)).atan().to_degrees();
    let (min, max) = FIELD_OF_VIEW_DEG;
    (!(min..=max).contains(&degrees)).then(|| {
        format!(
            "{focal} px over {side} px is a field of view of {degrees:.3e} deg; a camera's is \
             between {min} and {max} deg"
        )
    })
}

/// The file layout of [`SpeedCamera`].
#[derive(Serialize)]
struct SpeedCameraFile {
    #[serde(rename = "Nu")]
    width: u32,
    #[serde(rename = "Nv")]
    height: u32,
    #[serde(skip_serializing_if = "Option::is_none")]
    ppx: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    ppy: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    fx: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    fy: Option<f64>,
    ccx: f64,
    ccy: f64,
    #[serde(rename = "cameraMatrix")]
    camera_matrix: [[f64; 3]; 3],
    #[serde(rename = "distCoeffs")]
    dist_coeffs: [f64; 5],
}

impl SpeedCamera {
    /// Read and check a camera file in any of the layouts above; `distCoeffs` may be absent
    /// (no distortion).
    pub fn read(path: &Path) -> Result<SpeedCamera> {
        SpeedCamera::from_json(JsonFile::read(path)?)
    }

    /// [`SpeedCamera::read`] on the text of the file `path` names.
    ///
    /// ```
    /// use orbit_nerf_host::formats::camera::SpeedCamera;
    /// use std::path::Path;
    ///
    /// let text = r#"{"Nu": 640, "Nv": 480,
    ///     "cameraMatrix": [[800, 0, 320], [0, 800, 240], [0, 0, 1]]}"#;
    /// let camera = SpeedCamera::parse(Path::new("camera.json"), text).unwrap();
    /// assert_eq!((camera.pinhole().fx, camera.pinhole().cx), (800.0, 320.0));
    /// assert!(camera.distortion().is_none());
    ///
    /// // A skewed matrix is no pinhole camera.
    /// let skewed = text.replace("[[800, 0, 320]", "[[800, 5, 320]");
    /// assert!(SpeedCamera::parse(Path::new("camera.json"), &skewed).is_err());
    /// ```
    pub fn parse(path: &Path, text: &str) -> Result<SpeedCamera> {
        SpeedCamera::from_json(JsonFile::parse(path, text)?)
    }

    fn from_json(json: JsonFile) -> Result<SpeedCamera> {
        let path = json.path.as_path();
        let value = &json.root;
        let optional = |key: &str| -> Result<Option<f64>> {
            value.get(key).map(|v| json.positive(v, key)).transpose()
        };
        let size = |key: &str| -> Result<u32> {
            value
                .get(key)
                .and_then(Value::as_u64)
                .filter(|&v| v > 0 && v <= u16::MAX as u64)
                .map(|v| v as u32)
                .ok_or_else(|| {
                    HostError::field(path, key, "missing or not an image size in 1..=65535")
                })
        };
        let (width, height) = (size("Nu")?, size("Nv")?);
        let pixel_pitch = match (optional("ppx")?, optional("ppy")?) {
            (Some(x), Some(y)) => Some([x, y]),
            (None, None) => None,
            (Some(_), None) => return Err(HostError::field(path, "ppy", "missing (ppx is given)")),
            (None, Some(_)) => return Err(HostError::field(path, "ppx", "missing (ppy is given)")),
        };
        let matrix = match value.get("cameraMatrix") {
            Some(rows) => Some(read_camera_matrix(&json, rows)?),
            None => None,
        };
        // The focal lengths in pixels from `fx`/`fy`: metres over the pitch when it is given.
        let focal = |key: &str, axis: usize| -> Result<Option<f64>> {
            let Some(f) = optional(key)? else {
                return Ok(None);
            };
            match pixel_pitch {
                Some(pitch) => Ok(Some(f / pitch[axis])),
                None if matrix.is_none() && f < 1.0 => Err(HostError::field(
                    path,
                    key,
                    format!(
                        "{f} is under one pixel: a focal length in metres needs the pixel \
                         pitch (ppx, ppy) or a cameraMatrix"
                    ),
                )),
                // With a matrix and no pitch, `fx` is read in pixels only if it looks like
                // pixels; metres without a pitch cannot be checked, so they are left out.
                None if f < 1.0 => Ok(None),
                None => Ok(Some(f)),
            }
        };
        let (fx, fy) = (focal("fx", 0)?, focal("fy", 1)?);
        let centre = |key: &str| -> Result<Option<f64>> {
            value.get(key).map(|v| json.number(v, key)).transpose()
        };
        let (ccx, ccy) = (centre("ccx")?, centre("ccy")?);
        let camera_matrix = match matrix {
            Some(k) => {
                let given = [
                    (
                        "fx",
                        fx,
                        k[0][0],
                        FOCAL_AGREEMENT * k[0][0].abs(),
                        "cameraMatrix[0][0]",
                    ),
                    (
                        "fy",
                        fy,
                        k[1][1],
                        FOCAL_AGREEMENT * k[1][1].abs(),
                        "cameraMatrix[1][1]",
                    ),
                    (
                        "ccx",
                        ccx,
                        k[0][2],
                        CENTRE_AGREEMENT_PX,
                        "cameraMatrix[0][2]",
                    ),
                    (
                        "ccy",
                        ccy,
                        k[1][2],
                        CENTRE_AGREEMENT_PX,
                        "cameraMatrix[1][2]",
                    ),
                ];
                for (key, value, expected, tolerance, matrix_field) in given {
                    if let Some(value) = value.filter(|v| (v - expected).abs() > tolerance) {
                        let unit = if key.starts_with('f') && pixel_pitch.is_some() {
                            " px (metres over the pixel pitch)"
                        } else {
                            " px"
                        };
                        return Err(HostError::field(
                            path,
                            key,
                            format!("gives {value:.4}{unit}, but {matrix_field} is {expected:.4}"),
                        ));
                    }
                }
                k
            }
            None => {
                if fx.is_none() && fy.is_none() && ccx.is_none() && ccy.is_none() {
                    return Err(HostError::field(
                        path,
                        "cameraMatrix",
                        "missing: give cameraMatrix, or fx/fy/ccx/ccy in pixels, or fx/fy in \
                         metres with ppx/ppy and ccx/ccy",
                    ));
                }
                let need = |key: &str, v: Option<f64>| {
                    v.ok_or_else(|| {
                        HostError::field(path, key, "missing (no cameraMatrix to take it from)")
                    })
                };
                let (fx, fy) = (need("fx", fx)?, need("fy", fy)?);
                let (cx, cy) = (need("ccx", ccx)?, need("ccy", ccy)?);
                [[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]
            }
        };
        for (field, focal, side) in [
            ("cameraMatrix[0][0]", camera_matrix[0][0], width),
            ("cameraMatrix[1][1]", camera_matrix[1][1], height),
        ] {
            if let Some(problem) = focal_problem(focal, side as f64) {
                return Err(HostError::field(path, field, problem));
            }
        }
        let dist_coeffs = match value.get("distCoeffs") {
            Some(coeffs) => json.numbers_exact(coeffs, "distCoeffs")?,
            None => [0.0; 5],
        };
        for (i, (c, name)) in dist_coeffs
            .iter()
            .zip(["k1", "k2", "p1", "p2", "k3"])
            .enumerate()
        {
            let limit = Distortion::limit(name);
            if c.abs() > limit {
                return Err(HostError::field(
                    path,
                    format!("distCoeffs[{i}]"),
                    format!("{c} is not a lens distortion coefficient (|{name}| <= {limit})"),
                ));
            }
        }
        let camera = SpeedCamera {
            width,
            height,
            pixel_pitch,
            camera_matrix,
            dist_coeffs,
        };
        if !camera.pinhole().is_valid() {
            return Err(HostError::field(
                path,
                "cameraMatrix",
                "focal lengths must be positive",
            ));
        }
        Ok(camera)
    }

    /// Write the camera to `path` (atomically) in the SPEED+ layout: the metre fields `ppx`,
    /// `ppy`, `fx`, `fy` only when the pixel pitch is known.
    pub fn write(&self, path: &Path) -> Result<()> {
        let k = &self.camera_matrix;
        let metres = |axis: usize| self.pixel_pitch.map(|p| k[axis][axis] * p[axis]);
        let file = SpeedCameraFile {
            width: self.width,
            height: self.height,
            ppx: self.pixel_pitch.map(|p| p[0]),
            ppy: self.pixel_pitch.map(|p| p[1]),
            fx: metres(0),
            fy: metres(1),
            ccx: k[0][2],
            ccy: k[1][2],
            camera_matrix: *k,
            dist_coeffs: self.dist_coeffs,
        };
        write_json(path, &file)
    }

    /// The pinhole intrinsics in pixels (from `cameraMatrix`).
    pub fn pinhole(&self) -> Camera {
        let k = &self.camera_matrix;
        Camera {
            width: self.width as u16,
            height: self.height as u16,
            fx: k[0][0] as f32,
            fy: k[1][1] as f32,
            cx: k[0][2] as f32,
            cy: k[1][2] as f32,
        }
    }

    /// Whether any distortion coefficient is non-zero.
    pub fn has_distortion(&self) -> bool {
        self.dist_coeffs.iter().any(|&c| c != 0.0)
    }

    /// The lens distortion, `None` when every coefficient is zero.
    pub fn distortion(&self) -> Option<Distortion> {
        self.has_distortion().then(|| self.lens())
    }

    /// Apply the OpenCV distortion to normalised image coordinates `(x, y)` (z = 1).
    pub fn distort(&self, x: f32, y: f32) -> (f32, f32) {
        self.lens().apply(x, y)
    }

    /// The distortion coefficients as used (f32), zero or not.
    fn lens(&self) -> Distortion {
        Distortion::Opencv(self.dist_coeffs.map(|c| c as f32))
    }

    /// Invert [`SpeedCamera::distort`] by fixed-point iteration (as OpenCV's `undistortPoints`).
    pub fn undistort(&self, xd: f32, yd: f32) -> (f32, f32) {
        self.lens().invert(xd, yd)
    }
}

/// `cameraMatrix`: 3x3 finite numbers in the pinhole layout `[[fx, 0, cx], [0, fy, cy], [0, 0,
/// 1]]` (a skew or a projective last row is no lens this reader can cast rays through).
fn read_camera_matrix(json: &JsonFile, rows: &Value) -> Result<[[f64; 3]; 3]> {
    let rows = rows
        .as_array()
        .filter(|rows| rows.len() == 3)
        .ok_or_else(|| json.field("cameraMatrix", "expected a 3x3 matrix"))?;
    let mut matrix = [[0.0; 3]; 3];
    for (r, (out, row)) in matrix.iter_mut().zip(rows).enumerate() {
        *out = json.numbers_exact(row, &format!("cameraMatrix[{r}]"))?;
    }
    for (r, c, expected) in [
        (0, 1, 0.0),
        (1, 0, 0.0),
        (2, 0, 0.0),
        (2, 1, 0.0),
        (2, 2, 1.0),
    ] {
        if matrix[r][c] != expected {
            return Err(json.field(
                format!("cameraMatrix[{r}][{c}]"),
                format!(
                    "is {}, not {expected}: a pinhole camera matrix is [[fx, 0, cx], [0, fy, \
                     cy], [0, 0, 1]]{}",
                    matrix[r][c],
                    if (r, c) == (0, 1) { " (no skew)" } else { "" }
                ),
            ));
        }
    }
    Ok(matrix)
}
