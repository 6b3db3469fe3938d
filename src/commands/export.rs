//! `orbit-nerf export`: the trained field's geometry as files other tools read: the surface
//! of its density as a coloured mesh (PLY or OBJ), or as a coloured point cloud (PLY).

use super::{CliResult, machine_threads, parse_threads};
use clap::{Args, Subcommand};
use orbit_nerf_core::glam::Vec3;
use orbit_nerf_host::geometry::{self, SurfaceOptions, files};
use orbit_nerf_host::{pipeline, values};
use std::path::PathBuf;

/// Side of the --preview picture in pixels.
const PREVIEW_SIZE: u32 = 512;

#[derive(Subcommand)]
pub enum ExportCommand {
    /// The surface where the field's density crosses the threshold, inside the checkpoint's
    /// scene box (Naive Surface Nets on a regular grid), as a triangle mesh with per-vertex
    /// normals and colours; the format follows the extension of --out: .ply (binary) or .obj.
    Mesh(ExportArgs),
    /// The same surface's vertices (one per grid cell the surface crosses) with normals and
    /// colours, as a PLY point cloud.
    Points(ExportArgs),
}

#[derive(Args)]
pub struct ExportArgs {
    /// A `train` run folder: its checkpoint.onrf.
    #[arg(
        long,
        conflicts_with = "checkpoint",
        required_unless_present = "checkpoint"
    )]
    run: Option<PathBuf>,
    /// A checkpoint written by `train`, `stream` or `ablate`, instead of --run.
    #[arg(long)]
    checkpoint: Option<PathBuf>,
    /// Output file (.ply, or .obj for a mesh) [default with --run: RUN/mesh.ply or
    /// RUN/points.ply].
    #[arg(long, required_unless_present = "run")]
    out: Option<PathBuf>,
    /// Grid samples along the longest side of the scene box (8 to 2048; cubic voxels).
    #[arg(long, default_value_t = geometry::extract::DEFAULT_RESOLUTION,
          value_parser = parse_resolution, allow_hyphen_values = true)]
    resolution: u32,
    /// The density the surface passes through (sigma, per unit of length where the unit is the
    /// scene box's largest half-side over 1.5, so thresholds carry over between scenes of any
    /// size). Default: where a 1/128 of the box diagonal becomes half opaque (ln 2 * 128 /
    /// diagonal in those units; 17.1 on a cubic box); lower it for a fuller surface, raise it
    /// for a tighter one.
    #[arg(long, value_parser = values::positive, allow_hyphen_values = true)]
    threshold: Option<f32>,
    /// Also write a picture of the mesh to this PNG (orthographic, 512 px, seen from
    /// --preview-from towards the box centre, shaded vertex colours).
    #[arg(long)]
    preview: Option<PathBuf>,
    /// Direction from the centre to the preview's viewer, x,y,z (world axes).
    #[arg(long, default_value = "1,-1,0.8", value_parser = values::direction, allow_hyphen_values = true)]
    preview_from: [f32; 3],
    /// The preview's up direction, x,y,z (world axes).
    #[arg(long, default_value = "0,0,1", value_parser = values::direction, allow_hyphen_values = true)]
    preview_up: [f32; 3],
    /// Score the surface against a simulated scene's true shape (a preset such as lightbox,
    /// or a scene file): prints the symmetric Chamfer distance (mean, 95th percentile).
    #[arg(long)]
    chamfer_against: Option<String>,
    /// Replace --out (and --preview) if it exists.
    #[arg(long)]
    force: bool,
    /// Largest memory the model, the density grid and the mesh may take together (K/M/G/T
    /// suffixes); default: 80 % of the machine's available memory. Checked before anything
    /// large is allocated (the mesh once the densities are sampled, before it is built).
    #[arg(long, value_parser = values::byte_size)]
    memory_limit: Option<u64>,
    /// Worker threads, 1 to 1024 (results do not depend on it) [default: the machine's cores].
    #[arg(long, default_value_t = machine_threads(), hide_default_value = true, value_parser = parse_threads)]
    threads: usize,
}

fn parse_resolution(text: &str) -> Result<u32, String> {
    values::count_in(text, 8..=geometry::extract::MAX_RESOLUTION as usize).map(|v| v as u32)
}

pub fn run(command: &ExportCommand) -> CliResult {
    let (args, points) = match command {
        ExportCommand::Mesh(args) => (args, false),
        ExportCommand::Points(args) => (args, true),
    };
    let (checkpoint, out) = match (&args.run, &args.checkpoint) {
        (Some(run), _) => (
            run.join(pipeline::CHECKPOINT_FILE),
            (args.out.clone())
                .unwrap_or_else(|| run.join(if points { "points.ply" } else { "mesh.ply" })),
        ),
        (None, Some(checkpoint)) => (
            checkpoint.clone(),
            args.out
                .clone()
                .ok_or("--out FILE is needed with --checkpoint")?,
        ),
        (None, None) => {
            return Err("give --run DIR (a `train` run folder) or --checkpoint FILE".into());
        }
    };
    let (checkpoint, out) = (&checkpoint, &out);
    let format = files::MeshFormat::of(out, points)?;
    let outputs = std::iter::once(out).chain(&args.preview);
    orbit_nerf_host::io::check_new_files(outputs.map(PathBuf::as_path), args.force)?;
    if let Some(parent) = out.parent() {
        orbit_nerf_host::io::check_output_folder(parent)?;
    }
    let options = SurfaceOptions {
        resolution: args.resolution,
        threshold: args.threshold,
    };
    let say = &mut |line: String| println!("{line}");
    let work = (args.threads, args.memory_limit);
    let mesh = pipeline::extract_surface(checkpoint, &options, work, say)?;
    format.write(out, &mesh, points)?;
    if let Some(scene) = &args.chamfer_against {
        let truth = orbit_nerf_host::ablation_report::true_surface(scene)?;
        let samples = geometry::chamfer::DEFAULT_SAMPLES;
        match geometry::chamfer_distance(&mesh.triangle_corners(), &truth, samples) {
            Some(c) => println!(
                "Chamfer distance to {scene}'s true shape: mean {:.1} mm, 95th percentile {:.1} mm ({samples} points on each)",
                c.mean * 1000.0,
                c.p95 * 1000.0
            ),
            None => return Err("the surface has no area: no Chamfer distance".into()),
        }
    }
    if let Some(picture) = &args.preview {
        let (from, up) = (
            Vec3::from_array(args.preview_from),
            Vec3::from_array(args.preview_up),
        );
        let rgb = geometry::preview::preview(&mesh, PREVIEW_SIZE, from, up);
        orbit_nerf_host::io::write_png(picture, PREVIEW_SIZE, PREVIEW_SIZE, 3, &rgb)?;
        println!("picture -> {}", picture.display());
    }
    println!(
        "{} vertices{} -> {}",
        mesh.positions.len(),
        if points {
            String::new()
        } else {
            format!(", {} triangles", mesh.triangles.len())
        },
        out.display()
    );
    Ok(())
}
