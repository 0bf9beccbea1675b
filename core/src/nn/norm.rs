//! Instance normalisation, L2 normalisation and the activations.

use super::blocking::{
    channels_for_rows, NORM_CHANNELS, SHORT_ROW_CHANNELS, WIDE_SHORT_ROW_CHANNELS,
};
use super::dispatch::{with_fma, Fma, Kernel, Portable};
use super::sqrt::sqrt;

/// Epsilon of the reference's `InstanceNorm1d/2d` (affine = false).
pub const INSTANCE_NORM_EPS: f64 = 1e-5;
/// Epsilon of the reference's `F.normalize`.
pub const L2_EPS: f32 = 1e-12;

/// One pass's running sum of instance-norm statistics: in f64, as the reference's CPU kernel
/// sums (bit for bit), or, with the core's `f32-statistics` feature, a compensated (Kahan)
/// f32 sum for FPUs without double precision such as the Cortex-M4F's, whose results are
/// close to the default's but not the same bits.
#[derive(Debug, Clone, Copy, Default)]
pub struct StatSum {
    #[cfg(not(feature = "f32-statistics"))]
    sum: f64,
    #[cfg(feature = "f32-statistics")]
    sum: f32,
    /// The low part that the last addition to `sum` lost (Kahan).
    #[cfg(feature = "f32-statistics")]
    lost: f32,
}

impl StatSum {
    /// Adds one value.
    #[inline(always)]
    pub fn add(&mut self, x: f32) {
        #[cfg(not(feature = "f32-statistics"))]
        {
            self.sum += f64::from(x);
        }
        #[cfg(feature = "f32-statistics")]
        {
            let y = x - self.lost;
            let t = self.sum + y;
            self.lost = (t - self.sum) - y;
            self.sum = t;
        }
    }

    /// A running sum that has reached `sum` (the f64 sums of [`row_sums_x86`]).
    #[cfg(all(target_arch = "x86_64", not(feature = "f32-statistics")))]
    fn of_f64(sum: f64) -> Self {
        StatSum { sum }
    }

    /// The sum divided by `count` (not 0), rounded to f32.
    fn mean_over(&self, count: usize) -> f32 {
        #[cfg(not(feature = "f32-statistics"))]
        let mean = (self.sum / count as f64) as f32;
        #[cfg(feature = "f32-statistics")]
        let mean = self.sum / count as f32;
        mean
    }

    /// The sum rounded to f32.
    fn rounded(&self) -> f32 {
        #[cfg(not(feature = "f32-statistics"))]
        let rounded = self.sum as f32;
        #[cfg(feature = "f32-statistics")]
        let rounded = self.sum;
        rounded
    }
}

/// `1 / sqrt(variance + eps)`: in f64 as the reference, in f32 with `f32-statistics`.
fn inverse_deviation(variance: f32) -> f32 {
    #[cfg(not(feature = "f32-statistics"))]
    let inverse = (1.0 / super::sqrt::sqrt_f64(f64::from(variance) + INSTANCE_NORM_EPS)) as f32;
    #[cfg(feature = "f32-statistics")]
    let inverse = 1.0 / sqrt(variance + INSTANCE_NORM_EPS as f32);
    inverse
}

/// Per-channel statistics of instance norm, computed as the reference's CPU kernel does so
/// that f32 results agree bit for bit: the mean is an f64 sum divided by the count and
/// rounded to f32; the variance sums the f32 squares of `x - mean` in f64, rounds the sum
/// to f32 and divides it by the count in f32; `1 / sqrt(var + eps)` is taken in f64 (sums
/// and root in f32 with `f32-statistics`, see [`StatSum`]).
#[derive(Debug, Clone, Copy)]
pub struct Moments {
    sum: StatSum,
    count: usize,
}

impl Moments {
    /// The first pass over `count` values whose [`StatSum`] (added in their order) is `sum`.
    #[inline(always)]
    pub fn of(sum: StatSum, count: usize) -> Self {
        Moments { sum, count }
    }

