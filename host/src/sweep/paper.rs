//! The paper's tables from one command (`orbit-nerf paper`): the main table (each of the
//! three training sets, baseline and ours, scored on one separate test set), the image-count
//! study and the pose-noise sweeps. Each is a sweep description (built in, or given), written
//! into the output folder and run there by the local runner, so a rerun continues where it
//! stopped and `sweep slurm` takes the same descriptions to a cluster; `paper.md` gathers
//! the tables with the CPU that ran them.

use super::results::{TaskResult, fixed, read_result};
use super::studies::{Written, write_description};
use super::{Source, Sweep, TestSet};
use crate::error::{HostError, Result};
use crate::io::write_atomic;
use crate::report::markdown_table;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// The built-in main-table descriptions, one per training set (`sweeps/paper-main-*.toml`).
pub const MAIN: [(&str, &str); 3] = [
    (
        "main-synthetic",
        include_str!("../../../sweeps/paper-main-synthetic.toml"),
    ),
    (
        "main-lightbox",
        include_str!("../../../sweeps/paper-main-lightbox.toml"),
    ),
    (
        "main-sunlamp",
        include_str!("../../../sweeps/paper-main-sunlamp.toml"),
    ),
];
/// The built-in image-count study (`sweeps/image-counts-quick.toml`).
pub const IMAGE_COUNTS: &str = include_str!("../../../sweeps/image-counts-quick.toml");
/// The built-in pose-noise sweeps (`sweeps/paper-pose-noise.toml`).
pub const POSE_NOISE: &str = include_str!("../../../sweeps/paper-pose-noise.toml");

/// One table's sweep: its folder name in the output and its description's text.
#[derive(Clone, Debug)]
pub struct PaperSweep {
    /// The sweep's folder in the output (`main-synthetic`, `image-counts`, `pose-noise`).
    pub name: String,
    /// The description (TOML); relative paths in it are relative to the output folder.
    pub text: String,
}

impl PaperSweep {
    /// The built-in sweeps of the tables asked for (`main`, `image-counts`, `pose-noise`).
    pub fn built_in(tables: &[Table]) -> Vec<PaperSweep> {
        let sweep = |name: &str, text: &str| PaperSweep {
            name: name.into(),
            text: text.into(),
        };
        let mut sweeps = Vec::new();
        for table in tables {
            match table {
                Table::Main => sweeps.extend(MAIN.iter().map(|(name, text)| sweep(name, text))),
                Table::ImageCounts => sweeps.push(sweep("image-counts", IMAGE_COUNTS)),
                Table::PoseNoise => sweeps.push(sweep("pose-noise", POSE_NOISE)),
            }
        }
        sweeps
    }

    /// Replace the description of the sweep `NAME` among `sweeps` with the file's text, as
    /// `--description NAME=FILE` gives them (errors name the flag).
    pub fn replace(sweeps: &mut [PaperSweep], given: &str) -> Result<()> {
        let flag = format!("--description {given}");
        let (name, file) = (given.split_once('='))
            .ok_or_else(|| HostError::invalid(&flag, "expected NAME=FILE"))?;
        let names: Vec<String> = sweeps.iter().map(|s| s.name.clone()).collect();
        let sweep = (sweeps.iter_mut())
            .find(|s| s.name == name)
            .ok_or_else(|| {
                HostError::invalid(
                    &flag,
                    format!(
                        "no table asked for has a sweep `{name}` (these have: {})",
                        names.join(", ")
                    ),
                )
            })?;
        sweep.text = std::fs::read_to_string(file).map_err(|e| HostError::io(file, e))?;
        Ok(())
    }

    /// The description file in the output folder `out`.
    fn description(&self, out: &Path) -> PathBuf {
        out.join(format!("{}.toml", self.name))
    }
}

/// The paper's tables.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Table {
    /// Table 2: baseline and ours on each training set, scored on the separate test set.
    Main,
    /// Table 3: baseline and ours against the number of training images.
    ImageCounts,
    /// Figures 5-6: SSIM, JNB and pose error against rotation and translation noise.
    PoseNoise,
}

