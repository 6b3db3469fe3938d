//! New views: camera paths around the target (a circle at the dataset's mean camera distance,
//! or a path file), their renders, the animated GIF and the MP4 of them.
//!
//! **Path file** (text, UTF-8): one camera per line, `eye_x eye_y eye_z target_x target_y
//! target_z`, optionally followed by `up_x up_y up_z` (default: the dataset's mean camera
//! up), all in world units; blank lines and lines starting with `#` are skipped. The camera
//! sits at the eye and looks at the target, its image's up as close to `up` as the view
//! allows. Every number must be finite, the eye must differ from the target and `up` must not
//! be parallel to the view direction.

use crate::error::{HostError, Result};
use crate::pipeline::SplitData;
use crate::train::to_rgb8;
use image::codecs::gif::{GifEncoder, Repeat};
use image::{Delay, Frame, RgbaImage};
use orbit_nerf_core::glam::{Mat3, Vec3};
use orbit_nerf_core::{Executor, Pose, Trainer};
use std::path::{Path, PathBuf};

/// Where the dataset's cameras are, as an orbit needs it: its centre, the mean camera up,
/// the mean distance to the centre and the mean elevation above the plane normal to up.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Surroundings {
    /// The point the cameras are measured from (the scene box centre), world units.
    pub centre: Vec3,
    /// The cameras' mean up (unit length), the orbit's axis.
    pub up: Vec3,
    /// Mean distance of the cameras from `centre`, world units (always finite and > 0).
    pub distance: f32,
    /// Mean elevation of the cameras above the plane through `centre` normal to `up`, degrees
    /// (negative below it).
    pub elevation_deg: f32,
    /// Unit direction (normal to up) of the first camera, where the orbit starts.
    pub start: Vec3,
}

/// The surroundings of `poses` about `centre` (the scene box centre). `None` without poses
/// or when they are all at the centre.
pub fn surroundings(poses: &[Pose], centre: Vec3) -> Option<Surroundings> {
    let first = poses.first()?;
    let up = mean_up(poses);
    let n = poses.len() as f32;
    let distance = poses.iter().map(|p| p.center.distance(centre)).sum::<f32>() / n;
    let elevation_deg = poses
        .iter()
        .filter_map(|p| (p.center - centre).try_normalize())
        .map(|d| d.dot(up).clamp(-1.0, 1.0).asin().to_degrees())
        .sum::<f32>()
        / n;
    let start = reject(first.center - centre, up)
        .or_else(|| reject(Vec3::X, up))
        .or_else(|| reject(Vec3::Y, up))?;
    (distance.is_finite() && distance > 0.0).then_some(Surroundings {
        centre,
        up,
        distance,
        elevation_deg,
        start,
    })
}

/// The world's up for `poses`: the direction most nearly normal to every camera's image x
/// axis (exactly normal for cameras without roll, as in turntable and drone captures),
/// signed like the cameras' mean image up (-y in OpenCV axes). The mean image up alone
/// leans towards where the cameras look when they look down or up at the target.
fn mean_up(poses: &[Pose]) -> Vec3 {
    let image_up = poses
        .iter()
        .map(|p| -p.rotation.col(1))
        .sum::<Vec3>()
        .try_normalize()
        .unwrap_or(Vec3::Z);
    // The smallest eigenvector of sum(x x^T) is the largest of n I - sum(x x^T) (power
    // iteration, from the image up).
    let rights: Vec<Vec3> = poses.iter().map(|p| p.rotation.col(0)).collect();
    let n = rights.len() as f32;
    let mut up = image_up;
    for _ in 0..200 {
        let next = up * n - rights.iter().map(|x| *x * x.dot(up)).sum::<Vec3>();
        match next.try_normalize() {
            Some(v) => up = v,
            None => return image_up,
        }
    }
    if up.dot(image_up) < 0.0 { -up } else { up }
}

/// The unit part of `v` normal to unit `axis`, if there is one.
fn reject(v: Vec3, axis: Vec3) -> Option<Vec3> {
    (v - axis * v.dot(axis)).try_normalize()
}

