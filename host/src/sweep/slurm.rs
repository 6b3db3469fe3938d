//! The Slurm job-array script of a sweep: one array task per sweep task, each running
//! `orbit-nerf sweep run-task` (the local runner's entry point) with its output in the task's
//! folder. The binary, the description and the output folder must be on a filesystem every
//! node sees. [`submit`] writes the script of the unfinished tasks and hands it to `sbatch`.

use super::Sweep;
use super::results::{array_spec, unfinished};
use crate::error::{HostError, Result};
use crate::io::write_atomic;
use std::path::{Path, PathBuf};
use std::process::Command;

/// What the `#SBATCH` lines say besides the array.
#[derive(Clone, Debug, PartialEq)]
pub struct Resources {
    /// CPUs of each array task (`--cpus-per-task`), 1 to [`MAX_CPUS_PER_TASK`].
    pub cpus_per_task: u32,
    /// `None`: the cluster's default partition.
    pub partition: Option<String>,
    /// Slurm time format (`minutes`, `HH:MM:SS`, `D-HH:MM`, ...); `None`: the partition's.
    pub time: Option<String>,
}

/// Largest `--cpus-per-task` accepted.
pub const MAX_CPUS_PER_TASK: u32 = 1024;

/// Check `--cpus-per-task`, `--partition` and `--time`; the error names the flag.
pub fn check(resources: &Resources) -> Result<(), String> {
    if !(1..=MAX_CPUS_PER_TASK).contains(&resources.cpus_per_task) {
        return Err(format!(
            "--cpus-per-task: {} is not between 1 and {MAX_CPUS_PER_TASK}",
            resources.cpus_per_task
        ));
    }
    if let Some(partition) = &resources.partition {
        let ok = !partition.is_empty()
            && (partition.chars()).all(|c| c.is_ascii_alphanumeric() || "_.-,".contains(c));
        if !ok {
            return Err(format!(
                "--partition: `{partition}` is not a partition name (letters, digits, _ . -; several separated by commas)"
            ));
        }
    }
    if let Some(time) = &resources.time {
        check_time(time).map_err(|e| format!("--time: `{time}`: {e}"))?;
    }
    Ok(())
}

/// Slurm's time limit formats: `M`, `M:S`, `H:M:S`, `D-H`, `D-H:M`, `D-H:M:S`; not zero.
fn check_time(time: &str) -> Result<(), String> {
    let numbers = |text: &str| -> Result<Vec<u64>, String> {
        (text.split(':'))
            .map(|part| {
                (!part.is_empty() && part.len() <= 6 && part.chars().all(|c| c.is_ascii_digit()))
                    .then(|| part.parse::<u64>().unwrap_or(0))
                    .ok_or_else(|| {
                        "expected minutes, M:S, H:M:S, D-H, D-H:M or D-H:M:S".to_string()
                    })
            })
            .collect()
    };
    let (days, rest) = match time.split_once('-') {
        Some((days, rest)) => (numbers(days)?, numbers(rest)?),
        None => (vec![0], numbers(time)?),
    };
    if days.len() != 1 || !(1..=3).contains(&rest.len()) {
        return Err("expected minutes, M:S, H:M:S, D-H, D-H:M or D-H:M:S".into());
    }
    if days[0] == 0 && rest.iter().all(|&n| n == 0) {
        return Err("a time limit of zero".into());
    }
    Ok(())
}

/// Check that the output folder can stand in an `#SBATCH --output` line: Slurm splits those at
/// whitespace and reads `%` as a file-name pattern.
pub fn check_output_folder(out: &Path) -> Result<(), String> {
    let text = out.display().to_string();
    match text.chars().find(|c| c.is_whitespace() || *c == '%') {
        Some(c) => Err(format!(
            "--out: {text}: Slurm's #SBATCH lines cannot hold a path with {c:?}; choose another folder"
        )),
        None => Ok(()),
    }
}

/// `text` as one shell word (single quotes).
fn quoted(text: &str) -> String {
    format!("'{}'", text.replace('\'', r"'\''"))
}

