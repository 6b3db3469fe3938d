//! Side-by-side comparison strips of captioned tiles.

use super::canvas::{Canvas, GLYPH_ADVANCE, GLYPH_HEIGHT, INK, Rgb, text_width};

/// Pixels between tiles in [`side_by_side`].
const TILE_GAP: usize = 2;
const STRIP_BACKGROUND: Rgb = [255, 255, 255];
/// Captions wrap onto at most this many lines before their scale is reduced.
const MAX_CAPTION_LINES: usize = 2;

/// The tiles (RGB8, each `width x height`) in one row, 2 px apart on a white background, each
/// with a caption band above it holding its label, centred. Returns `(width, height, RGB8
/// pixels)` of the strip.
///
/// Captions are drawn at one scale for the whole strip, the largest that grows with the tile
/// (2x, 10x14-px glyphs, for 128-px tiles) at which every label fits its tile on at most two
/// lines, wrapping at spaces; at 1x, what still does not fit is cut. No tiles give an empty
/// `(0, 0, [])` image.
///
/// # Panics
/// When a tile's buffer is not `width * height * 3` bytes: that is a caller bug, not input.
pub fn side_by_side(tiles: &[(&str, &[u8])], width: u32, height: u32) -> (u32, u32, Vec<u8>) {
    if tiles.is_empty() {
        return (0, 0, Vec::new());
    }
    let (tile_width, tile_height) = (width as usize, height as usize);
    let (scale, captions) = layout_captions(tiles.iter().map(|(label, _)| *label), tile_width);
    let padding = 2 * scale;
    let line_pitch = (GLYPH_HEIGHT + 2) * scale;
    let lines = captions.iter().map(Vec::len).max().unwrap_or(0).max(1);
    let band = 2 * padding + lines * line_pitch - 2 * scale;
    let strip_width = tiles.len() * tile_width + (tiles.len() - 1) * TILE_GAP;
    let strip_height = band + tile_height;
    let mut pixels = STRIP_BACKGROUND.repeat(strip_width * strip_height);
    let mut canvas = Canvas {
        pixels: &mut pixels,
        width: strip_width,
        height: strip_height,
    };
    let row_bytes = tile_width * 3;
    for (index, ((label, tile), caption)) in tiles.iter().zip(&captions).enumerate() {
        assert_eq!(
            tile.len(),
            row_bytes * tile_height,
            "tile {index} ({label:?}) is not a {tile_width}x{tile_height} RGB8 image"
        );
        let left = index * (tile_width + TILE_GAP);
        for row in 0..tile_height {
            let start = ((band + row) * strip_width + left) * 3;
            canvas.pixels[start..start + row_bytes]
                .copy_from_slice(&tile[row * row_bytes..(row + 1) * row_bytes]);
        }
        for (line_index, line) in caption.iter().enumerate() {
            let x = left + tile_width.saturating_sub(text_width(line, scale)) / 2;
            let y = padding + line_index * line_pitch;
            canvas.text(x, y, line, scale, INK);
        }
    }
    (strip_width as u32, strip_height as u32, pixels)
}

/// The caption scale, from 1 up to one step per 64 px of tile width (at most 4), and each
/// label's lines at that scale: the largest scale at which every label wraps onto at most
/// [`MAX_CAPTION_LINES`] lines, keeping a one-glyph-pixel margin on each side.
fn layout_captions<'a>(
    labels: impl Iterator<Item = &'a str> + Clone,
    tile_width: usize,
) -> (usize, Vec<Vec<String>>) {
    let largest = (tile_width / 64).clamp(1, 4);
    let wrap_all = |scale: usize| -> Vec<Vec<String>> {
        let max_chars = (tile_width / scale).saturating_sub(1) / GLYPH_ADVANCE;
        labels
            .clone()
            .map(|label| wrap_caption(label, max_chars))
            .collect()
    };
    for scale in (2..=largest).rev() {
        let captions = wrap_all(scale);
        if captions
            .iter()
            .all(|lines| lines.len() <= MAX_CAPTION_LINES)
        {
            return (scale, captions);
        }
    }
    let mut captions = wrap_all(1);
    for lines in &mut captions {
        lines.truncate(MAX_CAPTION_LINES);
    }
    (1, captions)
}

