//! Separable filters on `f64` planes, bit-compatible with scipy.ndimage: Gaussian and Sobel.

/// A packed single-channel `f64` image.
#[derive(Clone, Debug)]
pub(super) struct Plane {
    pub(super) width: usize,
    pub(super) height: usize,
    pub(super) values: Vec<f64>,
}

impl Plane {
    pub(super) fn at(&self, x: usize, y: usize) -> f64 {
        self.values[y * self.width + x]
    }
}

/// What a filter sees beyond the image edge (scipy.ndimage's `mode`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) enum Border {
    /// `reflect`: mirror about the edge, repeating the edge sample (d c b a | a b c d).
    Reflect,
    /// `constant` with value 0.
    Zero,
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) enum Axis {
    /// Along a column (scipy axis 0).
    Vertical,
    /// Along a row (scipy axis 1).
    Horizontal,
}

/// scipy's normalised Gaussian taps `exp(-x^2 / (2 sigma^2)) / sum`, x = -radius..=radius.
/// The sum is taken in numpy's pairwise order so the taps match scipy's to the last bit.
pub(super) fn gaussian_kernel(sigma: f64, radius: usize) -> Vec<f64> {
    let factor = -0.5 / (sigma * sigma);
    let taps: Vec<f64> = (-(radius as i64)..=radius as i64)
        .map(|x| (factor * (x * x) as f64).exp())
        .collect();
    let sum = numpy_pairwise_sum(&taps);
    taps.iter().map(|t| t / sum).collect()
}

/// numpy's `add.reduce` for short contiguous arrays: eight running partial sums combined in a
/// tree, then the remainder added in order.
fn numpy_pairwise_sum(values: &[f64]) -> f64 {
    if values.len() < 8 {
        return values.iter().fold(0.0, |acc, v| acc + v);
    }
    let mut partial = [0.0; 8];
    partial.copy_from_slice(&values[..8]);
    let blocks_end = values.len() - values.len() % 8;
    for chunk in values[8..blocks_end].chunks_exact(8) {
        for (p, v) in partial.iter_mut().zip(chunk) {
            *p += v;
        }
    }
    let mut sum = ((partial[0] + partial[1]) + (partial[2] + partial[3]))
        + ((partial[4] + partial[5]) + (partial[6] + partial[7]));
    for v in &values[blocks_end..] {
        sum += v;
    }
    sum
}

/// Index of sample `i` (possibly outside `0..n`) under `border`, or `None` for a zero sample.
pub(super) fn border_index(i: isize, n: usize, border: Border) -> Option<usize> {
    let n = n as isize;
    if (0..n).contains(&i) {
        return Some(i as usize);
    }
    match border {
        Border::Zero => None,
        Border::Reflect => {
            let m = i.rem_euclid(2 * n);
            Some(if m < n { m } else { 2 * n - 1 - m } as usize)
        }
    }
}

/// scipy.ndimage.correlate1d with an odd, symmetric (`antisymmetric = false`) or antisymmetric
/// kernel, summed in scipy's order: centre tap first, then the pairs from the outside in.
fn correlate1d(
    plane: &Plane,
    kernel: &[f64],
    axis: Axis,
    border: Border,
    antisymmetric: bool,
) -> Plane {
    let radius = kernel.len() / 2;
    let (len, lines) = match axis {
        Axis::Horizontal => (plane.width, plane.height),
        Axis::Vertical => (plane.height, plane.width),
    };
    let index = |line: usize, pos: usize| match axis {
        Axis::Horizontal => line * plane.width + pos,
        Axis::Vertical => pos * plane.width + line,
    };
    let mut out = vec![0.0; plane.values.len()];
    let mut buffer = vec![0.0; len + 2 * radius];
    for line in 0..lines {
        for (k, slot) in buffer.iter_mut().enumerate() {
            let pos = k as isize - radius as isize;
            *slot = border_index(pos, len, border).map_or(0.0, |p| plane.values[index(line, p)]);
        }
        for pos in 0..len {
            let centre = pos + radius;
            let mut acc = buffer[centre] * kernel[radius];
            for j in (1..=radius).rev() {
                let (before, after) = (buffer[centre - j], buffer[centre + j]);
                acc += if antisymmetric {
                    (after - before) * kernel[radius + j]
                } else {
                    (before + after) * kernel[radius - j]
                };
            }
            out[index(line, pos)] = acc;
        }
    }
    Plane {
        width: plane.width,
        height: plane.height,
        values: out,
    }
}

/// scipy.ndimage.gaussian_filter: the 1-D filter along axis 0, then along axis 1.
pub(super) fn gaussian_filter(plane: &Plane, kernel: &[f64], border: Border) -> Plane {
    let vertical = correlate1d(plane, kernel, Axis::Vertical, border, false);
    correlate1d(&vertical, kernel, Axis::Horizontal, border, false)
}

/// scipy.ndimage.sobel: derivative `[-1, 0, 1]` along `axis`, smoothing `[1, 2, 1]` across it.
pub(super) fn sobel(plane: &Plane, axis: Axis) -> Plane {
    let across = match axis {
        Axis::Vertical => Axis::Horizontal,
        Axis::Horizontal => Axis::Vertical,
    };
    let derivative = correlate1d(plane, &[-1.0, 0.0, 1.0], axis, Border::Reflect, true);
    correlate1d(
        &derivative,
        &[1.0, 2.0, 1.0],
        across,
        Border::Reflect,
        false,
    )
}
