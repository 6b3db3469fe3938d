//! Edge maps and widths: scikit-image's Canny, Octave's thinned Sobel and Marziliano widths.

use super::filters::{Axis, Border, Plane, border_index, gaussian_filter, gaussian_kernel, sobel};
use std::collections::VecDeque;

/// Marziliano widths stop growing after this many steps on each side.
const MAX_HALF_WIDTH_STEPS: usize = 100;

/// scikit-image's `feature.canny` with its defaults (sigma 1, zero padding corrected for the
/// weight lost over the border, hysteresis thresholds 0.1 and 0.2 in the units of the input),
/// applied to 0..255 gray levels as cpbd does, which makes nearly every gradient ridge an edge.
pub(super) fn canny(gray: &Plane) -> Vec<bool> {
    // Defaults of skimage.filters.gaussian: sigma 1 truncated at 4 sigma.
    let kernel = gaussian_kernel(1.0, 4);
    let ones = Plane {
        width: gray.width,
        height: gray.height,
        values: vec![1.0; gray.values.len()],
    };
    let bleed = gaussian_filter(&ones, &kernel, Border::Zero);
    let mut smoothed = gaussian_filter(gray, &kernel, Border::Zero);
    for (s, b) in smoothed.values.iter_mut().zip(&bleed.values) {
        *s /= b + f64::EPSILON;
    }
    let isobel = sobel(&smoothed, Axis::Vertical);
    let jsobel = sobel(&smoothed, Axis::Horizontal);
    let magnitude: Vec<f64> = isobel
        .values
        .iter()
        .zip(&jsobel.values)
        .map(|(i, j)| (i * i + j * j).sqrt())
        .collect();

    // skimage passes the low threshold through a C `float`.
    let low = 0.1f32 as f64;
    let high = 0.2;
    let suppressed = nonmaximum_suppression(
        gray.width,
        gray.height,
        &isobel.values,
        &jsobel.values,
        &magnitude,
        low,
    );
    hysteresis(gray.width, gray.height, &suppressed, high)
}

/// skimage's `_nonmaximum_suppression_bilinear`: keep a pixel's magnitude when it is at least
/// the bilinearly interpolated magnitude on both sides along the gradient. Border pixels are
/// never edges.
fn nonmaximum_suppression(
    width: usize,
    height: usize,
    isobel: &[f64],
    jsobel: &[f64],
    magnitude: &[f64],
    low: f64,
) -> Vec<f64> {
    let mut out = vec![0.0; magnitude.len()];
    let at = |r: usize, c: usize| magnitude[r * width + c];
    for r in 1..height.saturating_sub(1) {
        for c in 1..width.saturating_sub(1) {
            let i = r * width + c;
            let m = magnitude[i];
            if m < low {
                continue;
            }
            let (gi, gj) = (isobel[i], jsobel[i]);
            let is_down = gi <= 0.0;
            let is_left = gj <= 0.0;
            let (ai, aj) = (gi.abs(), gj.abs());
            let keep = |w: f64, plus: (f64, f64), minus: (f64, f64)| {
                plus.1 * w + plus.0 * (1.0 - w) <= m && minus.1 * w + minus.0 * (1.0 - w) <= m
            };
            let maximal = if is_down == is_left {
                // Gradient in the first or third quadrant.
                if ai > aj {
                    keep(
                        aj / ai,
                        (at(r + 1, c), at(r + 1, c + 1)),
                        (at(r - 1, c), at(r - 1, c - 1)),
                    )
                } else {
                    keep(
                        ai / aj,
                        (at(r, c + 1), at(r + 1, c + 1)),
                        (at(r, c - 1), at(r - 1, c - 1)),
                    )
                }
            } else if ai < aj {
                keep(
                    ai / aj,
                    (at(r, c + 1), at(r - 1, c + 1)),
                    (at(r, c - 1), at(r + 1, c - 1)),
                )
            } else {
                keep(
                    aj / ai,
                    (at(r - 1, c), at(r - 1, c + 1)),
                    (at(r + 1, c), at(r + 1, c - 1)),
                )
            };
            if maximal {
                out[i] = m;
            }
        }
    }
    out
}

/// Keep the 8-connected groups of non-zero suppressed magnitudes that reach `high` somewhere.
fn hysteresis(width: usize, height: usize, suppressed: &[f64], high: f64) -> Vec<bool> {
    let mut edge = vec![false; suppressed.len()];
    let mut queue = VecDeque::new();
    for (i, &m) in suppressed.iter().enumerate() {
        if m >= high && !edge[i] {
            edge[i] = true;
            queue.push_back(i);
            while let Some(j) = queue.pop_front() {
                let (r, c) = ((j / width) as isize, (j % width) as isize);
                for (dr, dc) in NEIGHBOURS_8 {
                    let (nr, nc) = (r + dr, c + dc);
                    if nr < 0 || nc < 0 || nr >= height as isize || nc >= width as isize {
                        continue;
                    }
                    let k = nr as usize * width + nc as usize;
                    if suppressed[k] > 0.0 && !edge[k] {
                        edge[k] = true;
                        queue.push_back(k);
                    }
                }
            }
        }
    }
    edge
}

