//! Fuzzing of every loader on stable Rust: each loader's parsing entry is called on mutated
//! versions of valid seed files (bit flips, deletions, duplications, truncations, and numbers
//! replaced by hostile tokens such as `NaN`, `1e999` or `18446744073709551616`). Every input
//! must give a value or an error, never a panic. A panicking input is saved under
//! `target/fuzz-crashes/` and the test fails naming it (then it becomes a regression test).
//!
//! CI runs a smoke run (`FUZZ_SMOKE_INPUTS` inputs per loader). The long run:
//! `ORBIT_NERF_FUZZ_INPUTS=1000000 cargo test --test fuzz_loaders -- --nocapture` (figures in
//! the README, "Hard cases"). The test profile is optimised (`opt-level = 2`) and keeps
//! overflow checks and debug assertions, which turn silent wrap-arounds into found panics.

use orbit_nerf_core::glam::{Quat, Vec3};
use orbit_nerf_core::rng::Rng;
use orbit_nerf_core::{Config, MemoryPlan, Pose, Trainer};
use orbit_nerf_host::formats::speedplus::{
    self, FrameDecoder, Label, SpeedCamera, Truth, TruthFrame,
};
use orbit_nerf_host::formats::transforms::LoadOptions;
use orbit_nerf_host::formats::{nerf_synthetic, nerfstudio};
use orbit_nerf_host::sim::{self, Scene};
use orbit_nerf_host::{checkpoint, train};
use std::panic::{AssertUnwindSafe, catch_unwind};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// Inputs per loader in CI.
const FUZZ_SMOKE_INPUTS: u64 = 20_000;

fn inputs_per_loader() -> u64 {
    std::env::var("ORBIT_NERF_FUZZ_INPUTS")
        .ok()
        .and_then(|n| n.parse().ok())
        .unwrap_or(FUZZ_SMOKE_INPUTS)
}

/// Values that break parsers and the code after them.
const HOSTILE: [&str; 22] = [
    "NaN",
    "Infinity",
    "-Infinity",
    "nan",
    "inf",
    "1e999",
    "-1e999",
    "1e-320",
    "0",
    "-0",
    "-1",
    "18446744073709551616",
    "4294967296",
    "65536",
    "9e18",
    "null",
    "true",
    "\"\"",
    "[]",
    "{}",
    "[[[[[[[[",
    "\u{1F680}",
];

/// Seeded mutations of seed inputs.
struct Mutator(Rng);

impl Mutator {
    fn below(&mut self, n: usize) -> usize {
        (self.0.next_u64() % n.max(1) as u64) as usize
    }

    /// Replace `data` by a mutation of `seed` (the buffer is reused from input to input).
    fn mutate(&mut self, seed: &[u8], data: &mut Vec<u8>) {
        data.clear();
        data.extend_from_slice(seed);
        for _ in 0..1 + self.below(4) {
            let at = self.below(data.len() + 1);
            match self.below(7) {
                0 if !data.is_empty() => {
                    let i = at.min(data.len() - 1);
                    data[i] ^= 1 << self.below(8);
                }
                1 => {
                    let token = HOSTILE[self.below(HOSTILE.len())];
                    data.splice(at..at, token.bytes());
                }
                2 => {
                    let end = (at + 1 + self.below(16)).min(data.len());
                    data.drain(at.min(end)..end);
                }
                3 => {
                    let end = (at + 1 + self.below(64)).min(data.len());
                    let copy = data[at.min(end)..end].to_vec();
                    let to = self.below(data.len() + 1);
                    data.splice(to..to, copy);
                }
                4 => data.truncate(at),
                _ => {
                    // Replace the number nearest after `at` by a hostile token.
                    let start = data[at..]
                        .iter()
                        .position(|b| b.is_ascii_digit())
                        .map(|p| at + p);
                    if let Some(start) = start {
                        let end = data[start..]
                            .iter()
                            .position(|b| !(b.is_ascii_digit() || b"+-.eE".contains(b)))
                            .map_or(data.len(), |p| start + p);
                        let token = HOSTILE[self.below(HOSTILE.len())];
                        data.splice(start..end, token.bytes());
                    }
                }
            }
        }
    }
}

