//! Helpers shared by the end-to-end tests: the repository root, the shared reference data
//! (tests skip with a message when it is absent), scratch folders and the CLI binary.

// Each test binary compiles this module and uses only part of it.
#![allow(dead_code)]

use orbit_nerf_host::sim::{self, Scene};
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// The repository root (where `budgets/` and `Cargo.toml` are).
pub fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// The shared reference data (`../shared/data`), when its SPEED+ camera (which the simulator's
/// presets need) is there; otherwise `None` and a message saying the test skips.
pub fn shared_data() -> Option<PathBuf> {
    let dir = root().join("../shared/data");
    if dir.join("speedplus/camera.json").is_file() {
        Some(dir)
    } else {
        eprintln!("skipping: reference data not found at {}", dir.display());
        None
    }
}

/// An empty folder under the system temp dir, named after the test binary, `name` and the
/// process (left in place: tests remove it when they pass).
pub fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!(
        "orbit-nerf-{}-{name}-{}",
        env!("CARGO_CRATE_NAME"),
        std::process::id()
    ));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// A fresh folder for one test ([`temp_dir`]), removed when dropped (also when the test fails).
pub struct Scratch(pub PathBuf);

impl Scratch {
    pub fn new(name: &str) -> Scratch {
        Scratch(temp_dir(name))
    }

    /// `name` inside the folder.
    pub fn path(&self, name: &str) -> PathBuf {
        self.0.join(name)
    }
}

impl Drop for Scratch {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// Simulate `frames` frames of the lightbox preset at `size` px into the dataset folder `out`
/// (needs the reference data: check [`shared_data`] first).
pub fn simulated_lightbox(out: &Path, frames: u32, size: u16) {
    let mut scene = Scene::load("lightbox").unwrap();
    scene.spec.frames = frames;
    scene.spec.size = size;
    sim::simulate(&scene, out, &|| {}).unwrap();
}

/// The `orbit-nerf` binary with `args`, run from the repository root.
pub fn orbit_nerf(args: &[&str]) -> Command {
    let mut command = Command::new(env!("CARGO_BIN_EXE_orbit-nerf"));
    command.args(args).current_dir(root());
    command
}

/// Run `orbit-nerf` with `args` to the end: whether it succeeded, and its stdout and stderr.
pub fn run_orbit_nerf(args: &[&str]) -> (bool, String) {
    let out = orbit_nerf(args).output().expect("the binary runs");
    (out.status.success(), output_text(&out))
}

/// Stdout then stderr of a finished process.
pub fn output_text(out: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    )
}