/// Write every sweep's description into `out` (checked first; a folder holding another
/// description under the same name is refused), run the unfinished tasks of each with
/// `run_local` (the caller's runner: `sweep::run::run_local` with the binary), and write
/// `out/paper.md`: the main table from the main sweeps' records, then a link to each other
/// sweep's `sweep.md`. Returns `paper.md`'s text.
pub fn run(
    sweeps: &[PaperSweep],
    out: &Path,
    run_local: &mut dyn FnMut(&Path, &Path) -> Result<String>,
    say: &mut dyn FnMut(String),
) -> Result<String> {
    let mut described = Vec::new();
    for sweep in sweeps {
        let path = sweep.description(out);
        let what = format!("another description of `{}`", sweep.name);
        let (checked, written) = write_description(&path, &sweep.text, &what)?;
        if written == Written::Continued {
            say(format!("{}: continuing it", path.display()));
        }
        described.push((sweep, checked));
    }
    for (sweep, _) in &described {
        say(format!("{}:", sweep.name));
        run_local(&sweep.description(out), &out.join(&sweep.name))?;
    }
    let mut text = format!(
        "# The paper's tables\n\nWritten by `orbit-nerf paper --out {}` on {}. Each table is a sweep in its own folder (its description beside it, `<name>.toml`); rerunning the command continues unfinished tasks.\n",
        out.display(),
        crate::machine::cpu_summary()
    );
    let main: Vec<(&PaperSweep, &Sweep)> = (described.iter())
        .filter(|(s, _)| s.name.starts_with("main-"))
        .map(|(s, sweep)| (*s, sweep))
        .collect();
    if !main.is_empty() {
        text.push_str(&main_table(&main, out)?);
    }
    for (sweep, _) in described
        .iter()
        .filter(|(s, _)| !s.name.starts_with("main-"))
    {
        let _ = write!(
            text,
            "\n## `{0}`\n\nThe tables and plots: [{0}/sweep.md]({0}/sweep.md).\n",
            sweep.name
        );
    }
    write_atomic(&out.join("paper.md"), text.as_bytes())?;
    Ok(text)
}

/// The main table: a row per training set and model, the held-out figures on the separate
/// test set (PSNR, SSIM and JNB of the whole view as the paper reports them, and the
/// foreground PSNR), laid out as the paper's Table 2.
fn main_table(main: &[(&PaperSweep, &Sweep)], out: &Path) -> Result<String> {
    let header = [
        "training set",
        "model",
        "PSNR dB",
        "SSIM",
        "JNB",
        "fg PSNR dB",
        "test views",
        "frames, px, steps",
    ];
    let mut rows = Vec::new();
    let mut tests = Vec::new();
    for (paper_sweep, sweep) in main {
        let dir = out.join(&paper_sweep.name);
        let set = match &sweep.source {
            Source::Scene(scene) => scene.clone(),
            Source::Data(data) => data.display().to_string(),
        };
        tests.push(match &sweep.test {
            Some(TestSet::Scene { scene, frames }) => {
                format!("{frames} views of `{scene}` (exact poses)")
            }
            Some(TestSet::Data(data)) => format!("every view of `{}`", data.display()),
            None => format!("every {}th view of the training set", sweep.holdout),
        });
        for task in &sweep.tasks {
            let result: TaskResult = read_result(sweep, &dir, task)?.ok_or_else(|| {
                HostError::invalid(&dir, format!("task {} has no result", task.index))
            })?;
            let m = &result.metrics;
            rows.push(vec![
                format!("`{set}`"),
                result.variant.clone(),
                fixed(m.psnr_full, 2),
                fixed(m.ssim_full, 4),
                fixed(m.jnb_full, 3),
                fixed(m.psnr_foreground, 2),
                result.held_out_views.to_string(),
                format!("{}, {}, {}", task.frames, result.size, result.steps),
            ]);
        }
    }
    tests.dedup();
    Ok(format!(
        "\n## Main table: each training set, scored on the separate test set\n\nTest set: {}. PSNR and SSIM of the whole view (masked sky), JNB the blur per edge (lower is sharper), fg: over the target's pixels; held-out embeddings fitted on each test view's left half.\n\n{}",
        tests.join("; "),
        markdown_table(&header, &rows)
    ))
}
