//! No-reference sharpness: JNB (Ferzli & Karam 2009) and CPBD (Narvekar & Karam 2011) on the
//! edge machinery of the `cpbd` package.

use super::edges::{canny, marziliano_widths, octave_sobel_edges};
use super::filters::Plane;
use super::{ImageRef, MetricError, Sample};

/// How the JNB metric counts blocks and picks the just-noticeable width. Both variants appear
/// in the wild and give different numbers on the same image (they agree when every block is an
/// edge block and no block contrast lies in 51..=59). The orbit-NeRF paper does not say which
/// it used, so a report must name the variant next to the number.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum JnbVariant {
    /// The ASU reference MATLAB code (Ferzli & Karam's lab): `L` counts every 64x64 block of the
    /// image, and `W_JNB = 5` for block contrast below 60 (3 otherwise).
    Asu,
    /// The paper's text: `L` counts the processed (edge) blocks, and `W_JNB = 5` for block
    /// contrast of at most 50 (3 otherwise).
    Paper,
}

/// Result of [`jnb`]. `D` is the pooled distortion
/// `D = (sum_b D_b^beta)^(1/beta)`, `D_b = (sum_{edges e in b} (w_e / W_JNB(b))^beta)^(1/beta)`,
/// `beta = 3.6`, over the edge blocks `b`, and `L` the block count of the chosen variant.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct JnbScore {
    /// Ferzli & Karam's sharpness `S = L / D`: higher is sharper. `f64::INFINITY` when no edge
    /// width was measured (nothing blurred to see).
    pub sharpness: f64,
    /// `1 / S = D / L`: lower is sharper. The orbit-NeRF paper reports JNB this way round
    /// ("lower is better"; 0.0337 -> 0.0496 as training images drop from 400 to 25), but the
    /// ratio falls with the block count `L` (the image's area) and grows with the edge count
    /// through `D`: its magnitudes are those of 1920 x 1200 images, so the reports use
    /// [`JnbScore::blur_per_edge`] instead.
    pub blur: f64,
    /// Number of 64x64 blocks in the image (`floor(H/64) * floor(W/64)`).
    pub blocks: usize,
    /// Blocks with enough Canny edge pixels to be processed.
    pub edge_blocks: usize,
    /// The pooled distortion `D`.
    pub distortion: f64,
    /// Edge widths measured (in edge blocks).
    pub edges: usize,
    /// The blur per edge, `D / edges^(1/beta)`: the beta-mean of the edges' width over their
    /// just-noticeable width, which depends on how blurred the edges are and not on how many
    /// blocks or edges the image has (so images of any size compare). Lower is sharper; 1 is
    /// the just-noticeable blur; 0 without edges.
    pub blur_per_edge: f64,
}

/// No-reference JNB sharpness (Ferzli & Karam, "A no-reference objective image sharpness metric
/// based on the notion of just noticeable blur", IEEE TIP 2009), on the gray levels of `image`
/// (RGB is turned into Rec.601 luma).
///
/// The image is cut into 64x64 blocks (a partial block at the right or bottom is ignored). A
/// block is an edge block when more than 0.2 % of its pixels are Canny edges; in it, every
/// thinned-Sobel edge pixel whose gradient points along the row contributes its Marziliano
/// width `w` (the extent of the monotone intensity run through it), weighted by the block's
/// just-noticeable width `W_JNB` (5 for low-contrast blocks, 3 otherwise; see [`JnbVariant`]).
pub fn jnb<T: Sample>(image: &ImageRef<T>, variant: JnbVariant) -> Result<JnbScore, MetricError> {
    let gray = image.gray_255("JNB")?;
    let analysis = EdgeAnalysis::new(&gray);
    let blocks = analysis.block_count();
    let (mut edge_blocks, mut edges) = (0, 0);
    let mut pooled = 0.0;
    for block in analysis.edge_blocks() {
        edge_blocks += 1;
        edges += block.widths.len();
        let just_noticeable = match variant {
            JnbVariant::Asu if block.contrast < 60 => 5.0,
            JnbVariant::Paper if block.contrast <= 50 => 5.0,
            _ => 3.0,
        };
        let block_sum: f64 = block
            .widths
            .iter()
            .map(|w| (w / just_noticeable).powf(JNB_BETA))
            .sum();
        let block_distortion = block_sum.powf(1.0 / JNB_BETA);
        pooled += block_distortion.powf(JNB_BETA);
    }
    let distortion = pooled.powf(1.0 / JNB_BETA);
    let counted = match variant {
        JnbVariant::Asu => blocks,
        JnbVariant::Paper => edge_blocks,
    };
    let (sharpness, blur) = if distortion > 0.0 {
        (counted as f64 / distortion, distortion / counted as f64)
    } else {
        (f64::INFINITY, 0.0)
    };
    let blur_per_edge = if edges > 0 {
        distortion / (edges as f64).powf(1.0 / JNB_BETA)
    } else {
        0.0
    };
    Ok(JnbScore {
        sharpness,
        blur,
        blocks,
        edge_blocks,
        distortion,
        edges,
        blur_per_edge,
    })
}

