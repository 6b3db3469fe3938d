//! The paper's experiments: the three models (baseline K-Planes, with appearance embeddings,
//! and with appearance embeddings and pose correction) trained with the same budget on one
//! dataset, scored with the paper's protocol, and the pose-error report against the
//! simulator's exact poses.

use crate::dataset::Dataset;
use crate::error::{HostError, Result};
use crate::geometry::{self, Chamfer, Mesh, SurfaceOptions, Triangle};
use crate::report::{
    self, FramePose, MeansAt, ModelFigures, PoseErrors, PoseRefinementFigures, PoseUncertainty,
    TrainingFigures, ViewFigures, ViewMetrics,
};
use crate::train::{self, RayonExecutor};
use orbit_nerf_core::{Config, MemoryPlan, Pose, PoseFit, StepReport, Trainer};
use std::time::Instant;

/// Which of the method's additions a model uses.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Variant {
    /// The model's name in tables and `metrics.json` (`""` for an unnamed run).
    pub name: &'static str,
    /// Appearance embedding size per frame (0: no appearance embeddings).
    pub embedding_dim: u16,
    /// Whether the model learns a pose correction per training frame.
    pub pose_correction: bool,
}

/// Appearance embedding size of the method's models.
pub const EMBEDDING_DIM: u16 = 32;

/// Plain K-Planes: no appearance embeddings, no pose correction.
pub const BASELINE: Variant = Variant {
    name: "baseline",
    embedding_dim: 0,
    pose_correction: false,
};
/// The method with appearance embeddings ([`EMBEDDING_DIM`]) and no pose correction.
pub const APPEARANCE: Variant = Variant {
    name: "ours",
    embedding_dim: EMBEDDING_DIM,
    pose_correction: false,
};
/// The full method: appearance embeddings ([`EMBEDDING_DIM`]) and pose correction.
pub const APPEARANCE_POSE: Variant = Variant {
    name: "ours + pose",
    embedding_dim: EMBEDDING_DIM,
    pose_correction: true,
};

/// What training and evaluating one model gave.
pub struct VariantResult {
    /// The model's variant (named `""` when it came from [`Experiment::run`]).
    pub variant: Variant,
    /// Wall time of training, pose refinement included, seconds (anytime scoring and
    /// progress saves left out; summed over resumed stretches).
    pub train_seconds: f64,
    /// Mean over the held-out views.
    pub metrics: ViewMetrics,
    /// The held-out figures at each of the experiment's `score_at` steps, then at the end.
    pub curve: Vec<CurvePoint>,
    /// Samples the training rays met in the scene box, over the whole run.
    pub samples: u64,
    /// Bytes of the model's arena (the memory plan's total).
    pub arena_bytes: usize,
    /// Renders of the held-out views (RGB f32), in `test` order.
    pub renders: Vec<Vec<f32>>,
    /// Pose error of the training labels against the exact poses; `None` when the dataset
    /// has none.
    pub pose_before: Option<PoseErrors>,
    /// Pose error of the training labels with the learned corrections applied, against the
    /// exact poses; `None` when the dataset has none.
    pub pose_after: Option<PoseErrors>,
    /// Each training frame's pose refinement (its uncertainty), in training order; empty
    /// without pose correction.
    pub pose_fits: Vec<PoseFit>,
    /// Each training frame's refined pose: uncertainty and, with exact poses, true error.
    pub pose_frames: Vec<FramePose>,
    /// Their summary (with pose correction).
    pub pose_uncertainty: Option<PoseUncertainty>,
    /// Seconds of the pose refinement (part of `train_seconds`).
    pub pose_refine_seconds: f64,
    /// The held-out means with each view at its exact pose; `None` when the data has no
    /// exact poses (`metrics` is at the labels).
    pub metrics_exact: Option<ViewMetrics>,
    /// The held-out means with each view at its label aligned by the pose refinement
    /// (test-time alignment).
    pub metrics_aligned: ViewMetrics,
    /// Each held-out view's figures, in `test` order.
    pub views: Vec<ViewFigures>,
    /// The training figures for `metrics.json`: steps, skipped steps, seconds, samples per ray.
    pub training: TrainingFigures,
    /// The field's surface (`geometry::extract_surface` with the default options and the
    /// mean training embedding), or why there is none.
    pub surface: Result<Mesh>,
}