/// The array script: tasks `array` (a Slurm `--array` list) of the sweep `description` into
/// `out`, run by `binary`. Paths should be absolute: the nodes start it elsewhere.
pub fn script(
    binary: &Path,
    description: &Path,
    out: &Path,
    array: &str,
    resources: &Resources,
) -> String {
    let mut lines = vec![
        "#!/bin/bash".to_string(),
        "# orbit-nerf sweep: one array task per sweep task (written by `orbit-nerf sweep slurm`)."
            .to_string(),
        "#SBATCH --job-name=orbit-nerf-sweep".to_string(),
        format!("#SBATCH --array={array}"),
        "#SBATCH --ntasks=1".to_string(),
        format!("#SBATCH --cpus-per-task={}", resources.cpus_per_task),
    ];
    if let Some(partition) = &resources.partition {
        lines.push(format!("#SBATCH --partition={partition}"));
    }
    if let Some(time) = &resources.time {
        lines.push(format!("#SBATCH --time={time}"));
    }
    // Slurm's own messages (before the task starts, a time limit hit); the task's output goes
    // to its folder's log, as in a local run.
    lines.push(format!(
        "#SBATCH --output={}",
        out.join("slurm").join("%A_%a.out").display()
    ));
    lines.push("set -euo pipefail".to_string());
    lines.push(format!(
        "task={}/tasks/\"$SLURM_ARRAY_TASK_ID\"",
        quoted(&out.display().to_string())
    ));
    lines.push("mkdir -p \"$task\"".to_string());
    lines.push(format!(
        "exec {} sweep run-task {} \"$SLURM_ARRAY_TASK_ID\" --out {} --threads \"${{SLURM_CPUS_PER_TASK:-1}}\" >\"$task/log.txt\" 2>&1",
        quoted(&binary.display().to_string()),
        quoted(&description.display().to_string()),
        quoted(&out.display().to_string()),
    ));
    let mut text = lines.join("\n");
    text.push('\n');
    text
}

/// What [`submit`] did.
#[derive(Debug, PartialEq)]
pub enum Submission {
    /// Every task has a result: no script written.
    NothingToRun,
    /// The script of `pending` of `tasks` tasks (array `array`) written to `script`; `job` is
    /// the job id `sbatch` gave, `None` when only written.
    Script {
        /// The sbatch script.
        script: PathBuf,
        /// Tasks without a result, in the array.
        pending: usize,
        /// Tasks of the description.
        tasks: usize,
        /// The array's `--array` value.
        array: String,
        /// The submitted job's id.
        job: Option<String>,
    },
}

impl Submission {
    /// What was done and what to do next, for the description at `description` and the
    /// sweep folder `out`.
    pub fn report(&self, description: &Path, out: &Path) -> String {
        let collect = format!(
            "orbit-nerf sweep collect {} --out {}",
            description.display(),
            out.display()
        );
        match self {
            Submission::NothingToRun => {
                format!("every task has a result: nothing to submit; merge them with `{collect}`")
            }
            Submission::Script {
                script,
                pending,
                tasks,
                array,
                job,
            } => {
                let next = match job {
                    None => format!("submit it with `sbatch {}`", script.display()),
                    Some(job) => {
                        format!("submitted job array {job}; when it has finished: {collect}")
                    }
                };
                format!(
                    "wrote {} ({pending} of {tasks} tasks: --array={array})\n{next}",
                    script.display()
                )
            }
        }
    }
}

