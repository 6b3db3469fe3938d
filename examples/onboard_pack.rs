//! The host side of the Cortex-M check (scripts/onboard.sh): writes the render pack the
//! firmware holds in flash from a trained checkpoint, renders the firmware's view from the
//! same sections with the core on this machine, and prints the image's fingerprint.
//!
//! Usage: `cargo run --release --example onboard_pack -- CHECKPOINT.onrf PACK`

use orbit_nerf_core::{Config, MemoryPlan, Sequential, Trainer};
use orbit_nerf_host::{checkpoint, io, train};
use std::path::PathBuf;

#[path = "../firmware/src/pack.rs"]
mod pack;

type Fallible<T> = Result<T, Box<dyn std::error::Error>>;

fn main() {
    if let Err(e) = run() {
        eprintln!("error: {e}");
        std::process::exit(1);
    }
}

fn run() -> Fallible<()> {
    let args: Vec<PathBuf> = std::env::args_os().skip(1).map(PathBuf::from).collect();
    let [source, out] = args.as_slice() else {
        return Err("usage: onboard_pack CHECKPOINT.onrf PACK".into());
    };
    let saved = checkpoint::load(source)?;
    let config = with_render_capacities(&train::checkpoint_config(source, &saved)?);
    if config != pack::CONFIG {
        return Err(format!(
            "{}: its config differs from the firmware's (firmware/src/pack.rs CONFIG)\n\
             checkpoint: {config:?}\nfirmware:   {:?}",
            source.display(),
            pack::CONFIG
        )
        .into());
    }
    let mut arena = vec![0u8; MemoryPlan::render_only(&config).total];
    let mut trainer = Trainer::new_render_only(config, &mut arena)?;
    let mut bytes = pack::MAGIC.to_vec();
    for name in pack::SECTIONS {
        let section = saved.section(name)?;
        bytes.extend_from_slice(&u32::try_from(section.len())?.to_le_bytes());
        bytes.extend_from_slice(section);
    }
    // Restore from the pack as the firmware reads it, so both render from the same bytes.
    let sections = pack::sections(&bytes).ok_or("the pack just written does not read back")?;
    for (name, section) in pack::SECTIONS.iter().zip(sections) {
        trainer
            .restore_section(name, section)
            .map_err(|e| format!("{}: section `{name}`: {e}", source.display()))?;
    }
    io::write_atomic(out, &bytes)?;

    let mut image = vec![0.0f32; pack::CAMERA.pixel_count() * 3];
    let samples = trainer.render(&Sequential, &pack::CAMERA, &pack::pose(), &[], &mut image)?;
    println!(
        "host render: {}x{} px, {samples} samples/ray, fnv1a {:#018x} ({} pack bytes in {})",
        pack::CAMERA.width,
        pack::CAMERA.height,
        pack::fnv1a(&image),
        bytes.len(),
        out.display()
    );
    Ok(())
}

/// `config` with the capacities of `pack::CONFIG`: equal to `pack::CONFIG` exactly when a checkpoint
/// trained with `config` renders the same on the firmware.
fn with_render_capacities(config: &Config) -> Config {
    Config {
        max_frames: pack::CONFIG.max_frames,
        max_pixels_per_frame: pack::CONFIG.max_pixels_per_frame,
        rays_per_batch: pack::CONFIG.rays_per_batch,
        chunks: pack::CONFIG.chunks,
        samples_per_chunk: pack::CONFIG.samples_per_chunk,
        ..*config
    }
}
