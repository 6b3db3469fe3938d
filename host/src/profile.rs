//! Where the time goes: the clock the host lends the core's stage timers (feature `profile`),
//! and the per-stage table and stacked bar chart `bench --profile` prints and writes.

use crate::error::Result;
use crate::report::{markdown_table, stacked_bars};
use orbit_nerf_core::profile::{Stage, StageTimes};
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
