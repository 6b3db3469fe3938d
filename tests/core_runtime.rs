//! The core's runtime guarantees, end to end: memory budgets, no allocation in a step,
//! determinism across runs and thread counts, skipped non-finite steps, rejected bad input,
//! and checkpoints.

mod common;

use common::root;
use orbit_nerf_core::config::PART_ALIGN;
use orbit_nerf_core::glam::{Mat3, Vec3};
use orbit_nerf_core::{
    Camera, Config, Error, Ingested, MemoryPlan, Pose, Replacement, Sequential, Trainer,
};
use orbit_nerf_host::dataset::{self, Dataset};
use orbit_nerf_host::sweep::results::fnv1a;
use orbit_nerf_host::train::{self, RayonExecutor};
use orbit_nerf_host::{formats, report};
use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::path::Path;
use std::sync::OnceLock;
use std::sync::atomic::{AtomicUsize, Ordering};

/// Counts allocations made by threads that armed it, so other tests running in parallel do
/// not interfere.
struct CountingAllocator;

static ALLOCATIONS: AtomicUsize = AtomicUsize::new(0);
thread_local! {
    static ARMED: Cell<bool> = const { Cell::new(false) };
}

unsafe impl GlobalAlloc for CountingAllocator {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        if ARMED.try_with(|a| a.get()).unwrap_or(false) {
            ALLOCATIONS.fetch_add(1, Ordering::SeqCst);
        }
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        if ARMED.try_with(|a| a.get()).unwrap_or(false) {
            ALLOCATIONS.fetch_add(1, Ordering::SeqCst);
        }
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: CountingAllocator = CountingAllocator;

const LEGO: &str = "../shared/data/nerf_synthetic/lego";

/// Lego at 40 px, loaded once; `None` (and a message) when the shared data is absent.
fn lego() -> Option<&'static Dataset> {
    static DATA: OnceLock<Option<Dataset>> = OnceLock::new();
    DATA.get_or_init(|| {
        let path = root().join(LEGO);
        if !path.exists() {
            eprintln!("skipping: {} not found", path.display());
            return None;
        }
        Some(formats::open(&path, Some(40), [1.0; 3]).expect("lego loads"))
    })
    .as_ref()
}

fn tiny_config() -> Config {
    train::read_config(&root().join("budgets/tiny.toml"), &Config::DEFAULT)
        .expect("tiny budget parses")
}

/// Train `steps` steps of the tiny profile on lego with `threads` workers and return the
/// checkpoint bytes.
fn checkpoint_after(steps: u32, threads: usize, seed: u64) -> Option<Vec<u8>> {
    let mut config = tiny_config();
    config.steps = steps;
    config.warmup_steps = 32.min(steps);
    config.seed = seed;
    checkpoint_of_config(config, threads)
}

/// Train `config.steps` steps of `config` on 32 lego views and return the checkpoint bytes.
fn checkpoint_of_config(config: Config, threads: usize) -> Option<Vec<u8>> {
    let data = lego()?;
    let steps = config.steps;
    let plan = MemoryPlan::new(&config);
    let mut arena = vec![0u8; plan.total];
    let mut trainer = Trainer::new(config, &mut arena).unwrap();
    let (train_idx, _) = dataset::split_every(data.frames.len(), 8);
    train::load_frames(
        &mut trainer,
        train_idx.iter().take(32).map(|&i| &data.frames[i]),
    )
    .unwrap();
    let executor = RayonExecutor::new(threads).unwrap();
    for _ in 0..steps {
        trainer.step(&executor).unwrap();
    }
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("run.onrf");
    train::save_checkpoint(&path, &trainer, &[]).unwrap();
    Some(std::fs::read(path).unwrap())
}

#[test]
fn same_seed_gives_identical_checkpoints_and_threads_do_not_matter() {
    let Some(a) = checkpoint_after(200, 2, 7) else {
        return;
    };
    let b = checkpoint_after(200, 2, 7).unwrap();
    assert!(a == b, "two runs with the same seed differ");
    let one_thread = checkpoint_after(200, 1, 7).unwrap();
    assert!(a == one_thread, "1 thread and 2 threads differ");
    let other_seed = checkpoint_after(200, 2, 8).unwrap();
    assert!(a != other_seed, "the seed has no effect");
}

