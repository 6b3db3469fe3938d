//! `orbit-nerf render`: render views of a dataset's cameras with a checkpoint to PNG, or new
//! views (an orbit around the target, or a path file) to PNG frames and an animated GIF.

use super::{
    CliResult, DataArgs, FIT_STEPS, Fallible, RunArgs, evaluate_checkpoint, machine_threads,
    open_dataset, parse_threads,
};
use clap::Args;
use orbit_nerf_core::Pose;
use orbit_nerf_core::glam::Vec3;
use orbit_nerf_host::orbit::{self, Surroundings};
use orbit_nerf_host::pipeline::{self, SplitData};
use orbit_nerf_host::train::{self, RayonExecutor, to_rgb8};
use orbit_nerf_host::{io, values};
use std::path::{Path, PathBuf};

#[derive(Args)]
pub struct RenderArgs {
    #[command(flatten)]
    model: RunArgs,
    #[command(flatten)]
    data: DataArgs,
    /// Views to render (dataset indices); default: the held-out views.
    #[arg(long, value_delimiter = ',', conflicts_with_all = ["orbit", "path"])]
    views: Vec<usize>,
    /// Render N new views instead, on a circle about the dataset cameras' mean up through the
    /// scene box centre, at their mean distance from it, with the first view's intrinsics:
    /// orbit_0000.png ... and orbit.gif in --out (and orbit.mp4 when ffmpeg is on the PATH).
    #[arg(long, value_parser = parse_orbit, conflicts_with = "path", allow_hyphen_values = true)]
    orbit: Option<usize>,
    /// Elevation of the orbit above the plane normal to the mean up, degrees (-89 to 89);
    /// default: the dataset cameras' mean elevation.
    #[arg(long, requires = "orbit", allow_hyphen_values = true, value_parser = parse_elevation)]
    elevation: Option<f32>,
    /// Render the cameras of a path file instead: one camera per line, `eye_x eye_y eye_z
    /// target_x target_y target_z [up_x up_y up_z]` in world units, `#` comments (README,
    /// "Outputs"); written like --orbit.
    #[arg(long)]
    path: Option<PathBuf>,
    /// Milliseconds each GIF frame is shown (10 to 10000).
    #[arg(long, default_value_t = 80, value_parser = parse_frame_ms)]
    frame_ms: u32,
    /// Replace renders (views, orbit frames, GIF, MP4) already in --out.
    #[arg(long)]
    force: bool,
    /// Output folder: view_NNN.png per dataset view, or the orbit's frames and GIF
    /// [default: RUN/render with --run, else runs/render].
    #[arg(long)]
    out: Option<PathBuf>,
    /// Worker threads, 1 to 1024 (results do not depend on it) [default: the machine's cores].
    #[arg(long, default_value_t = machine_threads(), hide_default_value = true, value_parser = parse_threads)]
    threads: usize,
    /// Steps fitting each view's appearance embedding on its left half.
    #[arg(long, default_value_t = FIT_STEPS)]
    fit_steps: u32,
    /// Also fit each view's pose correction in those steps and render it at its corrected
    /// label (as `eval --align-poses`), instead of at its label.
    #[arg(long)]
    align_poses: bool,
}

impl RenderArgs {
    /// `--out`, else the run's `render` folder, else `runs/render`.
    fn out(&self) -> PathBuf {
        match (&self.out, &self.model.run) {
            (Some(out), _) => out.clone(),
            (None, Some(run)) => run.join("render"),
            (None, None) => PathBuf::from("runs/render"),
        }
    }
}

fn parse_orbit(text: &str) -> Result<usize, String> {
    values::count_in(text, 1..=3600)
}

fn parse_elevation(text: &str) -> Result<f32, String> {
    values::number_in(text, -89.0..=89.0).map(|v| v as f32)
}

fn parse_frame_ms(text: &str) -> Result<u32, String> {
    values::count_in(text, 10..=10_000).map(|v| v as u32)
}

pub fn run(args: &RenderArgs) -> CliResult {
    let out = &args.out();
    if args.orbit.is_some() || args.path.is_some() {
        return new_views(args);
    }
    let (checkpoint, settings) = args.model.checkpoint_and_data(&args.data, "render")?;
    let data = open_dataset(&settings, None, &[])?;
    let views = if args.views.is_empty() {
        data.test.clone()
    } else {
        args.views.clone()
    };
    let files = train::render_files(out, &views);
    io::check_new_files(files.iter().map(PathBuf::as_path), args.force)?;
    let scores = evaluate_checkpoint(
        &checkpoint,
        (args.threads, None),
        &data,
        &views,
        (args.fit_steps, args.align_poses),
        Some(out),
    )?;
    for s in &scores {
        println!(
            "view {:>3}: {:.2} dB -> {}",
            s.index,
            s.metrics.psnr_full,
            out.join(format!("view_{:03}.png", s.index)).display()
        );
    }
    Ok(())
}