    /// Mean of the values.
    pub fn mean(&self) -> f32 {
        if self.count == 0 {
            0.0
        } else {
            self.sum.mean_over(self.count)
        }
    }

    /// One value's term of the second pass, given [`Moments::mean`], to add to a
    /// [`StatSum`].
    #[inline(always)]
    pub fn squared_deviation(x: f32, mean: f32) -> f32 {
        let d = x - mean;
        d * d
    }

    /// The normalisation given the sum of [`Moments::squared_deviation`] over the same
    /// values.
    pub fn normalizer(&self, squared_deviations: &StatSum) -> Normalizer {
        let variance = if self.count == 0 {
            0.0
        } else {
            squared_deviations.rounded() / self.count as f32
        };
        let scale = inverse_deviation(variance);
        Normalizer {
            scale,
            offset: -(self.mean() * scale),
        }
    }
}

/// `x -> (x - mean) / sqrt(var + eps)`, applied as the fused `x * scale + offset`.
#[derive(Debug, Clone, Copy)]
pub struct Normalizer {
    scale: f32,
    offset: f32,
}

impl Normalizer {
    /// The normalised value of `x`; monotone increasing in `x`.
    #[inline(always)]
    pub fn apply(&self, x: f32) -> f32 {
        self.apply_with(Portable, x)
    }

    /// [`Normalizer::apply`] with the given [`Fma`] (same bits).
    #[inline(always)]
    pub fn apply_with<F: Fma>(&self, fma: F, x: f32) -> f32 {
        fma.mul_add(x, self.scale, self.offset)
    }
}

/// Instance norm of one channel over its points, in place: `(x - mean) / sqrt(var + eps)`
/// with the biased variance (supp. "Feature Encoder"; `InstanceNorm1d`, affine = false).
pub fn instance_norm(x: &mut [f32]) {
    instance_norm_rows(x, x.len());
}

/// [`instance_norm`] of every row (channel) of `x`, `n` values a row. Rows are taken
/// [`NORM_CHANNELS`] at a time ([`SHORT_ROW_CHANNELS`] on short rows): each row's sums still
/// run over its values in order, and the rows' independent sums overlap in the CPU (one row
/// alone waits for each f64 add).
pub fn instance_norm_rows(x: &mut [f32], n: usize) {
    if n > 0 {
        with_fma(InstanceNormRows { x, n });
    }
}

/// The arguments of one [`instance_norm_rows`] call.
struct InstanceNormRows<'a> {
    x: &'a mut [f32],
    n: usize,
}

impl Kernel<()> for InstanceNormRows<'_> {
    #[inline(always)]
    fn run<F: Fma>(self, fma: F) {
        let n = self.n;
        let group = channels_for_rows(NORM_CHANNELS, n, F::WIDE_REGISTERS);
        if group == WIDE_SHORT_ROW_CHANNELS {
            normalize_groups::<F, WIDE_SHORT_ROW_CHANNELS>(fma, self.x, n);
        } else if group == SHORT_ROW_CHANNELS {
            normalize_groups::<F, SHORT_ROW_CHANNELS>(fma, self.x, n);
        } else {
            normalize_groups::<F, NORM_CHANNELS>(fma, self.x, n);
        }
    }
}

/// Instance norm of the rows of `x` (`n` values a row), `G` rows at a time, then one at a time.
#[inline(always)]
fn normalize_groups<F: Fma, const G: usize>(fma: F, x: &mut [f32], n: usize) {
    let mut groups = x.chunks_exact_mut(n * G);
    for group in &mut groups {
        normalize_rows::<F, G>(fma, group, n);
    }
    for row in groups.into_remainder().chunks_exact_mut(n) {
        normalize_rows::<F, 1>(fma, row, n);
    }
}