/// CPBD, the cumulative probability of blur detection (Narvekar & Karam 2011), as PyPI `cpbd`
/// 1.0.7 computes it: the fraction of edge widths (in edge blocks, same edges as [`jnb`]) whose
/// probability of blur detection `1 - exp(-(w / W_JNB)^3.6)`, rounded to a percent, is below
/// 64 %. Higher is sharper, in [0, 1]; 0 when the image has no measurable edge.
pub fn cpbd<T: Sample>(image: &ImageRef<T>) -> Result<f64, MetricError> {
    let gray = image.gray_255("CPBD")?;
    let analysis = EdgeAnalysis::new(&gray);
    let (mut total, mut sharp) = (0usize, 0usize);
    for block in analysis.edge_blocks() {
        let just_noticeable = if block.contrast <= 50 { 5.0 } else { 3.0 };
        for w in &block.widths {
            let probability = 1.0 - (-(w / just_noticeable).powf(JNB_BETA)).exp();
            // cpbd bins the probability into 101 percent buckets (Python's round, ties to even)
            // and sums buckets 0..=63.
            if (probability * 100.0).round_ties_even() < 64.0 {
                sharp += 1;
            }
            total += 1;
        }
    }
    Ok(if total == 0 {
        0.0
    } else {
        sharp as f64 / total as f64
    })
}

const JNB_BETA: f64 = 3.6;
const JNB_BLOCK: usize = 64;
/// A block is an edge block when more than this fraction of its pixels are Canny edges.
const EDGE_BLOCK_FRACTION: f64 = 0.002;

/// The edge maps both JNB and CPBD read.
struct EdgeAnalysis<'a> {
    gray: &'a Plane,
    /// Canny edges: decide which blocks are edge blocks.
    canny: Vec<bool>,
    /// Marziliano width at each thinned-Sobel edge pixel, 0 elsewhere.
    widths: Vec<f64>,
}

struct EdgeBlock {
    /// `int(max - min)` of the block's gray levels.
    contrast: i64,
    /// Non-zero edge widths in the block.
    widths: Vec<f64>,
}

impl<'a> EdgeAnalysis<'a> {
    fn new(gray: &'a Plane) -> Self {
        let canny = canny(gray);
        let widths = marziliano_widths(gray, &octave_sobel_edges(gray));
        EdgeAnalysis {
            gray,
            canny,
            widths,
        }
    }

    fn block_count(&self) -> usize {
        (self.gray.width / JNB_BLOCK) * (self.gray.height / JNB_BLOCK)
    }

    /// Edge blocks in row-major block order.
    fn edge_blocks(&self) -> impl Iterator<Item = EdgeBlock> + '_ {
        let width = self.gray.width;
        let (rows, cols) = (self.gray.height / JNB_BLOCK, width / JNB_BLOCK);
        let min_edges = (JNB_BLOCK * JNB_BLOCK) as f64 * EDGE_BLOCK_FRACTION;
        (0..rows * cols).filter_map(move |block| {
            let (top, left) = ((block / cols) * JNB_BLOCK, (block % cols) * JNB_BLOCK);
            let pixels = || {
                (top..top + JNB_BLOCK)
                    .flat_map(move |y| (left..left + JNB_BLOCK).map(move |x| y * width + x))
            };
            let edges = pixels().filter(|&i| self.canny[i]).count();
            if edges as f64 <= min_edges {
                return None;
            }
            let (lo, hi) = pixels().fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), i| {
                (lo.min(self.gray.values[i]), hi.max(self.gray.values[i]))
            });
            let widths = pixels()
                .map(|i| self.widths[i])
                .filter(|&w| w != 0.0)
                .collect();
            Some(EdgeBlock {
                contrast: (hi - lo) as i64,
                widths,
            })
        })
    }
}
