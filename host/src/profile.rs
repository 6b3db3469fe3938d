//! Where the time goes: the clock the host lends the core's stage timers (feature `profile`),
//! and the per-stage table and stacked bar chart `bench --profile` prints and writes.

use crate::dataset::Dataset;
use crate::error::Result;
use crate::report::{markdown_table, stacked_bars};
use orbit_nerf_core::profile::{Stage, StageTimes};
use orbit_nerf_core::{Executor, Trainer};
use std::path::Path;
use std::sync::OnceLock;
use std::time::Instant;

/// Nanoseconds since the first call: the [`orbit_nerf_core::profile::Clock`] the host lends
/// the trainer (`Trainer::set_clock(Some(clock_ns))`).
pub fn clock_ns() -> u64 {
    static ORIGIN: OnceLock<Instant> = OnceLock::new();
    ORIGIN.get_or_init(Instant::now).elapsed().as_nanos() as u64
}

/// The stage times of `count` repetitions of one kind of work (training steps, or rendered
/// views), and the elapsed time measured around all of them.
#[derive(Clone, Copy, Debug)]
pub struct Breakdown {
    /// Summed over the chunks (CPU time over all threads).
    pub cpu: StageTimes,
    /// Elapsed, each parallel pass shared out over its stages.
    pub wall: StageTimes,
    /// Elapsed time around all the work, measured by the caller.
    pub elapsed_ns: u64,
    /// Steps or views.
    pub count: u32,
}

impl Breakdown {
    /// Milliseconds per repetition of `ns` nanoseconds in total.
    fn per_item_ms(&self, ns: u64) -> f64 {
        ns as f64 / 1e6 / self.count.max(1) as f64
    }

    /// The stages that took any time, with their wall and CPU milliseconds per repetition.
    pub fn stages(&self) -> Vec<(Stage, f64, f64)> {
        Stage::ALL
            .iter()
            .filter(|&&s| self.wall.get(s) > 0 || self.cpu.get(s) > 0)
            .map(|&s| {
                (
                    s,
                    self.per_item_ms(self.wall.get(s)),
                    self.per_item_ms(self.cpu.get(s)),
                )
            })
            .collect()
    }

    /// Elapsed time outside every timed stage (loop overhead, the caller's own work), in ms
    /// per repetition; never negative.
    pub fn untimed_ms(&self) -> f64 {
        self.per_item_ms(self.elapsed_ns.saturating_sub(self.wall.total()))
    }

    /// A markdown table: stage, wall ms per `unit`, share of the elapsed time, CPU ms per
    /// `unit` summed over the threads; then the untimed rest and the measured total.
    pub fn table(&self, unit: &str) -> String {
        let total = self.per_item_ms(self.elapsed_ns);
        let share = |ms: f64| {
            if total > 0.0 {
                format!("{:.1} %", 100.0 * ms / total)
            } else {
                "-".into()
            }
        };
        let mut rows: Vec<Vec<String>> = self
            .stages()
            .into_iter()
            .map(|(stage, wall, cpu)| {
                vec![
                    stage.name().into(),
                    format!("{wall:.3}"),
                    share(wall),
                    format!("{cpu:.3}"),
                ]
            })
            .collect();
        let untimed = self.untimed_ms();
        rows.push(vec![
            "untimed (loop, bookkeeping)".into(),
            format!("{untimed:.3}"),
            share(untimed),
            "-".into(),
        ]);
        rows.push(vec![
            format!("total (measured per {unit})"),
            format!("{total:.3}"),
            share(total),
            format!("{:.3}", self.per_item_ms(self.cpu.total())),
        ]);
        let wall = format!("wall ms per {unit}");
        let cpu = format!("CPU ms per {unit} (all threads)");
        markdown_table(&["stage", &wall, "share of wall", &cpu], &rows)
    }
}