/// Write the Slurm array script of the unfinished tasks to `<out>/sweep.sbatch`, running
/// `exe sweep run-task` per task, and submit it with `sbatch` unless `no_submit`. The binary,
/// the description and `out` must be on a filesystem every node sees (paths are made
/// absolute).
pub fn submit(
    exe: &Path,
    description: &Path,
    out: &Path,
    resources: &Resources,
    no_submit: bool,
) -> Result<Submission> {
    check(resources).map_err(|reason| HostError::invalid(description, reason))?;
    let sweep = Sweep::read(description)?;
    crate::io::check_output_folder(out)?;
    let pending = unfinished(&sweep, out)?;
    if pending.is_empty() {
        return Ok(Submission::NothingToRun);
    }
    let slurm_dir = out.join("slurm");
    std::fs::create_dir_all(&slurm_dir).map_err(|e| HostError::io(&slurm_dir, e))?;
    let absolute = |p: &Path| std::fs::canonicalize(p).map_err(|e| HostError::io(p, e));
    let (exe, description_abs, out_abs) = (absolute(exe)?, absolute(description)?, absolute(out)?);
    check_output_folder(&out_abs).map_err(|reason| HostError::invalid(out, reason))?;
    let array = array_spec(&pending);
    let script_path = out.join("sweep.sbatch");
    let text = script(&exe, &description_abs, &out_abs, &array, resources);
    write_atomic(&script_path, text.as_bytes())?;
    let job = if no_submit {
        None
    } else {
        let output = Command::new("sbatch")
            .arg("--parsable")
            .arg(&script_path)
            .output()
            .map_err(|e| {
                HostError::invalid(
                    &script_path,
                    format!(
                        "sbatch: {e} (is Slurm installed here? --no-submit only writes the script)"
                    ),
                )
            })?;
        if !output.status.success() {
            return Err(HostError::invalid(
                &script_path,
                format!(
                    "sbatch refused it: {}",
                    String::from_utf8_lossy(&output.stderr).trim()
                ),
            ));
        }
        Some(String::from_utf8_lossy(&output.stdout).trim().to_string())
    };
    Ok(Submission::Script {
        script: script_path,
        pending: pending.len(),
        tasks: sweep.tasks.len(),
        array,
        job,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn resources(cpus: u32, partition: Option<&str>, time: Option<&str>) -> Resources {
        Resources {
            cpus_per_task: cpus,
            partition: partition.map(str::to_string),
            time: time.map(str::to_string),
        }
    }

    #[test]
    fn resources_are_checked_and_the_error_names_the_flag() {
        for time in ["30", "10:00", "01:00:00", "2-0", "1-12:00", "1-00:00:00"] {
            assert_eq!(
                check(&resources(2, Some("debug"), Some(time))),
                Ok(()),
                "{time}"
            );
        }
        for (bad, flag) in [
            (resources(0, None, None), "--cpus-per-task"),
            (resources(5000, None, None), "--cpus-per-task"),
            (resources(1, Some(""), None), "--partition"),
            (resources(1, Some("a b"), None), "--partition"),
            (resources(1, Some("x;rm"), None), "--partition"),
            (resources(1, None, Some("0")), "--time"),
            (resources(1, None, Some("00:00:00")), "--time"),
            (resources(1, None, Some("1:2:3:4")), "--time"),
            (resources(1, None, Some("-5")), "--time"),
            (resources(1, None, Some("inf")), "--time"),
            (resources(1, None, Some("1-2-3")), "--time"),
            (resources(1, None, Some("")), "--time"),
        ] {
            let error = check(&bad).unwrap_err();
            assert!(error.starts_with(flag), "{bad:?}: {error}");
        }
    }

    #[test]
    fn output_folders_with_spaces_or_patterns_are_refused() {
        assert_eq!(
            check_output_folder(Path::new("/shared/runs/sweep-1")),
            Ok(())
        );
        for bad in ["/shared/my runs", "/shared/100%", "/shared/a\tb"] {
            let error = check_output_folder(Path::new(bad)).unwrap_err();
            assert!(error.starts_with("--out: "), "{error}");
        }
    }

    #[test]
    fn the_script_runs_the_task_entry_point_per_array_index() {
        let text = script(
            Path::new("/opt/orbit nerf/orbit-nerf"),
            Path::new("/shared/sweep's.toml"),
            Path::new("/shared/out"),
            "0-2,5",
            &resources(4, Some("cpu"), Some("01:00:00")),
        );
        for line in [
            "#SBATCH --array=0-2,5",
            "#SBATCH --cpus-per-task=4",
            "#SBATCH --partition=cpu",
            "#SBATCH --time=01:00:00",
            "#SBATCH --output=/shared/out/slurm/%A_%a.out",
        ] {
            assert!(text.lines().any(|l| l == line), "{line}\n{text}");
        }
        assert!(text.contains(
            "exec '/opt/orbit nerf/orbit-nerf' sweep run-task '/shared/sweep'\\''s.toml' \"$SLURM_ARRAY_TASK_ID\" --out '/shared/out'"
        ), "{text}");
        let defaults = script(
            Path::new("/b"),
            Path::new("/d"),
            Path::new("/o"),
            "0",
            &resources(1, None, None),
        );
        assert!(
            !defaults.contains("--partition") && !defaults.contains("--time"),
            "{defaults}"
        );
    }
}
