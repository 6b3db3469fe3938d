//! Stacked bar charts (the bitmap font for the text, plain rectangles for the bars).

use super::canvas::{Canvas, GLYPH_HEIGHT, INK, Rgb, TICK_LENGTH, text_width};
use super::plot::tick_labels;
use crate::error::Result;
use crate::io;
use plotters::coord::types::RangedCoordf64;
use plotters::prelude::Ranged;

const WIDTH: usize = 1100;
const HEIGHT: usize = 520;
const TEXT_SCALE: usize = 2;
const SWATCH: usize = 16;
const LEGEND_ROW: usize = 22;
const GRID: Rgb = [225, 225, 225];
/// Tableau 20's strong and light tones, alternating, so neighbouring segments differ.
const SEGMENT_COLOURS: [Rgb; 14] = [
    [31, 119, 180],
    [255, 127, 14],
    [44, 160, 44],
    [214, 39, 40],
    [148, 103, 189],
    [140, 86, 75],
    [227, 119, 194],
    [127, 127, 127],
    [188, 189, 34],
    [23, 190, 207],
    [174, 199, 232],
    [255, 187, 120],
    [152, 223, 138],
    [255, 152, 150],
];

/// A PNG of vertical stacked bars: bar `b` stacks `bars[b].1[s]` for each segment `s` (named
/// `segments[s]`, one colour each, cycling after fourteen; the legend to the right), from the
/// bottom up. Non-finite and negative values count as 0. The y axis starts at 0 and is
/// labelled `y_label`; each bar's name is printed under it. Written atomically.
pub fn stacked_bars(
    path: &std::path::Path,
    title: &str,
    y_label: &str,
    segments: &[&str],
    bars: &[(&str, Vec<f64>)],
) -> Result<()> {
    let clean = |v: f64| if v.is_finite() { v.max(0.0) } else { 0.0 };
    let tallest = bars
        .iter()
        .map(|(_, values)| values.iter().copied().map(clean).sum::<f64>())
        .fold(0.0f64, f64::max);
    let top_value = if tallest > 0.0 { tallest * 1.05 } else { 1.0 };
    let axis = RangedCoordf64::from(0.0..top_value);
    let ticks = axis.key_points(6usize);
    let labels = tick_labels(&ticks);

    let text_height = GLYPH_HEIGHT * TEXT_SCALE;
    let widest = |texts: &mut dyn Iterator<Item = &str>| {
        texts.map(|t| text_width(t, TEXT_SCALE)).max().unwrap_or(0)
    };
    let tick_label_width = widest(&mut labels.iter().map(String::as_str));
    let legend_width = SWATCH + 8 + widest(&mut segments.iter().copied());
    let left = 10 + text_height + 12 + tick_label_width + 6 + TICK_LENGTH;
    let right = WIDTH.saturating_sub(16 + legend_width + 16);
    let top = 12 + text_height + 16;
    let bottom = HEIGHT - (8 + text_height + 12 + text_height + 10);
    let plot_height = (bottom - top) as f64;
    let row_of = |v: f64| bottom - ((v / top_value) * plot_height).round() as usize;

    let mut pixels = vec![255u8; WIDTH * HEIGHT * 3];
    let mut canvas = Canvas {
        pixels: &mut pixels,
        width: WIDTH,
        height: HEIGHT,
    };
    for (&tick, label) in ticks.iter().zip(&labels) {
        let row = row_of(tick);
        canvas.fill_rect(left, row, right - left, 1, GRID);
        canvas.fill_rect(left - TICK_LENGTH, row, TICK_LENGTH, 1, INK);
        let label_left = left - TICK_LENGTH - 6 - text_width(label, TEXT_SCALE);
        canvas.text(
            label_left,
            row.saturating_sub(text_height / 2),
            label,
            TEXT_SCALE,
            INK,
        );
    }
    let slot = (right - left) / bars.len().max(1);
    let bar_width = slot * 3 / 5;
    for (b, (name, values)) in bars.iter().enumerate() {
        let x = left + b * slot + (slot - bar_width) / 2;
        let mut base = 0.0;
        for (s, &v) in values.iter().enumerate() {
            let (low, high) = (row_of(base), row_of(base + clean(v)));
            let colour = SEGMENT_COLOURS[s % SEGMENT_COLOURS.len()];
            canvas.fill_rect(x, high, bar_width, low - high, colour);
            base += clean(v);
        }
        let centre = x + bar_width / 2;
        let label_left = centre.saturating_sub(text_width(name, TEXT_SCALE) / 2);
        canvas.text(label_left, bottom + 8, name, TEXT_SCALE, INK);
    }
    // The axes over the bars' ends.
    canvas.fill_rect(left, top, 1, bottom - top + 1, INK);
    canvas.fill_rect(left, bottom, right - left, 1, INK);

    let centre = (left + right) / 2;
    let centred = |text: &str| centre.saturating_sub(text_width(text, TEXT_SCALE) / 2);
    canvas.text(centred(title), 12, title, TEXT_SCALE, INK);
    let y_label_bottom = (top + bottom + text_width(y_label, TEXT_SCALE)) / 2;
    canvas.text_up(10, y_label_bottom, y_label, TEXT_SCALE, INK);
    let swatch_left = right + 16;
    // The legend lists the segments top-down in the order they are stacked bottom-up.
    for (s, name) in segments.iter().enumerate() {
        let row = top + (segments.len() - 1 - s) * LEGEND_ROW;
        let colour = SEGMENT_COLOURS[s % SEGMENT_COLOURS.len()];
        canvas.fill_rect(swatch_left, row, SWATCH, text_height, colour);
        canvas.text(swatch_left + SWATCH + 8, row, name, TEXT_SCALE, INK);
    }
    io::write_png(path, WIDTH as u32, HEIGHT as u32, 3, &pixels)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stacked_bars_draw_every_segment() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("bars.png");
        let bars = [
            ("step", vec![1.0, 2.0, 3.0]),
            ("view", vec![0.5, f64::NAN, 4.0]),
        ];
        stacked_bars(&path, "time", "ms", &["a", "b", "c"], &bars).unwrap();
        let image = image::open(&path).unwrap().to_rgb8();
        assert_eq!(image.dimensions(), (WIDTH as u32, HEIGHT as u32));
        for colour in &SEGMENT_COLOURS[..3] {
            let count = image.pixels().filter(|p| p.0 == *colour).count();
            assert!(count > 500, "segment colour {colour:?}: {count} pixels");
        }
        let empty = dir.path().join("empty.png");
        stacked_bars(&empty, "none", "ms", &[], &[]).unwrap();
        assert!(image::open(&empty).is_ok());
    }
}
