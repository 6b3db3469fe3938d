//! `orbit-nerf ablate`: the paper's ablation (baseline, + appearance, + appearance and pose
//! correction on one scene), its pose-noise sweep on the `synthetic` preset and its
//! image-count study (run as a sweep).

use super::{
    FIT_STEPS, Fallible, SceneBox, machine_threads, parse_scene_box, parse_threads, preset_parser,
};
use orbit_nerf_core::Config;
use orbit_nerf_host::ablation_report::{self, AblationData};
use orbit_nerf_host::formats::Format;
use orbit_nerf_host::pipeline::{self, Overrides};
use orbit_nerf_host::presets;
use orbit_nerf_host::sweep::studies::{self, ImageCounts, StudyData};
use std::path::PathBuf;

#[derive(clap::Args, Debug, Clone)]
pub struct AblateArgs {
    /// Scene to simulate: a preset (synthetic, lightbox, sunlamp, inspection, rendezvous; lightbox-test: a separate test set) or a scene file.
    #[arg(long, default_value = "lightbox")]
    pub scene: String,
    /// Use this dataset (SPEED+/SHIRT/simulator, NeRF-synthetic or nerfstudio) instead of simulating one.
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// Frames to simulate, 2 to 100000.
    #[arg(long, default_value_t = 400, value_parser = clap::value_parser!(u32).range(2..=100_000))]
    pub frames: u32,
    /// Image size in pixels: the simulated frames' side, or the longer side a --data set's
    /// frames are resized to (never upsampled); at least 22, so each half of a held-out view
    /// is wide enough for SSIM's 11x11 window.
    #[arg(long, default_value_t = orbit_nerf_host::pipeline::DEFAULT_SIZE as u16, value_parser = clap::value_parser!(u16).range(22..))]
    pub size: u16,
    /// Training steps of every model (the same budget for all; default: the config's).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..))]
    pub steps: Option<u32>,
    /// Built-in config the three models start from (default: `spacecraft`, the method's).
    #[arg(long, value_parser = preset_parser())]
    pub preset: Option<String>,
    /// Config file (TOML) of the fields to change in the preset's config, at the top level or
    /// in a `[config]` table (a full file works too).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Run the pose-noise sweeps on the `synthetic` preset instead.
    #[arg(long)]
    pub pose_noise: bool,
    /// Which of the paper's two sweeps to run: rotation noise alone, translation noise alone,
    /// or both (sharing the noise-free level).
    #[arg(long, value_enum, default_value_t = Sweep::Both)]
    pub sweep: Sweep,
    /// Rotation-noise levels of the rotation sweep (standard deviation of the label's
    /// rotation angle, degrees); default: the paper's five.
    #[arg(long, value_delimiter = ',', default_values_t = ROTATION_LEVELS_DEG)]
    pub levels: Vec<f32>,
    /// Translation-noise levels of the translation sweep (standard deviation per axis of the
    /// label's position, mm); default: the paper's five.
    #[arg(long, value_delimiter = ',', default_values_t = TRANSLATION_LEVELS_MM)]
    pub translation_levels: Vec<f32>,
    /// The paper's image-count study: baseline and ours + pose trained on each of these
    /// numbers of --scene frames (e.g. 25,50,100,200,400) and scored on the same separate
    /// test set (--test-scene), as a sweep in --out (`image-counts.toml`, its tasks, sweep.md
    /// with the image-count table and plots). Rerunning continues the unfinished tasks.
    #[arg(long, value_delimiter = ',', conflicts_with_all = ["data", "test_data", "pose_noise", "holdout"], value_parser = |text: &str| orbit_nerf_host::values::count_in(text, 2..=100_000))]
    pub image_counts: Vec<usize>,
    /// The separate test set of the image-count study: a scene preset or scene file,
    /// simulated with exact labels.
    #[arg(long, default_value = "lightbox-test")]
    pub test_scene: String,
    /// Frames of the image-count study's test set (default: the test scene's own; the paper
    /// has 200).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=100_000))]
    pub test_frames: Option<u32>,
    /// Every N-th view is held out.
    #[arg(long, default_value_t = 8, value_parser = |text: &str| orbit_nerf_host::values::count_in(text, 1..=1_000_000))]
    pub holdout: usize,
    /// Test on this separate dataset (any format; every view held out, scored at its exact
    /// pose where it has one) and train on every view of the training set, as the paper does
    /// (train on one set, test on another set's viewpoints and lighting); --holdout is then
    /// not used.
    #[arg(long, conflicts_with_all = ["holdout", "pose_noise"])]
    pub test_data: Option<PathBuf>,
    /// Steps fitting each held-out view's embedding on its left half.
    #[arg(long, default_value_t = FIT_STEPS)]
    pub fit_steps: u32,
    /// Worker threads, 1 to 1024 (results do not depend on it) [default: the machine's cores].
    #[arg(long, default_value_t = machine_threads(), hide_default_value = true, value_parser = parse_threads)]
    pub threads: usize,
    /// Output folder: ablation.md (or pose_noise.md), metrics.json, pictures, the simulated set.
    #[arg(long, default_value = "runs/ablate")]
    pub out: PathBuf,
    /// The scene box, xmin,ymin,zmin,xmax,ymax,zmax (wins over a config file's box,
    /// truth.json's and the box found from the data).
    #[arg(long, value_parser = parse_scene_box, allow_hyphen_values = true)]
    pub scene_box: Option<SceneBox>,
    /// Keep the sky as recorded: by default, where a frame has a mask, its background pixels
    /// get the background colour for training and scoring (as the paper removes it).
    #[arg(long)]
    pub no_masks: bool,
}

