//! Sweep descriptions written from a command's settings: the trade-off study (`tradeoff`:
//! the reference config, then one variant per knob value, scored at fixed steps) and the
//! paper's image-count study (`ablate --image-counts`: baseline and ours + pose per training
//! image count, every task scored on one separate test set). Paths in them are made
//! absolute, so a description runs from any folder and on a cluster; each is checked by
//! [`Sweep::parse`] before it is written, so a bad value names its field and leaves nothing.

use super::Sweep;
use super::tradeoff::{Knob, default_knobs, parse_vary};
use super::{above_data_side, data_image_side};
use crate::ablation::{APPEARANCE_POSE, BASELINE};
use crate::error::{HostError, Result};
use crate::io::{check_output_folder, write_atomic};
use crate::train::with_overrides;
use orbit_nerf_core::Config;
use std::path::{Path, PathBuf};

/// `path` made absolute (links resolved), for a description run from any folder.
pub fn absolute(path: &Path) -> Result<String> {
    Ok(std::fs::canonicalize(path)
        .map_err(|e| HostError::io(path, e))?
        .display()
        .to_string())
}

/// A scene preset's name as it is, a scene file's path made absolute.
pub fn scene_reference(scene: &str) -> Result<String> {
    if crate::sim::scene::preset_names().any(|p| p == scene) {
        return Ok(scene.to_string());
    }
    std::fs::canonicalize(scene)
        .map(|p| p.display().to_string())
        .map_err(|e| {
            HostError::invalid(
                format!("--scene {scene}"),
                format!(
                    "no such preset ({}) and no such file: {e}",
                    crate::sim::scene::preset_names()
                        .collect::<Vec<_>>()
                        .join(", ")
                ),
            )
        })
}

/// Where a study's description was written.
#[derive(Debug, PartialEq)]
pub enum Written {
    /// A new description.
    New,
    /// The folder held this same description: the study continues.
    Continued,
}

/// Check `text` as a description (errors name `path` and the field), then write it to `path`
/// unless it is there already; a different description at `path` (another study: its tasks
/// would not match) is refused, naming `what` it holds.
pub fn write_description(path: &Path, text: &str, what: &str) -> Result<(Sweep, Written)> {
    let sweep = Sweep::parse(path, text)?;
    if let Some(folder) = path.parent() {
        check_output_folder(folder)?;
    }
    match std::fs::read_to_string(path) {
        Ok(existing) if existing != text => Err(HostError::invalid(
            path,
            format!("holds {what} (other settings); choose another --out, or remove the folder"),
        )),
        Ok(_) => Ok((sweep, Written::Continued)),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            if let Some(folder) = path.parent() {
                std::fs::create_dir_all(folder).map_err(|e| HostError::io(folder, e))?;
            }
            write_atomic(path, text.as_bytes())?;
            Ok((sweep, Written::New))
        }
        Err(e) => Err(HostError::io(path, e)),
    }
}

/// What a study trains on and how it scores, shared by both studies.
#[derive(Clone, Debug)]
pub struct StudyData {
    /// The scene simulated (a preset or a scene file) when `data` is `None`.
    pub scene: String,
    /// A dataset folder of any format instead of a simulated scene.
    pub data: Option<PathBuf>,
    /// The built-in preset the models start from (`None`: by the data's format).
    pub preset: Option<String>,
    /// A config file of fields changed in the preset.
    pub config: Option<PathBuf>,
    /// Training steps (`None`: the config's).
    pub steps: Option<u32>,
    /// Image size, pixels (longer side; never upsampled).
    pub size: u32,
    /// Every N-th view held out (unused with a separate test set).
    pub holdout: usize,
    /// Steps fitting a held-out view's embedding.
    pub fit_steps: u32,
    /// Apply the frames' masks.
    pub masks: bool,
}