/// The MLP kernels at sixteen lanes per instruction (AVX-512, where the CPU has it) give the
/// checkpoint bytes of the eight-lane ones: every output sums its terms in the same order.
/// On a CPU without AVX-512 there is nothing to compare (`lego_checkpoint_bytes_equal_the_recorded_ones`
/// then checks the eight-lane kernels against the records).
#[test]
fn the_avx512_kernels_give_the_bytes_of_the_eight_lane_ones() {
    if !orbit_nerf_core::wide_vectors() {
        println!("no AVX-512 on this CPU: nothing to compare");
        return;
    }
    let Some(wide) = checkpoint_after(200, 2, 7) else {
        return;
    };
    orbit_nerf_core::allow_wide_vectors(false);
    let narrow = checkpoint_after(200, 2, 7);
    orbit_nerf_core::allow_wide_vectors(true);
    assert!(Some(wide) == narrow, "AVX-512 and AVX2 kernels differ");
}

/// Refactors and ports must not change a single bit of what training computes: the checkpoint
/// bytes after a fixed run equal the ones recorded when this test was written. Two runs: the
/// tiny profile (stochastic rounding, no embeddings), and the same with every method path on
/// (f32 master copy, appearance embeddings, pose correction about the target, random
/// backgrounds, foreground sampling). Re-recorded for checkpoint format 3 (issue 13): only the
/// header's version changed (with the version set back to 2 the old hashes still matched, as
/// lego's box has length unit 1). Re-recorded for format 4 (issue 14): with the version set
/// back to 3 and the config's two new fields (`plane_tv_weight`, `coarse_to_fine_steps`, both
/// 0) cut out, the bytes hash to the format-3 records (0xe701_c3ed_4afd_6a3a and
/// 0x285f_41bd_5683_c514). Re-recorded for the colour layer's per-ray term (issue 16): its
/// sums run in a new order (format unchanged; lego's quality unchanged, README). Re-recorded
/// for the training passes that keep their activations (issue 16): a chunk now trains every
/// ray in passes of `samples_per_chunk` samples (none dropped), and the backward pass runs
/// the density MLP over every marched sample's mini-batch, so its sums run in a new order.
/// Re-recorded for the backward pass over mini-batches of kept samples (issue 16): the
/// density MLP's rows are compacted to the samples the early stop keeps, and each mini-batch
/// runs the colour, density and plane parts in turn, so the pose gradients' sums run in a new
/// order (the plain run cuts no sample in its 60 steps and keeps its bytes). Re-recorded for
/// format 5 (issue 39): the config gained the pose prior and refinement fields and the
/// training state the pose corrections' own update count (the plain run, without pose
/// correction, takes none of the new paths); the method run's poses now learn on their own
/// schedule and update count, under the gauge, so its bytes move. Re-recorded for format 6
/// (issue 43): the config gained `ray_store`, `loss_weighted_frames` and `lr_decay_start`,
/// the training state the ray reservoir's counts and each frame slot's metadata its running
/// loss; with the version set back to 5, the three config fields (a zero byte each, four for
/// `lr_decay_start`) cut from the config, the state cut back to its first 20 bytes and each
/// slot's metadata to its first 104, both runs' bytes hash to the format-5 records
/// (0x4ae3_dabb_0a99_713c and 0xa041_a93c_cf94_0ead): whole-frame training moved no bit.
/// Re-recorded for format 7 (issue 43: a stream checkpoint's section gained the settle): with
/// the version set back to 6 both runs hash to the format-6 records (0xab35_5504_7826_b388
/// and 0xb6fc_1748_fa61_44e2). Re-recorded for format 8 (issue 43: the stream section says
/// whether the settle plans the learning rate anew): with the version set back to 7 both runs
/// hash to the format-7 records (0x6b78_9bda_e338_5c21 and 0xddf4_7763_831b_ef97).
/// Re-recorded for format 9 (issue 43: reservoir runs in each slot's metadata): against the
/// format-8 build, every section of both runs has the same bytes, the metadata once each
/// slot's is cut back to its first 108 (the new 32 bytes of runs are zero for whole frames):
/// whole-frame training moved no bit.
#[test]
fn lego_checkpoint_bytes_equal_the_recorded_ones() {
    let mut plain = tiny_config();
    plain.steps = 60;
    plain.warmup_steps = 16;
    let mut method = plain;
    method.texel_update = orbit_nerf_core::TexelUpdate::MasterCopy;
    method.embedding_dim = 4;
    method.pose_correction = true;
    method.pose_pivot = orbit_nerf_core::PosePivot::TargetOrigin;
    method.pose_warmup_steps = 20;
    method.random_background = true;
    method.foreground_fraction = 0.5;
    for (name, config, recorded) in [
        ("tiny", plain, 0xf4cc_1bd6_e5ac_f261),
        ("tiny + method", method, 0x8355_3d79_4582_a4fc),
    ] {
        let Some(bytes) = checkpoint_of_config(config, 2) else {
            return;
        };
        let hash = fnv1a(&bytes);
        println!("{name}: {} bytes, fnv1a {hash:#018x}", bytes.len());
        assert_eq!(
            hash, recorded,
            "{name}: checkpoint bytes changed ({hash:#018x})"
        );
    }
}

