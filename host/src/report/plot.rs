//! Line plots (plotters draws the geometry, the bitmap font the text).

use super::canvas::{Canvas, GLYPH_HEIGHT, INK, TICK_LENGTH, text_width};
use crate::error::{HostError, Result};
use crate::io;
use plotters::coord::Shift;
use plotters::coord::types::RangedCoordf64;
use plotters::prelude::*;
use std::ops::Range;
use std::path::Path;

const PLOT_WIDTH: usize = 800;
const PLOT_HEIGHT: usize = 480;
/// Text is drawn at 2x (10x14-px glyphs): legible in a PNG viewer without zooming.
const PLOT_TEXT_SCALE: usize = 2;
const LEGEND_SWATCH: usize = 24;
const LEGEND_ROW: usize = 24;
/// Series with at most this many points also get a dot at each point, so a sweep over a few
/// settings (noise levels, image counts) shows where the measurements are.
const MARKER_LIMIT: usize = 30;
const GRID: RGBColor = RGBColor(225, 225, 225);
/// Tableau 10: distinct for most colour-vision deficiencies, and on a white background.
const PALETTE: [RGBColor; 10] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(214, 39, 40),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(127, 127, 127),
    RGBColor(188, 189, 34),
    RGBColor(23, 190, 207),
];

/// An 800x480 PNG line plot of `series` (name, points): a framed plot area with grid lines,
/// ticks and tick labels on both axes, a title, axis labels, and a legend to the right with
/// one colour per series (cycling after ten). Non-finite points are left out; with no finite
/// point at all the axes run 0..1. Written atomically with [`io::write_png`].
pub fn line_plot(
    path: &Path,
    title: &str,
    x_label: &str,
    y_label: &str,
    series: &[(&str, Vec<(f64, f64)>)],
) -> Result<()> {
    let styled: Vec<Series> = (series.iter().enumerate())
        .map(|(i, (name, points))| Series {
            name,
            points: points.clone(),
            line: true,
            colour: PALETTE[i % PALETTE.len()],
        })
        .collect();
    plot(path, title, x_label, y_label, &styled, &[])
}

/// Colour of the points off the front in [`labelled_scatter`].
const OFF_FRONT: RGBColor = RGBColor(127, 127, 127);

/// A PNG scatter plot of named points (`names[i]` at `points[i]`, each name printed beside its
/// point), the points with indices in `front` joined by a line in their order (a Pareto
/// front), the rest grey; axes, ticks, title and legend as in [`line_plot`].
pub fn labelled_scatter(
    path: &Path,
    title: &str,
    x_label: &str,
    y_label: &str,
    names: &[&str],
    points: &[(f64, f64)],
    front: &[usize],
) -> Result<()> {
    let series = [
        Series {
            name: "Pareto front",
            points: front
                .iter()
                .filter_map(|&i| points.get(i).copied())
                .collect(),
            line: true,
            colour: PALETTE[0],
        },
        Series {
            name: "other",
            points: (0..points.len())
                .filter(|i| !front.contains(i))
                .map(|i| points[i])
                .collect(),
            line: false,
            colour: OFF_FRONT,
        },
    ];
    let labels: Vec<((f64, f64), &str)> =
        points.iter().copied().zip(names.iter().copied()).collect();
    plot(path, title, x_label, y_label, &series, &labels)
}

/// One series of [`plot`]: its points joined by a line or not.
struct Series<'a> {
    name: &'a str,
    points: Vec<(f64, f64)>,
    line: bool,
    colour: RGBColor,
}

/// Point labels are printed at 1x (5x7-px glyphs), beside their points.
const POINT_LABEL_SCALE: usize = 1;

