//! `orbit-nerf render`: render views of a dataset's cameras with a checkpoint to PNG, or new
//! views (an orbit around the target, or a path file) to PNG frames and an animated GIF.

use super::{
    CliResult, DataArgs, FIT_STEPS, RunArgs, machine_threads, open_dataset, parse_threads,
};
use clap::Args;
use orbit_nerf_host::orbit::{self, CameraPath};
use orbit_nerf_host::pipeline;
use orbit_nerf_host::train::{self, RayonExecutor};
use orbit_nerf_host::{io, values};
use std::path::PathBuf;

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
    let scores = pipeline::evaluate_checkpoint(
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

/// Render an orbit or a path file's cameras with the mean training embedding.
fn new_views(args: &RenderArgs) -> CliResult {
    // The output folder is checked before the data is read (`render_path` checks its files).
    io::check_output_folder(&args.out())?;
    let (checkpoint, settings) = args.model.checkpoint_and_data(&args.data, "render")?;
    let data = open_dataset(&settings, None, &[])?;
    let path = match (&args.path, args.orbit) {
        (Some(file), _) => CameraPath::File(file.clone()),
        (None, count) => CameraPath::Orbit {
            count: count.unwrap_or(0),
            elevation_deg: args.elevation,
        },
    };
    let executor = RayonExecutor::new(args.threads)?;
    let done = pipeline::with_checkpoint(&checkpoint, None, &[], |trainer| {
        let what = (checkpoint.as_path(), &data);
        orbit::render_path(
            trainer,
            &executor,
            what,
            &path,
            &args.out(),
            (args.frame_ms, args.force),
        )
    })?;
    println!(
        "{} views of {}x{} px at {:.3} from the box centre -> {}",
        done.count,
        done.width,
        done.height,
        done.distance,
        done.gif.display()
    );
    match done.mp4 {
        Some(mp4) => println!("-> {}", mp4.display()),
        None => println!("ffmpeg is not on the PATH: no MP4"),
    }
    Ok(())
}