/// Instance norm of the `G` rows of `x` (`G x n`), their statistics summed side by side.
#[inline(always)]
fn normalize_rows<F: Fma, const G: usize>(fma: F, x: &mut [f32], n: usize) {
    let rows: [&[f32]; G] = core::array::from_fn(|c| &x[c * n..(c + 1) * n]);
    let pass = RowPass {
        rows: &rows,
        n,
        means: None,
    };
    let sums = fma.row_sums(pass);
    let moments = sums.map(|sum| Moments::of(sum, n));
    let means = moments.map(|m| m.mean());
    let deviations = fma.row_sums(RowPass {
        means: Some(&means),
        ..pass
    });
    for ((row, m), d) in x.chunks_exact_mut(n).zip(&moments).zip(&deviations) {
        let normalizer = m.normalizer(d);
        for v in row.iter_mut() {
            *v = normalizer.apply_with(fma, *v);
        }
    }
}

/// One of instance norm's two passes over `G` rows side by side.
#[derive(Clone, Copy)]
pub struct RowPass<'a, const G: usize> {
    /// The rows.
    pub rows: &'a [&'a [f32]; G],
    /// Values summed of each row (its first).
    pub n: usize,
    /// `None`: the values are summed (first pass); each row's mean: their
    /// [`Moments::squared_deviation`]s from it (second pass).
    pub means: Option<&'a [f32; G]>,
}

/// Instance norm's sums with the instructions of a kernel set ([`Fma`]): [`row_sums_x86`]
/// where the set has AVX2, else [`row_sums`]. Every [`Fma`] has them.
pub trait NormVariants: Fma {
    /// [`row_sums`]: instance norm's running sums of `G` rows side by side (AVX2 on x86-64
    /// for sixteen rows, and for thirty-two with AVX-512's 32 registers, with the default f64
    /// statistics; the same additions in the same order, so every path gives the same bits).
    #[inline(always)]
    fn row_sums<const G: usize>(self, pass: RowPass<'_, G>) -> [StatSum; G] {
        #[cfg(all(target_arch = "x86_64", not(feature = "f32-statistics")))]
        {
            if let Some(avx512) = self.x86_avx512() {
                return row_sums_x86(avx512, pass);
            }
            if let Some(avx2) = self.x86_avx2() {
                return row_sums_x86(avx2, pass);
            }
        }
        row_sums(pass)
    }
}

impl<F: Fma> NormVariants for F {}

/// Each row's [`StatSum`] over its first `n` values in order, for one [`RowPass`].
#[inline(always)]
pub fn row_sums<const G: usize>(pass: RowPass<'_, G>) -> [StatSum; G] {
    continued_row_sums([StatSum::default(); G], pass, 0)
}

/// `sums` (each row's over its values before point `first`) continued over points
/// `first..n`, in order.
#[inline(always)]
fn continued_row_sums<const G: usize>(
    mut sums: [StatSum; G],
    pass: RowPass<'_, G>,
    first: usize,
) -> [StatSum; G] {
    let RowPass { rows, n, means } = pass;
    for i in first..n {
        for (c, (sum, row)) in sums.iter_mut().zip(rows).enumerate() {
            let x = row[i];
            sum.add(match means {
                Some(means) => Moments::squared_deviation(x, means[c]),
                None => x,
            });
        }
    }
    sums
}

