//! JSON files read by the loaders: one parser (which names the field holding a `NaN` that
//! Python wrote) and field readers whose errors say `file: field \`path\`: reason`.

use super::camera::FIELD_OF_VIEW_DEG;
use crate::error::{HostError, Result};
use crate::io::write_atomic;
use glam::{DMat3, DVec3, Mat3, Quat, Vec3};
use orbit_nerf_core::Pose;
use serde::Serialize;
use serde_json::Value;
use std::path::{Path, PathBuf};

/// Read a JSON file; `NaN` and `Infinity` literals (which Python writes) become marked strings,
/// so the number check names the field that holds one.
pub(crate) fn read_json(path: &Path) -> Result<Value> {
    let text = std::fs::read_to_string(path).map_err(|e| HostError::io(path, e))?;
    parse_json(path, &text)
}

/// [`read_json`] on the text of the file `path` names.
pub(crate) fn parse_json(path: &Path, text: &str) -> Result<Value> {
    serde_json::from_str(&quote_non_finite_literals(text))
        .map_err(|e| HostError::invalid(path, format!("malformed JSON: {e}")))
}

/// Write `value` as pretty JSON (with a final newline), atomically.
pub(crate) fn write_json<T: Serialize + ?Sized>(path: &Path, value: &T) -> Result<()> {
    let mut text = serde_json::to_string_pretty(value)
        .map_err(|e| HostError::invalid(path, format!("cannot encode JSON: {e}")))?;
    text.push('\n');
    write_atomic(path, text.as_bytes())
}

/// A parsed JSON file that reports problems as `file: field \`path\`: reason`.
pub(crate) struct JsonFile {
    pub(crate) path: PathBuf,
    pub(crate) root: Value,
}

impl JsonFile {
    /// A file whose top level is an object.
    pub(crate) fn read(path: &Path) -> Result<JsonFile> {
        JsonFile::object(JsonFile::read_any(path)?)
    }

    /// [`JsonFile::read`] on the text of the file `path` names.
    pub(crate) fn parse(path: &Path, text: &str) -> Result<JsonFile> {
        JsonFile::object(JsonFile::parse_any(path, text)?)
    }

    fn object(json: JsonFile) -> Result<JsonFile> {
        let path = &json.path;
        if !json.root.is_object() {
            return Err(HostError::invalid(
                path,
                "malformed JSON: the top level must be an object",
            ));
        }
        Ok(json)
    }

    /// A file with any top level (a label file is a list).
    pub(crate) fn read_any(path: &Path) -> Result<JsonFile> {
        Ok(JsonFile {
            path: path.to_path_buf(),
            root: read_json(path)?,
        })
    }

    /// [`JsonFile::read_any`] on the text of the file `path` names.
    pub(crate) fn parse_any(path: &Path, text: &str) -> Result<JsonFile> {
        Ok(JsonFile {
            path: path.to_path_buf(),
            root: parse_json(path, text)?,
        })
    }

    pub(crate) fn field(&self, field: impl Into<String>, reason: impl Into<String>) -> HostError {
        HostError::field(&self.path, field, reason)
    }

    /// A path in the file, relative to the file's folder.
    pub(crate) fn resolve(&self, relative: &str) -> PathBuf {
        self.path.parent().unwrap_or(Path::new("")).join(relative)
    }