impl VariantResult {
    /// The model's figures for `metrics.json`, under its variant's name.
    pub fn figures(&self) -> ModelFigures {
        ModelFigures {
            name: self.variant.name.to_string(),
            mean: self.metrics,
            views: self.views.clone(),
            training: Some(self.training),
            mean_at: Some(MeansAt {
                exact_poses: self.metrics_exact,
                aligned: self.metrics_aligned,
            }),
            pose_refinement: self.pose_uncertainty.map(|summary| PoseRefinementFigures {
                summary,
                frames: self.pose_frames.clone(),
            }),
        }
    }
}

/// A dataset with its held-out split, the exact poses when known, and how a model is
/// evaluated on it: what every model of an experiment shares.
pub struct Experiment<'a> {
    /// The dataset every model trains and is scored on.
    pub dataset: &'a Dataset,
    /// Every frame's exact pose, indexed like `dataset.frames`; `None` when unknown.
    pub truth: Option<&'a [Pose]>,
    /// Indices into `dataset.frames` of the training views.
    pub train_idx: &'a [usize],
    /// Indices into `dataset.frames` of the held-out (scored) views.
    pub test_idx: &'a [usize],
    /// Worker threads.
    pub threads: usize,
    /// Steps fitting each held-out view's embedding on its left half.
    pub fit_steps: u32,
    /// Steps after which the held-out views are also scored (the anytime curve), with the
    /// training clock paused; ascending, each below the config's steps (the last step is
    /// always scored).
    pub score_at: &'a [u32],
    /// Where a long run keeps its state, so that a killed run continues to the same bytes.
    pub progress: Option<Progress<'a>>,
}

/// A run's progress checkpoint: the trainer's state and the figures so far, written
/// atomically every `every` steps (and at `stop_after`) and removed when the run ends. A run
/// that finds one continues from it.
#[derive(Clone, Copy, Debug)]
pub struct Progress<'a> {
    /// The progress checkpoint file (a trainer checkpoint with the figures so far).
    pub path: &'a std::path::Path,
    /// Save it every this many steps (0 is taken as 1).
    pub every: u32,
    /// Stop after this step (before the last), the state saved: [`HostError::Stopped`].
    pub stop_after: Option<u32>,
}

/// The figures a progress checkpoint carries beside the trainer's sections.
#[derive(serde::Serialize, serde::Deserialize)]
struct FiguresSoFar {
    train_seconds: f64,
    rays: u64,
    samples: u64,
    curve: Vec<CurvePoint>,
}

/// The progress checkpoint's section of [`FiguresSoFar`].
const FIGURES_SECTION: &str = "run_figures";

/// The held-out views' mean figures after `step` training steps, reached in `seconds` of
/// training (scoring time left out).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CurvePoint {
    /// Training steps taken.
    pub step: u32,
    /// Training wall time to reach them, seconds (scoring and saves left out).
    pub seconds: f64,
    /// The held-out views' mean metrics, at their labels.
    pub metrics: ViewMetrics,
}

/// A model's surface against the true shape: its size and the Chamfer distance, or why
/// there is none.
pub struct GeometryRow {
    /// The model's variant name.
    pub name: String,
    /// Vertices of its surface mesh (0 without a surface).
    pub vertices: usize,
    /// Triangles of its surface mesh (0 without a surface).
    pub triangles: usize,
    /// The Chamfer distance to the true surface, in the scene's units (metres for the
    /// simulator's scenes), or why there is none.
    pub chamfer: std::result::Result<Chamfer, String>,
}

