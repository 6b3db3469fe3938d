//! What accuracy costs in time: a sweep with `[anytime]` gives every variant an anytime curve
//! (its held-out quality after each scored step, against the training seconds it took to get
//! there), and this report turns them into `tradeoff.csv` (a row per task and point),
//! the markdown section (each variant's quality, time, memory and speed against the first
//! variant, the time to reach each target, the best variant within each budget), the Pareto
//! plots (final quality against training time and against arena memory) and the anytime
//! curves, one plot per knob (the variants named `<knob>=<value>`, with the reference).

use super::results::{METRICS_CSV_HEADER, TaskResult, TaskTiming, metric_cells};
use super::{Anytime, Quality, Sweep};
use crate::error::Result;
use crate::io::write_atomic;
use crate::report::{ViewMetrics, format_or_na, labelled_scatter, line_plot, markdown_table};
use orbit_nerf_core::{Config, TexelUpdate};
use std::path::Path;

/// One variant of a trade-off sweep: `<knob>=<value>`, the config fields it sets (or the image
/// size it uses).
#[derive(Clone, Debug, PartialEq)]
pub struct Knob {
    /// The variant's name, `<knob>=<value>` (`rays_per_batch=2048`).
    pub name: String,
    /// The config fields it sets (empty for a `size` knob).
    pub set: toml::Table,
    /// The image size it uses, pixels (longest side); `None`: the sweep's.
    pub size: Option<u32>,
}

impl Knob {
    /// `key = value` of the config (`size` sets the image size instead).
    pub fn new(key: &str, value: toml::Value) -> Knob {
        let name = format!("{key}={}", value_text(&value));
        if key == "size" {
            let size = value.as_integer().and_then(|v| u32::try_from(v).ok());
            // A size that is no u32 stays in `set`, where the sweep's check names it.
            if let Some(size) = size {
                return Knob {
                    name,
                    set: toml::Table::new(),
                    size: Some(size),
                };
            }
        }
        Knob {
            name,
            set: toml::Table::from_iter([(key.to_string(), value)]),
            size: None,
        }
    }

    /// Also set `key` to `value` (a field the knob's value implies), keeping the name.
    fn with(mut self, key: &str, value: toml::Value) -> Knob {
        self.set.insert(key.into(), value);
        self
    }
}

/// A value as a variant name shows it: arrays without spaces, strings unquoted.
fn value_text(value: &toml::Value) -> String {
    match value {
        toml::Value::String(s) => s.clone(),
        toml::Value::Array(items) => {
            let items: Vec<String> = items.iter().map(value_text).collect();
            format!("[{}]", items.join(","))
        }
        other => other.to_string(),
    }
}

/// `--vary KNOB=V1,V2,...`: the knob and its values, each a TOML value (commas inside `[..]`
/// belong to an array).
pub fn parse_vary(text: &str) -> std::result::Result<(String, Vec<toml::Value>), String> {
    let (key, list) = text
        .split_once('=')
        .ok_or_else(|| format!("`{text}`: expected KNOB=VALUE,VALUE,..."))?;
    let key = key.trim();
    if key.is_empty()
        || !key
            .chars()
            .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '_')
    {
        return Err(format!("`{key}`: a knob is a config field name or `size`"));
    }
    let mut values = Vec::new();
    let (mut depth, mut start) = (0i32, 0);
    let ends = list.bytes().enumerate().chain([(list.len(), b',')]);
    for (i, byte) in ends {
        match byte {
            b'[' => depth += 1,
            b']' => depth -= 1,
            // The last comma is the end of the text: it closes the last value whatever the
            // depth (an unclosed `[` then fails to parse).
            b',' if depth == 0 || i == list.len() => {
                let item = list[start..i].trim();
                start = i + 1;
                values.push(parse_value(key, item)?);
            }
            _ => {}
        }
    }
    Ok((key.to_string(), values))
}

/// One value of `--vary`: a TOML value, or a bare word as a string (`stochastic_rounding`).
fn parse_value(key: &str, item: &str) -> std::result::Result<toml::Value, String> {
    if item.is_empty() {
        return Err(format!("--vary {key}: an empty value"));
    }
    if let Ok(mut table) = toml::from_str::<toml::Table>(&format!("v = {item}"))
        && let Some(value) = table.remove("v")
    {
        return Ok(value);
    }
    if item.chars().all(|c| c.is_ascii_alphanumeric() || c == '_') {
        return Ok(toml::Value::String(item.into()));
    }
    Err(format!("`{item}` (of --vary {key}) is not a value"))
}

