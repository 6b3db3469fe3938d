//! `orbit-nerf simulate`: render a scene (a shipped preset or a TOML file) into a dataset in
//! the SPEED+ format, check that it loads back, and optionally print per-effect timings and
//! write a contact sheet.

use indicatif::{ProgressBar, ProgressStyle};
use orbit_nerf_host::formats::speedplus::{self, LoadOptions};
use orbit_nerf_host::sim::{self, Scene};
use orbit_nerf_host::{memory, values};
use std::path::PathBuf;

#[derive(clap::Args, Debug, Clone)]
pub struct SimulateArgs {
    /// A preset (synthetic, lightbox, sunlamp, inspection, lightbox-test, rendezvous) or the path of a scene TOML file.
    #[arg(long)]
    pub scene: String,
    /// Output folder. An existing one is replaced only if it is empty or a simulated dataset.
    #[arg(long)]
    pub out: PathBuf,
    /// Number of frames (overrides the scene's `frames`).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..))]
    pub frames: Option<u32>,
    /// Longer side of the images in pixels, the scene camera's aspect kept (overrides the
    /// scene's `size`).
    #[arg(long, value_parser = clap::value_parser!(u16).range(8..))]
    pub size: Option<u16>,
    /// Random seed, 0 to 2^63-1 (overrides the scene's `seed`; scene files hold it as a TOML
    /// integer).
    #[arg(long, value_parser = clap::value_parser!(u64).range(0..=i64::MAX as u64))]
    pub seed: Option<u64>,
    /// Print the time spent in each stage and effect, summed over frames.
    #[arg(long)]
    pub timings: bool,
    /// Also write a PNG contact sheet of frames spread through the dataset.
    #[arg(long, value_name = "PNG")]
    pub contact_sheet: Option<PathBuf>,
    /// Largest memory the simulation may take (e.g. 8G, 512M); default: 80 % of the
    /// machine's available memory. Checked before anything is rendered.
    #[arg(long, value_parser = values::byte_size)]
    pub memory_limit: Option<u64>,
    /// Replace the --contact-sheet file if it exists.
    #[arg(long)]
    pub force: bool,
    /// Tiles per row (and at most as many rows) of the contact sheet.
    #[arg(long, default_value_t = 4, value_parser = clap::value_parser!(u16).range(1..=32))]
    pub sheet_columns: u16,
}

pub fn run(args: &SimulateArgs) -> Result<(), Box<dyn std::error::Error>> {
    let mut scene = Scene::load(&args.scene)?;
    if let Some(frames) = args.frames {
        scene.spec.frames = frames;
    }
    if let Some(size) = args.size {
        scene.spec.set_longer_side(size);
    }
    if let Some(seed) = args.seed {
        scene.spec.seed = seed;
    }
    if let Some(sheet) = &args.contact_sheet {
        orbit_nerf_host::io::check_new_files([sheet.as_path()], args.force)?;
    }
    let spec = &scene.spec;
    memory::check_plan(
        &scene.origin,
        &sim::working_memory(spec, true),
        memory::limit_or_default(args.memory_limit),
    )?;
    let bar = ProgressBar::new(spec.frames as u64).with_style(
        ProgressStyle::with_template("{msg} [{bar:40}] {pos}/{len} frames, {per_sec}, eta {eta}")?
            .progress_chars("=> "),
    );
    bar.set_message(format!("simulating {}", spec.name));
    let report = sim::simulate(&scene, &args.out, &|| bar.inc(1))?;
    bar.finish_and_clear();

    let set = speedplus::load(&args.out, &LoadOptions::default())?;
    println!(
        "{}: {} frames of {}x{} px written to {} in {:.1} s (loads back: {} frames, {} labels)",
        spec.name,
        spec.frames,
        spec.size,
        spec.height(),
        args.out.display(),
        report.wall_time.as_secs_f64(),
        set.dataset.frames.len(),
        set.labels.len(),
    );
    if args.timings {
        print!("{}", report.timing_table());
    }
    if let Some(path) = &args.contact_sheet {
        let (width, height, pixels) =
            sim::contact_sheet(&set.dataset, args.sheet_columns as usize)?;
        orbit_nerf_host::io::write_png(path, width, height, 3, &pixels)?;
        println!("contact sheet: {}", path.display());
    }
    Ok(())
}