/// A stacked bar chart of a training step's and a rendered view's stages: wall time and CPU
/// time summed over the threads, one bar each, in milliseconds.
pub fn write_chart(path: &Path, title: &str, step: &Breakdown, view: &Breakdown) -> Result<()> {
    let stages: Vec<Stage> = Stage::ALL
        .iter()
        .copied()
        .filter(|&s| {
            [step, view]
                .iter()
                .any(|b| b.wall.get(s) > 0 || b.cpu.get(s) > 0)
        })
        .collect();
    let names: Vec<&str> = stages.iter().map(|s| s.name()).collect();
    let bar = |b: &Breakdown, times: &StageTimes| -> Vec<f64> {
        stages
            .iter()
            .map(|&s| b.per_item_ms(times.get(s)))
            .collect()
    };
    let bars = [
        ("step wall", bar(step, &step.wall)),
        ("step CPU", bar(step, &step.cpu)),
        ("view wall", bar(view, &view.wall)),
        ("view CPU", bar(view, &view.cpu)),
    ];
    stacked_bars(
        path,
        title,
        "ms per training step / per view",
        &names,
        &bars,
    )
}

/// The timed training steps of `bench --profile`, and the views to time renders on.
pub struct Timed<'d> {
    /// Worker threads of the timed steps.
    pub threads: usize,
    /// Steps timed.
    pub steps: u32,
    /// Their wall time, nanoseconds.
    pub steps_ns: u64,
    /// The dataset of the views.
    pub dataset: &'d Dataset,
    /// The held-out views rendered with the clock running.
    pub views: &'d [usize],
}

/// Lend `trainer` the host's clock, forgetting the times so far (the warm-up's).
pub fn start(trainer: &mut Trainer<'_>) {
    trainer.set_clock(Some(clock_ns));
    trainer.reset_profile();
}

/// The timed steps' stage times, then every held-out view of `timed` fitted (`fit_steps` on
/// its left half) and rendered with the clock running: both tables as markdown. With
/// `chart` (a PNG path and the data's name for its title) also the stacked bar chart. The
/// clock is taken back at the end.
pub fn report<E: Executor>(
    trainer: &mut Trainer<'_>,
    executor: &E,
    timed: &Timed<'_>,
    fit_steps: u32,
    chart: Option<(&Path, &str)>,
) -> Result<String> {
    let profile = trainer.profile();
    let step = Breakdown {
        cpu: profile.train_cpu,
        wall: profile.train_wall,
        elapsed_ns: timed.steps_ns,
        count: timed.steps,
    };
    trainer.reset_profile();
    let mut mean = vec![0.0f32; trainer.config().embedding_dim as usize];
    trainer.mean_embedding(&mut mean);
    let start = Instant::now();
    for &index in timed.views {
        let frame = &timed.dataset.frames[index];
        let (embedding, pose) =
            crate::train::fit_held_out(trainer, executor, frame, fit_steps, false, &mean)
                .map_err(|e| crate::HostError::Core(e.to_string()))?;
        let mut out = vec![0.0f32; frame.camera.pixel_count() * 3];
        trainer
            .render(executor, &frame.camera, &pose, &embedding, &mut out)
            .map_err(|e| crate::HostError::Core(e.to_string()))?;
    }
    let profile = trainer.profile();
    let view = Breakdown {
        cpu: profile.render_cpu,
        wall: profile.render_wall,
        elapsed_ns: start.elapsed().as_nanos() as u64,
        count: timed.views.len() as u32,
    };
    trainer.set_clock(None);
    let threads = timed.threads;
    let fit = if mean.is_empty() {
        "no appearance embedding to fit".to_string()
    } else {
        format!("{fit_steps} embedding-fit steps on the left half")
    };
    let text = format!(
        "### {threads} thread(s): a training step (mean of {} steps)\n\n{}\n\
         ### {threads} thread(s): a held-out view ({fit}, then the whole view; mean of {} \
         views)\n\n{}\n",
        step.count,
        step.table("step"),
        view.count,
        view.table("view"),
    );
    if let Some((path, data)) = chart {
        let title = format!("{data}: where the time goes, {threads} thread(s)");
        write_chart(path, &title, &step, &view)?;
    }
    Ok(text)
}