/// [`row_sums`] of `G` rows with x86-64 vectors, the same bits: sixteen rows with AVX2, or
/// thirty-two with the AVX-512 token (other counts take [`row_sums`]' path). Each point's
/// values (or squared deviations) are `G / 8` vectors (transposed blocks of 8 points), widened
/// to f64 (by halves to four 4-lane sums with AVX2; whole, `vcvtps2pd` to 512 bits, to four
/// 8-lane sums with AVX-512) and added point after point (each lane's sum adds its row's
/// values in order, as [`StatSum::add`]). The strided scalar loads of [`row_sums`] cost about
/// three instructions a value. The last `n % 8` points continue the blocks' sums as
/// [`row_sums`] does; rows shorter than `n` take [`row_sums`]' path.
#[cfg(all(target_arch = "x86_64", not(feature = "f32-statistics")))]
#[inline(always)]
#[allow(unsafe_code)]
pub fn row_sums_x86<const G: usize, const AVX512: bool>(
    fma: super::dispatch::X86Fma<AVX512>,
    pass: RowPass<'_, G>,
) -> [StatSum; G] {
    use core::arch::x86_64::{
        _mm256_add_pd, _mm256_castps256_ps128, _mm256_cvtps_pd, _mm256_extractf128_ps,
        _mm256_setzero_pd, _mm256_storeu_pd, _mm512_add_pd, _mm512_cvtps_pd, _mm512_setzero_pd,
        _mm512_storeu_pd,
    };
    let wide = G == 32 && AVX512;
    if !(G == 16 || wide) || pass.rows.iter().any(|r| r.len() < pass.n) {
        return row_sums(pass);
    }
    let mut sums = [0.0f64; G];
    // SAFETY: an `X86Fma` exists only on a CPU with AVX2, with `AVX512` only on one with
    // AVX-512 F (see `dispatch`); the rows hold `n` values (checked above); the stores write
    // 4 `f64` into `sums` (16) at 0, 4, 8 or 12, or 8 into `sums` (32) at 0, 8, 16 or 24;
    // `storeu` needs no alignment.
    unsafe {
        if wide {
            let mut acc = [_mm512_setzero_pd(); 4];
            point_vectors(fma.avx2(), pass, |h, v| {
                acc[h] = _mm512_add_pd(acc[h], _mm512_cvtps_pd(v));
            });
            for (q, a) in acc.iter().enumerate() {
                _mm512_storeu_pd(sums.as_mut_ptr().add(8 * q), *a);
            }
        } else {
            let mut acc = [_mm256_setzero_pd(); 4];
            point_vectors(fma.avx2(), pass, |h, v| {
                let low = _mm256_cvtps_pd(_mm256_castps256_ps128(v));
                let high = _mm256_cvtps_pd(_mm256_extractf128_ps::<1>(v));
                acc[2 * h] = _mm256_add_pd(acc[2 * h], low);
                acc[2 * h + 1] = _mm256_add_pd(acc[2 * h + 1], high);
            });
            for (q, a) in acc.iter().enumerate() {
                _mm256_storeu_pd(sums.as_mut_ptr().add(4 * q), *a);
            }
        }
    }
    continued_row_sums(sums.map(StatSum::of_f64), pass, pass.n / 8 * 8)
}