/// The built-in knobs, each one step to either side of `base` (at image size `size`): steps,
/// rays per step (with the sample capacity that keeps samples per ray), plane resolutions,
/// features and scales, the MLP widths, SH bands, embedding size, pose correction, image
/// size, texel update, occupancy resolution and the per-ray sample cap. Values the config
/// would refuse are left out.
pub fn default_knobs(base: &Config, size: u32) -> Vec<Knob> {
    let int = |v: u64| toml::Value::Integer(v as i64);
    let mut knobs = Vec::new();
    for steps in [base.steps / 2, base.steps.saturating_mul(2)] {
        knobs.push(Knob::new("steps", int(steps as u64)));
    }
    for rays in [
        base.rays_per_batch / 2,
        base.rays_per_batch.saturating_mul(2),
    ] {
        // A chunk trains its rays in as many passes as they need: the pass size stays.
        knobs.push(Knob::new("rays_per_batch", int(rays as u64)));
    }
    let scaled = |factor: f64| -> toml::Value {
        toml::Value::Array(
            (base.resolutions.iter().enumerate())
                .map(|(s, &r)| {
                    let r = if s < base.scales as usize {
                        ((r as f64 * factor).round() as u64).max(2)
                    } else {
                        r as u64
                    };
                    int(r)
                })
                .collect(),
        )
    };
    knobs.push(Knob::new("resolutions", scaled(0.5)));
    knobs.push(Knob::new("resolutions", scaled(2.0)));
    for features in [base.features / 2, base.features * 2] {
        knobs.push(Knob::new("features", int(features as u64)));
    }
    if base.scales > 1 {
        knobs.push(Knob::new("scales", int(base.scales as u64 - 1)));
    }
    if (base.scales as usize) < orbit_nerf_core::config::MAX_SCALES {
        // One more scale at twice the finest resolution.
        let s = base.scales as usize;
        let mut resolutions = base.resolutions;
        resolutions[s] = resolutions[s - 1].saturating_mul(2);
        let value = toml::Value::Array(resolutions.iter().map(|&r| int(r as u64)).collect());
        knobs.push(Knob::new("scales", int(s as u64 + 1)).with("resolutions", value));
    }
    for hidden in [base.density_hidden / 2, base.density_hidden * 2] {
        knobs.push(Knob::new("density_hidden", int(hidden as u64)));
    }
    for hidden in [base.colour_hidden / 2, base.colour_hidden * 2] {
        knobs.push(Knob::new("colour_hidden", int(hidden as u64)));
    }
    for bands in (1..base.sh_bands).rev().take(2) {
        knobs.push(Knob::new("sh_bands", int(bands as u64)));
    }
    let dims: &[u16] = if base.embedding_dim == 0 {
        &[16]
    } else {
        &[0, base.embedding_dim / 2, base.embedding_dim * 2]
    };
    for &dim in dims {
        knobs.push(Knob::new("embedding_dim", int(dim as u64)));
    }
    knobs.push(Knob::new(
        "pose_correction",
        toml::Value::Boolean(!base.pose_correction),
    ));
    knobs.push(Knob::new("size", int(size as u64 / 2)));
    knobs.push(Knob::new("size", int(size as u64 * 2)));
    let other = match base.texel_update {
        TexelUpdate::MasterCopy => "stochastic_rounding",
        TexelUpdate::StochasticRounding => "master_copy",
    };
    knobs.push(Knob::new("texel_update", toml::Value::String(other.into())));
    for res in [base.occupancy_res / 2, base.occupancy_res * 2] {
        knobs.push(Knob::new("occupancy_res", int(res as u64)));
    }
    for cap in [base.max_samples_per_ray / 2, base.max_samples_per_ray / 4] {
        knobs.push(Knob::new("max_samples_per_ray", int(cap as u64)));
    }
    knobs.retain(|k| {
        k.size.is_none_or(|s| (8..=super::MAX_SIZE).contains(&s))
            && crate::train::with_overrides(Path::new(""), "", base, &k.set).is_ok()
    });
    knobs
}