    pub(crate) fn get<'v>(&self, object: &'v Value, key: &str, field: &str) -> Result<&'v Value> {
        object.get(key).ok_or_else(|| self.field(field, "missing"))
    }

    pub(crate) fn frames(&self) -> Result<&Vec<Value>> {
        match self.get(&self.root, "frames", "frames")?.as_array() {
            Some(frames) if !frames.is_empty() => Ok(frames),
            Some(_) => Err(self.field("frames", "no frames")),
            None => Err(self.field("frames", "must be a list")),
        }
    }

    pub(crate) fn string<'v>(&self, value: &'v Value, field: &str) -> Result<&'v str> {
        value
            .as_str()
            .ok_or_else(|| self.field(field, format!("expected a string, found {value}")))
    }

    /// A number that stays finite as `f32` (what the dataset stores).
    pub(crate) fn number(&self, value: &Value, field: &str) -> Result<f64> {
        if let Some(literal) = value.as_str().and_then(|s| s.strip_prefix(NON_FINITE_MARK)) {
            return Err(self.field(field, format!("{literal} is not a finite number")));
        }
        let number = value
            .as_f64()
            .ok_or_else(|| self.field(field, format!("expected a number, found {value}")))?;
        if !(number as f32).is_finite() {
            return Err(self.field(field, format!("{number:e} is not a finite 32-bit number")));
        }
        Ok(number)
    }

    pub(crate) fn positive(&self, value: &Value, field: &str) -> Result<f64> {
        let number = self.number(value, field)?;
        if number <= 0.0 {
            return Err(self.field(field, format!("must be positive, found {number}")));
        }
        Ok(number)
    }

    /// A pinhole field of view in radians, within [`FIELD_OF_VIEW_DEG`].
    pub(crate) fn field_of_view(&self, value: &Value, field: &str) -> Result<f64> {
        let angle = self.positive(value, field)?;
        let (min, max) = FIELD_OF_VIEW_DEG;
        if !(min..=max).contains(&angle.to_degrees()) {
            return Err(self.field(
                field,
                format!(
                    "{angle} rad is not a pinhole camera's field of view (between {min} and \
                     {max} deg)"
                ),
            ));
        }
        Ok(angle)
    }

    pub(crate) fn numbers(&self, value: &Value, field: &str) -> Result<Vec<f64>> {
        let list = value
            .as_array()
            .ok_or_else(|| self.field(field, format!("expected a list, found {value}")))?;
        list.iter()
            .enumerate()
            .map(|(i, v)| self.number(v, &format!("{field}[{i}]")))
            .collect()
    }

    /// A list of exactly `N` numbers.
    pub(crate) fn numbers_exact<const N: usize>(
        &self,
        value: &Value,
        field: &str,
    ) -> Result<[f64; N]> {
        let values = self.numbers(value, field)?;
        <[f64; N]>::try_from(values).map_err(|values| {
            self.field(
                field,
                format!("expected {N} numbers, found {}", values.len()),
            )
        })
    }

    /// An OpenGL camera-to-world matrix (3x4 or 4x4, rows) as an OpenCV-axes pose. The rotation
    /// must be orthonormal with determinant +1 to within 1e-3; it is then snapped to the nearest
    /// rotation so the small rounding of the file does not accumulate downstream.
    pub(crate) fn pose(&self, value: &Value, field: &str) -> Result<Pose> {
        let rows = value
            .as_array()
            .ok_or_else(|| self.field(field, "expected a list of rows"))?;
        if rows.len() != 3 && rows.len() != 4 {
            return Err(self.field(field, format!("expected 3 or 4 rows, found {}", rows.len())));
        }
        let mut m = [[0.0f64; 4]; 4];
        for (r, row) in rows.iter().enumerate() {
            m[r] = self.numbers_exact(row, &format!("{field}[{r}]"))?;
        }
        if rows.len() == 4 {
            let bottom_error = m[3]
                .iter()
                .zip([0.0, 0.0, 0.0, 1.0])
                .map(|(a, b)| (a - b).abs())
                .fold(0.0, f64::max);
            if bottom_error > 1e-4 {
                return Err(self.field(
                    field,
                    format!("bottom row must be [0, 0, 0, 1], found {:?}", m[3]),
                ));
            }
        }
        let rotation = DMat3::from_cols(
            DVec3::new(m[0][0], m[1][0], m[2][0]),
            DVec3::new(m[0][1], m[1][1], m[2][1]),
            DVec3::new(m[0][2], m[1][2], m[2][2]),
        );
        let gram = rotation.transpose() * rotation - DMat3::IDENTITY;
        let orthonormality_error = gram
            .to_cols_array()
            .iter()
            .fold(0.0f64, |a, v| a.max(v.abs()));
        if orthonormality_error > 1e-3 {
            return Err(self.field(
                field,
                format!("not a rigid transform: the rotation part is not orthonormal (max |R^T R - I| = {orthonormality_error:.3e})"),
            ));
        }
        let det = rotation.determinant();
        if (det - 1.0).abs() > 1e-3 {
            return Err(self.field(
                field,
                format!("not a rigid transform: the rotation part has determinant {det:.4}"),
            ));
        }
        let rotation = Mat3::from_quat(Quat::from_mat3(&rotation.as_mat3()).normalize());
        // OpenGL (y up, looking down -z) to OpenCV (y down, looking down +z).
        let rotation = Mat3::from_cols(rotation.x_axis, -rotation.y_axis, -rotation.z_axis);
        let center = Vec3::new(m[0][3] as f32, m[1][3] as f32, m[2][3] as f32);
        Ok(Pose { rotation, center })
    }

    /// The two fields every `transforms.json` frame has: `file_path` and `transform_matrix`
    /// (as a pose, see [`JsonFile::pose`]), named `frames[index].key` in errors.
    pub(crate) fn frame_file_and_pose(
        &self,
        frame: &Value,
        index: usize,
    ) -> Result<(String, Pose)> {
        let path_field = format!("frames[{index}].file_path");
        let name = self
            .string(self.get(frame, "file_path", &path_field)?, &path_field)?
            .to_owned();
        let matrix_field = format!("frames[{index}].transform_matrix");
        let pose = self.pose(
            self.get(frame, "transform_matrix", &matrix_field)?,
            &matrix_field,
        )?;
        Ok((name, pose))
    }

    pub(crate) fn scene_box(&self, key: &str) -> Result<([f32; 3], [f32; 3])> {
        let corners = self.root[key]
            .as_array()
            .filter(|c| c.len() == 2)
            .ok_or_else(|| self.field(key, "expected [[min x, y, z], [max x, y, z]]"))?;
        let mut bounds = [[0.0f32; 3]; 2];
        for (i, corner) in corners.iter().enumerate() {
            let values: [f64; 3] = self.numbers_exact(corner, &format!("{key}[{i}]"))?;
            bounds[i] = values.map(|v| v as f32);
        }
        if (0..3).any(|axis| bounds[0][axis] >= bounds[1][axis]) {
            return Err(self.field(
                key,
                format!(
                    "min {:?} is not below max {:?} on every axis",
                    bounds[0], bounds[1]
                ),
            ));
        }
        Ok((bounds[0], bounds[1]))
    }
}

