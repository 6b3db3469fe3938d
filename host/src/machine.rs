//! What machine a measurement ran on: the CPU model and its cache sizes (issue #16), for the
//! headers of timing reports.

use std::path::Path;

/// The CPU model (`model name` of `/proc/cpuinfo`) and the first CPU's caches (`L1d 32K, L1i
/// 32K, L2 512K, L3 32768K` from `/sys/devices/system/cpu/cpu0/cache`); "unknown" for what
/// cannot be read (any system but Linux).
pub fn cpu_summary() -> String {
    let model = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|text| cpu_model(&text))
        .unwrap_or_else(|| "unknown".into());
    let caches = cache_sizes(Path::new("/sys/devices/system/cpu/cpu0/cache"));
    let caches = if caches.is_empty() {
        "unknown".into()
    } else {
        caches.join(", ")
    };
    format!("CPU: {model}; caches (cpu0): {caches}")
}

/// The first `model name` line's value.
fn cpu_model(cpuinfo: &str) -> Option<String> {
    let line = cpuinfo.lines().find(|l| l.starts_with("model name"))?;
    let model = line.split_once(':')?.1.trim();
    (!model.is_empty()).then(|| model.to_string())
}

/// `L<level><d|i|> <size>` of each `index*` folder under `dir`, in index order; the folders
/// that cannot be read are left out.
fn cache_sizes(dir: &Path) -> Vec<String> {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return Vec::new();
    };
    let mut indices: Vec<_> = entries
        .filter_map(|e| e.ok())
        .map(|e| e.path())
        .filter(|p| {
            p.file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| n.starts_with("index"))
        })
        .collect();
    indices.sort();
    let read = |path: &Path, name: &str| {
        std::fs::read_to_string(path.join(name))
            .ok()
            .map(|s| s.trim().to_string())
    };
    indices
        .iter()
        .filter_map(|index| {
            let level = read(index, "level")?;
            let size = read(index, "size")?;
            let kind = match read(index, "type").as_deref() {
                Some("Data") => "d",
                Some("Instruction") => "i",
                _ => "",
            };
            Some(format!("L{level}{kind} {size}"))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_the_model_and_the_caches() {
        let cpuinfo = "processor\t: 0\nmodel name\t: AMD EPYC 9654\nflags\t: fpu\n";
        assert_eq!(cpu_model(cpuinfo).as_deref(), Some("AMD EPYC 9654"));
        assert_eq!(cpu_model("processor: 0\n"), None);
        let dir = tempfile::tempdir().unwrap();
        for (index, level, kind, size) in [(0, "1", "Data", "32K"), (2, "2", "Unified", "1024K")] {
            let folder = dir.path().join(format!("index{index}"));
            std::fs::create_dir(&folder).unwrap();
            std::fs::write(folder.join("level"), level).unwrap();
            std::fs::write(folder.join("type"), kind).unwrap();
            std::fs::write(folder.join("size"), format!("{size}\n")).unwrap();
        }
        std::fs::create_dir(dir.path().join("index1")).unwrap();
        assert_eq!(cache_sizes(dir.path()), ["L1d 32K", "L2 1024K"]);
        assert!(cache_sizes(&dir.path().join("absent")).is_empty());
    }
}
