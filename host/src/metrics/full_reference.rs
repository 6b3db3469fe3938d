//! Full-reference metrics: MSE, PSNR and SSIM as scikit-image computes them.

use super::filters::{Border, Plane, gaussian_filter, gaussian_kernel};
use super::{ImageRef, MetricError, Sample};

fn same_shape<T: Sample>(a: &ImageRef<T>, b: &ImageRef<T>) -> Result<(), MetricError> {
    if a.shape() != b.shape() {
        return Err(MetricError::ShapeMismatch {
            a: a.shape(),
            b: b.shape(),
        });
    }
    Ok(())
}

/// Mean squared error over all pixels and channels, in the samples' own units.
pub fn mse<T: Sample>(a: &ImageRef<T>, b: &ImageRef<T>) -> Result<f64, MetricError> {
    same_shape(a, b)?;
    let mut sum = 0.0;
    for y in 0..a.height {
        for x in 0..a.width {
            for c in 0..a.channels {
                let d = a.sample(x, y, c) - b.sample(x, y, c);
                sum += d * d;
            }
        }
    }
    Ok(sum / (a.width * a.height * a.channels) as f64)
}

/// Peak signal-to-noise ratio in dB, `10 log10(L^2 / MSE)` with `L` the data range of `T`
/// (255 for `u8`, 1 for `f32`). Identical images give `f64::INFINITY`, as scikit-image does:
/// averaging PSNRs that may be infinite is the caller's decision, not something to hide here.
///
/// ```
/// use orbit_nerf_host::metrics::{ImageRef, psnr};
///
/// let reference = [10u8, 20, 30, 40];
/// let mut render = reference;
/// render[3] += 10; // one of four pixels off by 10: MSE 25
/// let a = ImageRef::new(&reference, 2, 2, 1).unwrap();
/// let b = ImageRef::new(&render, 2, 2, 1).unwrap();
/// assert_eq!(psnr(&a, &a).unwrap(), f64::INFINITY);
/// let db = psnr(&a, &b).unwrap(); // 10 log10(255^2 / 25)
/// assert!((db - 34.151).abs() < 1e-3, "{db}");
/// ```
pub fn psnr<T: Sample>(a: &ImageRef<T>, b: &ImageRef<T>) -> Result<f64, MetricError> {
    let mse = mse(a, b)?;
    Ok(10.0 * (T::DATA_RANGE * T::DATA_RANGE / mse).log10())
}

/// SSIM (Wang et al. 2004) as scikit-image computes it with `gaussian_weights=True, sigma=1.5,
/// use_sample_covariance=False, data_range=L`: local statistics from an 11-tap Gaussian filter
/// (sigma 1.5, truncated at 3.5 sigma) with mirror ("reflect") borders, K1 = 0.01, K2 = 0.03,
/// population covariance, and the SSIM map averaged after cropping 5 pixels from each border,
/// where the window hangs over the image edge.
///
/// A colour image scores the mean of its per-channel SSIMs (scikit-image's `channel_axis`
/// behaviour, and what NeRF papers report), not the SSIM of its luma.
///
/// Images smaller than 11x11 pixels (the window) are refused.
///
/// ```
/// use orbit_nerf_host::metrics::{ImageRef, ssim};
///
/// // A 16x16 gray ramp, and the same ramp with one pixel turned white.
/// let ramp: Vec<u8> = (0..16 * 16).map(|i| (i % 16 * 16) as u8).collect();
/// let mut changed = ramp.clone();
/// changed[8 * 16 + 8] = 255;
/// let a = ImageRef::new(&ramp, 16, 16, 1).unwrap();
/// let b = ImageRef::new(&changed, 16, 16, 1).unwrap();
/// assert!((ssim(&a, &a).unwrap() - 1.0).abs() < 1e-12);
/// let score = ssim(&a, &b).unwrap();
/// assert!(score > 0.5 && score < 0.99, "{score}");
///
/// let tiny = ImageRef::new(&ramp[..8 * 8], 8, 8, 1).unwrap();
/// assert!(ssim(&tiny, &tiny).is_err());
/// ```
pub fn ssim<T: Sample>(a: &ImageRef<T>, b: &ImageRef<T>) -> Result<f64, MetricError> {
    same_shape(a, b)?;
    if a.width < SSIM_WINDOW || a.height < SSIM_WINDOW {
        return Err(MetricError::TooSmall {
            metric: "SSIM",
            min: SSIM_WINDOW,
            width: a.width,
            height: a.height,
        });
    }
    let kernel = gaussian_kernel(SSIM_SIGMA, SSIM_RADIUS);
    let total: f64 = (0..a.channels)
        .map(|c| ssim_plane(&a.plane(c), &b.plane(c), &kernel, T::DATA_RANGE))
        .sum();
    Ok(total / a.channels as f64)
}

const SSIM_SIGMA: f64 = 1.5;
/// scipy's radius for a Gaussian truncated at 3.5 sigma: `int(3.5 * 1.5 + 0.5)`.
const SSIM_RADIUS: usize = 5;
const SSIM_WINDOW: usize = 2 * SSIM_RADIUS + 1;

fn ssim_plane(x: &Plane, y: &Plane, kernel: &[f64], data_range: f64) -> f64 {
    let filter = |p: &Plane| gaussian_filter(p, kernel, Border::Reflect);
    let product = |p: &Plane, q: &Plane| Plane {
        width: p.width,
        height: p.height,
        values: p.values.iter().zip(&q.values).map(|(a, b)| a * b).collect(),
    };
    let ux = filter(x);
    let uy = filter(y);
    let uxx = filter(&product(x, x));
    let uyy = filter(&product(y, y));
    let uxy = filter(&product(x, y));
    let c1 = (0.01 * data_range) * (0.01 * data_range);
    let c2 = (0.03 * data_range) * (0.03 * data_range);
    let mut sum = 0.0;
    for row in SSIM_RADIUS..x.height - SSIM_RADIUS {
        for col in SSIM_RADIUS..x.width - SSIM_RADIUS {
            let i = row * x.width + col;
            let (mx, my) = (ux.values[i], uy.values[i]);
            let vx = uxx.values[i] - mx * mx;
            let vy = uyy.values[i] - my * my;
            let vxy = uxy.values[i] - mx * my;
            // Same association as scikit-image, so results agree to the last few bits.
            let a1 = 2.0 * mx * my + c1;
            let a2 = 2.0 * vxy + c2;
            let b1 = mx * mx + my * my + c1;
            let b2 = vx + vy + c2;
            sum += (a1 * a2) / (b1 * b2);
        }
    }
    let count = (x.height - 2 * SSIM_RADIUS) * (x.width - 2 * SSIM_RADIUS);
    sum / count as f64
}
