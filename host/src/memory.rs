//! The memory a command will need, checked against a limit before anything large is
//! allocated, so that a size that cannot fit fails with the plan's numbers instead of
//! aborting with `memory allocation failed` part-way through.

use crate::error::{HostError, Result};
use crate::formats::transforms::{OutputSize, output_size};
use orbit_nerf_core::MemoryPlan;
use std::path::Path;

/// Share of the machine's available memory a command may plan for when no limit is given.
pub const DEFAULT_SHARE_OF_AVAILABLE: f64 = 0.8;

/// Memory available to new allocations on this machine (`MemAvailable` of `/proc/meminfo`),
/// in bytes; `None` where it cannot be read.
pub fn available_bytes() -> Option<u64> {
    let meminfo = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = meminfo.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    kib.checked_mul(1024)
}

/// The limit to plan against: the user's, else a share of the available memory, else none.
pub fn limit_or_default(user: Option<u64>) -> Option<u64> {
    user.or_else(|| {
        available_bytes().map(|bytes| (bytes as f64 * DEFAULT_SHARE_OF_AVAILABLE) as u64)
    })
}

/// One named part of a plan, in bytes.
pub type Part = (&'static str, u64);

/// Fail, naming `what` and listing `parts`, when their sum exceeds `limit` (bytes; `None`
/// means no limit).
pub fn check_plan(what: &Path, parts: &[Part], limit: Option<u64>) -> Result<()> {
    let total = total(parts);
    let Some(limit) = limit else {
        return Ok(());
    };
    if total <= limit {
        return Ok(());
    }
    Err(HostError::invalid(
        what,
        format!(
            "needs {}, more than the memory limit of {}; lower the sizes or raise --memory-limit",
            describe(parts),
            human(limit)
        ),
    ))
}

/// The sum of `parts`, saturating.
pub fn total(parts: &[Part]) -> u64 {
    (parts.iter()).fold(0u64, |total, (_, bytes)| total.saturating_add(*bytes))
}

/// `parts` as their total and the non-empty ones: "1.2 GiB (planes 1.0 GiB, MLPs 0.2 GiB)".
pub fn describe(parts: &[Part]) -> String {
    let listed: Vec<String> = (parts.iter())
        .filter(|(_, bytes)| *bytes > 0)
        .map(|(name, bytes)| format!("{name} {}", human(*bytes)))
        .collect();
    format!("{} ({})", human(total(parts)), listed.join(", "))
}

/// The parts of the core's memory plan (the arena) as named byte counts; the parts that grow
/// with a step's rays name the config fields that size them, so that a config asking for more
/// rays than the memory allows is refused naming the field.
pub fn arena_parts(plan: &MemoryPlan) -> [Part; 9] {
    [
        ("planes", plan.planes as u64),
        ("plane master copy", plan.plane_master as u64),
        ("plane moments", plan.plane_moments as u64),
        ("plane gradients", plan.plane_grads as u64),
        ("MLPs", plan.mlp as u64),
        ("occupancy", plan.occupancy as u64),
        ("frame store", plan.frames as u64),
        ("ray batch (rays_per_batch)", plan.ray_batch as u64),
        (
            "chunk buffers (samples_per_chunk, rays_per_batch)",
            plan.samples as u64,
        ),
    ]
}

/// `resident` followed by the arena of `plan` (its parts and the rest of its total:
/// alignment and small parts).
pub fn with_arena(resident: &[Part], plan: &MemoryPlan) -> Vec<Part> {
    let parts = arena_parts(plan);
    let listed: u64 = parts.iter().map(|(_, bytes)| *bytes).sum();
    let mut all = resident.to_vec();
    all.extend(parts);
    all.push((
        "other arena parts",
        (plan.total as u64).saturating_sub(listed),
    ));
    all
}

/// Check the arena of `plan` against `limit`, naming `what` in the error.
pub fn check_arena(what: &Path, plan: &MemoryPlan, limit: Option<u64>) -> Result<()> {
    check_plan(what, &with_arena(&[], plan), limit)
}

/// Folder levels below a dataset folder searched for images.
const IMAGE_SEARCH_DEPTH: usize = 4;

/// An upper bound of the memory the images of the dataset folder `folder` take once loaded
/// with their longer side at most `max_side` (never upsampled), read from the image headers
/// without decoding: every image below it (the loaders read at most these) as RGB plus a
/// mask, and the largest one decoded at its stored size (RGBA, f32 while resampled).
pub fn dataset_parts(folder: &Path, max_side: Option<u32>) -> [Part; 2] {
    let size = max_side.map_or(OutputSize::Original, OutputSize::MaxSide);
    let (mut loaded, mut largest) = (0u64, 0u64);
    for path in image_files(folder, IMAGE_SEARCH_DEPTH) {
        // Unreadable headers are left to the loader, which names the file.
        let Ok((w, h)) = image::image_dimensions(&path) else {
            continue;
        };
        let (out_w, out_h) = output_size(size, (w, h));
        loaded = loaded.saturating_add(out_w as u64 * out_h as u64 * 4);
        largest = largest.max(w as u64 * h as u64 * 4 * 4);
    }
    [("images loaded", loaded), ("image being decoded", largest)]
}

/// The longer side of the largest image below the dataset folder `folder` (from the image
/// headers, nothing decoded; `None` when no image is readable): a larger size gives the same
/// frames, as images are never upsampled.
pub fn largest_image_side(folder: &Path) -> Option<u32> {
    (image_files(folder, IMAGE_SEARCH_DEPTH).iter())
        .filter_map(|path| image::image_dimensions(path).ok())
        .map(|(w, h)| w.max(h))
        .max()
}

/// PNG and JPEG files below `dir`, `depth` folder levels deep at most.
fn image_files(dir: &Path, depth: usize) -> Vec<std::path::PathBuf> {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return Vec::new();
    };
    let mut files = Vec::new();
    for path in entries.filter_map(|e| e.ok().map(|e| e.path())) {
        if path.is_dir() && depth > 0 {
            files.extend(image_files(&path, depth - 1));
        } else if path
            .extension()
            .and_then(|e| e.to_str())
            .is_some_and(|e| ["png", "jpg", "jpeg"].contains(&e.to_ascii_lowercase().as_str()))
        {
            files.push(path);
        }
    }
    files
}