/// Call `load` on `inputs` mutations of `seeds` (the bytes of the file, parsed in memory as the
/// loader parses what it read: writing each input to disk cost 1.6 to 3.8 ms of file-system
/// work per input); returns the inputs that panicked (saved for reproduction) and prints the
/// loader's figures, with progress every 100 000 inputs for long runs.
fn fuzz(name: &str, seeds: &[Vec<u8>], load: &dyn Fn(&[u8]) -> bool) -> Vec<PathBuf> {
    for (i, seed) in seeds.iter().enumerate() {
        assert!(
            load(seed),
            "{name}: seed {i} does not load, so mutations test little"
        );
    }
    let inputs = inputs_per_loader();
    let mut mutator = Mutator(Rng::new(0x5eed ^ name.len() as u64));
    let crashes_dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("fuzz-crashes");
    let mut crashes = Vec::new();
    let mut accepted = 0u64;
    let mut slowest = Duration::ZERO;
    let mut input = Vec::new();
    let start = Instant::now();
    for index in 0..inputs {
        mutator.mutate(&seeds[index as usize % seeds.len()], &mut input);
        let started = Instant::now();
        match catch_unwind(AssertUnwindSafe(|| load(&input))) {
            Ok(ok) => accepted += u64::from(ok),
            Err(_) => {
                std::fs::create_dir_all(&crashes_dir).unwrap();
                let saved = crashes_dir.join(format!("{name}-{index}.bin"));
                std::fs::write(&saved, &input).unwrap();
                crashes.push(saved);
            }
        }
        slowest = slowest.max(started.elapsed());
        if (index + 1) % 100_000 == 0 && index + 1 < inputs {
            println!(
                "{name}: {} inputs in {:.1} s, {accepted} accepted, {} panics",
                index + 1,
                start.elapsed().as_secs_f64(),
                crashes.len()
            );
        }
    }
    println!(
        "{name}: {inputs} inputs in {:.1} s, {accepted} accepted, {} panics, slowest input {:.1} ms",
        start.elapsed().as_secs_f64(),
        crashes.len(),
        slowest.as_secs_f64() * 1e3
    );
    crashes
}

/// The input as text, as `read_to_string` would give it (`None`: not UTF-8, which the loader
/// refuses when it reads the file, before parsing).
fn text(bytes: &[u8]) -> Option<&str> {
    std::str::from_utf8(bytes).ok()
}

fn labels() -> Vec<Label> {
    (0..3)
        .map(|i| {
            let q = Quat::from_rotation_y(0.3 * i as f32);
            Label::new(format!("img{:06}.png", i + 1), q, Vec3::new(0.1, -0.2, 5.0))
        })
        .collect()
}

const CAMERA: &str = r#"{"Nu": 1920, "Nv": 1200, "ppx": 5.86E-6, "ppy": 5.86E-6,
 "fx": 0.017513075965995915, "fy": 0.017511673079277208, "ccx": 960, "ccy": 600,
 "cameraMatrix": [[2988.5795163815555, 0, 960], [0, 2988.3401159176124, 600], [0, 0, 1]],
 "distCoeffs": [-0.22383016606510672, 0.51409797089106379, -0.00066499611998340662,
  -0.00021404771667484594, -0.13124227429077406]}"#;

fn png(width: u32, height: u32) -> Vec<u8> {
    let image = image::RgbImage::from_fn(width, height, |x, y| {
        image::Rgb([x as u8 * 9, y as u8 * 13, (x ^ y) as u8])
    });
    let mut bytes = Vec::new();
    image
        .write_to(
            &mut std::io::Cursor::new(&mut bytes),
            image::ImageFormat::Png,
        )
        .unwrap();
    bytes
}

/// A checkpoint whose header's payload length (bytes 12..20) and CRC-32 (bytes 20..24) are
/// rewritten to match its payload, so a mutated payload
/// gets past the checksum and reaches the decoder and the restore.
fn resealed(bytes: &[u8]) -> Vec<u8> {
    let mut sealed = bytes.to_vec();
    if let Some(payload) = bytes.get(checkpoint::HEADER_LEN..) {
        sealed[12..20].copy_from_slice(&(payload.len() as u64).to_le_bytes());
        sealed[20..24].copy_from_slice(&crc32fast::hash(payload).to_le_bytes());
    }
    sealed
}