impl StudyData {
    /// The description's common fields: source, preset, config file, size, steps, fit steps
    /// and masks (`preset`: the one the base config was chosen from, if named).
    fn table(&self, preset: Option<&str>) -> Result<toml::Table> {
        let mut table = toml::Table::new();
        match &self.data {
            Some(data) => table.insert("data".into(), absolute(data)?.into()),
            None => table.insert("scene".into(), scene_reference(&self.scene)?.into()),
        };
        if let Some(preset) = preset {
            table.insert("preset".into(), preset.into());
        }
        if let Some(config) = &self.config {
            table.insert("config".into(), absolute(config)?.into());
        }
        table.insert("size".into(), i64::from(self.size).into());
        if let Some(steps) = self.steps {
            table.insert("steps".into(), i64::from(steps).into());
        }
        table.insert("fit_steps".into(), i64::from(self.fit_steps).into());
        table.insert("masks".into(), self.masks.into());
        Ok(table)
    }
}

/// The trade-off study's settings beside its data.
#[derive(Clone, Debug)]
pub struct Tradeoff {
    /// Frames simulated (a scene only; `None`: the scene's own).
    pub frames: Option<u32>,
    /// Knobs and their values, `KEY=V1,V2` each (empty: every built-in knob one step to
    /// either side, sizes above a dataset's images left out).
    pub vary: Vec<String>,
    /// Steps after which the held-out views are also scored (empty: 1/16, 1/8, 1/4, 1/2 and
    /// 3/4 of the reference's steps).
    pub at: Vec<u32>,
    /// The figure variants are ranked by (`None`: the description's default).
    pub quality: Option<String>,
    /// Quality levels whose time to reach the report gives.
    pub targets: Vec<f64>,
    /// Training times (s) within which the report names the best variant.
    pub budgets: Vec<f64>,
    /// A separate test set (every view scored), instead of held-out views.
    pub test_data: Option<PathBuf>,
}

/// The trade-off study's description: `base` (the config of `preset`, the preset chosen for
/// the data, with the config file's fields) as the reference with `data.steps`, then one
/// variant per knob value.
pub fn tradeoff_description(
    data: &StudyData,
    study: &Tradeoff,
    preset: &str,
    base: &Config,
) -> Result<String> {
    let mut table = data.table(Some(preset))?;
    let mut base = *base;
    let steps = crate::pipeline::Overrides {
        steps: data.steps,
        ..Default::default()
    };
    steps.apply(&mut base);
    table.insert("steps".into(), i64::from(base.steps).into());
    if let Some(frames) = study.frames {
        table.insert("frames".into(), i64::from(frames).into());
    }
    match &study.test_data {
        Some(test) => table.insert("test_data".into(), absolute(test)?.into()),
        None => table.insert("holdout".into(), (data.holdout as i64).into()),
    };
    let at: Vec<u32> = if study.at.is_empty() {
        let mut at: Vec<u32> = [16, 8, 4]
            .map(|d| base.steps / d)
            .into_iter()
            .chain([base.steps / 2, base.steps * 3 / 4])
            .filter(|&s| s > 0 && s < base.steps)
            .collect();
        at.dedup();
        at
    } else {
        study.at.clone()
    };
    let mut anytime = toml::Table::new();
    anytime.insert(
        "steps".into(),
        at.iter().map(|&s| i64::from(s)).collect::<Vec<_>>().into(),
    );
    if let Some(quality) = &study.quality {
        anytime.insert("quality".into(), quality.clone().into());
    }
    anytime.insert("targets".into(), study.targets.clone().into());
    anytime.insert("budgets_s".into(), study.budgets.clone().into());
    table.insert("anytime".into(), anytime.into());

    // Frames are never upsampled: a size above the data's images repeats a smaller one.
    // (The image headers are read once, when a knob sets a size.)
    let side = std::cell::OnceCell::new();
    let above_data = |size: u32| -> Option<String> {
        let folder = data.data.as_deref()?;
        above_data_side(size, *side.get_or_init(|| data_image_side(folder)), folder)
    };
    let knobs = if study.vary.is_empty() {
        let mut knobs = default_knobs(&base, data.size);
        knobs.retain(|k| k.size.is_none_or(|s| above_data(s).is_none()));
        knobs
    } else {
        let mut knobs = Vec::new();
        for flag in &study.vary {
            let origin = PathBuf::from(format!("--vary {flag}"));
            let (key, values) =
                parse_vary(flag).map_err(|reason| HostError::invalid(&origin, reason))?;
            for value in values {
                let knob = Knob::new(&key, value);
                // Checked here, so the error names the flag.
                if knob.size.is_none() {
                    with_overrides(&origin, "", &base, &knob.set)?;
                }
                if let Some(why) = knob.size.and_then(above_data) {
                    return Err(HostError::invalid(&origin, why));
                }
                knobs.push(knob);
            }
        }
        knobs
    };
    let mut variants = vec![variant("reference", &toml::Table::new(), None)];
    for knob in &knobs {
        if (variants.iter()).any(|v| v.get("name") == Some(&knob.name.clone().into())) {
            return Err(HostError::invalid(
                "--vary",
                format!("`{}` is given twice", knob.name),
            ));
        }
        variants.push(variant(&knob.name, &knob.set, knob.size));
    }
    table.insert(
        "variants".into(),
        toml::Value::Array(variants.into_iter().map(Into::into).collect()),
    );
    described(
        "Written by `orbit-nerf tradeoff`: the reference, then one variant per knob value.",
        &table,
    )
}