fn plot(
    path: &Path,
    title: &str,
    x_label: &str,
    y_label: &str,
    series: &[Series],
    labels: &[((f64, f64), &str)],
) -> Result<()> {
    let finite: Vec<Vec<(f64, f64)>> = series
        .iter()
        .map(|Series { points, .. }| {
            points
                .iter()
                .copied()
                .filter(|(x, y)| x.is_finite() && y.is_finite())
                .collect()
        })
        .collect();
    // A little room at the sides keeps end markers and lines off the frame.
    let x_range = data_range(finite.iter().flatten().map(|p| p.0), 0.02);
    let y_range = data_range(finite.iter().flatten().map(|p| p.1), 0.05);
    let x_ticks = RangedCoordf64::from(x_range.clone()).key_points(8usize);
    let y_ticks = RangedCoordf64::from(y_range.clone()).key_points(6usize);
    let x_tick_labels = tick_labels(&x_ticks);
    let y_tick_labels = tick_labels(&y_ticks);

    let text_height = GLYPH_HEIGHT * PLOT_TEXT_SCALE;
    let y_tick_label_width = widest_text(y_tick_labels.iter().map(String::as_str));
    let legend_width = LEGEND_SWATCH + 8 + widest_text(series.iter().map(|s| s.name));
    let margins = PlotMargins {
        top: 12 + text_height + 14,
        bottom: TICK_LENGTH + 6 + text_height + 12 + text_height + 10,
        left: 10 + text_height + 12 + y_tick_label_width + 6 + TICK_LENGTH,
        right: 16 + legend_width + 10,
    };

    let mut pixels = vec![255u8; PLOT_WIDTH * PLOT_HEIGHT * 3];
    let frame = {
        let size = (PLOT_WIDTH as u32, PLOT_HEIGHT as u32);
        let root = BitMapBackend::with_buffer(&mut pixels, size).into_drawing_area();
        let geometry = PlotGeometry {
            margins: &margins,
            x_range,
            y_range,
            x_ticks: &x_ticks,
            y_ticks: &y_ticks,
            series: &finite,
            styles: series,
        };
        draw_plot_geometry(&root, &geometry)
            .and_then(|frame| root.present().map(|()| frame))
            .map_err(|e| HostError::invalid(path, format!("drawing the plot failed: {e}")))?
    };

    let mut canvas = Canvas {
        pixels: &mut pixels,
        width: PLOT_WIDTH,
        height: PLOT_HEIGHT,
    };
    let centred_at =
        |text: &str, centre: usize| centre.saturating_sub(text_width(text, PLOT_TEXT_SCALE) / 2);
    let plot_centre = (frame.left + frame.right) / 2;
    canvas.text(
        centred_at(title, plot_centre),
        12,
        title,
        PLOT_TEXT_SCALE,
        INK,
    );
    let x_tick_label_top = frame.bottom + TICK_LENGTH + 6;
    for (label, &x) in x_tick_labels.iter().zip(&frame.x_ticks) {
        let left = centred_at(label, x);
        canvas.text(left, x_tick_label_top, label, PLOT_TEXT_SCALE, INK);
    }
    for (label, &y) in y_tick_labels.iter().zip(&frame.y_ticks) {
        let left = frame.left - TICK_LENGTH - 6 - text_width(label, PLOT_TEXT_SCALE);
        let top = y.saturating_sub(text_height / 2);
        canvas.text(left, top, label, PLOT_TEXT_SCALE, INK);
    }
    canvas.text(
        centred_at(x_label, plot_centre),
        x_tick_label_top + text_height + 12,
        x_label,
        PLOT_TEXT_SCALE,
        INK,
    );
    let y_label_bottom = (frame.top + frame.bottom + text_width(y_label, PLOT_TEXT_SCALE)) / 2;
    canvas.text_up(10, y_label_bottom, y_label, PLOT_TEXT_SCALE, INK);
    for &((x, y), label) in labels {
        if let Some((column, row)) = frame.pixel_of(x, y) {
            // Right of the point, or left of it where the text would cross the frame.
            let width = text_width(label, POINT_LABEL_SCALE);
            let left = if column + 5 + width > frame.right {
                column.saturating_sub(5 + width)
            } else {
                column + 5
            };
            canvas.text(left, row.saturating_sub(9), label, POINT_LABEL_SCALE, INK);
        }
    }
    let swatch_left = frame.right + 16;
    // Rows that would run off the image are left out of the legend.
    let rows = (PLOT_HEIGHT.saturating_sub(frame.top + 4 + text_height)) / LEGEND_ROW + 1;
    for (index, Series { name, colour, .. }) in series.iter().enumerate().take(rows) {
        let RGBColor(r, g, b) = *colour;
        let top = frame.top + 4 + index * LEGEND_ROW;
        let swatch_top = top + text_height / 2 - 2;
        canvas.fill_rect(swatch_left, swatch_top, LEGEND_SWATCH, 4, [r, g, b]);
        let label_left = swatch_left + LEGEND_SWATCH + 8;
        canvas.text(label_left, top, name, PLOT_TEXT_SCALE, INK);
    }
    io::write_png(path, PLOT_WIDTH as u32, PLOT_HEIGHT as u32, 3, &pixels)
}

fn widest_text<'a>(texts: impl Iterator<Item = &'a str>) -> usize {
    texts
        .map(|text| text_width(text, PLOT_TEXT_SCALE))
        .max()
        .unwrap_or(0)
}

