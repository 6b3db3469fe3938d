//! What a run shows while and after it trains, as text: the running train-loss PSNR, the
//! tally of a session's steps with its progress and summary lines, and the held-out scores'
//! table. A front end (the CLI's bars, a ground-segment log) only prints these.

use crate::pipeline::StepTally;
use crate::report::{ViewMetrics, mean_metrics};
use crate::train::ViewScore;
use orbit_nerf_core::StepReport;
use std::fmt::Write as _;
use std::time::Instant;

/// The figure shown while training: the PSNR of an exponential average of the training
/// batches' loss (skipped steps left out), in dB. It is labelled "train-loss PSNR": it is not
/// the held-out PSNR, which only `report::score_view` defines.
#[derive(Clone, Copy, Debug, Default)]
pub struct RunningPsnr(Option<f64>);

impl RunningPsnr {
    /// Take one step's report (a skipped step changes nothing).
    pub fn add(&mut self, report: &StepReport) {
        if report.skipped {
            return;
        }
        let mse = report.mse as f64;
        self.0 = Some(self.0.map_or(mse, |r| 0.95 * r + 0.05 * mse));
    }

    /// The PSNR of the running loss, dB; 0 before the first step.
    pub fn db(&self) -> f64 {
        self.0.map_or(0.0, |m| -10.0 * m.max(1e-12).log10())
    }
}

/// A training session's steps as they come: rays, samples, skipped steps, wall time and the
/// running train-loss PSNR.
#[derive(Clone, Copy, Debug)]
pub struct SessionProgress {
    /// The steps' rays, samples and seconds.
    pub tally: StepTally,
    /// Steps the core skipped (no ray met the box, or a non-finite loss).
    pub skipped: u32,
    /// The running train-loss PSNR.
    pub running: RunningPsnr,
    started: Instant,
}

impl Default for SessionProgress {
    fn default() -> SessionProgress {
        SessionProgress {
            tally: StepTally::default(),
            skipped: 0,
            running: RunningPsnr::default(),
            started: Instant::now(),
        }
    }
}

impl SessionProgress {
    /// Start the session's clock now.
    pub fn restart_clock(&mut self) {
        self.started = Instant::now();
    }

    /// Count one step's `report`.
    pub fn add(&mut self, report: &StepReport) {
        self.tally
            .count(report, self.started.elapsed().as_secs_f64());
        if report.skipped {
            self.skipped += 1;
        }
        self.running.add(report);
    }

    /// The short message beside a progress bar after `report`.
    pub fn bar_message(&self, report: &StepReport) -> String {
        format!(
            "loss {:.5} train-loss PSNR {:.2} dB {:.1} samples/ray",
            report.mse,
            self.running.db(),
            report.samples as f32 / report.rays.max(1) as f32
        )
    }

    /// A plain progress line at `step` of `end` (for logs, where no bar is drawn).
    pub fn line(&self, step: u32, end: u32, report: &StepReport) -> String {
        let tally = &self.tally;
        let per_step = tally.seconds / tally.steps.max(1) as f64;
        format!(
            "step {step}/{end}: loss {:.5}, {:.0} rays/s, ETA {:.0} s",
            report.mse,
            tally.rays as f64 / tally.seconds.max(1e-9),
            per_step * end.saturating_sub(step) as f64
        )
    }

    /// Speed, samples per ray and skipped steps of the session.
    pub fn summary(&self) -> String {
        let s = &self.tally;
        if s.steps == 0 {
            // Stopped within the first step of the session, which was given up.
            return "no training step finished in this session".into();
        }
        format!(
            "trained in {:.1} s: {:.0} rays/s, {:.0} samples/s ({:.1} samples/ray after early stop, {:.1} marched), {} steps skipped",
            s.seconds,
            s.rays as f64 / s.seconds,
            s.samples as f64 / s.seconds,
            s.samples_per_ray(),
            s.marched as f64 / s.rays.max(1) as f64,
            self.skipped
        )
    }
}

/// The held-out scores as text, one line per view and the mean (metrics as
/// `report::score_view` defines them), and the mean's metrics.
pub fn scores_table(scores: &[ViewScore]) -> (String, ViewMetrics) {
    let mut text = format!(
        "{:>6}  {:>8}  {:>8}  {:>8}  {:>6}  {:>6}  {:>11}  view\n",
        "index", "PSNR dB", "right dB", "fg dB", "SSIM", "JNB", "samples/ray"
    );
    for s in scores {
        let m = &s.metrics;
        let _ = writeln!(
            text,
            "{:>6}  {:>8.2}  {:>8.2}  {:>8.2}  {:>6.4}  {:>6.3}  {:>11.1}  {}",
            s.index,
            m.psnr_full,
            m.psnr_right,
            m.psnr_foreground,
            m.ssim_full,
            m.jnb_full,
            s.samples_per_ray,
            s.name
        );
    }
    let per_view: Vec<ViewMetrics> = scores.iter().map(|s| s.metrics).collect();
    let mean = mean_metrics(&per_view);
    let _ = writeln!(
        text,
        "mean PSNR over {} held-out views: {:.2} dB",
        scores.len(),
        mean.psnr_full
    );
    let _ = write!(
        text,
        "mean right-half PSNR {:.2} dB, foreground PSNR {:.2} dB (right half {:.2} dB), SSIM {:.4}, JNB {:.3} (blur per edge), CPBD {:.3}",
        mean.psnr_right,
        mean.psnr_foreground,
        mean.psnr_foreground_right,
        mean.ssim_full,
        mean.jnb_full,
        mean.cpbd_full
    );
    (text, mean)
}
