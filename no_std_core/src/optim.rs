//! Adam with a warm-up + cosine learning-rate schedule; plane texels are updated sparsely
//! (only those a batch touched) and stored in f16 either from an f32 master copy or by
//! seeded stochastic rounding.

use crate::config::Config;
use crate::rng;
use half::f16;

/// Learning rate at `step` (0-based): linear warm-up, the peak for `lr_decay_start` of the
/// remaining steps, then cosine decay to `learning_rate * final_lr_factor` at the last step.
pub fn learning_rate(c: &Config, step: u32) -> f32 {
    let base = c.learning_rate;
    if step < c.warmup_steps {
        return base * (step + 1) as f32 / c.warmup_steps as f32;
    }
    let span = (c.steps - c.warmup_steps).max(1) as f32;
    let progress = ((step - c.warmup_steps) as f32 / span).min(1.0);
    let progress = if c.lr_decay_start > 0.0 {
        ((progress - c.lr_decay_start) / (1.0 - c.lr_decay_start)).max(0.0)
    } else {
        progress
    };
    let cosine = 0.5 * (1.0 + libm::cosf(core::f32::consts::PI * progress));
    base * (c.final_lr_factor + (1.0 - c.final_lr_factor) * cosine)
}

/// Learning rate of the pose corrections at `step`: zero before they start learning
/// (`Config::pose_warmup_steps`), then a cosine from `learning_rate * pose_lr_factor` down
/// to zero at the last step. Adam moves a parameter by about its rate whatever the size of
/// its gradient, so a weakly constrained pose walks for as long as the rate lasts; a rate
/// that ends at zero ends the walk.
pub fn pose_learning_rate(c: &Config, step: u32) -> f32 {
    if !c.pose_learns_at(step) {
        return 0.0;
    }
    let span = c.steps.saturating_sub(c.pose_warmup_steps).max(1) as f32;
    let progress = ((step - c.pose_warmup_steps) as f32 / span).min(1.0);
    c.learning_rate * c.pose_lr_factor * 0.5 * (1.0 + libm::cosf(core::f32::consts::PI * progress))
}

/// The per-step constants of Adam with bias correction folded into the step size.
#[derive(Clone, Copy, Debug)]
pub struct AdamStep {
    /// Decay of the first-moment (mean) estimate, from `Config::adam_beta1`.
    pub beta1: f32,
    /// Decay of the second-moment (squared gradient) estimate, from `Config::adam_beta2`.
    pub beta2: f32,
    /// lr * sqrt(1 - beta2^t) / (1 - beta1^t)
    pub step_size: f32,
    /// eps * sqrt(1 - beta2^t), so the update equals the textbook one.
    pub eps_hat: f32,
}

impl AdamStep {
    /// `t` counts applied updates, starting at 1 (0 is taken as 1: the bias correction at
    /// t = 0 would divide 0 by 0).
    pub fn new(c: &Config, lr: f32, t: u32) -> Self {
        let t = t.max(1);
        let b1t = libm::powf(c.adam_beta1, t as f32);
        let b2t = libm::powf(c.adam_beta2, t as f32);
        let root = libm::sqrtf(1.0 - b2t);
        AdamStep {
            beta1: c.adam_beta1,
            beta2: c.adam_beta2,
            step_size: lr * root / (1.0 - b1t),
            eps_hat: c.adam_eps * root,
        }
    }

    /// Update moments with gradient `g` and return the parameter change.
    #[inline(always)]
    pub fn delta(&self, g: f32, m: &mut f32, v: &mut f32) -> f32 {
        *m = self.beta1 * *m + (1.0 - self.beta1) * g;
        *v = self.beta2 * *v + (1.0 - self.beta2) * g * g;
        -self.step_size * *m / (libm::sqrtf(*v) + self.eps_hat)
    }

    /// Dense update of `params` from `grads`.
    pub fn apply(&self, params: &mut [f32], grads: &[f32], m: &mut [f32], v: &mut [f32]) {
        for (((p, g), m), v) in params
            .iter_mut()
            .zip(grads)
            .zip(m.iter_mut())
            .zip(v.iter_mut())
        {
            *p += self.delta(*g, m, v);
        }
    }
}

/// `x` as the nearest f16, saturating at the largest finite f16 instead of overflowing to
/// infinity (NaN stays NaN).
pub fn saturating_f16(x: f32) -> f16 {
    f16::from_f32(x.clamp(-f16::MAX.to_f32(), f16::MAX.to_f32()))
}

/// Round `x` to one of the two f16 values around it, choosing the upper one with probability
/// equal to its fractional distance, so the expected result is `x` (within f16 range; beyond
/// it, the largest finite f16 of that sign).
pub fn stochastic_round(x: f32, bits: u64) -> f16 {
    let nearest = saturating_f16(x);
    let y = nearest.to_f32();
    if y == x || !x.is_finite() || x.abs() >= f16::MAX.to_f32() {
        return nearest;
    }
    // The f16 neighbour on the other side of x: one unit in the last place toward x.
    let raw = nearest.to_bits();
    let toward_x = if (y < x) == (raw & 0x8000 == 0) {
        raw.wrapping_add(1)
    } else {
        raw.wrapping_sub(1)
    };
    // Crossing zero from +0 goes to the smallest negative subnormal.
    let other = if raw & 0x7fff == 0 {
        f16::from_bits(if x > 0.0 { 1 } else { 0x8001 })
    } else {
        f16::from_bits(toward_x)
    };
    let z = other.to_f32();
    let (lo, hi, lo_h, hi_h) = if y < z {
        (y, z, nearest, other)
    } else {
        (z, y, other, nearest)
    };
    let p_hi = (x - lo) / (hi - lo);
    if rng::unit_f32(bits) < p_hi {
        hi_h
    } else {
        lo_h
    }
}