/// Bytes as KiB (below 1 MiB), MiB or GiB (from 1 GiB), one decimal, for messages.
///
/// ```
/// use orbit_nerf_host::memory::human;
///
/// assert_eq!(human(512), "0.5 KiB");
/// assert_eq!(human(3 << 20), "3.0 MiB");
/// assert_eq!(human(5 << 30), "5.0 GiB");
/// ```
pub fn human(bytes: u64) -> String {
    let mib = bytes as f64 / (1u64 << 20) as f64;
    if mib < 1.0 {
        format!("{:.1} KiB", bytes as f64 / 1024.0)
    } else if mib >= 1024.0 {
        format!("{:.1} GiB", mib / 1024.0)
    } else {
        format!("{mib:.1} MiB")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_plan_over_the_limit_fails_with_its_numbers() {
        let parts = [("planes", 3 << 30), ("frames", 2 << 30), ("rays", 0)];
        let error = check_plan(Path::new("run"), &parts, Some(1 << 30))
            .unwrap_err()
            .to_string();
        assert!(error.contains("needs 5.0 GiB"), "{error}");
        assert!(error.contains("planes 3.0 GiB, frames 2.0 GiB"), "{error}");
        assert!(!error.contains("rays"), "{error}");
        assert!(error.contains("limit of 1.0 GiB"), "{error}");
        assert!(check_plan(Path::new("run"), &parts, Some(5 << 30)).is_ok());
        assert!(check_plan(Path::new("run"), &[("x", u64::MAX), ("y", 9)], None).is_ok());
        assert!(check_plan(Path::new("run"), &[("x", u64::MAX), ("y", 9)], Some(1)).is_err());
    }

    #[test]
    fn the_images_of_a_dataset_are_estimated_from_their_headers_never_upsampled() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::create_dir_all(dir.path().join("images")).unwrap();
        for name in ["images/a.png", "b.PNG"] {
            image::RgbImage::new(64, 32)
                .save_with_format(dir.path().join(name), image::ImageFormat::Png)
                .unwrap();
        }
        std::fs::write(dir.path().join("labels.json"), b"[]").unwrap();
        let decoding = 64 * 32 * 16;
        assert_eq!(
            dataset_parts(dir.path(), Some(16)),
            [
                ("images loaded", 2 * 16 * 8 * 4),
                ("image being decoded", decoding)
            ]
        );
        assert_eq!(
            dataset_parts(dir.path(), Some(1000)),
            [
                ("images loaded", 2 * 64 * 32 * 4),
                ("image being decoded", decoding)
            ]
        );
        assert_eq!(largest_image_side(dir.path()), Some(64));
        assert_eq!(largest_image_side(&dir.path().join("none")), None);
    }

    #[test]
    fn this_machine_reports_its_available_memory() {
        if Path::new("/proc/meminfo").exists() {
            assert!(available_bytes().is_some_and(|bytes| bytes > 0));
        }
    }
}