/// Space around the plot area, in pixels, for text and the legend.
struct PlotMargins {
    top: usize,
    bottom: usize,
    left: usize,
    right: usize,
}

/// What [`draw_plot_geometry`] draws: everything but text.
struct PlotGeometry<'a> {
    margins: &'a PlotMargins,
    x_range: Range<f64>,
    y_range: Range<f64>,
    x_ticks: &'a [f64],
    y_ticks: &'a [f64],
    series: &'a [Vec<(f64, f64)>],
    styles: &'a [Series<'a>],
}

/// Where the plot frame and the ticks landed, in pixels, for placing text around them.
struct PlotFrame {
    left: usize,
    top: usize,
    right: usize,
    bottom: usize,
    /// Column of each x tick.
    x_ticks: Vec<usize>,
    /// Row of each y tick.
    y_ticks: Vec<usize>,
    x_range: Range<f64>,
    y_range: Range<f64>,
}

impl PlotFrame {
    /// The pixel of data point `(x, y)`, `None` when it is not finite or outside the frame.
    fn pixel_of(&self, x: f64, y: f64) -> Option<(usize, usize)> {
        let fx = (x - self.x_range.start) / (self.x_range.end - self.x_range.start);
        let fy = (y - self.y_range.start) / (self.y_range.end - self.y_range.start);
        ((0.0..=1.0).contains(&fx) && (0.0..=1.0).contains(&fy)).then(|| {
            let column = self.left as f64 + fx * (self.right - self.left) as f64;
            let row = self.bottom as f64 - fy * (self.bottom - self.top) as f64;
            (column.round() as usize, row.round() as usize)
        })
    }
}

/// Grid, series, plot frame and tick marks, drawn with plotters. Plotters draws no text here:
/// this build has no font backend for it.
fn draw_plot_geometry<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    geometry: &PlotGeometry,
) -> std::result::Result<PlotFrame, DrawingAreaErrorKind<DB::ErrorType>> {
    let margins = geometry.margins;
    root.fill(&WHITE)?;
    let area = root.margin(
        margins.top as i32,
        margins.bottom as i32,
        margins.left as i32,
        margins.right as i32,
    );
    let mut chart = ChartBuilder::on(&area)
        .build_cartesian_2d(geometry.x_range.clone(), geometry.y_range.clone())?;
    let (x0, x1) = (geometry.x_range.start, geometry.x_range.end);
    let (y0, y1) = (geometry.y_range.start, geometry.y_range.end);
    let vertical_grid = geometry
        .x_ticks
        .iter()
        .map(|&x| PathElement::new(vec![(x, y0), (x, y1)], GRID));
    let horizontal_grid = geometry
        .y_ticks
        .iter()
        .map(|&y| PathElement::new(vec![(x0, y), (x1, y)], GRID));
    chart.draw_series(vertical_grid.chain(horizontal_grid))?;
    for (points, style) in geometry.series.iter().zip(geometry.styles) {
        let colour = style.colour;
        if style.line {
            chart.draw_series(LineSeries::new(
                points.iter().copied(),
                colour.stroke_width(2),
            ))?;
        }
        if points.len() <= MARKER_LIMIT || !style.line {
            let markers = points
                .iter()
                .map(|&point| Circle::new(point, 3, colour.filled()));
            chart.draw_series(markers)?;
        }
    }

    // The frame goes exactly through the data range's corners, so the ticks sit on it.
    let (left, top) = chart.backend_coord(&(x0, y1));
    let (right, bottom) = chart.backend_coord(&(x1, y0));
    root.draw(&Rectangle::new([(left, top), (right, bottom)], BLACK))?;
    let tick = TICK_LENGTH as i32;
    let mut x_ticks = Vec::with_capacity(geometry.x_ticks.len());
    for &x in geometry.x_ticks {
        let (column, _) = chart.backend_coord(&(x, y0));
        root.draw(&PathElement::new(
            vec![(column, bottom), (column, bottom + tick)],
            BLACK,
        ))?;
        x_ticks.push(column.max(0) as usize);
    }
    let mut y_ticks = Vec::with_capacity(geometry.y_ticks.len());
    for &y in geometry.y_ticks {
        let (_, row) = chart.backend_coord(&(x0, y));
        root.draw(&PathElement::new(
            vec![(left - tick, row), (left, row)],
            BLACK,
        ))?;
        y_ticks.push(row.max(0) as usize);
    }
    let pixel = |v: i32| v.max(0) as usize;
    Ok(PlotFrame {
        left: pixel(left),
        top: pixel(top),
        right: pixel(right),
        bottom: pixel(bottom),
        x_ticks,
        y_ticks,
        x_range: geometry.x_range.clone(),
        y_range: geometry.y_range.clone(),
    })
}