const NEIGHBOURS_8: [(isize, isize); 8] = [
    (-1, -1),
    (-1, 0),
    (-1, 1),
    (0, -1),
    (0, 1),
    (1, -1),
    (1, 0),
    (1, 1),
];

/// cpbd's Octave-style Sobel: squared response of the horizontal-derivative Sobel kernel
/// (normalised to unit absolute sum), zeroed at or below `2 sqrt(mean)`, then thinned to pixels
/// that are strict maxima horizontally or vertically (zero beyond the image).
pub(super) fn octave_sobel_edges(gray: &Plane) -> Vec<bool> {
    let (w, h) = (gray.width, gray.height);
    let mut strength = vec![0.0; w * h];
    for r in 0..h {
        for c in 0..w {
            let px = |dr: isize, dc: isize| {
                let rr = border_index(r as isize + dr, h, Border::Reflect)
                    .expect("reflect always maps inside");
                let cc = border_index(c as isize + dc, w, Border::Reflect)
                    .expect("reflect always maps inside");
                gray.at(cc, rr)
            };
            let right = px(-1, 1) + 2.0 * px(0, 1) + px(1, 1);
            let left = px(-1, -1) + 2.0 * px(0, -1) + px(1, -1);
            let response = (right - left) / 8.0;
            strength[r * w + c] = response * response;
        }
    }
    let threshold = 2.0 * (strength.iter().sum::<f64>() / strength.len() as f64).sqrt();
    for s in &mut strength {
        if *s <= threshold {
            *s = 0.0;
        }
    }
    let s = |r: isize, c: isize| {
        if r < 0 || c < 0 || r >= h as isize || c >= w as isize {
            0.0
        } else {
            strength[r as usize * w + c as usize]
        }
    };
    let mut edges = vec![false; w * h];
    for r in 0..h as isize {
        for c in 0..w as isize {
            let v = s(r, c);
            let horizontal_max = v > s(r, c - 1) && v > s(r, c + 1);
            let vertical_max = v > s(r - 1, c) && v > s(r + 1, c);
            edges[r as usize * w + c as usize] = horizontal_max || vertical_max;
        }
    }
    edges
}

/// Marziliano et al. edge widths, as cpbd measures them: at each edge pixel (not on the image
/// border) whose gradient (numpy.gradient: central differences, one-sided at the border) points
/// along the row (angle within 22.5 degrees of 0 or 180), count the pixels on each side over
/// which the intensity keeps rising or falling monotonically, at most 101 per side.
///
/// cpbd gives a zero horizontal gradient an angle of 0 whatever the vertical gradient is, so
/// such pixels are measured as rising edges; that is kept, because it is part of the numbers
/// the reference implementation produces. One cpbd special case is not kept: it measures no
/// width at all when every pixel's angle is exactly 0 (e.g. one rising vertical step with
/// identical rows), an artefact of how it skips flat images.
pub(super) fn marziliano_widths(gray: &Plane, edges: &[bool]) -> Vec<f64> {
    let (w, h) = (gray.width, gray.height);
    let mut widths = vec![0.0; w * h];
    let gradient = |get: &dyn Fn(usize) -> f64, i: usize, n: usize| {
        if n < 2 {
            0.0
        } else if i == 0 {
            get(1) - get(0)
        } else if i == n - 1 {
            get(n - 1) - get(n - 2)
        } else {
            (get(i + 1) - get(i - 1)) / 2.0
        }
    };
    for r in 1..h.saturating_sub(1) {
        for c in 1..w.saturating_sub(1) {
            if !edges[r * w + c] {
                continue;
            }
            let gx = gradient(&|k| gray.at(k, r), c, w);
            let gy = gradient(&|k| gray.at(c, k), r, h);
            let eighths = if gx != 0.0 {
                gy.atan2(gx).to_degrees() / 45.0
            } else {
                0.0
            };
            // numpy.round rounds halves to even: +-0.5 goes to 0 and +-3.5 to +-4.
            let rising = eighths.abs() <= 0.5;
            let falling = eighths.abs() >= 3.5;
            if !(rising || falling) {
                continue;
            }
            let row = |k: usize| gray.at(k, r);
            // Walk away from the edge while the profile keeps its monotone direction.
            let left = (0..=MAX_HALF_WIDTH_STEPS)
                .find(|&m| {
                    let Some(outer) = c.checked_sub(2 + m) else {
                        return true;
                    };
                    let step = row(outer) - row(outer + 1);
                    if rising { step >= 0.0 } else { step <= 0.0 }
                })
                .unwrap_or(MAX_HALF_WIDTH_STEPS);
            let right = (0..=MAX_HALF_WIDTH_STEPS)
                .find(|&m| {
                    let outer = c + 2 + m;
                    if outer >= w {
                        return true;
                    }
                    let step = row(outer) - row(outer - 1);
                    if rising { step <= 0.0 } else { step >= 0.0 }
                })
                .unwrap_or(MAX_HALF_WIDTH_STEPS);
            widths[r * w + c] = (left + 1 + right + 1) as f64;
        }
    }
    widths
}