/// One variant's anytime curve, the mean over its seeds.
#[derive(Clone, Debug, PartialEq)]
pub struct VariantCurve {
    /// The variant's name.
    pub variant: String,
    /// Its image size, pixels (longest side; 0 in records that do not hold it).
    pub size: u16,
    /// Bytes of its model's arena.
    pub arena_bytes: u64,
    /// Samples per second of training (samples the rays met / training seconds).
    pub samples_per_second: f64,
    /// `(step, training seconds, held-out means)`, ascending in steps; the last is the end.
    pub points: Vec<(u32, f64, ViewMetrics)>,
}

impl VariantCurve {
    /// The quality and seconds of the last point.
    fn end(&self, quality: Quality) -> (f64, f64) {
        self.points
            .last()
            .map_or((f64::NAN, f64::NAN), |(_, s, m)| (quality.of(m), *s))
    }

    /// Training seconds at the first scored point whose quality reaches `target`.
    pub fn time_to_reach(&self, quality: Quality, target: f64) -> Option<f64> {
        (self.points.iter())
            .find(|(_, _, m)| quality.of(m) >= target)
            .map(|(_, s, _)| *s)
    }

    /// The best quality among the points reached within `budget` training seconds, with its
    /// seconds.
    pub fn best_within(&self, quality: Quality, budget: f64) -> Option<(f64, f64)> {
        (self.points.iter())
            .filter(|(_, s, m)| *s <= budget && quality.of(m).is_finite())
            .map(|(_, s, m)| (quality.of(m), *s))
            .fold(None, |best: Option<(f64, f64)>, p| match best {
                Some(b) if b.0 >= p.0 => Some(b),
                _ => Some(p),
            })
    }
}

/// Each variant's curve, in the order the variants first appear among the tasks; seeds are
/// averaged point by point (a variant's seeds share its config, so its points).
pub fn variant_curves(
    sweep: &Sweep,
    results: &[TaskResult],
    timings: &[TaskTiming],
) -> Vec<VariantCurve> {
    let mut names: Vec<&str> = Vec::new();
    for task in &sweep.tasks {
        if !names.contains(&task.variant.as_str()) {
            names.push(&task.variant);
        }
    }
    names
        .into_iter()
        .filter_map(|name| {
            let runs: Vec<(&TaskResult, &TaskTiming)> = (results.iter().zip(timings))
                .filter(|(r, _)| r.variant == name)
                .collect();
            let (first, _) = *runs.first()?;
            let n = runs.len() as f64;
            // Points every seed has (records are checked against the description, but a
            // short one must not index past its end).
            let common = (runs.iter())
                .map(|(r, t)| r.curve.len().min(t.seconds.len()))
                .min()?;
            let points = (0..common)
                .map(|i| {
                    let metrics: Vec<ViewMetrics> = runs
                        .iter()
                        .map(|(r, _)| r.curve[i].metrics.into())
                        .collect();
                    let seconds = runs.iter().map(|(_, t)| t.seconds[i]).sum::<f64>() / n;
                    (
                        first.curve[i].step,
                        seconds,
                        crate::report::mean_metrics(&metrics),
                    )
                })
                .collect();
            let samples_per_second = runs
                .iter()
                .map(|(r, t)| r.samples as f64 / t.seconds.last().copied().unwrap_or(f64::NAN))
                .sum::<f64>()
                / n;
            Some(VariantCurve {
                variant: name.to_string(),
                size: first.size,
                arena_bytes: first.arena_bytes,
                samples_per_second,
                points,
            })
        })
        .collect()
}

/// Indices of the points no other point beats: none has a cost as low and a quality as high,
/// with one of them strictly better. Points with a non-finite coordinate are on no front.
/// Ascending in cost.
pub fn pareto_front(points: &[(f64, f64)]) -> Vec<usize> {
    let finite = |p: &(f64, f64)| p.0.is_finite() && p.1.is_finite();
    let mut front: Vec<usize> = (0..points.len())
        .filter(|&i| finite(&points[i]))
        .filter(|&i| {
            let (c, q) = points[i];
            !points
                .iter()
                .enumerate()
                .any(|(j, p)| j != i && finite(p) && p.0 <= c && p.1 >= q && (p.0 < c || p.1 > q))
        })
        .collect();
    front.sort_by(|&a, &b| points[a].0.total_cmp(&points[b].0));
    front
}

/// The knob a variant varies: its name up to `=` (`rays_per_batch=2048` -> `rays_per_batch`),
/// or the whole name.
fn knob(variant: &str) -> &str {
    variant.split_once('=').map_or(variant, |(k, _)| k).trim()
}

