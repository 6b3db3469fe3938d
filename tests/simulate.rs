//! End-to-end tests of the scene simulator: datasets written by `sim::simulate` load back through
//! the SPEED+ loader, labels and geometry agree, disabled effects cost nothing, bad scene files
//! are rejected with one error naming the file and the field.
//!
//! They need the reference data in `../shared/data` (camera and landmarks); without it each
//! test says so and passes.

mod common;
// The CLI's `simulate` command, compiled into this test so its argument spelling is tested too.
#[path = "../src/commands/simulate.rs"]
mod simulate_command;

use clap::Parser;
use common::shared_data;
use orbit_nerf_core::glam::Vec3;
use orbit_nerf_host::HostError;
use orbit_nerf_host::formats::speedplus::{self, LoadOptions, SpeedPlusSet};
use orbit_nerf_host::sim::{self, Scene, SimulationReport, Stage};
use std::path::{Path, PathBuf};
use std::time::Duration;

/// A folder under the system temp dir, removed when dropped.
struct TempDir(PathBuf);

impl TempDir {
    fn new(name: &str) -> TempDir {
        TempDir(common::temp_dir(name))
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

fn preset(name: &str, frames: u32, size: u16) -> Scene {
    let mut scene = Scene::load(name).unwrap();
    scene.spec.frames = frames;
    scene.spec.set_longer_side(size);
    scene
}

fn simulate(scene: &Scene, out: &Path) -> SimulationReport {
    sim::simulate(scene, out, &|| {}).unwrap()
}

fn load(out: &Path) -> SpeedPlusSet {
    speedplus::load(out, &LoadOptions::default()).unwrap()
}

#[test]
fn sunlamp_100_frames_at_128px_writes_a_dataset_that_loads() {
    if shared_data().is_none() {
        return;
    }
    #[derive(clap::Parser)]
    struct Command {
        #[command(flatten)]
        args: simulate_command::SimulateArgs,
    }
    let dir = TempDir::new("sunlamp100");
    let out = dir.0.join("sunlamp");
    let sheet = dir.0.join("sheet.png");
    let command = Command::parse_from([
        "orbit-nerf-simulate",
        "--scene",
        "sunlamp",
        "--frames",
        "100",
        "--size",
        "128",
        "--timings",
        "--out",
        out.to_str().unwrap(),
        "--contact-sheet",
        sheet.to_str().unwrap(),
    ]);
    simulate_command::run(&command.args).unwrap();
    assert!(sheet.is_file());
    // The library call with the same settings gives the same dataset.
    let report = simulate(&preset("sunlamp", 100, 128), &dir.0.join("again"));
    for file in [
        "labels.json",
        "truth.json",
        "camera.json",
        "scene.toml",
        "images/img000100.png",
        "masks/img000001.png",
    ] {
        assert!(out.join(file).is_file(), "missing {file}");
    }
    let set = load(&out);
    let dataset = &set.dataset;
    assert_eq!(dataset.frames.len(), 100);
    assert_eq!(dataset.background, [0.0; 3]);
    let truth = set.truth.as_ref().expect("truth.json is loaded");
    assert_eq!(truth, &report.truth);
    for frame in &dataset.frames {
        assert_eq!((frame.camera.width, frame.camera.height), (128, 128));
        assert_eq!(frame.pixels.len(), 128 * 128 * 3);
        // Grayscale camera: expanded to r = g = b.
        assert!(
            frame
                .pixels
                .chunks_exact(3)
                .all(|p| p[0] == p[1] && p[1] == p[2])
        );
        let mask = frame.mask.as_ref().expect("masks are loaded");
        let covered = mask.iter().filter(|&&m| m == 255).count();
        assert!(
            covered > 20,
            "{}: target covers only {covered} pixels",
            frame.name
        );
    }
    // The target box holds the target with a margin and is tight (TANGO is about 1.1 m wide).
    let size = Vec3::from(dataset.scene_max) - Vec3::from(dataset.scene_min);
    assert!(
        size.x > 1.0 && size.x < 1.5 && size.z > 0.3 && size.z < 0.5,
        "scene box {size}"
    );
    // Sunlamp varies exposure and sun direction frame to frame.
    let exposures: Vec<f64> = truth.frames.iter().map(|f| f.exposure).collect();
    assert!(exposures.iter().any(|&e| e > 2.0) && exposures.iter().any(|&e| e < 0.5));
    let suns: Vec<Vec3> = truth
        .frames
        .iter()
        .map(|f| Vec3::from(f.sun_direction_body.map(|v| v as f32)))
        .collect();
    assert!(suns.windows(2).all(|w| (w[0] - w[1]).length() > 1e-3));
    assert!(suns.iter().all(|s| (s.length() - 1.0).abs() < 1e-5));
}

#[test]
fn labels_written_equal_labels_loaded() {
    if shared_data().is_none() {
        return;
    }
    let dir = TempDir::new("labels");
    for name in ["synthetic", "lightbox"] {
        let out = dir.0.join(name);
        let report = simulate(&preset(name, 12, 48), &out);
        let set = load(&out);
        assert_eq!(set.labels, report.labels, "{name}: labels.json round trip");
        for (frame, label) in set.dataset.frames.iter().zip(&report.labels) {
            assert_eq!(frame.name, label.filename);
            assert_eq!(
                frame.pose,
                label.pose().unwrap(),
                "{name}: pose of {}",
                frame.name
            );
        }
        let truth = set.truth.unwrap();
        let angles_deg: Vec<f32> = truth
            .frames
            .iter()
            .zip(&set.labels)
            .map(|(exact, label)| {
                exact
                    .label()
                    .rotation()
                    .angle_between(label.rotation())
                    .to_degrees()
            })
            .collect();
        let offsets_m: Vec<f32> = truth
            .frames
            .iter()
            .zip(&set.labels)
            .map(|(exact, label)| (exact.label().translation() - label.translation()).length())
            .collect();
        if name == "synthetic" {
            // Exact labels: what the method trains on is the truth.
            assert!(
                angles_deg.iter().chain(&offsets_m).all(|&e| e == 0.0),
                "{angles_deg:?} {offsets_m:?}"
            );
        } else {
            // Lightbox: E_R = 0.5 deg, E_T = 0.01 m per axis.
            let mean = |v: &[f32]| v.iter().sum::<f32>() / v.len() as f32;
            assert!(
                (0.1..1.5).contains(&mean(&angles_deg)),
                "rotation noise {angles_deg:?}"
            );
            assert!(
                (0.004..0.04).contains(&mean(&offsets_m)),
                "translation noise {offsets_m:?}"
            );
        }
    }
}

#[test]
fn landmarks_projected_with_the_true_pose_land_on_the_mask() {
    let Some(data) = shared_data() else { return };
    let landmarks = sim::read_landmarks(&data.join("speedplus/landmarks.csv")).unwrap();
    assert_eq!(landmarks.len(), 11);
    let dir = TempDir::new("landmarks");
    // The third case renders through the SPEED+ lens distortion (mild near the centre); the
    // loader undistorts images and masks back to the pinhole camera used for projecting. The
    // fourth renders 128 x 80 px frames (inspection's aspect). The fifth is the streaming
    // scene's approach: the target in view, every landmark in the image, from 6 m to 2.8 m.
    for (name, distortion) in [
        ("synthetic", false),
        ("sunlamp", false),
        ("sunlamp", true),
        ("inspection", false),
        ("rendezvous", false),
    ] {
        let out = dir.0.join(format!("{name}-{distortion}"));
        let mut scene = preset(name, 10, 128);
        scene.spec.camera.distortion = distortion;
        simulate(&scene, &out);
        let set = load(&out);
        assert_eq!(set.camera.has_distortion(), distortion);
        let expected_height = if name == "inspection" { 80 } else { 128 };
        assert_eq!(
            (set.camera.width, set.camera.height),
            (128, expected_height),
            "{name}"
        );
        let truth = set.truth.unwrap();
        for (frame, exact) in set.dataset.frames.iter().zip(&truth.frames) {
            let label = exact.label();
            let mask = frame.mask.as_ref().unwrap();
            let camera = frame.camera;
            let mut in_frame = 0;
            for (k, landmark) in landmarks.iter().enumerate() {
                let p = label.rotation() * *landmark + label.translation();
                let (u, v) = (
                    camera.fx * p.x / p.z + camera.cx,
                    camera.fy * p.y / p.z + camera.cy,
                );
                // A close target may not fit a wide image's height: a landmark cut off by the
                // border has no mask to land on.
                if !(0.0..camera.width as f32).contains(&u)
                    || !(0.0..camera.height as f32).contains(&v)
                {
                    continue;
                }
                in_frame += 1;
                let (i, j) = (u.floor() as i64, v.floor() as i64);
                // Within one pixel of the mask (a corner's pixel may be less than half covered).
                let on_mask = (-1..=1).any(|dj| {
                    (-1..=1).any(|di| {
                        let (x, y) = (i + di, j + dj);
                        (0..camera.width as i64).contains(&x)
                            && (0..camera.height as i64).contains(&y)
                            && mask[(y * camera.width as i64 + x) as usize] == 255
                    })
                });
                assert!(
                    on_mask,
                    "{name} {}: landmark {k} projects to ({u:.1}, {v:.1}), off the mask",
                    frame.name
                );
            }
            // Only inspection's 128 x 80 frames are too short for a close target; the square
            // presets keep every landmark in the image.
            let all_in_frame = in_frame == landmarks.len();
            assert!(
                all_in_frame || (name == "inspection" && in_frame > 0),
                "{name} {}: {in_frame} of {} landmarks in the image",
                frame.name,
                landmarks.len()
            );
        }
    }
}

#[test]
fn same_seed_gives_identical_bytes_and_another_seed_does_not() {
    if shared_data().is_none() {
        return;
    }
    let dir = TempDir::new("determinism");
    let scene = preset("sunlamp", 6, 48);
    let files = |out: &Path| -> Vec<(String, Vec<u8>)> {
        let mut files = Vec::new();
        for sub in ["", "images", "masks"] {
            let mut names: Vec<_> = std::fs::read_dir(out.join(sub))
                .unwrap()
                .map(|e| e.unwrap().path())
                .collect();
            names.sort();
            files.extend(
                names
                    .into_iter()
                    .filter(|p| p.is_file())
                    .map(|p| (p.display().to_string(), std::fs::read(&p).unwrap())),
            );
        }
        files
            .into_iter()
            .map(|(p, bytes)| (p.replace(&out.display().to_string(), ""), bytes))
            .collect()
    };
    simulate(&scene, &dir.0.join("a"));
    simulate(&scene, &dir.0.join("b"));
    let (a, b) = (files(&dir.0.join("a")), files(&dir.0.join("b")));
    assert_eq!(a.len(), 6 * 2 + 4);
    assert_eq!(a, b);
    let mut other = scene.clone();
    other.spec.seed += 1;
    simulate(&other, &dir.0.join("c"));
    let c = files(&dir.0.join("c"));
    let image = |files: &[(String, Vec<u8>)]| {
        files
            .iter()
            .find(|(p, _)| p.ends_with("img000001.png"))
            .unwrap()
            .1
            .clone()
    };
    assert_ne!(image(&a), image(&c));
}

#[test]
fn disabled_effects_cost_nothing() {
    if shared_data().is_none() {
        return;
    }
    let dir = TempDir::new("timings");
    for name in ["synthetic", "lightbox", "sunlamp"] {
        let scene = preset(name, 4, 64);
        let report = simulate(&scene, &dir.0.join(name));
        let table = report.timing_table();
        for stage in Stage::ALL {
            let time = report.times.get(stage);
            if stage.runs_with(&scene.spec.effects) {
                assert!(
                    time > Duration::ZERO,
                    "{name}: {} ran but took no time\n{table}",
                    stage.name()
                );
            } else {
                assert_eq!(
                    time,
                    Duration::ZERO,
                    "{name}: {} is off but took time\n{table}",
                    stage.name()
                );
            }
        }
        // The synthetic preset asks for direct sun only.
        if name == "synthetic" {
            let off = table
                .lines()
                .filter(|line| line.split_whitespace().any(|w| w == "no"))
                .count();
            assert_eq!(off, 8, "{table}");
        }
    }
}

#[test]
fn an_obj_mesh_with_per_part_materials_renders_quickly() {
    let Some(data) = shared_data() else { return };
    let dir = TempDir::new("mesh");
    let scene_path = dir.0.join("tdrs.toml");
    let text = format!(
        r#"
name = "tdrs"
frames = 3
seed = 5
size = 256
[target]
model = "mesh"
path = "{mesh}"
[target.materials]
default = "mli"
polySurface5_1 = "solar_cell"
transform8 = "metal"
[camera]
intrinsics = "{camera}"
[poses]
kind = "random"
distance_m = [2.5, 4.0]
[sun]
path = "random"
[effects.sun]
[effects.shadows]
[effects.specular]
"#,
        mesh = data.join("meshes/tdrs.obj").display(),
        camera = data.join("speedplus/camera.json").display()
    );
    std::fs::write(&scene_path, text).unwrap();
    let scene = Scene::load(scene_path.to_str().unwrap()).unwrap();
    let report = simulate(&scene, &dir.0.join("out"));
    assert!(report.triangles > 2900, "{} triangles", report.triangles);
    let set = load(&dir.0.join("out"));
    for frame in &set.dataset.frames {
        let covered = frame
            .mask
            .as_ref()
            .unwrap()
            .iter()
            .filter(|&&m| m == 255)
            .count();
        assert!(
            covered > 1000,
            "{}: target covers {covered} pixels",
            frame.name
        );
    }
    let render = report.times.get(Stage::Geometry) + report.times.get(Stage::Shadows);
    let per_frame = render / report.frames;
    eprintln!("{}", report.timing_table());
    assert!(
        per_frame < Duration::from_secs(1),
        "ray casting took {per_frame:?} per 256x256 frame"
    );
}

/// Each kind of bad scene file gives one error naming the file and the field.
#[test]
fn bad_scene_files_name_the_file_and_the_field() {
    if shared_data().is_none() {
        return;
    }
    let base = std::fs::read_to_string(common::root().join("scenes/synthetic.toml")).unwrap();
    let dir = TempDir::new("bad");
    let cases: [(&str, String, &str); 7] = [
        (
            "unknown_effect",
            format!("{base}\n[effects.glare]\n"),
            "effects.glare",
        ),
        (
            "missing_mesh",
            base.replace(
                "model = \"tango\"\nlandmarks = \"tango-landmarks.csv\"",
                "model = \"mesh\"\npath = \"no/such/mesh.obj\"",
            )
            .replace(
                "[target.materials]\nbody = \"mli\"\npanel = \"solar_cell\"\nantenna = \"metal\"\n",
                "",
            ),
            "target.path",
        ),
        (
            "tiny_height",
            base.replace("size = 256", "size = 256\nheight = 4"),
            "height",
        ),
        (
            "negative_frames",
            base.replace("frames = 400", "frames = -5"),
            "frames",
        ),
        (
            "zero_quaternion",
            base.replace(
                "attitude = [1.0, 0.0, 0.0, 0.0]",
                "attitude = [0.0, 0.0, 0.0, 0.0]",
            ),
            "poses.attitude",
        ),
        (
            "non_finite",
            base.replace("distance_m = [5.0, 2.8]", "distance_m = [nan, 2.8]"),
            "poses.distance_m[0]",
        ),
        (
            "unknown_material",
            base.replace("panel = \"solar_cell\"", "panel = \"unobtanium\""),
            "target.materials.panel",
        ),
    ];
    for (name, text, expected_field) in cases {
        assert_ne!(text, base, "{name}: the case did not change the scene");
        let path = dir.0.join(format!("{name}.toml"));
        std::fs::write(&path, text).unwrap();
        let error = Scene::load(path.to_str().unwrap()).and_then(|scene| {
            // Paths are checked when the scene is built.
            sim::simulate(&scene, &dir.0.join(format!("{name}-out")), &|| {})
        });
        match error {
            Err(HostError::Field {
                file,
                field,
                reason,
            }) => {
                assert_eq!(file, path, "{name}");
                assert_eq!(field, expected_field, "{name}: {reason}");
            }
            other => panic!("{name}: expected a field error, got {other:?}"),
        }
        assert!(
            !dir.0.join(format!("{name}-out")).exists(),
            "{name}: output left behind"
        );
    }
}

/// `--size` below the smallest image side is refused naming it, and nothing is written: by the
/// command's parser, and by the library for every caller that sets a size after loading.
#[test]
fn a_size_below_the_minimum_is_refused_and_nothing_is_written() {
    #[derive(clap::Parser)]
    struct Command {
        #[command(flatten)]
        args: simulate_command::SimulateArgs,
    }
    let dir = TempDir::new("tiny-size");
    for size in [0u16, 3, 7] {
        let out = dir.0.join(format!("size-{size}"));
        let parsed = Command::try_parse_from([
            "orbit-nerf-simulate",
            "--scene",
            "lightbox",
            "--size",
            &size.to_string(),
            "--out",
            out.to_str().unwrap(),
        ]);
        let message = parsed.err().expect("the parser must refuse it").to_string();
        assert!(message.contains("--size"), "{message}");

        for name in ["lightbox", "inspection"] {
            let scene = preset(name, 2, size);
            match sim::simulate(&scene, &out, &|| {}) {
                Err(HostError::Field { field, reason, .. }) => {
                    assert_eq!(field, "size", "{name} --size {size}: {reason}");
                    assert!(reason.contains("--size"), "{reason}");
                }
                other => panic!("{name} --size {size}: expected a field error, got {other:?}"),
            }
            assert!(!out.exists(), "{name} --size {size}: output written");
        }
    }
}
