//! Where streamed frames come from, one at a time and in arrival order: a dataset folder
//! (SPEED+ / SHIRT or NeRF-synthetic, optionally paced at a fixed rate), a folder being watched while files appear in it, or the
//! simulator rendering a preset frame by frame. No source holds more than the frame it hands
//! out; a held-out frame is read (or rendered) again when it is scored.
//!
//! **Watched folder format.** The folder holds `camera.json` (SPEED+ camera file) and, per
//! frame, an image `NAME.png` (or `.jpg`) and a label `NAME.json`: one SPEED+ label object
//! (`filename`, `q_vbs2tango_true` or `q_vbs2tango`, `r_Vo2To_vbs_true` or `r_Vo2To_vbs`).
//! Every frame that appears is taken once, whatever its name: of the frames not taken yet, the
//! first in natural name order (`img2` before `img10`) comes next, so a late arrival whose name
//! sorts before frames already taken is still ingested (or reported). A frame whose
//! files are not both there and readable yet is waited for (up to a grace period, since a
//! writer may be half-way through) before it is reported as bad. The stream ends when a file
//! named `END` appears and every frame before it is in, after an idle timeout with nothing new
//! (if one is set), or at a maximum frame count.

use crate::dataset::Frame;
use crate::error::{HostError, Result};
use crate::formats::nerf_synthetic::{self, SyntheticReader, SyntheticSplit};
use crate::formats::speedplus::{self, FrameDecoder, LoadOptions, SpeedCamera, SpeedPlusReader};
use crate::formats::transforms::{self, OutputSize};
#[cfg(feature = "simulator")]
use crate::sim::{FrameSimulator, Scene};
use orbit_nerf_core::Pose;
use std::cmp::Ordering as Order;
use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

/// What the trainer needs to know about a source before the first frame.
#[derive(Clone, Debug)]
pub struct SourceInfo {
    /// Where the frames come from, for messages.
    pub name: String,
    /// What identifies the source across runs (canonical path, or scene and its settings):
    /// a stream resumes only from the same source.
    pub identity: String,
    /// The box (world units) that holds the scene; `None` when the source cannot know it (a
    /// SPEED+ folder without `truth.json`: the stream sees one frame at a time, too few to
    /// find it, so the user states it).
    pub scene_box: Option<([f32; 3], [f32; 3])>,
    /// Colour the frames were composited on (and masked-out pixels get), in [0, 1].
    pub background: [f32; 3],
    /// Pixels of the largest frame.
    pub max_pixels: usize,
    /// Frames the source will deliver, when it knows.
    pub frames: Option<u64>,
    /// Whether the source knows its frames' exact poses ([`FrameSource::exact_pose`]: the
    /// simulator, a SPEED+ folder with `truth.json`): held-out views are scored there.
    pub exact_poses: bool,
}

/// One arriving frame: usable, or bad (the error names the file and the problem).
pub enum Arrival {
    /// A frame that read.
    Frame(Frame),
    /// A frame that did not read, and why.
    Bad(HostError),
}

/// Frames arriving one at a time: a dataset folder, the simulator, a watched folder, or any
/// feed a program brings (a camera, a downlink).
pub trait FrameSource {
    /// What the trainer needs to know before the first frame.
    fn info(&self) -> &SourceInfo;
    /// The next frame in arrival order, waiting for it if need be; `None` when the stream has
    /// ended or `stop` was raised while waiting.
    fn next(&mut self, stop: &AtomicBool) -> Option<Arrival>;
    /// Frames handed out (or skipped) so far: the position of the next one.
    fn position(&self) -> u64;
    /// Names of the frames handed out so far, in arrival order, where the order cannot be
    /// recomputed from the position alone (a watched folder); saved in the stream checkpoint.
    fn arrived(&self) -> &[String] {
        &[]
    }
    /// Skip forward so the next frame is the one at `position` (resuming a stream); `arrived`
    /// is what [`FrameSource::arrived`] returned when the checkpoint was written.
    fn seek(&mut self, position: u64, arrived: &[String]) -> Result<()>;
    /// The frame at a past position again (held-out evaluation).
    fn reload(&self, position: u64) -> Result<Frame>;
    /// The exact pose of the frame at a past position, where the source knows it
    /// ([`SourceInfo::exact_poses`]); held-out views are scored there rather than at their
    /// labels, as the paper's test set is.
    fn exact_pose(&self, _position: u64) -> Result<Option<Pose>> {
        Ok(None)
    }
}