/// `count` cameras evenly spaced on the circle about `s.up` through the centre, at `s`'s
/// distance and at `elevation_deg` above the plane normal to up, starting beside the
/// dataset's first camera, each looking at the centre.
pub fn orbit(s: &Surroundings, count: usize, elevation_deg: f32) -> Vec<Pose> {
    let side = s.up.cross(s.start);
    let elevation = elevation_deg.to_radians();
    (0..count)
        .map(|k| {
            let azimuth = std::f32::consts::TAU * k as f32 / count as f32;
            let around = s.start * azimuth.cos() + side * azimuth.sin();
            let direction = around * elevation.cos() + s.up * elevation.sin();
            // The orbit's own points are never on the up axis (|elevation| < 90 degrees).
            look_at(s.centre + direction * s.distance, s.centre, s.up).unwrap_or(Pose {
                rotation: Mat3::IDENTITY,
                center: s.centre,
            })
        })
        .collect()
}

/// The camera at `eye` looking at `target` with its image's up towards `up` (OpenCV axes:
/// x right, y down, z forward). `None` when the eye is the target or `up` is along the view.
pub fn look_at(eye: Vec3, target: Vec3, up: Vec3) -> Option<Pose> {
    let forward = (target - eye).try_normalize()?;
    let right = forward.cross(up).try_normalize()?;
    let down = forward.cross(right);
    Some(Pose {
        rotation: Mat3::from_cols(right, down, forward),
        center: eye,
    })
}

/// Read a path file (format in the module documentation); `default_up` for lines without one.
pub fn read_path(path: &Path, default_up: Vec3) -> Result<Vec<Pose>> {
    let text = std::fs::read_to_string(path).map_err(|e| HostError::io(path, e))?;
    let mut poses = Vec::new();
    for (number, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let field = format!("line {}", number + 1);
        let values: Vec<f32> = line
            .split_whitespace()
            .map(|v| v.parse::<f32>().ok().filter(|v| v.is_finite()))
            .collect::<Option<_>>()
            .ok_or_else(|| HostError::field(path, &field, "expected finite numbers"))?;
        let at = |i: usize| Vec3::new(values[i], values[i + 1], values[i + 2]);
        let (eye, target, up) = match values.len() {
            6 => (at(0), at(3), default_up),
            9 => (at(0), at(3), at(6)),
            n => {
                return Err(HostError::field(
                    path,
                    &field,
                    format!("{n} numbers; expected 6 (eye, target) or 9 (eye, target, up)"),
                ));
            }
        };
        let pose = look_at(eye, target, up).ok_or_else(|| {
            HostError::field(
                path,
                &field,
                "the eye is the target, or up is along the view direction",
            )
        })?;
        poses.push(pose);
    }
    if poses.is_empty() {
        return Err(HostError::invalid(path, "holds no camera"));
    }
    Ok(poses)
}

/// Write RGB8 frames of `width` x `height` as an endlessly looping animated GIF, each shown
/// for `frame_ms` milliseconds (atomically).
pub fn write_gif(
    path: &Path,
    width: u32,
    height: u32,
    frames: &[Vec<u8>],
    frame_ms: u32,
) -> Result<()> {
    let mut bytes = Vec::new();
    {
        let mut encoder = GifEncoder::new_with_speed(&mut bytes, 10);
        let fail =
            |e: image::ImageError| HostError::invalid(path, format!("GIF encoding failed: {e}"));
        encoder.set_repeat(Repeat::Infinite).map_err(fail)?;
        for rgb in frames {
            let rgba: Vec<u8> = rgb
                .chunks_exact(3)
                .flat_map(|p| [p[0], p[1], p[2], 255])
                .collect();
            let image = RgbaImage::from_raw(width, height, rgba)
                .ok_or_else(|| HostError::invalid(path, "frame does not match the image size"))?;
            let delay = Delay::from_numer_denom_ms(frame_ms, 1);
            encoder
                .encode_frame(Frame::from_parts(image, 0, 0, delay))
                .map_err(fail)?;
        }
    }
    crate::io::write_atomic(path, &bytes)
}