/// For each point of the whole blocks of 8 points, in order, `add(h, v)` for each group `h`
/// of 8 rows: `v` holds the point's values of rows `8h..8h + 8` (squared deviations from the
/// means in f32, as [`Moments::squared_deviation`], on the second pass). The blocks of each
/// row are loaded whole and transposed (8 x 8). The caller checked that every row holds `n`
/// values and `G` is 8, 16, 24 or 32.
#[cfg(all(target_arch = "x86_64", not(feature = "f32-statistics")))]
#[inline(always)]
#[allow(unsafe_code)]
fn point_vectors<const G: usize>(
    avx2: super::dispatch::X86Fma,
    pass: RowPass<'_, G>,
    mut add: impl FnMut(usize, core::arch::x86_64::__m256),
) {
    use core::arch::x86_64::{_mm256_loadu_ps, _mm256_mul_ps, _mm256_setzero_ps, _mm256_sub_ps};
    /// Most groups of 8 rows.
    const OCTETS: usize = 4;
    let RowPass { rows, n, means } = pass;
    // SAFETY: an `X86Fma` exists only on a CPU with AVX2 (see `dispatch`). Each load reads 8
    // `f32` of a row at `8b`, `8b + 8 <= n <= len` (the caller's check), or of `means` (`G`)
    // at `8h < G`; `loadu` needs no alignment.
    unsafe {
        let mut centre = [_mm256_setzero_ps(); OCTETS];
        if let Some(m) = means {
            for (h, c) in centre.iter_mut().enumerate().take(G / 8) {
                *c = _mm256_loadu_ps(m.as_ptr().add(8 * h));
            }
        }
        for b in 0..n / 8 {
            let mut points = [[_mm256_setzero_ps(); 8]; OCTETS];
            for (h, columns) in points.iter_mut().enumerate().take(G / 8) {
                let mut block = [_mm256_setzero_ps(); 8];
                for (i, row) in block.iter_mut().enumerate() {
                    *row = _mm256_loadu_ps(rows[8 * h + i].as_ptr().add(8 * b));
                }
                *columns = super::transpose::transpose8(avx2, block);
            }
            for t in 0..8 {
                for (h, columns) in points.iter().enumerate().take(G / 8) {
                    let v = columns[t];
                    if means.is_some() {
                        let d = _mm256_sub_ps(v, centre[h]);
                        add(h, _mm256_mul_ps(d, d));
                    } else {
                        add(h, v);
                    }
                }
            }
        }
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

/// Leaky ReLU with slope 0.2 (supp. eq. 4-5): `x` where `x > 0`, else `0.2 x`, written as
/// `max(x, 0.2 x)` (the same value for every `x`, NaN included), which compiles to plain
/// vector code where a select between `x` and `0.2 x` in place became masked stores, slow
/// on AMD CPUs.
#[inline(always)]
pub fn leaky_relu(x: f32) -> f32 {
    x.max(0.2 * x)
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
        *s = sqrt(*s).max(L2_EPS);
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
        let s = 1.0 / libm::sqrt(1.25 + INSTANCE_NORM_EPS);
        for (v, z) in x.iter().zip([-1.5, -0.5, 0.5, 1.5]) {
            assert!((f64::from(*v) - z * s).abs() < 1e-6, "{v}");
        }
    }

    /// The reference's f64 statistics, bit for bit (not those of `f32-statistics`).
    #[cfg(not(feature = "f32-statistics"))]
    #[test]
    fn instance_norm_of_a_constant_channel_is_pytorchs_rounding_residue() {
        // PyTorch gives 3.0518e-05 here too: `7 * scale + offset` with `offset` rounded.
        let mut x = [7.0f32; 5];
        instance_norm(&mut x);
        assert_eq!(x, [3.0517578e-5; 5]);
    }

    #[test]
    fn activations() {
        assert_eq!(relu(-2.0), 0.0);
        assert_eq!(relu(3.0), 3.0);
        assert_eq!(leaky_relu(-2.0), -0.4);
        assert_eq!(leaky_relu(3.0), 3.0);
    }

    /// `max(x, 0.2 x)` is the select of the definition, bit for bit, on every 97th f32
    /// (both zeros, subnormals, infinities; NaN stays NaN).
    #[test]
    fn leaky_relu_is_its_definition() {
        let select = |x: f32| if x > 0.0 { x } else { 0.2 * x };
        let specials = [
            0.0f32,
            -0.0,
            f32::INFINITY,
            f32::NEG_INFINITY,
            1e-45,
            -1e-45,
        ];
        let sweep = (0..=u32::MAX).step_by(97).map(f32::from_bits);
        for x in specials.into_iter().chain(sweep) {
            if x.is_nan() {
                assert!(leaky_relu(x).is_nan());
            } else {
                assert_eq!(leaky_relu(x).to_bits(), select(x).to_bits(), "{x:e}");
            }
        }
    }

    /// The AVX2 sums of 16 rows and the AVX-512 sums of 32 (8 x 8 transposes) are the
    /// portable ones bit for bit, on both passes, for lengths around the blocks of 8 points
    /// and for values of every magnitude.
    #[cfg(all(target_arch = "x86_64", not(feature = "f32-statistics")))]
    #[test]
    fn avx2_row_sums_are_the_portable_sums() {
        use crate::nn::dispatch::X86Fma;
        let Some(avx2) = X86Fma::detect() else {
            return;
        };
        vector_sums_are_the_portable_sums::<16>(|pass: RowPass<'_, 16>| row_sums_x86(avx2, pass));
        if let Some(avx512) = X86Fma::detect_avx512() {
            vector_sums_are_the_portable_sums::<32>(|pass: RowPass<'_, 32>| {
                row_sums_x86(avx512, pass)
            });
        }
    }

    /// `vector` (the sums of `G` rows) against [`row_sums`], bit for bit.
    #[cfg(all(target_arch = "x86_64", not(feature = "f32-statistics")))]
    fn vector_sums_are_the_portable_sums<const G: usize>(
        vector: impl Fn(RowPass<'_, G>) -> [StatSum; G],
    ) {
        let mut state = 0x9E37_79B9_7F4A_7C15u64;
        let mut next = || {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1);
            let bits = (state >> 33) as u32;
            let scale = [1e-30f32, 1e-3, 1.0, 1e3, 1e30][(bits % 5) as usize];
            (bits as f32 / u32::MAX as f32 - 0.25) * scale
        };
        for n in [0, 1, 7, 8, 9, 16, 255, 256, 257, 300] {
            let values: [[f32; 300]; G] =
                core::array::from_fn(|_| core::array::from_fn(|_| next()));
            let rows: [&[f32]; G] = core::array::from_fn(|c| &values[c][..n]);
            let means: [f32; G] = core::array::from_fn(|_| next());
            for m in [None, Some(&means)] {
                let pass = RowPass {
                    rows: &rows,
                    n,
                    means: m,
                };
                let (portable, vector) = (row_sums(pass), vector(pass));
                for (p, v) in portable.iter().zip(&vector) {
                    assert_eq!(p.sum.to_bits(), v.sum.to_bits(), "G = {G}, n = {n}");
                }
            }
        }
        // Points past the last block of 8 continue the blocks' sums (8 + 2^-50 rounds back to 8
        // four times; the four small values summed first would not).
        let row: [f32; 12] = core::array::from_fn(|i| if i < 8 { 1.0 } else { 2f32.powi(-50) });
        let rows: [&[f32]; G] = [&row; G];
        let pass = RowPass {
            rows: &rows,
            n: 12,
            means: None,
        };
        let (portable, vector) = (row_sums(pass), vector(pass));
        assert_eq!(portable[0].sum, 8.0);
        assert_eq!(vector[0].sum.to_bits(), portable[0].sum.to_bits());
    }

    #[test]
    fn l2_normalize_columns() {
        // two channels, three points: (3,4), (0,0), (1,0)
        let mut x = [3.0f32, 0.0, 1.0, 4.0, 0.0, 0.0];
        let mut norms = [0.0; 3];
        l2_normalize_points(&mut x, 2, 3, &mut norms);
        assert_eq!(x, [0.6, 0.0, 1.0, 0.8, 0.0, 0.0]);
    }

    /// Either statistics (f64 sums, or the compensated f32 sums of `f32-statistics`) give
    /// the normalised values of a long, offset channel within 2e-6 of an f64 computation.
    #[test]
    fn instance_norm_of_a_long_offset_channel_is_close_to_f64() {
        extern crate std;
        let x: std::vec::Vec<f32> = (0..10_240)
            .map(|i| 1000.0 + libm::sinf(i as f32 * 0.37) * (1.0 + (i % 7) as f32))
            .collect();
        let n = x.len() as f64;
        let mean = x.iter().map(|&v| f64::from(v)).sum::<f64>() / n;
        let variance = x
            .iter()
            .map(|&v| (f64::from(v) - mean).powi(2))
            .sum::<f64>()
            / n;
        let inverse = 1.0 / (variance + INSTANCE_NORM_EPS).sqrt();
        let mut y = x.clone();
        instance_norm(&mut y);
        for (&v, &out) in x.iter().zip(&y) {
            let expected = (f64::from(v) - mean) * inverse;
            assert!(
                (f64::from(out) - expected).abs() < 2e-6,
                "{out} vs {expected}"
            );
        }
    }
}