/// Another source with its frames' masks applied (`Frame::apply_mask`, the source's background
/// colour where the mask is 0), for training and for scoring alike.
pub struct MaskedSource<'a> {
    inner: &'a mut dyn FrameSource,
}

impl<'a> MaskedSource<'a> {
    /// `inner` with its frames' masks applied.
    pub fn new(inner: &'a mut dyn FrameSource) -> Self {
        MaskedSource { inner }
    }
}

impl FrameSource for MaskedSource<'_> {
    fn info(&self) -> &SourceInfo {
        self.inner.info()
    }
    fn next(&mut self, stop: &AtomicBool) -> Option<Arrival> {
        let background = self.inner.info().background;
        self.inner.next(stop).map(|arrival| match arrival {
            Arrival::Frame(mut frame) => {
                frame.apply_mask(background);
                Arrival::Frame(frame)
            }
            bad => bad,
        })
    }
    fn position(&self) -> u64 {
        self.inner.position()
    }
    fn arrived(&self) -> &[String] {
        self.inner.arrived()
    }
    fn seek(&mut self, position: u64, arrived: &[String]) -> Result<()> {
        self.inner.seek(position, arrived)
    }
    fn reload(&self, position: u64) -> Result<Frame> {
        let mut frame = self.inner.reload(position)?;
        frame.apply_mask(self.inner.info().background);
        Ok(frame)
    }
    fn exact_pose(&self, position: u64) -> Result<Option<Pose>> {
        self.inner.exact_pose(position)
    }
}

/// A dataset folder read frame by frame in file order, optionally paced at `rate` frames per
/// second (pacing never changes what is learned): SPEED+ / SHIRT / simulator output in label
/// order, or a NeRF-synthetic scene's training split in `transforms_train.json` order
/// (composited on white, as NeRF-synthetic results are).
pub struct DatasetSource {
    reader: DatasetReader,
    info: SourceInfo,
    next: u64,
    rate: Option<f64>,
    paced_since: Option<(Instant, u64)>,
}

enum DatasetReader {
    SpeedPlus(Box<SpeedPlusReader>),
    Synthetic(SyntheticReader),
}

impl DatasetReader {
    fn len(&self) -> usize {
        match self {
            DatasetReader::SpeedPlus(reader) => reader.len(),
            DatasetReader::Synthetic(reader) => reader.len(),
        }
    }

    fn frame(&self, index: usize) -> Result<Frame> {
        match self {
            DatasetReader::SpeedPlus(reader) => reader.frame(index),
            DatasetReader::Synthetic(reader) => reader.frame(index),
        }
    }
}

/// Pacing rates (frames per second) a dataset source accepts: from one frame in 1000 s to
/// a million per second, so every due time is a representable `Duration`.
pub const RATE_RANGE: std::ops::RangeInclusive<f64> = 1e-3..=1e6;

/// `path` made absolute and free of links where it exists (as given otherwise).
fn canonical(path: &Path) -> PathBuf {
    path.canonicalize().unwrap_or_else(|_| path.to_path_buf())
}

/// NeRF-synthetic images are composited on white.
const SYNTHETIC_BACKGROUND: [f32; 3] = [1.0; 3];