/// The cameras of a new-view render.
#[derive(Clone, Debug)]
pub enum CameraPath {
    /// `count` views on a circle about the training cameras' mean up through the box centre,
    /// at their mean distance, at `elevation_deg` (default: their mean elevation).
    Orbit {
        /// Views on the circle.
        count: usize,
        /// Elevation above the plane normal to the mean up, degrees (-89 to 89).
        elevation_deg: Option<f32>,
    },
    /// The cameras of a path file (see the module's documentation).
    File(PathBuf),
}

/// What [`render_path`] wrote.
#[derive(Clone, Debug)]
pub struct RenderedPath {
    /// Views rendered (`orbit_NNNN.png` each).
    pub count: usize,
    /// Their width, pixels.
    pub width: u32,
    /// Their height, pixels.
    pub height: u32,
    /// The orbit's distance from the box centre, world units.
    pub distance: f32,
    /// The animated GIF.
    pub gif: PathBuf,
    /// The MP4, when ffmpeg was on the PATH.
    pub mp4: Option<PathBuf>,
}

/// The files a path of `count` views writes into `out`: the frames, the GIF and the MP4.
fn path_outputs(out: &Path, count: usize) -> Vec<PathBuf> {
    let mut files: Vec<PathBuf> = (0..count)
        .map(|k| out.join(format!("orbit_{k:04}.png")))
        .collect();
    files.push(out.join("orbit.gif"));
    files.push(out.join("orbit.mp4"));
    files
}

/// Render `path`'s cameras with `trainer` (the checkpoint at `checkpoint`, named in errors),
/// the first training view's intrinsics and the mean training embedding, into `out`:
/// `orbit_NNNN.png` per view, `orbit.gif` (each frame shown `frame_ms`) and `orbit.mp4` when
/// ffmpeg is on the PATH. An existing output is refused unless `force`; a render with a
/// non-finite pixel is refused (the checkpoint is broken).
pub fn render_path<E: Executor>(
    trainer: &mut Trainer<'_>,
    executor: &E,
    (checkpoint, data): (&Path, &SplitData),
    path: &CameraPath,
    out: &Path,
    (frame_ms, force): (u32, bool),
) -> Result<RenderedPath> {
    crate::io::check_output_folder(out)?;
    let dataset = &data.dataset;
    let camera = dataset.frames[0].camera;
    let training: Vec<Pose> = (data.train.iter())
        .map(|&i| dataset.frames[i].pose)
        .collect();
    let c = *trainer.config();
    let centre = (Vec3::from_array(c.aabb_min) + Vec3::from_array(c.aabb_max)) * 0.5;
    let around = surroundings(&training, centre).ok_or_else(|| {
        HostError::invalid(
            &dataset.source,
            "the training cameras give no orbit (none, or all at the box centre)",
        )
    })?;
    let poses = match path {
        CameraPath::File(file) => read_path(file, around.up)?,
        CameraPath::Orbit {
            count,
            elevation_deg,
        } => {
            let elevation = elevation_deg.unwrap_or(around.elevation_deg.clamp(-89.0, 89.0));
            // At +-90 degrees the view runs along up: no camera looks there with that up.
            if !(-89.0..=89.0).contains(&elevation) || *count == 0 {
                return Err(HostError::invalid(
                    out,
                    format!(
                        "an orbit needs 1 or more views at an elevation of -89 to 89 degrees, not {count} at {elevation}"
                    ),
                ));
            }
            orbit(&around, *count, elevation)
        }
    };
    let files = path_outputs(out, poses.len());
    crate::io::check_new_files(files.iter().map(PathBuf::as_path), force)?;
    let mut embedding = vec![0.0f32; c.embedding_dim as usize];
    trainer.mean_embedding(&mut embedding);
    let (width, height) = (camera.width as u32, camera.height as u32);
    let mut frames = Vec::with_capacity(poses.len());
    let mut image = vec![0.0f32; camera.pixel_count() * 3];
    for (pose, file) in poses.iter().zip(&files) {
        trainer
            .render(executor, &camera, pose, &embedding, &mut image)
            .map_err(|e| HostError::Core(e.to_string()))?;
        if image.iter().any(|v| !v.is_finite()) {
            return Err(HostError::invalid(
                checkpoint,
                format!(
                    "the render of {} holds non-finite pixels: the checkpoint is broken",
                    file.display()
                ),
            ));
        }
        let rgb = to_rgb8(&image);
        crate::io::write_png(file, width, height, 3, &rgb)?;
        frames.push(rgb);
    }
    let gif = files[poses.len()].clone();
    write_gif(&gif, width, height, &frames, frame_ms)?;
    let mp4 = encode_mp4(out, poses.len(), frame_ms, &files[poses.len() + 1])?;
    Ok(RenderedPath {
        count: poses.len(),
        width,
        height,
        distance: around.distance,
        gif,
        mp4,
    })
}