/// `min..max` of the values widened by `padding` of the span on each side; a single value is
/// widened to a span of 1 (or 10 % of its size), and no values give `0..1`.
fn data_range(values: impl Iterator<Item = f64>, padding: f64) -> Range<f64> {
    let (lo, hi) = values.fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
        (lo.min(v), hi.max(v))
    });
    if lo > hi {
        return 0.0..1.0;
    }
    let span = hi - lo;
    if span <= f64::EPSILON * hi.abs().max(lo.abs()) {
        let half = (0.05 * lo.abs()).max(0.5);
        return lo - half..hi + half;
    }
    lo - padding * span..hi + padding * span
}

/// Tick values printed with the fewest decimals (up to 6) that keep them distinct and exact to
/// a millionth of the tick spacing; scientific notation for very large or very small values.
pub(super) fn tick_labels(ticks: &[f64]) -> Vec<String> {
    let spacing = ticks
        .windows(2)
        .map(|pair| (pair[1] - pair[0]).abs())
        .fold(f64::INFINITY, f64::min);
    let magnitude = ticks.iter().fold(0.0f64, |m, t| m.max(t.abs()));
    let scientific = magnitude >= 1e6 || (magnitude > 0.0 && magnitude < 1e-3);
    let unit = if spacing.is_finite() && spacing > 0.0 {
        spacing
    } else {
        magnitude.max(1.0)
    };
    let exact = |decimals: usize| {
        ticks.iter().all(|&t| {
            let shown: f64 = format!("{t:.decimals$}").parse().unwrap_or(f64::NAN);
            (shown - t).abs() <= 1e-6 * unit
        })
    };
    let decimals = (0..=6).find(|&d| exact(d));
    ticks
        .iter()
        // Adding 0.0 turns -0.0 into 0.0, so no tick reads "-0".
        .map(|&t| match decimals {
            Some(d) if !scientific => format!("{:.d$}", t + 0.0),
            _ => format!("{:.2e}", t + 0.0),
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn line_plot_writes_a_readable_png() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("plots/psnr.png");
        let steps = |f: fn(f64) -> f64| -> Vec<(f64, f64)> {
            (0..=40).map(|i| (i as f64 * 250.0, f(i as f64))).collect()
        };
        let series = [
            (
                "baseline",
                steps(|i| 14.0 + 8.0 * (1.0 - (-i / 10.0).exp())),
            ),
            ("ours", steps(|i| 15.0 + 15.0 * (1.0 - (-i / 8.0).exp()))),
            (
                "ours + pose",
                vec![(0.0, 16.0), (5000.0, 29.0), (10000.0, f64::NAN)],
            ),
        ];
        line_plot(&path, "PSNR while training", "step", "PSNR (dB)", &series).unwrap();
        let image = image::open(&path).unwrap().to_rgb8();
        assert_eq!(image.dimensions(), (PLOT_WIDTH as u32, PLOT_HEIGHT as u32));
        for RGBColor(r, g, b) in &PALETTE[..3] {
            let count = image.pixels().filter(|p| p.0 == [*r, *g, *b]).count();
            assert!(count > 40, "series colour {:?}: {count} pixels", (r, g, b));
        }
        let ink = image.pixels().filter(|p| p.0 == INK).count();
        assert!(ink > 2000, "text and axes: {ink} black pixels");

        // Degenerate input still gives a plot rather than an error.
        let flat = dir.path().join("flat.png");
        line_plot(
            &flat,
            "empty",
            "x",
            "y",
            &[("none", vec![]), ("one", vec![(1.0, 2.0)])],
        )
        .unwrap();
        assert!(image::open(&flat).is_ok());
    }

    #[test]
    fn tick_labels_use_just_enough_decimals() {
        assert_eq!(tick_labels(&[0.0, 0.25, 0.5]), ["0.00", "0.25", "0.50"]);
        assert_eq!(tick_labels(&[-5000.0, 0.0, 5000.0]), ["-5000", "0", "5000"]);
        assert_eq!(tick_labels(&[-0.0, 1.0]), ["0", "1"]);
        assert_eq!(tick_labels(&[0.0, 2e6]), ["0.00e0", "2.00e6"]);
        assert_eq!(data_range([3.0].into_iter(), 0.05), 2.5..3.5);
        assert_eq!(data_range(std::iter::empty(), 0.05), 0.0..1.0);
    }
}