impl DatasetSource {
    /// Open `path` (a folder or a label / transforms file); `max_side` resizes frames to that
    /// longer side (never upsampling).
    pub fn open(path: &Path, max_side: Option<u32>, rate: Option<f64>) -> Result<DatasetSource> {
        let name = path.display().to_string();
        if let Some(rate) = rate.filter(|r| !RATE_RANGE.contains(r)) {
            return Err(HostError::invalid(
                path,
                format!(
                    "pacing rate {rate} frames/s is outside {}..={}",
                    RATE_RANGE.start(),
                    RATE_RANGE.end()
                ),
            ));
        }
        let identity = format!("dataset {}", canonical(path).display());
        let transforms = if path.is_dir() {
            Some(path.join(SyntheticSplit::Train.file_name())).filter(|p| p.is_file())
        } else {
            Some(path.to_path_buf()).filter(|p| {
                p.file_name()
                    .and_then(|n| n.to_str())
                    .is_some_and(|n| n.starts_with("transforms_"))
            })
        };
        let (reader, info) = match transforms {
            Some(json) => {
                let options = transforms::LoadOptions {
                    size: max_side.map_or(OutputSize::Original, OutputSize::MaxSide),
                    background: SYNTHETIC_BACKGROUND,
                };
                let reader = SyntheticReader::open(&json, &options)?;
                let info = SourceInfo {
                    name,
                    identity,
                    scene_box: Some((
                        nerf_synthetic::NERF_SYNTHETIC_SCENE_MIN,
                        nerf_synthetic::NERF_SYNTHETIC_SCENE_MAX,
                    )),
                    background: SYNTHETIC_BACKGROUND,
                    max_pixels: reader.output_pixels(),
                    frames: Some(reader.len() as u64),
                    exact_poses: false,
                };
                (DatasetReader::Synthetic(reader), info)
            }
            None => {
                let options = LoadOptions {
                    max_side,
                    domain: None,
                };
                let reader = SpeedPlusReader::open(path, &options)?;
                let info = SourceInfo {
                    name,
                    identity,
                    scene_box: reader.scene_box(),
                    background: [0.0; 3],
                    max_pixels: reader.decoder.output_camera().pixel_count(),
                    frames: Some(reader.len() as u64),
                    exact_poses: reader.truth.is_some(),
                };
                (DatasetReader::SpeedPlus(Box::new(reader)), info)
            }
        };
        Ok(DatasetSource {
            reader,
            info,
            next: 0,
            rate,
            paced_since: None,
        })
    }
}

impl FrameSource for DatasetSource {
    fn info(&self) -> &SourceInfo {
        &self.info
    }

    fn next(&mut self, stop: &AtomicBool) -> Option<Arrival> {
        if self.next >= self.reader.len() as u64 || stop.load(Ordering::SeqCst) {
            return None;
        }
        if let Some(rate) = self.rate {
            let (start, first) = *self.paced_since.get_or_insert((Instant::now(), self.next));
            // In range for any rate in RATE_RANGE over u64 positions, but never a panic.
            let wait = Duration::try_from_secs_f64((self.next - first) as f64 / rate)
                .unwrap_or(Duration::MAX);
            let due = start.checked_add(wait).unwrap_or_else(Instant::now);
            std::thread::sleep(due.saturating_duration_since(Instant::now()));
        }
        let arrival = match self.reader.frame(self.next as usize) {
            Ok(frame) => Arrival::Frame(frame),
            Err(e) => Arrival::Bad(e),
        };
        self.next += 1;
        Some(arrival)
    }

    fn position(&self) -> u64 {
        self.next
    }

    fn seek(&mut self, position: u64, _arrived: &[String]) -> Result<()> {
        self.next = position;
        Ok(())
    }

    fn reload(&self, position: u64) -> Result<Frame> {
        self.reader.frame(position as usize)
    }

    fn exact_pose(&self, position: u64) -> Result<Option<Pose>> {
        let DatasetReader::SpeedPlus(reader) = &self.reader else {
            return Ok(None);
        };
        let Some(truth) = &reader.truth else {
            return Ok(None);
        };
        let label = reader.label(position as usize)?;
        let path = reader.label_file.with_file_name("truth.json");
        Ok(truth.poses_for(&path, &[label])?.pop())
    }
}