/// `result`'s surface scored against the true surface `truth` (the Chamfer distance with
/// [`geometry::chamfer::DEFAULT_SAMPLES`] points on each).
pub fn geometry_row(result: &VariantResult, truth: &[Triangle]) -> GeometryRow {
    let (vertices, triangles, chamfer) = match &result.surface {
        Ok(mesh) => (
            mesh.positions.len(),
            mesh.triangles.len(),
            geometry::chamfer_distance(
                &mesh.triangle_corners(),
                truth,
                geometry::chamfer::DEFAULT_SAMPLES,
            )
            .ok_or_else(|| "a surface without area".to_string()),
        ),
        Err(e) => (0, 0, Err(e.to_string())),
    };
    GeometryRow {
        name: result.variant.name.to_string(),
        vertices,
        triangles,
        chamfer,
    }
}

/// Train one variant of `base` on the `train` views for `base.steps` steps (calling
/// `on_step` after each) and evaluate it on the `test` views (fitting held-out embeddings
/// for `fit_steps` steps).
#[allow(clippy::too_many_arguments)]
pub fn run_variant(
    dataset: &Dataset,
    truth: Option<&[Pose]>,
    train_idx: &[usize],
    test_idx: &[usize],
    base: &Config,
    variant: Variant,
    threads: usize,
    fit_steps: u32,
    on_step: &mut dyn FnMut(u32, &StepReport),
) -> Result<VariantResult> {
    let mut config = *base;
    config.embedding_dim = variant.embedding_dim;
    config.pose_correction = variant.pose_correction;
    let experiment = Experiment {
        dataset,
        truth,
        train_idx,
        test_idx,
        threads,
        fit_steps,
        score_at: &[],
        progress: None,
    };
    let mut result = experiment.run(&config, on_step, None)?;
    result.variant = variant;
    Ok(result)
}