/// Timing a run (the host's clock lent to the core's stage timers) changes no bit of it: the
/// checkpoint and a fitted, rendered held-out view equal those of the same run untimed. Every
/// stage of a step gets some time, and the stages' wall times add up to no more than the time
/// measured around the steps (the timers nest inside it; 1 ms of slack for clock reads).
#[cfg(feature = "profile")]
#[test]
fn profiling_changes_no_bit_and_times_every_stage() {
    use orbit_nerf_core::profile::{Profile, Stage};
    use orbit_nerf_host::profile::clock_ns;
    let Some(data) = lego() else { return };
    let mut config = tiny_config();
    config.steps = 40;
    config.warmup_steps = 16;
    config.occupancy_every = 8;
    config.embedding_dim = 4;
    config.pose_correction = true;
    config.pose_warmup_steps = 10;
    let (train_idx, test_idx) = dataset::split_every(data.frames.len(), 8);
    let run = |timed: bool| -> (Vec<u8>, Vec<f32>, Profile, u64, u64) {
        let plan = MemoryPlan::new(&config);
        let mut arena = vec![0u8; plan.total];
        let mut trainer = Trainer::new(config, &mut arena).unwrap();
        train::load_frames(
            &mut trainer,
            train_idx.iter().take(16).map(|&i| &data.frames[i]),
        )
        .unwrap();
        if timed {
            trainer.set_clock(Some(clock_ns));
        }
        let executor = RayonExecutor::new(2).unwrap();
        let start = std::time::Instant::now();
        for _ in 0..config.steps {
            trainer.step(&executor).unwrap();
        }
        let steps_ns = start.elapsed().as_nanos() as u64;
        let frame = &data.frames[test_idx[0]];
        let mut mean = vec![0.0f32; 4];
        trainer.mean_embedding(&mut mean);
        let mut image = vec![0.0f32; frame.camera.pixel_count() * 3];
        let start = std::time::Instant::now();
        let (embedding, pose) =
            train::fit_held_out(&mut trainer, &executor, frame, 5, true, &mean).unwrap();
        trainer
            .render(&executor, &frame.camera, &pose, &embedding, &mut image)
            .unwrap();
        let view_ns = start.elapsed().as_nanos() as u64;
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("run.onrf");
        train::save_checkpoint(&path, &trainer, &[]).unwrap();
        let bytes = std::fs::read(path).unwrap();
        (bytes, image, trainer.profile(), steps_ns, view_ns)
    };
    let (plain, plain_image, untimed, _, _) = run(false);
    let (timed, timed_image, profile, steps_ns, view_ns) = run(true);
    assert!(plain == timed, "timing the steps changed the checkpoint");
    assert!(
        plain_image
            .iter()
            .zip(&timed_image)
            .all(|(a, b)| a.to_bits() == b.to_bits()),
        "timing changed the rendered view"
    );
    assert_eq!(
        untimed,
        Profile::default(),
        "without a clock nothing is timed"
    );
    let slack = 1_000_000;
    for stage in &Stage::ALL[..Stage::ALL.len() - 1] {
        assert!(
            profile.train_wall.get(*stage) > 0,
            "{}: no wall time",
            stage.name()
        );
        assert!(
            profile.train_cpu.get(*stage) > 0,
            "{}: no CPU time",
            stage.name()
        );
    }
    assert_eq!(profile.train_wall.get(Stage::FitEmbedding), 0);
    assert!(
        profile.train_wall.total() <= steps_ns + slack,
        "stages {} ns > steps {steps_ns} ns",
        profile.train_wall.total()
    );
    for stage in [
        Stage::FitEmbedding,
        Stage::Marching,
        Stage::DensityForward,
        Stage::ColourForward,
        Stage::Compositing,
    ] {
        assert!(
            profile.render_wall.get(stage) > 0,
            "view, {}: no time",
            stage.name()
        );
    }
    assert!(
        profile.render_wall.total() <= view_ns + slack,
        "view stages {} ns > view {view_ns} ns",
        profile.render_wall.total()
    );
}

