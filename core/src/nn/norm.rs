//! Instance normalisation, L2 normalisation and the activations.

/// Epsilon of the reference's `InstanceNorm1d/2d` (affine = false).
pub const INSTANCE_NORM_EPS: f32 = 1e-5;
/// Epsilon of the reference's `F.normalize`.
pub const L2_EPS: f32 = 1e-12;

/// Running mean and variance of a stream of values, accumulated in f64 in two passes
/// (the mean first, then the squared deviations) for accuracy.
#[derive(Debug, Clone, Copy, Default)]
pub struct Moments {
    sum: f64,
    count: usize,
}

impl Moments {
    /// Adds one value to the first pass.
    #[inline(always)]
    pub fn add(&mut self, x: f32) {
        self.sum += f64::from(x);
        self.count += 1;
    }

    /// Mean of the values added.
    pub fn mean(&self) -> f64 {
        if self.count == 0 {
            0.0
        } else {
            self.sum / self.count as f64
        }
    }

    /// `(mean, 1 / sqrt(biased variance + eps))` given the sum of squared deviations from
    /// [`Moments::mean`] over the same values.
    pub fn normalizer(&self, squared_deviations: f64) -> (f32, f32) {
        let variance = if self.count == 0 {
            0.0
        } else {
            squared_deviations / self.count as f64
        };
        let inv_std = 1.0 / libm::sqrtf(variance as f32 + INSTANCE_NORM_EPS);
        (self.mean() as f32, inv_std)
    }
}

/// Instance norm of one channel over its points, in place: `(x - mean) / sqrt(var + eps)`
/// with the biased variance (supp. "Feature Encoder"; `InstanceNorm1d`, affine = false).
pub fn instance_norm(x: &mut [f32]) {
    let mut moments = Moments::default();
    for &v in x.iter() {
        moments.add(v);
    }
    let mean = moments.mean();
    let deviations: f64 = x
        .iter()
        .map(|&v| {
            let d = f64::from(v) - mean;
            d * d
        })
        .sum();
    let (mean, inv_std) = moments.normalizer(deviations);
    for v in x.iter_mut() {
        *v = (*v - mean) * inv_std;
    }
}

/// `max(x, 0)`.
#[inline(always)]
pub fn relu(x: f32) -> f32 {
    if x > 0.0 {
        x
    } else {
        0.0
    }
}

/// Leaky ReLU with slope 0.2 (supp. eq. 4-5).
#[inline(always)]
pub fn leaky_relu(x: f32) -> f32 {
    if x > 0.0 {
        x
    } else {
        0.2 * x
    }
}

/// Divides every point (column) of a channel-major `channels x n` matrix by
/// `max(||x_i||, 1e-12)` (`F.normalize`), using `norms` (`n` values) as scratch.
pub fn l2_normalize_points(x: &mut [f32], channels: usize, n: usize, norms: &mut [f32]) {
    let norms = &mut norms[..n];
    norms.fill(0.0);
    for row in x[..channels * n].chunks_exact(n) {
        for (s, &v) in norms.iter_mut().zip(row) {
            *s += v * v;
        }
    }
    for s in norms.iter_mut() {
        *s = libm::sqrtf(*s).max(L2_EPS);
    }
    for row in x[..channels * n].chunks_exact_mut(n) {
        for (v, &s) in row.iter_mut().zip(norms.iter()) {
            *v /= s;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn instance_norm_of_a_known_channel() {
        // mean 2.5, biased variance 1.25
        let mut x = [1.0f32, 2.0, 3.0, 4.0];
        instance_norm(&mut x);
        let s = 1.0 / libm::sqrtf(1.25 + 1e-5);
        assert_eq!(x, [-1.5 * s, -0.5 * s, 0.5 * s, 1.5 * s]);
    }

    #[test]
    fn instance_norm_of_a_constant_channel_is_zero() {
        let mut x = [7.0f32; 5];
        instance_norm(&mut x);
        assert_eq!(x, [0.0; 5]);
    }

    #[test]
    fn activations() {
        assert_eq!(relu(-2.0), 0.0);
        assert_eq!(relu(3.0), 3.0);
        assert_eq!(leaky_relu(-2.0), -0.4);
        assert_eq!(leaky_relu(3.0), 3.0);
    }

    #[test]
    fn l2_normalize_columns() {
        // two channels, three points: (3,4), (0,0), (1,0)
        let mut x = [3.0f32, 0.0, 1.0, 4.0, 0.0, 0.0];
        let mut norms = [0.0; 3];
        l2_normalize_points(&mut x, 2, 3, &mut norms);
        assert_eq!(x, [0.6, 0.0, 1.0, 0.8, 0.0, 0.0]);
    }
}