impl Experiment<'_> {
    /// Train `config` (its scene box and capacities fitted to the dataset) on the training
    /// views (calling `on_step` after each step), save its checkpoint to `checkpoint` when
    /// given, and evaluate it on the held-out views. The result's variant is named after
    /// nothing (`""`), with the config's embedding size and pose correction.
    pub fn run(
        &self,
        config: &Config,
        on_step: &mut dyn FnMut(u32, &StepReport),
        checkpoint: Option<&std::path::Path>,
    ) -> Result<VariantResult> {
        let (dataset, train_idx) = (self.dataset, self.train_idx);
        let config = train::fit_config(config, dataset, train_idx.len());
        let executor = RayonExecutor::new(self.threads)?;
        let names: Vec<String> = train_idx
            .iter()
            .map(|&i| dataset.frames[i].name.clone())
            .collect();
        if let Some(truth) = self.truth.filter(|t| t.len() != dataset.frames.len()) {
            return Err(HostError::invalid(
                &dataset.source,
                format!(
                    "{} exact poses for {} frames: they cannot be paired",
                    truth.len(),
                    dataset.frames.len()
                ),
            ));
        }
        let frames: Vec<_> = train_idx.iter().map(|&i| &dataset.frames[i]).collect();
        // The arena is checked against the default share of the machine's memory first.
        crate::pipeline::with_trainer(&dataset.source, (config, None), &[], &frames, |trainer| {
            // The held-out views' scores and their mean, at the labels, at the exact poses
            // (`poses`) or aligned.
            let score_at = |trainer: &mut Trainer<'_>,
                            poses: Option<&[Pose]>,
                            align: bool|
             -> Result<(Vec<train::ViewScore>, ViewMetrics)> {
                let scores = train::evaluate_at(
                    trainer,
                    &executor,
                    dataset,
                    self.test_idx,
                    poses,
                    (self.fit_steps, align),
                    None,
                )?;
                let per_view: Vec<ViewMetrics> = scores.iter().map(|s| s.metrics).collect();
                Ok((scores, report::mean_metrics(&per_view)))
            };
            let score = |trainer: &mut Trainer<'_>| score_at(trainer, None, false);
            let mut so_far = FiguresSoFar {
                train_seconds: 0.0,
                rays: 0,
                samples: 0,
                curve: Vec::with_capacity(self.score_at.len() + 1),
            };
            if let Some(progress) = self.progress.filter(|p| p.path.exists()) {
                so_far = resume(progress.path, &config, trainer)?;
            }
            let mut observer = ExperimentSteps {
                on_step,
                score: &|trainer: &mut Trainer<'_>| Ok(score(trainer)?.1),
                score_at: self.score_at,
                progress: self.progress,
                so_far,
                clock: Instant::now(),
            };
            crate::pipeline::train_steps(trainer, &executor, config.steps, &mut observer).map_err(
                |e| match e {
                    HostError::Core(reason) => HostError::invalid(&dataset.source, reason),
                    other => other,
                },
            )?;
            let FiguresSoFar {
                mut train_seconds,
                rays,
                samples,
                mut curve,
            } = observer.so_far;
            let start = observer.clock;
            // The poses' refinement with the field frozen is the run's last training stage.
            let refine_start = Instant::now();
            let pose_fits = train::refine_poses(trainer, &executor)?;
            let pose_refine_seconds = refine_start.elapsed().as_secs_f64();
            train_seconds += start.elapsed().as_secs_f64();
            let tally = train::TrainingTally {
                steps: config.steps as u64,
                samples,
            };
            train::check_trained(&dataset.source, trainer, tally)?;
            let training = TrainingFigures {
                steps: trainer.state().step as u64,
                steps_skipped: trainer.state().skipped as u64,
                seconds: train_seconds,
                samples_per_ray: samples as f64 / rays.max(1) as f64,
            };
            if let Some(path) = checkpoint {
                train::save_checkpoint(path, trainer, &[])?;
            }
            let (scores, metrics) = score(trainer)?;
            curve.push(CurvePoint {
                step: config.steps,
                seconds: train_seconds,
                metrics,
            });
            let mut mean = vec![0.0f32; config.embedding_dim as usize];
            trainer.mean_embedding(&mut mean);
            let surface = geometry::extract_surface(
                trainer,
                &executor,
                &mean,
                &SurfaceOptions::default(),
                &dataset.source,
                crate::memory::limit_or_default(None),
            );
            let metrics_exact = match self.truth {
                Some(truth) => Some(score_at(trainer, Some(truth), false)?.1),
                None => None,
            };
            let (_, metrics_aligned) = score_at(trainer, None, true)?;
            let labels: Vec<Pose> = train_idx.iter().map(|&i| dataset.frames[i].pose).collect();
            let corrected: Vec<Pose> = labels
                .iter()
                .enumerate()
                .map(|(slot, label)| {
                    let correction = trainer.pose_correction(slot).unwrap_or_default();
                    correction.apply(label, config.pose_pivot_point())
                })
                .collect();
            let exact: Option<Vec<Pose>> = self
                .truth
                .map(|truth| train_idx.iter().map(|&i| truth[i]).collect());
            let (pose_before, pose_after) = match &exact {
                Some(exact) => (
                    Some(report::pose_errors(&labels, exact)),
                    Some(report::pose_errors(&corrected, exact)),
                ),
                None => (None, None),
            };
            let pose_frames = report::frame_poses(&names, &pose_fits, &corrected, exact.as_deref());
            let pose_uncertainty =
                (!pose_frames.is_empty()).then(|| report::pose_uncertainty(&pose_frames));
            if let Some(progress) = self.progress {
                // The run's own scratch file: its figures are in the result now.
                match std::fs::remove_file(progress.path) {
                    Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
                        return Err(HostError::io(progress.path, e));
                    }
                    _ => {}
                }
            }
            Ok(VariantResult {
                variant: Variant {
                    name: "",
                    embedding_dim: config.embedding_dim,
                    pose_correction: config.pose_correction,
                },
                train_seconds,
                metrics,
                curve,
                samples,
                arena_bytes: MemoryPlan::new(&config).total,
                views: train::view_figures(&scores),
                renders: scores.into_iter().map(|s| s.render).collect(),
                pose_before,
                pose_after,
                pose_fits,
                pose_frames,
                pose_uncertainty,
                pose_refine_seconds,
                metrics_exact,
                metrics_aligned,
                training,
                surface,
            })
        })
    }
}