/// A file-name part of `text`: letters and digits kept, the rest `_`.
fn file_part(text: &str) -> String {
    text.chars()
        .map(|c| if c.is_ascii_alphanumeric() { c } else { '_' })
        .collect()
}

fn mib(bytes: u64) -> f64 {
    bytes as f64 / (1024.0 * 1024.0)
}

/// Write `tradeoff.csv` and the plots into `out`; return the markdown section.
pub fn report(
    sweep: &Sweep,
    anytime: &Anytime,
    results: &[TaskResult],
    timings: &[TaskTiming],
    out: &Path,
) -> Result<String> {
    write_atomic(&out.join("tradeoff.csv"), csv(results, timings).as_bytes())?;
    let curves = variant_curves(sweep, results, timings);
    let quality = anytime.quality;
    let mut text = format!(
        "\n## What accuracy costs in time\n\nQuality: mean held-out {} (`{}`). Times are training seconds (scoring left out) on {}, {} thread(s) per task. Differences are against `{}`, the first variant.\n\n",
        quality.label(),
        quality.name(),
        timings
            .first()
            .map_or("an unknown CPU", |t| t.cpu.trim_start_matches("CPU: ")),
        timings.first().map_or(0, |t| t.threads),
        curves.first().map_or("", |c| c.variant.as_str()),
    );
    text.push_str(&table(&curves, anytime));
    if !anytime.budgets_s.is_empty() {
        text.push_str("\nBest variant within each training time:\n\n");
        for &budget in &anytime.budgets_s {
            let best = (curves.iter())
                .filter_map(|c| c.best_within(quality, budget).map(|b| (c, b)))
                .fold(
                    None,
                    |best: Option<(&VariantCurve, (f64, f64))>, p| match best {
                        Some(b) if b.1.0 >= p.1.0 => Some(b),
                        _ => Some(p),
                    },
                );
            text.push_str(&match best {
                Some((curve, (q, s))) => format!(
                    "- {budget} s: `{}`, {} after {s:.1} s\n",
                    curve.variant,
                    format_or_na(q, 3)
                ),
                None => format!("- {budget} s: no variant scored a view within it\n"),
            });
        }
    }
    let ends: Vec<(f64, f64)> = curves.iter().map(|c| c.end(quality)).collect();
    let names: Vec<&str> = curves.iter().map(|c| c.variant.as_str()).collect();
    let by_time: Vec<(f64, f64)> = ends.iter().map(|&(q, s)| (s, q)).collect();
    let by_memory: Vec<(f64, f64)> = (curves.iter().zip(&ends))
        .map(|(c, &(q, _))| (mib(c.arena_bytes), q))
        .collect();
    labelled_scatter(
        &out.join("pareto_time.png"),
        "Quality against training time (line: Pareto front)",
        "training time (s)",
        quality.label(),
        &names,
        &by_time,
        &pareto_front(&by_time),
    )?;
    labelled_scatter(
        &out.join("pareto_memory.png"),
        "Quality against memory (line: Pareto front)",
        "arena (MiB)",
        quality.label(),
        &names,
        &by_memory,
        &pareto_front(&by_memory),
    )?;
    text.push_str(
        "\n![quality against time](pareto_time.png)\n\n![quality against memory](pareto_memory.png)\n\n### Anytime curves\n\n",
    );
    // One pair of plots per knob, each with the reference variant.
    let mut knobs: Vec<&str> = Vec::new();
    for curve in curves.iter().skip(1) {
        if !knobs.contains(&knob(&curve.variant)) {
            knobs.push(knob(&curve.variant));
        }
    }
    if curves.len() == 1 {
        knobs.push(knob(&curves[0].variant));
    }
    for name in knobs {
        let members: Vec<&VariantCurve> = (curves.iter().enumerate())
            .filter(|(i, c)| *i == 0 || knob(&c.variant) == name)
            .map(|(_, c)| c)
            .collect();
        let series = |x: fn(&(u32, f64, ViewMetrics)) -> f64| -> Vec<(&str, Vec<(f64, f64)>)> {
            members
                .iter()
                .map(|c| {
                    let points = c.points.iter().map(|p| (x(p), quality.of(&p.2))).collect();
                    (c.variant.as_str(), points)
                })
                .collect()
        };
        let file = file_part(name);
        line_plot(
            &out.join(format!("anytime_{file}.png")),
            &format!("Anytime: {name}"),
            "training time (s)",
            quality.label(),
            &series(|p| p.1),
        )?;
        line_plot(
            &out.join(format!("anytime_{file}_steps.png")),
            &format!("Anytime: {name}"),
            "training step",
            quality.label(),
            &series(|p| p.0 as f64),
        )?;
        text.push_str(&format!(
            "![{name} against time](anytime_{file}.png) ![{name} against steps](anytime_{file}_steps.png)\n\n"
        ));
    }
    Ok(text)
}