/// Writes one texel feature after an update, following the configured policy.
#[inline(always)]
pub fn store_texel(
    texel: &mut f16,
    master: Option<&mut f32>,
    delta: f32,
    seed: u64,
    step: u32,
    index: usize,
) {
    match master {
        Some(m) => {
            *m += delta;
            *texel = saturating_f16(*m);
        }
        None => {
            let bits = rng::hash(seed, rng::domain::ROUNDING, step as u64, index as u64);
            *texel = stochastic_round(texel.to_f32() + delta, bits);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn schedule_warms_up_then_decays_to_the_floor() {
        let mut c = Config::DEFAULT;
        c.steps = 1000;
        c.warmup_steps = 100;
        assert!(learning_rate(&c, 0) < learning_rate(&c, 50));
        assert!((learning_rate(&c, 99) - c.learning_rate).abs() < 1e-7);
        assert!(learning_rate(&c, 500) < c.learning_rate);
        assert!((learning_rate(&c, 1000) - c.learning_rate * c.final_lr_factor).abs() < 1e-7);
        assert!((100..1000).all(|s| learning_rate(&c, s + 1) <= learning_rate(&c, s)));
    }

    #[test]
    fn the_pose_rate_starts_after_the_warm_up_and_decays_to_zero() {
        let mut c = Config::DEFAULT;
        c.steps = 1000;
        c.pose_correction = true;
        c.pose_warmup_steps = 200;
        assert_eq!(pose_learning_rate(&c, 199), 0.0);
        let peak = c.learning_rate * c.pose_lr_factor;
        assert!((pose_learning_rate(&c, 200) - peak).abs() < 1e-9);
        assert!((200..1000).all(|s| pose_learning_rate(&c, s + 1) <= pose_learning_rate(&c, s)));
        assert!(pose_learning_rate(&c, 999) < 1e-4 * peak);
        assert_eq!(pose_learning_rate(&c, 1000), 0.0);
        assert_eq!(pose_learning_rate(&c, 5000), 0.0);
        c.pose_correction = false;
        assert_eq!(pose_learning_rate(&c, 500), 0.0);
    }

    #[test]
    fn adam_first_step_moves_by_the_learning_rate() {
        let c = Config::DEFAULT;
        let adam = AdamStep::new(&c, 0.01, 1);
        let (mut m, mut v) = (0.0, 0.0);
        let d = adam.delta(3.0, &mut m, &mut v);
        assert!((d + 0.01).abs() < 1e-6, "{d}");
    }

    #[test]
    fn adam_at_t_0_takes_the_first_step_instead_of_dividing_0_by_0() {
        let c = Config::DEFAULT;
        let (mut m, mut v) = (0.0, 0.0);
        let d = AdamStep::new(&c, 0.01, 0).delta(3.0, &mut m, &mut v);
        assert!((d + 0.01).abs() < 1e-6, "{d}");
    }

    #[test]
    fn master_copy_texels_saturate_instead_of_overflowing() {
        let (mut texel, mut master) = (f16::ZERO, 65000.0f32);
        store_texel(&mut texel, Some(&mut master), 1e6, 1, 1, 0);
        assert_eq!(texel, f16::MAX);
        store_texel(&mut texel, Some(&mut master), -1e7, 1, 1, 0);
        assert_eq!(texel, f16::MIN);
        store_texel(&mut texel, None, -1e7, 1, 1, 0);
        assert_eq!(texel, f16::MIN);
    }

    #[test]
    fn stochastic_rounding_is_unbiased_where_nearest_rounding_vanishes() {
        // 1e-4 is far below half an f16 ulp at 0.3 (about 1.2e-4 ulp), so round-to-nearest
        // would never move; stochastic rounding moves on average by the exact amount.
        let start = 0.3f32;
        let mut sum = 0.0f64;
        let n = 20_000;
        for i in 0..n {
            let r = stochastic_round(start + 1e-5, rng::hash(1, 2, 3, i));
            sum += r.to_f32() as f64;
        }
        let mean = sum / n as f64;
        let nearest_start = f16::from_f32(start).to_f32() as f64;
        assert_eq!(f16::from_f32(start + 1e-5).to_f32() as f64, nearest_start);
        assert!((mean - (start as f64 + 1e-5)).abs() < 3e-6, "mean {mean}");
        // Exact values, zero crossings and huge values stay sane.
        assert_eq!(stochastic_round(0.5, 7).to_f32(), 0.5);
        assert!(stochastic_round(-1e-9, 5).to_f32().abs() < 1e-7);
        assert_eq!(stochastic_round(1e9, 5), f16::MAX);
        assert_eq!(stochastic_round(-1e9, 5), f16::MIN);
        assert_eq!(stochastic_round(65519.0, 5), f16::MAX);
        assert!(stochastic_round(f32::NAN, 5).is_nan());
    }
}