/// `mp4` from the frames `orbit_NNNN.png` in `out` with ffmpeg when it is on the PATH
/// (written to a temporary name and renamed); `None` without it.
fn encode_mp4(out: &Path, frames: usize, frame_ms: u32, mp4: &Path) -> Result<Option<PathBuf>> {
    let ffmpeg = std::process::Command::new("ffmpeg")
        .arg("-version")
        .output();
    if !ffmpeg.is_ok_and(|o| o.status.success()) || frames == 0 {
        return Ok(None);
    }
    let tmp = out.join(format!("orbit.tmp{}.mp4", std::process::id()));
    let result = std::process::Command::new("ffmpeg")
        .args(["-loglevel", "error", "-y", "-framerate"])
        .arg(format!("{}/{frame_ms}", 1000))
        .arg("-i")
        .arg(out.join("orbit_%04d.png"))
        .args([
            "-vf",
            "pad=ceil(iw/2)*2:ceil(ih/2)*2",
            "-pix_fmt",
            "yuv420p",
        ])
        .arg(&tmp)
        .status();
    match result {
        Ok(s) if s.success() => {
            std::fs::rename(&tmp, mp4).map_err(|e| HostError::io(mp4, e))?;
            Ok(Some(mp4.to_path_buf()))
        }
        _ => {
            let _ = std::fs::remove_file(&tmp);
            Err(HostError::invalid(mp4, "ffmpeg failed to write it"))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn orbit_cameras_circle_the_centre_and_look_at_it() {
        let centre = Vec3::new(0.5, -0.2, 0.1);
        let dataset: Vec<Pose> = [Vec3::new(3.0, 0.0, 1.0), Vec3::new(0.0, 3.0, 1.5)]
            .iter()
            .map(|&e| look_at(centre + e, centre, Vec3::Z).unwrap())
            .collect();
        let s = surroundings(&dataset, centre).unwrap();
        assert!(s.up.distance(Vec3::Z) < 1e-5, "{s:?}");
        let poses = orbit(&s, 12, 30.0);
        assert_eq!(poses.len(), 12);
        for pose in &poses {
            assert!((pose.center.distance(centre) - s.distance).abs() < 1e-4);
            let forward = pose.rotation.col(2);
            assert!(forward.dot((centre - pose.center).normalize()) > 0.9999);
            let elevation = (pose.center - centre).normalize().dot(Vec3::Z).asin();
            assert!((elevation.to_degrees() - 30.0).abs() < 1e-3);
            // The image's down is the world's down side.
            assert!(pose.rotation.col(1).dot(Vec3::Z) < 0.0);
        }
    }

    #[test]
    fn path_files_are_read_and_bad_lines_are_named() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("path.txt");
        std::fs::write(&file, "# eye target\n\n3 0 0  0 0 0\n0 3 0 0 0 0 0 0 1\n").unwrap();
        let poses = read_path(&file, Vec3::Z).unwrap();
        assert_eq!(poses.len(), 2);
        assert!(poses[0].rotation.col(2).distance(-Vec3::X) < 1e-6);
        for (text, field) in [
            ("3 0 0 0 0\n", "line 1"),
            ("\n1 1 1 1 1 1\n", "line 2"),
            ("3 0 0 0 0 nan\n", "line 1"),
            ("0 0 3 0 0 0\n", "line 1"),
        ] {
            std::fs::write(&file, text).unwrap();
            match read_path(&file, Vec3::Z) {
                Err(HostError::Field { field: f, .. }) => assert_eq!(f, field, "{text}"),
                other => panic!("{text}: {other:?}"),
            }
        }
        std::fs::write(&file, "# nothing\n").unwrap();
        assert!(read_path(&file, Vec3::Z).is_err());
    }
}