#[test]
fn every_loader_survives_mutated_inputs_without_panicking() {
    let dir = tempfile::tempdir().unwrap();
    let file = |name: &str| dir.path().join(name);
    let mut crashes = Vec::new();

    let labels_path = file("labels.json");
    speedplus::write_labels(&labels_path, &labels()).unwrap();
    let labels_seed = std::fs::read(&labels_path).unwrap();
    crashes.extend(fuzz("labels", &[labels_seed], &|bytes| {
        text(bytes).is_some_and(|text| speedplus::parse_labels(&labels_path, text).is_ok())
    }));
    let label_path = file("label.json");
    let label_seed = serde_json::to_vec(&labels()[0]).unwrap();
    crashes.extend(fuzz("label", &[label_seed], &|bytes| {
        text(bytes).is_some_and(|text| {
            speedplus::parse_label(&label_path, text).is_ok_and(|label| label.pose().is_some())
        })
    }));

    let camera_path = file("camera.json");
    crashes.extend(fuzz("camera", &[CAMERA.as_bytes().to_vec()], &|bytes| {
        text(bytes).is_some_and(|text| SpeedCamera::parse(&camera_path, text).is_ok())
    }));

    let truth = Truth {
        target_box_min: [-1.0, -1.0, -0.5],
        target_box_max: [1.0, 1.0, 0.5],
        frames: labels()
            .iter()
            .map(|label| TruthFrame {
                filename: label.filename.clone(),
                q_vbs2tango_true: label.q_vbs2tango,
                r_vo2to_vbs_true: label.r_vo2to_vbs,
                sun_direction_body: [0.0, 0.6, 0.8],
                exposure: 1.0,
            })
            .collect(),
    };
    let truth_path = file("truth.json");
    truth.write(&truth_path).unwrap();
    let truth_seed = std::fs::read(&truth_path).unwrap();
    crashes.extend(fuzz("truth", &[truth_seed], &|bytes| {
        text(bytes).is_some_and(|text| Truth::parse(&truth_path, text).is_ok())
    }));

    let landmarks_path = file("landmarks.csv");
    let landmarks_seed = b"x,y,z\n0.37,-0.38,0.16\n0.36,0.38,0.16\n-0.37,0.38,0.16\n".to_vec();
    crashes.extend(fuzz("landmarks", &[landmarks_seed], &|bytes| {
        text(bytes).is_some_and(|text| sim::parse_landmarks(&landmarks_path, text).is_ok())
    }));

    // Images, decoded for a 16 x 12 camera.
    let sensor = SpeedCamera::parse(&camera_path, CAMERA).unwrap();
    let mut camera = sim::output_camera(&sensor, 16, 16, false);
    camera.height = 12;
    let decoder = FrameDecoder::new(camera, Some(8));
    let pose = Pose::from_world_to_camera(Quat::IDENTITY, Vec3::new(0.0, 0.0, 5.0)).unwrap();
    let mut jpeg = Vec::new();
    image::DynamicImage::ImageRgb8(image::load_from_memory(&png(16, 12)).unwrap().to_rgb8())
        .write_to(
            &mut std::io::Cursor::new(&mut jpeg),
            image::ImageFormat::Jpeg,
        )
        .unwrap();
    let image_path = file("frame.png");
    crashes.extend(fuzz("image", &[png(16, 12), jpeg], &|bytes| {
        decoder
            .decode_bytes("frame".into(), pose, (&image_path, bytes), None)
            .is_ok()
    }));

    // NeRF-synthetic and nerfstudio transforms, next to valid images (read from disk).
    std::fs::create_dir_all(file("train")).unwrap();
    std::fs::write(file("train/r_0.png"), png(8, 8)).unwrap();
    std::fs::write(file("train/r_1.png"), png(8, 8)).unwrap();
    let matrix = |x: f32| format!("[[1, 0, 0, {x}], [0, 1, 0, 0.5], [0, 0, 1, 4.0], [0, 0, 0, 1]]");
    let synthetic_seed = format!(
        r#"{{"camera_angle_x": 0.69, "frames": [{{"file_path": "./train/r_0", "transform_matrix": {}}}, {{"file_path": "./train/r_1", "transform_matrix": {}}}]}}"#,
        matrix(0.0),
        matrix(0.3)
    );
    let options = LoadOptions::default();
    let synthetic_path = file("transforms_train.json");
    crashes.extend(fuzz(
        "transforms_train.json",
        &[synthetic_seed.into_bytes()],
        &|bytes| {
            text(bytes).is_some_and(|text| {
                nerf_synthetic::parse_nerf_synthetic_transforms(&synthetic_path, text, &options)
                    .is_ok()
            })
        },
    ));
    let nerfstudio_seed = format!(
        r#"{{"camera_model": "OPENCV", "aabb": [[-1, -1, -1], [1, 1, 1]], "fl_x": 10.0, "fl_y": 11.0, "cx": 4.0, "cy": 4.0, "w": 8, "h": 8, "k1": 0.01, "frames": [{{"file_path": "train/r_0.png", "transform_matrix": {}}}, {{"file_path": "train/r_1.png", "fl_x": 12.0, "transform_matrix": {}}}]}}"#,
        matrix(0.0),
        matrix(0.3)
    );
    let nerfstudio_path = file("transforms.json");
    crashes.extend(fuzz(
        "nerfstudio",
        &[nerfstudio_seed.into_bytes()],
        &|bytes| {
            text(bytes).is_some_and(|text| {
                nerfstudio::parse_nerfstudio(&nerfstudio_path, text, &options).is_ok()
            })
        },
    ));

    // A small model: the tiny profile with one scale and one frame slot.
    let mut small = train::read_config(
        &Path::new(env!("CARGO_MANIFEST_DIR")).join("budgets/tiny.toml"),
        &Config::DEFAULT,
    )
    .unwrap();
    small.scales = 1;
    small.resolutions = [16, 0, 0, 0];
    small.occupancy_res = 8;
    small.max_frames = 1;
    small.max_pixels_per_frame = 64;

    // Config TOML; a config that parses is also planned and, when small, built.
    let config_path = file("config.toml");
    let config_seed = train::config_to_toml(&small).unwrap().into_bytes();
    crashes.extend(fuzz("config", &[config_seed], &|bytes| {
        text(bytes).is_some_and(|text| {
            train::parse_config(&config_path, text, &Config::DEFAULT).is_ok_and(|config| {
                let plan = MemoryPlan::new(&config);
                plan.total > 64 << 20 || {
                    let mut arena = vec![0u8; plan.total];
                    Trainer::new(config, &mut arena).is_ok()
                }
            })
        })
    }));

    // Checkpoints of the small model; one that loads is restored into a trainer of its config.
    let small_plan = MemoryPlan::new(&small);
    let mut arena = vec![0u8; small_plan.total];
    let trainer = Trainer::new(small, &mut arena).unwrap();
    let checkpoint_path = file("run.onrf");
    train::save_checkpoint(&checkpoint_path, &trainer, &[]).unwrap();
    drop(trainer);
    let checkpoint_seed = std::fs::read(&checkpoint_path).unwrap();
    let restore = |bytes: &[u8]| {
        let p = checkpoint_path.as_path();
        let Ok(mut reader) = checkpoint::SectionReader::new(p, std::io::Cursor::new(bytes)) else {
            return false;
        };
        let Ok(config) = train::decode_config(p, &reader.kind, &reader.config) else {
            return false;
        };
        let plan = MemoryPlan::new(&config);
        if plan.total > 64 << 20 {
            return false;
        }
        let mut arena = vec![0u8; plan.total];
        let Ok(mut trainer) = Trainer::new(config, &mut arena) else {
            return false;
        };
        let every: Vec<&str> = trainer.sections().iter().map(|(name, _)| *name).collect();
        train::restore_from(&mut reader, &mut trainer, &[], &every).is_ok()
    };
    crashes.extend(fuzz(
        "checkpoint",
        std::slice::from_ref(&checkpoint_seed),
        &restore,
    ));
    // Most mutations above end at the checksum; these reach the payload's decoder.
    crashes.extend(fuzz("checkpoint-resealed", &[checkpoint_seed], &|bytes| {
        restore(&resealed(bytes))
    }));

    // Scene files (parsed and checked; building the target needs the reference data).
    let scene_seeds: Vec<Vec<u8>> = [
        include_str!("../scenes/synthetic.toml"),
        include_str!("../scenes/lightbox.toml"),
        include_str!("../scenes/sunlamp.toml"),
    ]
    .iter()
    .map(|text| text.as_bytes().to_vec())
    .collect();
    let scene_path = file("scene.toml");
    crashes.extend(fuzz("scene", &scene_seeds, &|bytes| {
        let text = String::from_utf8_lossy(bytes);
        Scene::parse(&text, scene_path.clone(), Vec::new()).is_ok()
    }));

    assert!(crashes.is_empty(), "inputs that panicked: {crashes:#?}");
}