/// The paper's rotation sweep: rotation noise on the labels, in degrees (exact positions).
const ROTATION_LEVELS_DEG: [f32; 5] = [0.0, 0.2, 0.4, 0.8, 1.6];
/// The paper's translation sweep: position noise on the labels, in mm (exact attitudes). The
/// simulated target is TANGO at its real size, as in the paper, so no scaling is needed.
const TRANSLATION_LEVELS_MM: [f32; 5] = [0.0, 2.0, 4.0, 8.0, 16.0];

/// The paper's two pose-noise sweeps.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum Sweep {
    Rotation,
    Translation,
    Both,
}

pub fn run(args: &AblateArgs) -> Fallible<()> {
    let data = AblationData {
        scene: args.scene.clone(),
        data: args.data.clone(),
        frames: args.frames,
        size: args.size,
        holdout: args.holdout,
        test_data: args.test_data.clone(),
        masks: !args.no_masks,
        scene_box: args.scene_box,
        config_file: args.config.clone(),
    };
    let say = &mut |line: String| println!("{line}");
    let work = (args.threads, args.fit_steps);
    if args.pose_noise {
        let levels = (
            (args.sweep != Sweep::Translation).then(|| args.levels.clone()),
            (args.sweep != Sweep::Rotation).then(|| args.translation_levels.clone()),
        );
        let levels = (levels.0.unwrap_or_default(), levels.1.unwrap_or_default());
        let model = (args.preset.clone(), args.steps);
        let sweep = ablation_report::pose_noise_sweep(&data, model, args.fit_steps, levels)?;
        let text = ablation_report::run_pose_noise_sweeps(&data, &sweep, work, &args.out, say)?;
        println!("{text}");
    } else if !args.image_counts.is_empty() {
        image_counts(args)?;
    } else {
        // The config is checked before the data is simulated or read.
        let base = base_config(args)?;
        let text = ablation_report::run_ablation(&data, &base, work, &args.out, say)?;
        println!("{text}");
        println!(
            "report, metrics.json and pictures in {}",
            args.out.display()
        );
    }
    Ok(())
}

/// The models' base config: `--preset` (default `spacecraft`: the data is a spacecraft's), a
/// `--config` file's fields, then `--steps`.
fn base_config(args: &AblateArgs) -> Fallible<Config> {
    let data = if args.data.is_some() {
        Format::SpeedPlus.folder()
    } else {
        "a simulated scene"
    };
    let (preset, file) = (args.preset.as_deref(), args.config.as_deref());
    let chosen = pipeline::preset_config(preset, presets::SPACECRAFT, data, file)?;
    println!("{}", chosen.note);
    let mut config = chosen.config;
    let steps = Overrides {
        steps: args.steps,
        ..Overrides::default()
    };
    steps.apply(&mut config);
    Ok(config)
}

/// The image-count study as a sweep description in `--out` (`image-counts.toml`), run here
/// by the sweep runner: one task per count and model, every task scored on the same test set.
fn image_counts(args: &AblateArgs) -> Fallible<()> {
    let data = StudyData {
        scene: args.scene.clone(),
        data: None,
        preset: args.preset.clone(),
        config: args.config.clone(),
        steps: args.steps,
        size: args.size.into(),
        holdout: args.holdout,
        fit_steps: args.fit_steps,
        masks: !args.no_masks,
    };
    let study = ImageCounts {
        counts: args.image_counts.clone(),
        test_scene: args.test_scene.clone(),
        test_frames: args.test_frames,
        scene_box: args.scene_box,
    };
    let text = studies::image_count_description(&data, &study)?;
    let path = args.out.join("image-counts.toml");
    studies::write_description(&path, &text, "the description of another image-count study")?;
    super::sweep::run_local(&path, &args.out, Some(1), Some(args.threads))
}