/// The image-count study's settings beside its data.
#[derive(Clone, Debug)]
pub struct ImageCounts {
    /// The training-image counts, one task per count and model.
    pub counts: Vec<usize>,
    /// The separate test set: a scene preset or scene file, simulated with exact labels.
    pub test_scene: String,
    /// Its frames (`None`: the test scene's own).
    pub test_frames: Option<u32>,
    /// The scene box, when the user stated one.
    pub scene_box: Option<([f32; 3], [f32; 3])>,
}

/// The image-count study's description: baseline and ours + pose trained on each count of
/// `data.scene` frames and scored on the same separate test set.
pub fn image_count_description(data: &StudyData, study: &ImageCounts) -> Result<String> {
    let mut table = data.table(data.preset.as_deref())?;
    let counts: Vec<i64> = study.counts.iter().map(|&n| n as i64).collect();
    table.insert("frames".into(), counts.into());
    table.insert(
        "test_scene".into(),
        scene_reference(&study.test_scene)?.into(),
    );
    if let Some(frames) = study.test_frames {
        table.insert("test_frames".into(), i64::from(frames).into());
    }
    if let Some(([x0, y0, z0], [x1, y1, z1])) = study.scene_box {
        table.insert(
            "scene_box".into(),
            format!("{x0},{y0},{z0},{x1},{y1},{z1}").into(),
        );
    }
    let variants: Vec<toml::Value> = [BASELINE, APPEARANCE_POSE]
        .iter()
        .map(|model| {
            let set = toml::Table::from_iter([
                (
                    "embedding_dim".to_string(),
                    i64::from(model.embedding_dim).into(),
                ),
                ("pose_correction".to_string(), model.pose_correction.into()),
            ]);
            variant(model.name, &set, None).into()
        })
        .collect();
    table.insert("variants".into(), variants.into());
    described(
        "Written by `orbit-nerf ablate --image-counts`: baseline and ours + pose per training-image count.",
        &table,
    )
}

/// `table` as TOML under a comment line saying what wrote it.
fn described(comment: &str, table: &toml::Table) -> Result<String> {
    let text = toml::to_string(table).map_err(|e| {
        HostError::invalid("the sweep description", format!("encoding failed: {e}"))
    })?;
    Ok(format!("# {comment}\n{text}"))
}

/// One `[[variants]]` entry.
fn variant(name: &str, set: &toml::Table, size: Option<u32>) -> toml::Table {
    let mut table = toml::Table::new();
    table.insert("name".into(), name.into());
    if !set.is_empty() {
        table.insert("set".into(), set.clone().into());
    }
    if let Some(size) = size {
        table.insert("size".into(), i64::from(size).into());
    }
    table
}
