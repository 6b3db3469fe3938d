//! Output files are written to a temporary name beside the target and renamed when complete,
//! so a crash or a kill never leaves half-written output.

use crate::error::{HostError, Result};
use std::io::Write;
use std::path::{Path, PathBuf};

fn temp_name(path: &Path) -> PathBuf {
    let mut name = path
        .file_name()
        .map(|n| n.to_os_string())
        .unwrap_or_default();
    name.push(format!(".tmp{}", std::process::id()));
    path.with_file_name(name)
}

/// Check, before any work, that `out` can be the output folder: it is a folder or does not
/// exist yet, and no existing part of its path is a file.
pub fn check_output_folder(out: &Path) -> Result<()> {
    if let Some(file) = out.ancestors().find(|p| p.exists() && !p.is_dir()) {
        return Err(HostError::invalid(
            file,
            format!(
                "is a file, not a folder, so {} cannot be the output folder",
                out.display()
            ),
        ));
    }
    Ok(())
}

/// Before a fresh run (a training run, a stream): refuse to replace the checkpoint of an
/// earlier `run` at `path` unless `replace`, after checking its folder can be the output
/// folder.
pub fn check_fresh_checkpoint(path: &Path, replace: bool, run: &str) -> Result<()> {
    if let Some(out) = path.parent() {
        check_output_folder(out)?;
    }
    if path.exists() && !replace {
        return Err(HostError::invalid(
            path,
            format!(
                "holds the checkpoint of an earlier {run}; continue it with --resume, or replace it with --force"
            ),
        ));
    }
    if path.is_dir() {
        return Err(HostError::invalid(
            path,
            format!("is a folder; the {run}'s checkpoint cannot be written there"),
        ));
    }
    Ok(())
}

/// Before any work: refuse to replace any of `files` that exists unless `replace` (the
/// user's `--force`), and refuse a folder where a file is to be written. Nothing the user did
/// not ask to replace is overwritten.
pub fn check_new_files<'p>(files: impl IntoIterator<Item = &'p Path>, replace: bool) -> Result<()> {
    for file in files {
        if file.is_dir() {
            return Err(HostError::invalid(
                file,
                "is a folder; a file is to be written there",
            ));
        }
        if file.exists() && !replace {
            return Err(HostError::invalid(
                file,
                "already exists; --force replaces it",
            ));
        }
    }
    Ok(())
}

/// Write `bytes` to `path` atomically (temporary file, fsync, rename). Creates parent folders.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    write_atomic_with(path, |file| file.write_all(bytes))
}

/// [`write_atomic`] of what `write` streams into the file (buffered), so a large output needs
/// no copy of itself in memory.
pub fn write_atomic_with(
    path: &Path,
    write: impl FnOnce(&mut dyn Write) -> std::io::Result<()>,
) -> Result<()> {
    if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent).map_err(|e| HostError::io(parent, e))?;
    }
    let tmp = temp_name(path);
    let result = (|| {
        let mut file = std::io::BufWriter::new(std::fs::File::create(&tmp)?);
        write(&mut file)?;
        let file = file.into_inner().map_err(|e| e.into_error())?;
        file.sync_all()?;
        std::fs::rename(&tmp, path)
    })();
    result.map_err(|e| {
        let _ = std::fs::remove_file(&tmp);
        HostError::io(path, e)
    })
}

/// Encode an L8 (1 channel), RGB8 (3) or RGBA8 (4) image, row-major, as PNG and write it
/// atomically; `width` and `height` are in pixels and must match the buffer's length.
pub fn write_png(path: &Path, width: u32, height: u32, channels: u8, pixels: &[u8]) -> Result<()> {
    let color = match channels {
        1 => image::ExtendedColorType::L8,
        3 => image::ExtendedColorType::Rgb8,
        4 => image::ExtendedColorType::Rgba8,
        _ => {
            return Err(HostError::invalid(
                path,
                format!("cannot write a PNG with {channels} channels"),
            ));
        }
    };
    if pixels.len() != width as usize * height as usize * channels as usize {
        return Err(HostError::invalid(
            path,
            "pixel buffer does not match the image size",
        ));
    }
    let mut encoded = Vec::new();
    image::codecs::png::PngEncoder::new(&mut encoded)
        .write_image(pixels, width, height, color)
        .map_err(|e| HostError::invalid(path, format!("PNG encoding failed: {e}")))?;
    write_atomic(path, &encoded)
}

use image::ImageEncoder as _;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn atomic_write_replaces_and_leaves_no_temporary() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("sub/out.bin");
        write_atomic(&path, b"first").unwrap();
        write_atomic(&path, b"second").unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), b"second");
        let names: Vec<_> = std::fs::read_dir(path.parent().unwrap()).unwrap().collect();
        assert_eq!(names.len(), 1);
    }

    #[test]
    fn png_round_trips() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("x.png");
        let px: Vec<u8> = (0..2 * 3 * 3).map(|v| v as u8 * 10).collect();
        write_png(&path, 2, 3, 3, &px).unwrap();
        let img = image::open(&path).unwrap().to_rgb8();
        assert_eq!(img.as_raw(), &px);
        assert!(write_png(&path, 2, 2, 3, &px).is_err());
    }
}