/// An experiment's observer of its training steps: the caller's `on_step`, the anytime scores
/// at `score_at` and the progress checkpoints, with the training clock paused while it scores
/// or saves.
struct ExperimentSteps<'o, 's> {
    on_step: &'o mut dyn FnMut(u32, &StepReport),
    score: &'s dyn Fn(&mut Trainer<'_>) -> Result<ViewMetrics>,
    score_at: &'o [u32],
    progress: Option<Progress<'o>>,
    so_far: FiguresSoFar,
    /// When the current stretch of training began.
    clock: Instant,
}

impl crate::pipeline::Observer for ExperimentSteps<'_, '_> {
    fn start(&mut self, _: &Trainer<'_>, _: u32) {
        self.clock = Instant::now();
    }

    fn step(
        &mut self,
        trainer: &mut Trainer<'_>,
        end: u32,
        report: &StepReport,
    ) -> Result<crate::pipeline::Flow> {
        let step = trainer.state().step;
        let so_far = &mut self.so_far;
        so_far.rays += report.rays as u64;
        so_far.samples += report.samples as u64;
        (self.on_step)(step, report);
        if self.score_at.contains(&step) && step < end {
            so_far.train_seconds += self.clock.elapsed().as_secs_f64();
            // Scoring reads the field and fits held-out embeddings in scratch buffers:
            // training goes on from the same state (the sweep test checks the bytes).
            let metrics = (self.score)(trainer)?;
            so_far.curve.push(CurvePoint {
                step,
                seconds: so_far.train_seconds,
                metrics,
            });
            self.clock = Instant::now();
        }
        if let Some(progress) = self.progress.filter(|_| step < end) {
            let stop = progress.stop_after == Some(step);
            if stop || step % progress.every.max(1) == 0 {
                so_far.train_seconds += self.clock.elapsed().as_secs_f64();
                save_progress(progress.path, trainer, so_far)?;
                if stop {
                    return Err(HostError::Stopped {
                        progress: progress.path.to_path_buf(),
                        step,
                    });
                }
                self.clock = Instant::now();
            }
        }
        Ok(crate::pipeline::Flow::Continue)
    }
}

/// Write the trainer's state and `figures` to the progress checkpoint `path` (atomically).
fn save_progress(
    path: &std::path::Path,
    trainer: &Trainer<'_>,
    figures: &FiguresSoFar,
) -> Result<()> {
    let bytes = postcard::to_allocvec(figures)
        .map_err(|e| HostError::invalid(path, format!("encoding the run's figures failed: {e}")))?;
    train::save_checkpoint(path, trainer, &[(FIGURES_SECTION, &bytes)])
}

/// Restore the progress checkpoint `path` into `trainer` (built from `config` with the run's
/// frames loaded) and return the figures it carries. Refuses the state of another run.
fn resume(
    path: &std::path::Path,
    config: &Config,
    trainer: &mut Trainer<'_>,
) -> Result<FiguresSoFar> {
    if crate::pipeline::checkpoint_config(path)? != *config {
        return Err(HostError::invalid(
            path,
            "holds the state of a run with another config: remove it to start this run over",
        ));
    }
    let kept = train::restore_checkpoint(path, trainer, &[FIGURES_SECTION])?;
    let figures = kept
        .first()
        .ok_or_else(|| HostError::field(path, FIGURES_SECTION, "missing section"))?;
    postcard::from_bytes(&figures.bytes)
        .map_err(|e| HostError::field(path, FIGURES_SECTION, format!("cannot decode: {e}")))
}