/// The `[bytes]` table and the cap of a budget file.
fn budget(name: &str) -> (Config, toml::Table, usize) {
    let path = root().join("budgets").join(name);
    let config = train::read_config(&path, &Config::DEFAULT).unwrap();
    let table: toml::Table = toml::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
    let bytes = table["bytes"].as_table().unwrap().clone();
    let cap = table["max_total_bytes"].as_integer().unwrap() as usize;
    (config, bytes, cap)
}

fn plan_parts(plan: &MemoryPlan) -> [(&'static str, usize); 10] {
    [
        ("planes", plan.planes),
        ("plane_master", plan.plane_master),
        ("plane_moments", plan.plane_moments),
        ("plane_grads", plan.plane_grads),
        ("mlp", plan.mlp),
        ("occupancy", plan.occupancy),
        ("frames", plan.frames),
        ("ray_batch", plan.ray_batch),
        ("samples", plan.samples),
        ("total", plan.total),
    ]
}

#[test]
fn memory_plans_match_the_recorded_budgets_and_the_arena_use() {
    // The render profile is a render-only arena (the firmware's).
    for (name, cap_expected, render_only) in [
        ("standard.toml", 64 << 20, false),
        ("tiny.toml", 8 << 20, false),
        ("render.toml", 256 << 10, true),
    ] {
        let (config, recorded, cap) = budget(name);
        assert_eq!(cap, cap_expected, "{name}: cap");
        let plan = if render_only {
            MemoryPlan::render_only(&config)
        } else {
            MemoryPlan::new(&config)
        };
        assert!(
            plan.total <= cap,
            "{name}: plan {} bytes exceeds the cap {cap}",
            plan.total
        );
        let mismatches: Vec<String> = plan_parts(&plan)
            .iter()
            .filter(|(part, bytes)| {
                recorded.get(*part).and_then(|v| v.as_integer()) != Some(*bytes as i64)
            })
            .map(|(part, bytes)| format!("{part} = {bytes}"))
            .collect();
        assert!(
            mismatches.is_empty(),
            "{name}: the plan differs from the recorded [bytes]; now:\n{}",
            mismatches.join("\n")
        );
        // The bytes the core takes from the arena equal the plan, part by part.
        let mut arena = vec![0u8; plan.total];
        let trainer = if render_only {
            Trainer::new_render_only(config, &mut arena).unwrap()
        } else {
            Trainer::new(config, &mut arena).unwrap()
        };
        let used = trainer.memory_used();
        assert_eq!(
            MemoryPlan {
                total: plan.total,
                ..used
            },
            plan,
            "{name}: parts used differ from the plan"
        );
        assert_eq!(
            used.total + PART_ALIGN,
            plan.total,
            "{name}: total used differs from the plan"
        );
    }
}

// The firmware's config and view; its pack reader and fingerprint run in scripts/onboard.sh.
#[allow(dead_code)]
#[path = "../firmware/src/pack.rs"]
mod firmware_pack;

/// A render-only trainer renders the bytes a full trainer renders from the same sections, and
/// refuses to train; the firmware's config is the render profile.
#[test]
fn render_only_trainer_renders_what_the_trainer_renders() {
    let (config, _, _) = budget("render.toml");
    assert_eq!(firmware_pack::CONFIG, config, "firmware/src/pack.rs CONFIG");
    let mut full_arena = vec![0u8; MemoryPlan::new(&config).total];
    let mut full = Trainer::new(config, &mut full_arena).unwrap();
    let mut arena = vec![0u8; MemoryPlan::render_only(&config).total];
    let mut renderer = Trainer::new_render_only(config, &mut arena).unwrap();
    for name in firmware_pack::SECTIONS {
        let (_, bytes) = full
            .sections()
            .into_iter()
            .find(|(n, _)| *n == name)
            .unwrap();
        let bytes = bytes.to_vec();
        renderer.restore_section(name, &bytes).unwrap();
    }
    let camera = firmware_pack::CAMERA;
    let mut from_full = vec![0.0f32; camera.pixel_count() * 3];
    let mut from_render_only = vec![1.0f32; camera.pixel_count() * 3];
    let pose = firmware_pack::pose();
    full.render(&Sequential, &camera, &pose, &[], &mut from_full)
        .unwrap();
    renderer
        .render(&Sequential, &camera, &pose, &[], &mut from_render_only)
        .unwrap();
    assert!(
        from_full.iter().any(|&v| v != 1.0),
        "the render is all background"
    );
    assert_eq!(
        bytemuck::cast_slice::<f32, u8>(&from_full),
        bytemuck::cast_slice::<f32, u8>(&from_render_only)
    );
    assert_eq!(renderer.step(&Sequential).unwrap_err(), Error::RenderOnly);
    let pixels = vec![0u8; 3];
    let one_pixel = Camera {
        width: 1,
        height: 1,
        ..camera
    };
    assert_eq!(
        renderer.set_frame(0, one_pixel, pose, &pixels, None),
        Err(Error::RenderOnly)
    );
    assert_eq!(
        renderer.restore_section("plane_m", &[0u8; 4]).unwrap_err(),
        Error::BadSection {
            name: "plane_m",
            expected: 0,
            got: 4
        }
    );
}

#[test]
fn arena_size_and_alignment_are_handled() {
    let config = tiny_config();
    let plan = MemoryPlan::new(&config);
    let mut small = vec![0u8; plan.total - 1];
    match Trainer::new(config, &mut small) {
        Err(Error::ArenaTooSmall { needed, got }) => {
            assert_eq!((needed, got), (plan.total, plan.total - 1))
        }
        other => panic!("expected ArenaTooSmall, got {:?}", other.err()),
    }
    // An arena starting at an odd address still works: the plan includes alignment slack.
    let mut big = vec![0u8; plan.total + 1];
    assert!(Trainer::new(config, &mut big[1..]).is_ok());
}

#[test]
fn bad_configs_name_the_field() {
    let base = tiny_config();
    type Breakage = (&'static str, fn(&mut Config));
    let cases: [Breakage; 16] = [
        ("scales", |c| c.scales = 0),
        ("resolutions", |c| c.resolutions[1] = 1),
        ("features", |c| c.features = 12),
        ("sh_bands", |c| c.sh_bands = 5),
        ("aabb", |c| c.aabb_max[0] = f32::NAN),
        ("rays_per_batch", |c| c.rays_per_batch = 1023),
        ("chunks", |c| c.chunks = 0),
        ("learning_rate", |c| c.learning_rate = f32::INFINITY),
        ("pose_lr_factor", |c| c.pose_lr_factor = 0.5),
        ("plane_tv_weight", |c| c.plane_tv_weight = f32::NAN),
        ("coarse_to_fine_steps", |c| {
            c.coarse_to_fine_steps = c.steps + 1
        }),
        ("max_samples_per_ray", |c| c.max_samples_per_ray = u16::MAX),
        ("pose_prior_rotation_deg", |c| {
            c.pose_prior_rotation_deg = -1.0
        }),
        ("pose_prior_position", |c| {
            c.pose_prior_position = f32::INFINITY
        }),
        ("pose_refine_iterations", |c| {
            c.pose_refine_iterations = 1000
        }),
        ("pose_refine_rays", |c| c.pose_refine_rays = 0),
    ];
    for (field, break_it) in cases {
        let mut config = base;
        break_it(&mut config);
        assert_eq!(config.validate(), Err(Error::InvalidConfig { field }));
        let mut arena = vec![0u8; 64];
        assert_eq!(
            Trainer::new(config, &mut arena).err(),
            Some(Error::InvalidConfig { field })
        );
    }
}

fn camera(size: u16) -> Camera {
    Camera {
        width: size,
        height: size,
        fx: 50.0,
        fy: 50.0,
        cx: size as f32 / 2.0,
        cy: size as f32 / 2.0,
    }
}

fn looking_at_origin() -> Pose {
    // Camera on -z looking along +z (OpenCV axes: x right, y down).
    Pose {
        rotation: Mat3::IDENTITY,
        center: Vec3::new(0.0, 0.0, -4.0),
    }
}

#[test]
fn bad_frames_are_rejected_and_leave_the_slot_unchanged() {
    let config = tiny_config();
    let plan = MemoryPlan::new(&config);
    let mut arena = vec![0u8; plan.total];
    let mut trainer = Trainer::new(config, &mut arena).unwrap();
    let pixels = vec![128u8; 16 * 16 * 3];
    let pose = looking_at_origin();
    let mut skewed = pose;
    skewed.rotation.x_axis.x = 1.5;
    let mut nan_pose = pose;
    nan_pose.center.y = f32::NAN;
    let zero_focal = Camera {
        fx: 0.0,
        ..camera(16)
    };
    let cases: Vec<(Error, Result<(), Error>)> = vec![
        (
            Error::InvalidFrame { field: "pixels" },
            trainer.set_frame(0, camera(16), pose, &pixels[1..], None),
        ),
        (
            Error::InvalidFrame { field: "mask" },
            trainer.set_frame(0, camera(16), pose, &pixels, Some(&[255; 3])),
        ),
        (
            Error::InvalidFrame { field: "camera" },
            trainer.set_frame(0, zero_focal, pose, &pixels, None),
        ),
        (
            Error::InvalidFrame {
                field: "pose.rotation",
            },
            trainer.set_frame(0, camera(16), skewed, &pixels, None),
        ),
        (
            Error::InvalidFrame { field: "pose" },
            trainer.set_frame(0, camera(16), nan_pose, &pixels, None),
        ),
        (
            Error::InvalidFrame { field: "slot" },
            trainer.set_frame(32, camera(16), pose, &pixels, None),
        ),
        (
            Error::FrameTooLarge {
                pixels: 128 * 128,
                capacity: 4096,
            },
            trainer.set_frame(0, camera(128), pose, &vec![0; 128 * 128 * 3], None),
        ),
    ];
    for (want, got) in cases {
        assert_eq!(got, Err(want));
    }
    assert!(trainer.frames().is_empty());
    // With no frames a step is an error, not a panic.
    assert_eq!(trainer.step(&Sequential).err(), Some(Error::NoFrames));
    // Empty (all-black) and saturated frames are valid input and train without trouble.
    trainer
        .set_frame(0, camera(16), pose, &[0; 16 * 16 * 3], None)
        .unwrap();
    trainer
        .set_frame(1, camera(16), pose, &[255; 16 * 16 * 3], Some(&[255; 256]))
        .unwrap();
    for _ in 0..20 {
        assert!(!trainer.step(&Sequential).unwrap().skipped);
    }
    // A cleared slot is no longer sampled; clearing an empty or missing slot is a no-op.
    trainer.clear_frame(0);
    trainer.clear_frame(31);
    trainer.clear_frame(1000);
    assert_eq!(trainer.frames().len(), 1);
    assert_eq!(trainer.frames().occupied_slot(0), Some(1));
    assert!(trainer.frames().pixels(0).is_none());
    assert!(!trainer.step(&Sequential).unwrap().skipped);
}

#[test]
fn a_step_with_non_finite_values_is_skipped_and_counted() {
    let config = tiny_config();
    let plan = MemoryPlan::new(&config);
    let mut arena = vec![0u8; plan.total];
    let mut trainer = Trainer::new(config, &mut arena).unwrap();
    trainer
        .set_frame(
            0,
            camera(16),
            looking_at_origin(),
            &[200; 16 * 16 * 3],
            None,
        )
        .unwrap();
    trainer.step(&Sequential).unwrap();
    // Finite but extreme colour weights (a checkpoint refuses NaN and infinities): the second
    // hidden layer's weights of f32::MAX overflow its activations to +inf, and the output
    // layer's alternating +-1e30 weights then give +inf and -inf terms, whose sum is NaN.
    // Every colour becomes NaN. (Overflowing products of finite values would not do: a fused
    // multiply-add adds the exact product, so inf + (-1e59) stays inf.)
    let mut mlp: Vec<f32> = trainer.mlp_parameters().to_vec();
    let layers = config.mlp().layers;
    let hidden = layers[orbit_nerf_core::config::COLOUR_HIDDEN2];
    let out_layer = layers[orbit_nerf_core::config::COLOUR_OUT];
    mlp[hidden.weights..hidden.biases].fill(f32::MAX);
    for (i, w) in mlp[out_layer.weights..out_layer.biases]
        .iter_mut()
        .enumerate()
    {
        *w = if i % 2 == 0 { 1e30 } else { -1e30 };
    }
    trainer
        .restore_section("mlp", bytemuck::cast_slice(&mlp))
        .unwrap();
    let planes_before = trainer.planes().to_vec();
    let report = trainer.step(&Sequential).unwrap();
    assert!(report.skipped);
    assert_eq!(trainer.state().skipped, 1);
    assert_eq!(trainer.state().updates, 1);
    assert!(
        trainer.planes() == planes_before.as_slice(),
        "a skipped step changed the planes"
    );
    assert!(
        trainer.mlp_parameters() == mlp.as_slice(),
        "a skipped step changed the MLP"
    );
}

#[test]
fn a_training_step_allocates_nothing() {
    let Some(data) = lego() else { return };
    let mut config = tiny_config();
    config.occupancy_every = 4;
    let plan = MemoryPlan::new(&config);
    let mut arena = vec![0u8; plan.total];
    let mut trainer = Trainer::new(config, &mut arena).unwrap();
    train::load_frames(&mut trainer, data.frames.iter().take(8)).unwrap();
    let frame = &data.frames[0];
    let mut image = vec![0.0f32; frame.camera.pixel_count() * 3];
    ALLOCATIONS.store(0, Ordering::SeqCst);
    ARMED.with(|a| a.set(true));
    for _ in 0..10 {
        trainer.step(&Sequential).unwrap();
    }
    trainer
        .render(&Sequential, &frame.camera, &frame.pose, &[], &mut image)
        .unwrap();
    let points = [[0.1f32, -0.2, 0.3]; 100];
    let mut sigma = [0.0f32; 100];
    trainer
        .density_at(&Sequential, &points, &mut sigma)
        .unwrap();
    let mut colours = [0.0f32; 300];
    let directions = [[0.0f32, 0.0, -1.0]; 100];
    trainer
        .render_rays(&Sequential, &points, &directions, &[], &mut colours)
        .unwrap();
    ARMED.with(|a| a.set(false));
    assert_eq!(
        ALLOCATIONS.load(Ordering::SeqCst),
        0,
        "the core allocated during steps, rendering or point queries"
    );
    assert!(
        trainer.state().refreshes >= 2,
        "the occupancy refresh ran inside the armed window"
    );
}

#[test]
fn streaming_frames_through_a_full_store_allocates_nothing() {
    // Whole frames under each policy, and a ray reservoir (a full table of remembered frames
    // under FIFO, so frames take over their predecessors' entries).
    for (replacement, ray_store) in [
        (Replacement::Fifo, 0),
        (Replacement::Novelty, 0),
        (Replacement::Coverage, 0),
        (Replacement::Fifo, 3000),
    ] {
        let mut config = tiny_config();
        config.max_frames = 4;
        config.replacement = replacement;
        config.ray_store = ray_store;
        config.foreground_fraction = 0.5;
        let plan = MemoryPlan::new(&config);
        let mut arena = vec![0u8; plan.total];
        let mut trainer = Trainer::new(config, &mut arena).unwrap();
        let pixels: Vec<u8> = (0..16 * 16 * 3).map(|i| (i % 251) as u8).collect();
        let poses: Vec<Pose> = (0..24)
            .map(|k| {
                let rotation = Mat3::from_rotation_y(k as f32 * 0.3);
                Pose {
                    rotation,
                    center: rotation * Vec3::new(0.0, 0.0, -4.0),
                }
            })
            .collect();
        ALLOCATIONS.store(0, Ordering::SeqCst);
        ARMED.with(|a| a.set(true));
        let mut stored = 0;
        for (arrival, pose) in poses.iter().enumerate() {
            let ingested = trainer.ingest_frame(arrival as u32, camera(16), *pose, &pixels, None);
            stored += matches!(ingested, Ok(Ingested::Stored { .. })) as usize;
            trainer.step(&Sequential).unwrap();
        }
        ARMED.with(|a| a.set(false));
        assert_eq!(
            ALLOCATIONS.load(Ordering::SeqCst),
            0,
            "{replacement:?}: ingesting frames allocated"
        );
        assert!(stored >= 4, "{replacement:?}: {stored} frames stored");
        assert_eq!(trainer.frames().len(), 4);
        assert_eq!(trainer.frames().keeps_rays(), ray_store > 0);
        // Each of the 4 frames held keeps all 256 of its pixels in each part (its share, 375
        // places, is more than a 16 x 16 frame holds).
        assert_eq!(
            trainer.state().rays.filled,
            [1024, 1024].map(|n| n * (ray_store > 0) as u32)
        );
    }
}

#[test]
fn training_reduces_the_loss_and_renders_the_held_out_views() {
    let Some(data) = lego() else { return };
    let mut config = tiny_config();
    config.steps = 300;
    let config = train::fit_config(&config, data, 32);
    let plan = MemoryPlan::new(&config);
    let mut arena = vec![0u8; plan.total];
    let mut trainer = Trainer::new(config, &mut arena).unwrap();
    let (train_idx, test_idx) = dataset::split_every(data.frames.len(), 8);
    train::load_frames(
        &mut trainer,
        train_idx.iter().take(32).map(|&i| &data.frames[i]),
    )
    .unwrap();
    let executor = RayonExecutor::new(2).unwrap();
    let score = |trainer: &mut Trainer<'_>| {
        train::evaluate(trainer, &executor, data, &test_idx[..3], 0, false, None).unwrap()
    };
    let first = trainer.step(&executor).unwrap().mse;
    let before = score(&mut trainer);
    let mut last = first;
    for _ in 1..300 {
        last = trainer.step(&executor).unwrap().mse;
    }
    let after = score(&mut trainer);
    assert!(last < first * 0.2, "loss {first} -> {last}");
    for (b, a) in before.iter().zip(&after) {
        assert!(
            a.metrics.psnr_full > b.metrics.psnr_full + 5.0 && a.metrics.psnr_full > 20.0,
            "view {}: {:.2} -> {:.2} dB",
            a.index,
            b.metrics.psnr_full,
            a.metrics.psnr_full
        );
    }
    assert!(
        trainer.occupancy_fraction() < 0.5,
        "occupancy did not prune empty space"
    );
    // `--align-poses`: a held-out view whose label is turned by 2 degrees gets back to
    // within half of that by fitting its pose correction on its left half.
    let mut frame = data.frames[test_idx[0]].clone();
    let exact = frame.pose;
    frame.pose.rotation =
        Mat3::from_axis_angle(Vec3::new(0.6, 0.8, 0.0), 2f32.to_radians()) * frame.pose.rotation;
    let mut mean = vec![0.0f32; config.embedding_dim as usize];
    trainer.mean_embedding(&mut mean);
    let (_, aligned) =
        train::fit_held_out(&mut trainer, &executor, &frame, 100, true, &mean).unwrap();
    let (_, unaligned) =
        train::fit_held_out(&mut trainer, &executor, &frame, 100, false, &mean).unwrap();
    let error = |pose: &orbit_nerf_core::Pose| report::rotation_error_deg(pose, &exact);
    assert_eq!(unaligned, frame.pose);
    assert!(
        error(&aligned) < 1.0,
        "2 degrees -> {} after alignment",
        error(&aligned)
    );
}

#[test]
fn checkpoints_round_trip_and_reject_damage() {
    let Some(bytes) = checkpoint_after(20, 2, 3) else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("a.onrf");
    std::fs::write(&path, &bytes).unwrap();
    let checkpoint = orbit_nerf_host::checkpoint::load(&path).unwrap();
    let config = train::checkpoint_config(&path, &checkpoint).unwrap();
    let plan = MemoryPlan::new(&config);
    let mut arena = vec![0u8; plan.total];
    let mut trainer = Trainer::new(config, &mut arena).unwrap();
    train::restore_checkpoint(&path, &mut trainer, &[]).unwrap();
    let again = dir.path().join("b.onrf");
    train::save_checkpoint(&again, &trainer, &[]).unwrap();
    assert!(
        std::fs::read(&again).unwrap() == bytes,
        "restore + save changed the checkpoint"
    );
    assert_eq!(trainer.state().step, 20);

    // Truncated file: a clear error naming the file.
    let cut = dir.path().join("cut.onrf");
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
    let err = orbit_nerf_host::checkpoint::load(&cut)
        .unwrap_err()
        .to_string();
    assert!(err.contains("cut.onrf"), "{err}");

    // A checkpoint of another model is refused by the trainer of another config.
    let mut other = config;
    other.features = 16;
    let plan = MemoryPlan::new(&other);
    let mut arena = vec![0u8; plan.total];
    let mut wrong = Trainer::new(other, &mut arena).unwrap();
    let err = train::restore_checkpoint(&path, &mut wrong, &[])
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("a.onrf") && err.contains("another config"),
        "{err}"
    );
}

#[test]
fn bad_config_files_name_the_file_and_field() {
    let dir = tempfile::tempdir().unwrap();
    let text = std::fs::read_to_string(root().join("budgets/tiny.toml")).unwrap();
    let cases = [
        ("features = 8", "features = 12", "features"),
        ("chunks = 2", "chunks = 0", "chunks"),
        ("seed = 0", "seed = 0\nunknown_knob = 1", "unknown_knob"),
        ("march_steps = 256", "march_steps = \"many\"", "march_steps"),
    ];
    for (from, to, field) in cases {
        let path = dir.path().join("bad.toml");
        std::fs::write(&path, text.replace(from, to)).unwrap();
        let err = train::read_config(&path, &Config::DEFAULT)
            .unwrap_err()
            .to_string();
        assert!(err.contains("bad.toml") && err.contains(field), "{err}");
    }
    let missing = train::read_config(Path::new("/nonexistent/config.toml"), &Config::DEFAULT)
        .unwrap_err()
        .to_string();
    assert!(missing.contains("/nonexistent/config.toml"), "{missing}");
}