/// The markdown table: a row per variant.
fn table(curves: &[VariantCurve], anytime: &Anytime) -> String {
    let quality = anytime.quality;
    let target_headers: Vec<String> = (anytime.targets.iter())
        .map(|t| format!("s to {t}"))
        .collect();
    let mut header = vec![
        "variant",
        "px",
        "steps",
        "quality",
        "change",
        "PSNR dB",
        "right dB",
        "fg dB",
        "SSIM",
        "train s",
        "change s",
        "arena MiB",
        "M samples/s",
    ];
    header.extend(target_headers.iter().map(String::as_str));
    let (q0, s0) = curves
        .first()
        .map_or((f64::NAN, f64::NAN), |c| c.end(quality));
    let signed = |v: f64, decimals: usize| {
        if v.is_finite() {
            format!("{v:+.decimals$}")
        } else {
            "n/a".into()
        }
    };
    let rows: Vec<Vec<String>> = curves
        .iter()
        .map(|c| {
            let (q, s) = c.end(quality);
            let last = c.points.last().map(|p| p.2);
            let m =
                |f: fn(&ViewMetrics) -> f64, d| format_or_na(last.as_ref().map_or(f64::NAN, f), d);
            let mut row = vec![
                c.variant.clone(),
                c.size.to_string(),
                c.points.last().map_or(0, |p| p.0).to_string(),
                format_or_na(q, 3),
                signed(q - q0, 3),
                m(|m| m.psnr_full, 2),
                m(|m| m.psnr_right, 2),
                m(|m| m.psnr_foreground, 2),
                m(|m| m.ssim_full, 4),
                format_or_na(s, 1),
                signed(s - s0, 1),
                format_or_na(mib(c.arena_bytes), 1),
                format_or_na(c.samples_per_second / 1e6, 3),
            ];
            row.extend(anytime.targets.iter().map(|&t| {
                c.time_to_reach(quality, t)
                    .map_or("not reached".into(), |s| format!("{s:.1}"))
            }));
            row
        })
        .collect();
    markdown_table(&header, &rows)
}

/// A row per task and curve point: the task, the point's step and training seconds, every
/// held-out mean, the arena and the task's samples per second.
fn csv(results: &[TaskResult], timings: &[TaskTiming]) -> String {
    let mut text = format!(
        "index,variant,seed,size,step,seconds,{METRICS_CSV_HEADER},arena_bytes,samples_per_second\n"
    );
    for (r, t) in results.iter().zip(timings) {
        let rate = r.samples as f64 / t.seconds.last().copied().unwrap_or(f64::NAN);
        for (point, seconds) in r.curve.iter().zip(&t.seconds) {
            let cells: Vec<String> = [
                r.index.to_string(),
                format!("\"{}\"", r.variant),
                r.seed.to_string(),
                r.size.to_string(),
                point.step.to_string(),
                seconds.to_string(),
            ]
            .into_iter()
            .chain(metric_cells(&point.metrics))
            .chain([
                r.arena_bytes.to_string(),
                if rate.is_finite() {
                    rate.to_string()
                } else {
                    String::new()
                },
            ])
            .collect();
            text.push_str(&cells.join(","));
            text.push('\n');
        }
    }
    text
}

#[cfg(test)]
mod tests {
    use super::*;

    fn metrics(fg: f64) -> ViewMetrics {
        ViewMetrics {
            psnr_full: fg + 10.0,
            psnr_right: fg + 9.0,
            psnr_foreground: fg,
            psnr_foreground_right: fg - 1.0,
            ssim_full: 0.9,
            ssim_right: 0.8,
            jnb_full: 1.0,
            jnb_right: 1.0,
            cpbd_full: 0.5,
        }
    }