/// `label` broken at spaces into lines of at most `max_chars` characters; a word longer than
/// a line is cut to fit.
fn wrap_caption(label: &str, max_chars: usize) -> Vec<String> {
    let mut lines = Vec::new();
    if max_chars == 0 {
        return lines;
    }
    let mut current = String::new();
    for word in label.split_whitespace() {
        let word: String = word.chars().take(max_chars).collect();
        if current.is_empty() {
            current = word;
        } else if current.chars().count() + 1 + word.chars().count() <= max_chars {
            current.push(' ');
            current.push_str(&word);
        } else {
            lines.push(std::mem::replace(&mut current, word));
        }
    }
    if !current.is_empty() {
        lines.push(current);
    }
    lines
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn side_by_side_lays_out_captioned_tiles() {
        let (w, h) = (128usize, 96usize);
        let red = [200u8, 0, 0].repeat(w * h);
        let green = [0u8, 200, 0].repeat(w * h);
        let blue = [0u8, 0, 200].repeat(w * h);
        let (sw, sh, pixels) = side_by_side(
            &[
                ("reference", red.as_slice()),
                ("baseline", green.as_slice()),
                ("ours + pose", blue.as_slice()),
            ],
            w as u32,
            h as u32,
        );
        let band = sh as usize - h;
        assert_eq!(sw as usize, 3 * w + 2 * TILE_GAP);
        assert_eq!(pixels.len(), (sw * sh * 3) as usize);
        // 2x captions on 128-px tiles, "ours + pose" on two lines: 2 x 14-px glyphs, 4 px
        // between the lines, 4 px of padding above and below.
        assert_eq!(band, 2 * 14 + 4 + 8);
        let at = |x: usize, y: usize| {
            let i = (y * sw as usize + x) * 3;
            [pixels[i], pixels[i + 1], pixels[i + 2]]
        };
        for (tile, colour) in [[200, 0, 0], [0, 200, 0], [0, 0, 200]].iter().enumerate() {
            let left = tile * (w + TILE_GAP);
            assert_eq!(at(left, band), *colour);
            assert_eq!(at(left + w - 1, sh as usize - 1), *colour);
            let inked = (0..band)
                .flat_map(|y| (left..left + w).map(move |x| (x, y)))
                .filter(|&(x, y)| at(x, y) != STRIP_BACKGROUND)
                .count();
            assert!(inked > 50, "tile {tile}: {inked} caption pixels");
        }
        assert_eq!(at(w, band + 10), STRIP_BACKGROUND, "gap between tiles");
        assert_eq!(side_by_side(&[], 8, 8), (0, 0, Vec::new()));
    }

    #[test]
    fn long_captions_wrap_then_shrink_then_cut() {
        assert_eq!(
            wrap_caption("a caption far too long for the tile", 10),
            ["a caption", "far too", "long for", "the tile"]
        );
        assert_eq!(wrap_caption("supercalifragilistic", 5), ["super"]);
        assert!(wrap_caption("x", 0).is_empty());
        let labels = ["reference", "ours + pose"];
        assert_eq!(
            layout_captions(labels.into_iter(), 128),
            (
                2,
                vec![
                    vec!["reference".to_string()],
                    vec!["ours +".into(), "pose".into()]
                ]
            )
        );
        // Three lines at 2x on a 128-px tile: drop to 1x, where two do.
        let (scale, captions) = layout_captions(["one two three four five six"].into_iter(), 128);
        assert_eq!(scale, 1);
        assert_eq!(captions, [["one two three four", "five six"]]);

        let tile = vec![0u8; 64 * 16 * 3];
        let label = "a caption far too long for the tile";
        let (sw, sh, _) = side_by_side(&[(label, tile.as_slice())], 64, 16);
        // 1x on a 64-px tile, cut to two lines: 2 x 7-px glyphs, 2 px between, 2 + 2 padding.
        assert_eq!((sw, sh), (64, 16 + 2 * 7 + 2 + 4));
    }
}
