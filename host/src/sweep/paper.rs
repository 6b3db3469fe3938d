//! The paper's tables from one command (`orbit-nerf paper`): the main table (each of the
//! three training sets, baseline and ours, scored on one separate test set), the image-count
//! study and the pose-noise sweeps. Each is a sweep description (built in, or given), written
//! into the output folder and run there by the local runner, so a rerun continues where it
//! stopped and `sweep slurm` takes the same descriptions to a cluster; `paper.md` gathers
//! the tables with the CPU that ran them.

use super::results::{IMAGE_COUNT_TITLE, TaskResult, fixed, read_result};
use super::studies::{Written, write_description};
use super::{Source, Sweep, TestSet};
use crate::ablation::BASELINE;
use crate::error::{HostError, Result};
use crate::io::write_atomic;
use crate::report::{POSE_NOISE_TITLES, markdown_table};
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
    /// The table it makes.
    pub table: Table,
}

impl PaperSweep {
    /// The built-in sweeps of the tables asked for (`main`, `image-counts`, `pose-noise`).
    pub fn built_in(tables: &[Table]) -> Vec<PaperSweep> {
        let sweep = |name: &str, text: &str, table: Table| PaperSweep {
            name: name.into(),
            text: text.into(),
            table,
        };
        let mut sweeps = Vec::new();
        for &table in tables {
            match table {
                Table::Main => {
                    sweeps.extend(MAIN.iter().map(|(name, text)| sweep(name, text, table)))
                }
                Table::ImageCounts => sweeps.push(sweep("image-counts", IMAGE_COUNTS, table)),
                Table::PoseNoise => sweeps.push(sweep("pose-noise", POSE_NOISE, table)),
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
    pub fn description(&self, out: &Path) -> PathBuf {
        out.join(format!("{}.toml", self.name))
    }

    /// The sweep's folder in the output folder `out`.
    pub fn folder(&self, out: &Path) -> PathBuf {
        out.join(&self.name)
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

/// Write every sweep's description into `out` as `<name>.toml` (checked first; a folder
/// holding another description under the same name is refused), each sweep's folder being
/// `out/<name>`: what `sweep run` or `sweep slurm` takes, for [`run`] to gather afterwards.
/// Returns each sweep with its description as read back.
pub fn describe<'s>(
    sweeps: &'s [PaperSweep],
    out: &Path,
    say: &mut dyn FnMut(String),
) -> Result<Vec<(&'s PaperSweep, Sweep)>> {
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
    Ok(described)
}

/// Write every sweep's description into `out` ([`describe`]), run the unfinished tasks of
/// each with `run_local` (the caller's runner: `sweep::run::run_local` with the binary;
/// tasks finished earlier, here or by a cluster's array, are skipped), and write
/// `out/paper.md`: the main table from the main sweeps' records, then each other sweep's
/// study sections. Returns `paper.md`'s text.
pub fn run(
    sweeps: &[PaperSweep],
    out: &Path,
    run_local: &mut dyn FnMut(&Path, &Path) -> Result<String>,
    say: &mut dyn FnMut(String),
) -> Result<String> {
    let described = describe(sweeps, out, say)?;
    let mut reports = Vec::new();
    for (sweep, _) in &described {
        say(format!("{}:", sweep.name));
        reports.push(run_local(&sweep.description(out), &sweep.folder(out))?);
    }
    let mut text = format!(
        "# The paper's tables\n\nWritten by `orbit-nerf paper --out {}` on {}. Each table is a sweep in its own folder (its description beside it, `<name>.toml`); rerunning the command continues unfinished tasks.\n",
        out.display(),
        crate::machine::cpu_summary()
    );
    let main: Vec<(&PaperSweep, &Sweep)> = (described.iter())
        .filter(|(s, _)| s.table == Table::Main)
        .map(|(s, sweep)| (*s, sweep))
        .collect();
    if !main.is_empty() {
        text.push_str(&main_table(&main, out)?);
    }
    for ((sweep, _), report) in described.iter().zip(&reports) {
        let paper_says = match sweep.table {
            Table::Main => continue,
            Table::ImageCounts => PAPER_IMAGE_COUNTS,
            Table::PoseNoise => PAPER_POSE_NOISE,
        };
        let _ = write!(
            text,
            "\n## `{0}`\n\nEvery task's figures: [{0}/sweep.md]({0}/sweep.md).\n",
            sweep.name
        );
        text.push_str(paper_says);
        text.push_str(&study_sections(report, &sweep.name));
    }
    write_atomic(&out.join("paper.md"), text.as_bytes())?;
    Ok(text)
}

/// The paper's figures for its main comparison (its text: 200 test images of SPEED+
/// Lightbox), per training set: PSNR dB, SSIM and JNB of the baseline, then of the full
/// method (with pose correction where the paper gives it; its `Synthetic` labels are exact).
/// `-` where the paper states no figure; each as the paper prints it.
type PaperFigures = [&'static str; 3];
const PAPER_MAIN: [(&str, PaperFigures, PaperFigures); 3] = [
    ("synthetic", ["22.0", "0.927", "-"], ["30.3", "0.948", "-"]),
    (
        "lightbox",
        ["24.35", "0.944", "-"],
        ["30.54", "0.950", "0.0333"],
    ),
    (
        "sunlamp",
        ["18.84", "0.932", "-"],
        ["27.14", "0.951", "0.0389"],
    ),
];

/// What the paper reports of its image-count study, beside the table.
const PAPER_IMAGE_COUNTS: &str = "\nThe paper (its method on `Lightbox`, tested on SPEED+ Lightbox): 27.46 dB, SSIM 0.933, JNB 0.0496 at 25 training images; 30.54 dB, 0.950, 0.0337 at 400 (its JNB is Ferzli and Karam's D / L over the 540 blocks of a 1920 x 1200 image, which grows with the block count; ours is the blur per edge, which does not: compare directions, not magnitudes).\n";

/// What the paper reports of its pose-noise sweeps, beside the tables.
const PAPER_POSE_NOISE: &str = "\nThe paper gives these sweeps as plots only (`Synthetic`, SSIM and JNB against the labels' rotation and position noise): with pose correction SSIM is higher and JNB lower at every level.\n";

/// The study sections of a sweep's `sweep.md` (the image-count table, the pose-noise tables)
/// for `paper.md`: one heading level down, their plots linked inside the sweep's `folder`.
fn study_sections(report: &str, folder: &str) -> String {
    let [rotation, translation] = POSE_NOISE_TITLES;
    let studies = [IMAGE_COUNT_TITLE, rotation, translation];
    let mut text = String::new();
    let mut inside = false;
    for line in report.lines() {
        if let Some(heading) = line.strip_prefix("## ") {
            inside = studies.contains(&heading);
        }
        if !inside {
            continue;
        }
        let line = match line.strip_prefix("## ") {
            Some(heading) => format!("### {heading}"),
            None => match line.split_once("](") {
                Some((label, link)) if line.starts_with("![") => {
                    format!("{label}]({folder}/{link}")
                }
                _ => line.to_string(),
            },
        };
        text.push_str(&line);
        text.push('\n');
    }
    if !text.is_empty() {
        text.insert(0, '\n');
    }
    text
}

/// The main table: a row per training set and model, the held-out figures on the separate
/// test set (PSNR, SSIM and JNB of the whole view as the paper reports them, and the
/// foreground PSNR), laid out as the paper's Table 2, with the paper's own figures beside.
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
        "the paper: PSNR dB / SSIM / JNB",
    ];
    let mut rows = Vec::new();
    let mut tests = Vec::new();
    for (paper_sweep, sweep) in main {
        let dir = paper_sweep.folder(out);
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
            let paper = (PAPER_MAIN.iter().find(|(name, _, _)| **name == *set))
                .map(|(_, baseline, ours)| match result.variant.as_str() {
                    name if name == BASELINE.name => baseline,
                    _ => ours,
                })
                .map_or(String::new(), |[psnr, ssim, jnb]| {
                    format!("{psnr} / {ssim} / {jnb}")
                });
            rows.push(vec![
                format!("`{set}`"),
                result.variant.clone(),
                fixed(m.psnr_full, 2),
                fixed(m.ssim_full, 4),
                fixed(m.jnb_full, 3),
                fixed(m.psnr_foreground, 2),
                result.held_out_views.to_string(),
                format!("{}, {}, {}", task.frames, result.size, result.steps),
                paper,
            ]);
        }
    }
    tests.dedup();
    Ok(format!(
        "\n## Main table: each training set, scored on the separate test set\n\nTest set: {}. PSNR and SSIM of the whole view (masked sky), JNB the blur per edge (lower is sharper), fg: over the target's pixels; held-out embeddings fitted on each test view's left half. The paper's figures (its text; baseline, then its method with pose correction) are on SPEED+ Lightbox's 200 test images at 1920 x 1200; its JNB is D / L over 540 blocks, ours the blur per edge: compare directions, not magnitudes.\n\n{}",
        tests.join("; "),
        markdown_table(&header, &rows)
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `paper.md` takes a sweep's study sections (not its per-task table or renders), one
    /// heading level down, with their plots linked inside the sweep's folder.
    #[test]
    fn study_sections_are_taken_one_level_down_with_their_plots_in_the_folder() {
        let report = "# Sweep `x.toml` on `lightbox`\n\n| task | variant |\n|---|---|\n| 0 | baseline |\n\n## Image-count study\n\n| training images | baseline: PSNR (dB) |\n|---|---|\n| 25 | 25.09 |\n\n![PSNR (dB)](image_counts_psnr.png)\n\n## First held-out view, every task\n\n![renders](renders.png)\n\n## Rotation noise (exact positions)\n\n| E_R deg | SSIM ours |\n\n![SSIM](rotation_ssim.png)\n";
        let text = study_sections(report, "image-counts");
        assert!(text.contains("\n### Image-count study\n"), "{text}");
        assert!(text.contains("| 25 | 25.09 |"), "{text}");
        assert!(
            text.contains("![PSNR (dB)](image-counts/image_counts_psnr.png)"),
            "{text}"
        );
        assert!(text.contains("\n### Rotation noise (exact positions)\n"));
        assert!(text.contains("![SSIM](image-counts/rotation_ssim.png)"));
        assert!(!text.contains("renders") && !text.contains("| 0 | baseline |"));
        assert!(!text.contains("\n## "), "{text}");
        assert_eq!(study_sections("# Sweep\n\n| a |\n", "x"), "");
    }
}