/// The simulator, rendering the frames of a scene one by one as the stream asks for them.
#[cfg(feature = "simulator")]
pub struct SimulatorSource<'s> {
    simulator: FrameSimulator<'s>,
    decoder: FrameDecoder,
    info: SourceInfo,
    frames: u32,
    next: u32,
}

#[cfg(feature = "simulator")]
impl<'s> SimulatorSource<'s> {
    /// The frames of `scene`, rendered as they are asked for.
    pub fn new(scene: &'s Scene) -> Result<SimulatorSource<'s>> {
        let simulator = FrameSimulator::new(scene)?;
        let decoder = FrameDecoder::new(simulator.camera_file().clone(), None);
        let spec = &scene.spec;
        let info = SourceInfo {
            name: format!("simulated {}", scene.origin.display()),
            identity: format!(
                "scene {} ({} frames, {}x{} px, seed {})",
                canonical(&scene.origin).display(),
                spec.frames,
                spec.size,
                spec.height(),
                spec.seed
            ),
            scene_box: Some(simulator.scene_box()),
            background: [0.0; 3],
            max_pixels: decoder.output_camera().pixel_count(),
            frames: Some(scene.spec.frames as u64),
            exact_poses: true,
        };
        Ok(SimulatorSource {
            simulator,
            decoder,
            info,
            frames: scene.spec.frames,
            next: 0,
        })
    }

    fn frame(&self, index: u32) -> Result<Frame> {
        let simulated = self.simulator.render(index)?;
        let name = PathBuf::from(&simulated.filename);
        let pose = simulated
            .label
            .pose()
            .ok_or_else(|| HostError::field(&name, "q_vbs2tango_true", "not a valid pose"))?;
        let camera = self.decoder.output_camera();
        let (w, h) = (camera.width as u32, camera.height as u32);
        let image = &simulated.image;
        let rgb: Vec<u8> = match image.channels {
            1 => image.pixels.iter().flat_map(|&v| [v, v, v]).collect(),
            _ => image.pixels.clone(),
        };
        let rgb = image::RgbImage::from_raw(w, h, rgb)
            .ok_or_else(|| HostError::invalid(&name, "rendered image has the wrong size"))?;
        let mask = image::GrayImage::from_raw(w, h, image.mask.clone())
            .ok_or_else(|| HostError::invalid(&name, "rendered mask has the wrong size"))?;
        self.decoder.from_images(
            simulated.filename.clone(),
            pose,
            (&name, &rgb),
            Some((&name, &mask)),
        )
    }
}

#[cfg(feature = "simulator")]
impl FrameSource for SimulatorSource<'_> {
    fn info(&self) -> &SourceInfo {
        &self.info
    }

    fn next(&mut self, stop: &AtomicBool) -> Option<Arrival> {
        if self.next >= self.frames || stop.load(Ordering::SeqCst) {
            return None;
        }
        let arrival = match self.frame(self.next) {
            Ok(frame) => Arrival::Frame(frame),
            Err(e) => Arrival::Bad(e),
        };
        self.next += 1;
        Some(arrival)
    }

    fn position(&self) -> u64 {
        self.next as u64
    }

    fn seek(&mut self, position: u64, _arrived: &[String]) -> Result<()> {
        self.next = position.min(self.frames as u64) as u32;
        Ok(())
    }

    fn reload(&self, position: u64) -> Result<Frame> {
        self.frame(position as u32)
    }

    fn exact_pose(&self, position: u64) -> Result<Option<Pose>> {
        self.simulator.exact_pose(position as u32).map(Some)
    }
}

/// When a watched-folder stream ends and how patiently it waits.
#[derive(Clone, Copy, Debug)]
pub struct WatchOptions {
    /// How often the folder is listed.
    pub poll: Duration,
    /// How long an incomplete or unreadable frame is waited for before it is reported bad.
    pub grace: Duration,
    /// End the stream after this long with no new file; `None` waits for ever.
    pub idle_timeout: Option<Duration>,
}