/// Prefix of the strings that stand in for `NaN` / `Infinity` literals. Only number fields
/// look for it, and a string there is an error anyway, so it cannot hide a real value.
const NON_FINITE_MARK: &str = "non-finite literal ";

/// Python's `json.dump` writes `NaN`, `Infinity` and `-Infinity`, which are not JSON. Quote
/// them (outside strings) so the file parses and the number check can name the field that holds
/// one, instead of failing with only a line and column.
fn quote_non_finite_literals(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    let mut in_string = false;
    let mut escaped = false;
    let mut rest = text;
    while let Some(c) = rest.chars().next() {
        if in_string {
            if escaped {
                escaped = false;
            } else if c == '\\' {
                escaped = true;
            } else if c == '"' {
                in_string = false;
            }
        } else if c == '"' {
            in_string = true;
        } else if let Some(literal) = ["-Infinity", "Infinity", "NaN"]
            .into_iter()
            .find(|l| rest.starts_with(l))
        {
            out.push('"');
            out.push_str(NON_FINITE_MARK);
            out.push_str(literal);
            out.push('"');
            rest = &rest[literal.len()..];
            continue;
        }
        out.push(c);
        rest = &rest[c.len_utf8()..];
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nan_literals_inside_strings_are_left_alone() {
        let text = r#"{"a": "NaN \" Infinity", "b": [NaN, -Infinity, 1]}"#;
        let value: Value = serde_json::from_str(&quote_non_finite_literals(text)).unwrap();
        assert_eq!(value["a"], "NaN \" Infinity");
        assert_eq!(
            value["b"][1]
                .as_str()
                .unwrap()
                .strip_prefix(NON_FINITE_MARK),
            Some("-Infinity")
        );
        assert_eq!(value["b"][2], 1);
    }
}