    fn curve(points: &[(u32, f64, f64)]) -> VariantCurve {
        VariantCurve {
            variant: "v".into(),
            size: 64,
            arena_bytes: 1 << 20,
            samples_per_second: 1e6,
            points: points.iter().map(|&(n, s, q)| (n, s, metrics(q))).collect(),
        }
    }

    #[test]
    fn the_pareto_front_keeps_only_points_nothing_beats() {
        let points = [
            (10.0, 20.0), // beaten by (5, 21)
            (5.0, 21.0),
            (30.0, 25.0),
            (30.0, 24.0), // beaten by (30, 25)
            (40.0, f64::NAN),
            (2.0, 15.0),
            (5.0, 21.0), // a tie: neither beats the other
        ];
        assert_eq!(pareto_front(&points), [5, 1, 6, 2]);
        assert!(pareto_front(&[]).is_empty());
    }

    #[test]
    fn time_to_reach_and_best_within_read_the_scored_points() {
        let c = curve(&[(100, 10.0, 20.0), (200, 20.0, 26.0), (300, 30.0, 25.5)]);
        let q = Quality::PsnrForeground;
        assert_eq!(c.time_to_reach(q, 25.0), Some(20.0));
        assert_eq!(c.time_to_reach(q, 20.0), Some(10.0));
        assert_eq!(c.time_to_reach(q, 27.0), None);
        assert_eq!(c.best_within(q, 5.0), None);
        assert_eq!(c.best_within(q, 15.0), Some((20.0, 10.0)));
        // The best point within the budget, not the last one.
        assert_eq!(c.best_within(q, 100.0), Some((26.0, 20.0)));
        assert_eq!(c.end(Quality::PsnrFull), (35.5, 30.0));
    }

    #[test]
    fn vary_flags_parse_into_values_and_arrays() {
        let (key, values) = parse_vary("resolutions=[16,32,64,0],[64, 128,256,0]").unwrap();
        assert_eq!(key, "resolutions");
        assert_eq!(values.len(), 2);
        assert_eq!(
            Knob::new(&key, values[1].clone()).name,
            "resolutions=[64,128,256,0]"
        );
        let (_, values) = parse_vary("texel_update=stochastic_rounding,master_copy").unwrap();
        let words: Vec<&str> = values.iter().filter_map(|v| v.as_str()).collect();
        assert_eq!(words, ["stochastic_rounding", "master_copy"]);
        let (_, values) = parse_vary("pose_correction=true").unwrap();
        assert_eq!(values, [toml::Value::Boolean(true)]);
        for bad in [
            "features",
            "=1",
            "features=",
            "features=1,,2",
            "Features=1",
            "x=[1",
        ] {
            assert!(parse_vary(bad).is_err(), "{bad}");
        }
        let size = Knob::new("size", toml::Value::Integer(64));
        assert_eq!(
            (size.size, size.set.len(), size.name.as_str()),
            (Some(64), 0, "size=64")
        );
    }

    #[test]
    fn the_default_knobs_change_one_thing_each_and_are_valid_configs() {
        for base in [Config::DEFAULT, Config::SPACECRAFT] {
            let knobs = default_knobs(&base, 128);
            let names: Vec<&str> = knobs.iter().map(|k| k.name.as_str()).collect();
            let more_rays = format!("rays_per_batch={}", 2 * base.rays_per_batch);
            for expected in [
                "steps=1500",
                &more_rays,
                "resolutions=[16,32,64,0]",
                "features=32",
                "scales=2",
                "scales=4",
                "density_hidden=128",
                "sh_bands=2",
                "pose_correction=true",
                "size=64",
                "size=256",
                "texel_update=stochastic_rounding",
                "occupancy_res=32",
                "max_samples_per_ray=64",
            ] {
                assert!(names.contains(&expected), "{expected} not in {names:?}");
            }
            for k in &knobs {
                let config =
                    crate::train::with_overrides(Path::new(""), "", &base, &k.set).unwrap();
                assert_ne!((config, k.size), (base, None), "{} changes nothing", k.name);
            }
        }
    }

    #[test]
    fn knobs_are_the_names_before_the_equals_sign() {
        assert_eq!(knob("rays_per_batch=2048"), "rays_per_batch");
        assert_eq!(knob("size = 64"), "size");
        assert_eq!(knob("ours + pose"), "ours + pose");
        assert_eq!(file_part("ours + pose"), "ours___pose");
    }
}