/// Image extensions a watched folder's frames may have.
const IMAGE_EXTENSIONS: [&str; 3] = ["png", "jpg", "jpeg"];
/// The file whose appearance ends a watched-folder stream.
pub const END_MARKER: &str = "END";

/// A folder watched for new frames (see the module docs for its format).
pub struct WatchedFolder {
    dir: PathBuf,
    decoder: FrameDecoder,
    info: SourceInfo,
    options: WatchOptions,
    /// Frame names handed out so far, in arrival order.
    names: Vec<String>,
    /// The same names, for lookups.
    taken: BTreeSet<String>,
}

impl WatchedFolder {
    /// Open `dir` (its `camera.json` must be there), resizing frames to the longer side
    /// `max_side` (never upsampling). The scene box is known only when the folder has a
    /// simulator `truth.json`.
    pub fn open(dir: &Path, max_side: Option<u32>, options: WatchOptions) -> Result<WatchedFolder> {
        let camera = SpeedCamera::read(&dir.join("camera.json"))?;
        let decoder = FrameDecoder::new(camera, max_side);
        let truth = dir.join("truth.json");
        let scene_box = if truth.is_file() {
            let truth = speedplus::Truth::read(&truth)?;
            Some((truth.target_box_min, truth.target_box_max))
        } else {
            None
        };
        let info = SourceInfo {
            name: dir.display().to_string(),
            identity: format!("watched folder {}", canonical(dir).display()),
            scene_box,
            background: [0.0; 3],
            max_pixels: decoder.output_camera().pixel_count(),
            frames: None,
            // Frames that arrive later than truth.json was written are not in it: held-out
            // views are scored at their labels.
            exact_poses: false,
        };
        Ok(WatchedFolder {
            dir: dir.to_path_buf(),
            decoder,
            info,
            options,
            names: Vec::new(),
            taken: BTreeSet::new(),
        })
    }

    /// Names of the frames with at least one file in the folder, in natural order.
    fn listed(&self) -> Result<Vec<String>> {
        let mut names: Vec<String> = std::fs::read_dir(&self.dir)
            .map_err(|e| HostError::io(&self.dir, e))?
            .filter_map(|entry| {
                let path = entry.ok()?.path();
                let extension = path.extension()?.to_str()?.to_ascii_lowercase();
                let stem = path.file_stem()?.to_str()?.to_owned();
                let is_frame_file = IMAGE_EXTENSIONS.contains(&extension.as_str())
                    || (extension == "json" && stem != "camera" && stem != "truth");
                // Temporary files of writers (`name.png.tmp`, `.name.png`) are not frames.
                (is_frame_file && !stem.starts_with('.') && !stem.contains('.')).then_some(stem)
            })
            .collect();
        names.sort_by(|a, b| natural_order(a, b));
        names.dedup();
        Ok(names)
    }

    fn image_path(&self, name: &str) -> Option<PathBuf> {
        IMAGE_EXTENSIONS
            .iter()
            .map(|ext| self.dir.join(format!("{name}.{ext}")))
            .find(|path| path.is_file())
    }

    /// The frame called `name`, if its files are complete and valid.
    fn read(&self, name: &str) -> Result<Frame> {
        let label_path = self.dir.join(format!("{name}.json"));
        let image_path = self
            .image_path(name)
            .ok_or_else(|| HostError::invalid(self.dir.join(name), "missing image"))?;
        if !label_path.is_file() {
            return Err(HostError::invalid(&label_path, "missing label"));
        }
        let label = speedplus::read_label(&label_path)?;
        let pose = label
            .pose()
            .ok_or_else(|| HostError::field(&label_path, "q_vbs2tango_true", "not a valid pose"))?;
        self.decoder
            .decode(image_path.display().to_string(), pose, &image_path, None)
    }
}

impl FrameSource for WatchedFolder {
    fn info(&self) -> &SourceInfo {
        &self.info
    }