/// The files a path of `count` views writes into `out`.
fn outputs(out: &Path, count: usize) -> Vec<PathBuf> {
    let mut files: Vec<PathBuf> = (0..count)
        .map(|k| out.join(format!("orbit_{k:04}.png")))
        .collect();
    files.push(out.join("orbit.gif"));
    files.push(out.join("orbit.mp4"));
    files
}

/// Render an orbit or a path file's cameras with the mean training embedding.
fn new_views(args: &RenderArgs) -> CliResult {
    let out = &args.out();
    io::check_output_folder(out)?;
    let (checkpoint, settings) = args.model.checkpoint_and_data(&args.data, "render")?;
    let SplitData {
        dataset,
        train: train_idx,
        ..
    } = open_dataset(&settings, None, &[])?;
    let camera = dataset.frames[0].camera;
    let training: Vec<Pose> = train_idx.iter().map(|&i| dataset.frames[i].pose).collect();
    let executor = RayonExecutor::new(args.threads)?;
    pipeline::with_checkpoint(&checkpoint, None, &[], |trainer| -> Fallible<()> {
        let c = trainer.config();
        let centre = (Vec3::from_array(c.aabb_min) + Vec3::from_array(c.aabb_max)) * 0.5;
        let around = orbit::surroundings(&training, centre).ok_or_else(|| {
            format!(
                "{}: the training cameras give no orbit (none, or all at the box centre)",
                dataset.source.display()
            )
        })?;
        let poses = camera_path(args, &around)?;
        let files = outputs(out, poses.len());
        if let Some(existing) = files.iter().find(|f| f.exists()).filter(|_| !args.force) {
            return Err(format!(
                "{}: already exists; --force replaces it",
                existing.display()
            )
            .into());
        }
        let mut embedding = vec![0.0f32; c.embedding_dim as usize];
        trainer.mean_embedding(&mut embedding);
        let (w, h) = (camera.width as u32, camera.height as u32);
        let mut frames = Vec::with_capacity(poses.len());
        let mut image = vec![0.0f32; camera.pixel_count() * 3];
        for (pose, file) in poses.iter().zip(&files) {
            trainer.render(&executor, &camera, pose, &embedding, &mut image)?;
            if image.iter().any(|v| !v.is_finite()) {
                return Err(format!(
                    "{}: the render of {} holds non-finite pixels: the checkpoint is broken",
                    checkpoint.display(),
                    file.display()
                )
                .into());
            }
            let rgb = to_rgb8(&image);
            io::write_png(file, w, h, 3, &rgb)?;
            frames.push(rgb);
        }
        let gif = &files[poses.len()];
        orbit::write_gif(gif, w, h, &frames, args.frame_ms)?;
        println!(
            "{} views of {w}x{h} px at {:.3} from the box centre -> {}",
            poses.len(),
            around.distance,
            gif.display()
        );
        encode_mp4(out, poses.len(), args.frame_ms, &files[poses.len() + 1])
    })
}

/// The cameras to render: the orbit, or the path file's.
fn camera_path(args: &RenderArgs, around: &Surroundings) -> Fallible<Vec<Pose>> {
    match (&args.path, args.orbit) {
        (Some(path), _) => Ok(orbit::read_path(path, around.up)?),
        (None, Some(count)) => Ok(orbit::orbit(
            around,
            count,
            args.elevation
                .unwrap_or(around.elevation_deg.clamp(-89.0, 89.0)),
        )),
        (None, None) => Err("neither --orbit nor --path".into()),
    }
}

/// `orbit.mp4` from the frames with ffmpeg when it is on the PATH (written to a temporary
/// name and renamed); nothing without it.
fn encode_mp4(out: &Path, frames: usize, frame_ms: u32, mp4: &Path) -> CliResult {
    let Ok(status) = std::process::Command::new("ffmpeg")
        .arg("-version")
        .output()
    else {
        println!("ffmpeg is not on the PATH: no MP4");
        return Ok(());
    };
    if !status.status.success() || frames == 0 {
        return Ok(());
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
            std::fs::rename(&tmp, mp4).map_err(|e| format!("{}: {e}", mp4.display()))?;
            println!("-> {}", mp4.display());
            Ok(())
        }
        _ => {
            let _ = std::fs::remove_file(&tmp);
            Err(format!("ffmpeg failed to write {}", mp4.display()).into())
        }
    }
}