    fn next(&mut self, stop: &AtomicBool) -> Option<Arrival> {
        let mut last_change = Instant::now();
        // The frame being waited for and when it was first seen.
        let mut pending: Option<(String, Instant)> = None;
        while !stop.load(Ordering::SeqCst) {
            let listed = match self.listed() {
                Ok(listed) => listed,
                Err(e) => return Some(Arrival::Bad(e)),
            };
            let candidate = listed.into_iter().find(|name| !self.taken.contains(name));
            match candidate {
                Some(name) => {
                    let since = match &pending {
                        Some((waiting, since)) if *waiting == name => *since,
                        _ => Instant::now(),
                    };
                    let result = self.read(&name);
                    if result.is_ok() || since.elapsed() >= self.options.grace {
                        self.taken.insert(name.clone());
                        self.names.push(name);
                        return Some(match result {
                            Ok(frame) => Arrival::Frame(frame),
                            Err(e) => Arrival::Bad(e),
                        });
                    }
                    pending = Some((name, since));
                    last_change = Instant::now();
                }
                None => {
                    if self.dir.join(END_MARKER).exists()
                        || self
                            .options
                            .idle_timeout
                            .is_some_and(|timeout| last_change.elapsed() >= timeout)
                    {
                        return None;
                    }
                }
            }
            std::thread::sleep(self.options.poll);
        }
        None
    }

    fn position(&self) -> u64 {
        self.names.len() as u64
    }

    fn arrived(&self) -> &[String] {
        &self.names
    }

    fn seek(&mut self, position: u64, arrived: &[String]) -> Result<()> {
        if arrived.len() as u64 != position {
            return Err(HostError::invalid(
                &self.dir,
                format!(
                    "cannot resume at frame {position}: the checkpoint names {} frames taken",
                    arrived.len()
                ),
            ));
        }
        if let Some(missing) = arrived.iter().find(|name| self.image_path(name).is_none()) {
            return Err(HostError::invalid(
                self.dir.join(missing),
                "taken before the checkpoint but no longer in the folder; cannot resume",
            ));
        }
        self.names = arrived.to_vec();
        self.taken = arrived.iter().cloned().collect();
        Ok(())
    }

    fn reload(&self, position: u64) -> Result<Frame> {
        let name = self.names.get(position as usize).ok_or_else(|| {
            HostError::invalid(&self.dir, format!("no frame at position {position}"))
        })?;
        self.read(name)
    }
}

/// Natural order of frame names: runs of digits compare as numbers (`img2` < `img10`), the
/// rest as text; names equal that way (`img02`, `img2`) fall back to plain text order.
fn natural_order(a: &str, b: &str) -> Order {
    fn chunks(name: &str) -> impl Iterator<Item = (bool, &str)> {
        let mut rest = name;
        std::iter::from_fn(move || {
            let first = rest.chars().next()?;
            let digits = first.is_ascii_digit();
            let end = rest
                .find(|c: char| c.is_ascii_digit() != digits)
                .unwrap_or(rest.len());
            let (chunk, tail) = rest.split_at(end);
            rest = tail;
            Some((digits, chunk))
        })
    }
    let (mut left, mut right) = (chunks(a), chunks(b));
    loop {
        let order = match (left.next(), right.next()) {
            (None, None) => return a.cmp(b),
            (None, Some(_)) => Order::Less,
            (Some(_), None) => Order::Greater,
            (Some((true, x)), Some((true, y))) => {
                let (x, y) = (x.trim_start_matches('0'), y.trim_start_matches('0'));
                x.len().cmp(&y.len()).then_with(|| x.cmp(y))
            }
            (Some((_, x)), Some((_, y))) => x.cmp(y),
        };
        if order != Order::Equal {
            return order;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::natural_order;

    #[test]
    fn natural_order_compares_counters_as_numbers() {
        let mut names = vec!["img10", "img2", "img1", "b", "img02", "a9"];
        names.sort_by(|a, b| natural_order(a, b));
        assert_eq!(names, ["a9", "b", "img1", "img02", "img2", "img10"]);
    }
}
