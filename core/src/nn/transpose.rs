//! Channel-major rows laid out point by point and back: the edge convolution's neighbour
//! and centre terms (`G` channels a point, the lanes of its vectors) and its per-point
//! maxima, and the 8 x 8 transpose that the AVX2 instance-norm sums share.

use super::dispatch::Fma;

/// The transposes with the instructions of a kernel set ([`Fma`]): AVX2 8 x 8 transposes
/// where the set has AVX2, else the portable loops (pure permutations, the same values).
/// Every [`Fma`] has them.
pub trait TransposeVariants: Fma {
    /// [`point_major`]: `G` channel-major rows laid out point by point
    /// ([`point_major_avx2`] on x86-64).
    #[inline(always)]
    fn point_major<const G: usize>(self, rows: &[f32], n: usize, out: &mut [f32]) {
        #[cfg(target_arch = "x86_64")]
        if let Some(avx2) = self.x86_avx2() {
            return point_major_avx2::<G>(avx2, rows, n, out);
        }
        point_major::<G>(rows, n, out);
    }

    /// [`channel_major`]: `n` points of `G` lanes laid out as `G` channel-major rows
    /// ([`channel_major_avx2`] on x86-64).
    #[inline(always)]
    fn channel_major<const G: usize>(self, points: &[f32], n: usize, out: &mut [f32]) {
        #[cfg(target_arch = "x86_64")]
        if let Some(avx2) = self.x86_avx2() {
            return channel_major_avx2::<G>(avx2, points, n, out);
        }
        channel_major::<G>(points, n, out);
    }
}

impl<F: Fma> TransposeVariants for F {}

/// `out[j * G + c] = rows[c * n + j]` for every point `j < n` and channel `c < G`: `G`
/// rows of `n` values (`rows` holds at least `G n`) laid out point by point (a pure
/// permutation).
#[inline(always)]
pub fn point_major<const G: usize>(rows: &[f32], n: usize, out: &mut [f32]) {
    for (j, lanes) in out.chunks_exact_mut(G).take(n).enumerate() {
        for (c, lane) in lanes.iter_mut().enumerate() {
            *lane = rows[c * n + j];
        }
    }
}

/// [`point_major`] with AVX2 for `G` a multiple of 8: blocks of 8 points of 8 rows are
/// loaded whole, transposed ([`transpose8`]) and stored as 8 points' lanes; the last
/// `n % 8` points as [`point_major`].
#[cfg(target_arch = "x86_64")]
#[inline(always)]
#[allow(unsafe_code)]
pub fn point_major_avx2<const G: usize>(
    avx2: super::dispatch::X86Fma,
    rows: &[f32],
    n: usize,
    out: &mut [f32],
) {
    use core::arch::x86_64::{_mm256_loadu_ps, _mm256_storeu_ps};
    if !G.is_multiple_of(8) || rows.len() < G * n || out.len() < G * n {
        return point_major::<G>(rows, n, out);
    }
    let blocks = n / 8;
    for h in 0..G / 8 {
        for b in 0..blocks {
            // SAFETY: an `X86Fma` exists only on a CPU with AVX2 (see `dispatch`). Row
            // `8h + i < G` is read at points `8b..8b + 8 <= n`, inside `rows` (`G n`, checked
            // above); point `8b + t < n` is written at lanes `8h..8h + 8 <= G`, inside `out`
            // (`G n`); `loadu`/`storeu` need no alignment.
            unsafe {
                let columns = transpose8(
                    avx2,
                    core::array::from_fn(|i| {
                        _mm256_loadu_ps(rows.as_ptr().add((8 * h + i) * n + 8 * b))
                    }),
                );
                for (t, column) in columns.into_iter().enumerate() {
                    _mm256_storeu_ps(out.as_mut_ptr().add((8 * b + t) * G + 8 * h), column);
                }
            }
        }
    }
    for j in 8 * blocks..n {
        for c in 0..G {
            out[j * G + c] = rows[c * n + j];
        }
    }
}

/// The inverse of [`point_major`]: `n` points of `G` lanes (`points[j * G + c]`) laid out
/// as `G` channel-major rows (`out[c * n + j]`).
#[inline(always)]
pub fn channel_major<const G: usize>(points: &[f32], n: usize, out: &mut [f32]) {
    for (j, lanes) in points.chunks_exact(G).take(n).enumerate() {
        for (c, &lane) in lanes.iter().enumerate() {
            out[c * n + j] = lane;
        }
    }
}

/// [`channel_major`] with AVX2 for `G` a multiple of 8: blocks of 8 points' 8 lanes are
/// loaded whole, transposed ([`transpose8`]) and stored as 8 rows' points; the last
/// `n % 8` points as [`channel_major`].
#[cfg(target_arch = "x86_64")]
#[inline(always)]
#[allow(unsafe_code)]
pub fn channel_major_avx2<const G: usize>(
    avx2: super::dispatch::X86Fma,
    points: &[f32],
    n: usize,
    out: &mut [f32],
) {
    use core::arch::x86_64::{_mm256_loadu_ps, _mm256_storeu_ps};
    if !G.is_multiple_of(8) || points.len() < G * n || out.len() < G * n {
        return channel_major::<G>(points, n, out);
    }
    let blocks = n / 8;
    for h in 0..G / 8 {
        for b in 0..blocks {
            // SAFETY: an `X86Fma` exists only on a CPU with AVX2 (see `dispatch`). Point
            // `8b + t < n` is read at lanes `8h..8h + 8 <= G`, inside `points` (`G n`, checked
            // above); row `8h + i < G` is written at points `8b..8b + 8 <= n`, inside `out`
            // (`G n`); `loadu`/`storeu` need no alignment.
            unsafe {
                let rows = transpose8(
                    avx2,
                    core::array::from_fn(|t| {
                        _mm256_loadu_ps(points.as_ptr().add((8 * b + t) * G + 8 * h))
                    }),
                );
                for (i, row) in rows.into_iter().enumerate() {
                    _mm256_storeu_ps(out.as_mut_ptr().add((8 * h + i) * n + 8 * b), row);
                }
            }
        }
    }
    for j in 8 * blocks..n {
        for c in 0..G {
            out[c * n + j] = points[j * G + c];
        }
    }
}

/// The 8 x 8 transpose of eight rows of 8 `f32`: `out[t][i] = rows[i][t]` (`vunpck*ps`,
/// `vshufps`, `vperm2f128`).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
#[allow(unsafe_code)]
pub fn transpose8(
    _avx2: super::dispatch::X86Fma,
    r: [core::arch::x86_64::__m256; 8],
) -> [core::arch::x86_64::__m256; 8] {
    use core::arch::x86_64::{
        _mm256_permute2f128_ps, _mm256_shuffle_ps, _mm256_unpackhi_ps, _mm256_unpacklo_ps,
    };
    // SAFETY: an `X86Fma` exists only on a CPU with AVX2 (see `dispatch`); the intrinsics
    // only touch registers.
    unsafe {
        let t = [
            _mm256_unpacklo_ps(r[0], r[1]),
            _mm256_unpackhi_ps(r[0], r[1]),
            _mm256_unpacklo_ps(r[2], r[3]),
            _mm256_unpackhi_ps(r[2], r[3]),
            _mm256_unpacklo_ps(r[4], r[5]),
            _mm256_unpackhi_ps(r[4], r[5]),
            _mm256_unpacklo_ps(r[6], r[7]),
            _mm256_unpackhi_ps(r[6], r[7]),
        ];
        let u = [
            _mm256_shuffle_ps::<0x44>(t[0], t[2]),
            _mm256_shuffle_ps::<0xEE>(t[0], t[2]),
            _mm256_shuffle_ps::<0x44>(t[1], t[3]),
            _mm256_shuffle_ps::<0xEE>(t[1], t[3]),
            _mm256_shuffle_ps::<0x44>(t[4], t[6]),
            _mm256_shuffle_ps::<0xEE>(t[4], t[6]),
            _mm256_shuffle_ps::<0x44>(t[5], t[7]),
            _mm256_shuffle_ps::<0xEE>(t[5], t[7]),
        ];
        [
            _mm256_permute2f128_ps::<0x20>(u[0], u[4]),
            _mm256_permute2f128_ps::<0x20>(u[1], u[5]),
            _mm256_permute2f128_ps::<0x20>(u[2], u[6]),
            _mm256_permute2f128_ps::<0x20>(u[3], u[7]),
            _mm256_permute2f128_ps::<0x31>(u[0], u[4]),
            _mm256_permute2f128_ps::<0x31>(u[1], u[5]),
            _mm256_permute2f128_ps::<0x31>(u[2], u[6]),
            _mm256_permute2f128_ps::<0x31>(u[3], u[7]),
        ]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The AVX2 layout is the portable one for lengths around the blocks of 8 points.
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn avx2_point_major_is_the_portable_layout() {
        let Some(avx2) = super::super::dispatch::X86Fma::detect() else {
            return;
        };
        for n in [0, 1, 7, 8, 9, 16, 23, 64, 100] {
            let rows: [f32; 16 * 100] = core::array::from_fn(|i| i as f32 * 0.5 - 3.0);
            let rows = &rows[..16 * n];
            let (mut portable, mut vector) = ([f32::NAN; 16 * 100], [f32::NAN; 16 * 100]);
            point_major::<16>(rows, n, &mut portable);
            point_major_avx2::<16>(avx2, rows, n, &mut vector);
            assert_eq!(
                portable.map(f32::to_bits),
                vector.map(f32::to_bits),
                "n = {n}"
            );
            let (mut portable, mut vector) = ([f32::NAN; 8 * 100], [f32::NAN; 8 * 100]);
            point_major::<8>(&rows[..8 * n], n, &mut portable);
            point_major_avx2::<8>(avx2, &rows[..8 * n], n, &mut vector);
            assert_eq!(
                portable.map(f32::to_bits),
                vector.map(f32::to_bits),
                "n = {n}"
            );
        }
    }

    /// [`channel_major`] undoes [`point_major`], and its AVX2 form gives the same layout,
    /// for lengths around the blocks of 8 points.
    #[test]
    fn channel_major_inverts_point_major() {
        for n in [0, 1, 7, 8, 9, 16, 23, 64, 100] {
            let rows: [f32; 16 * 100] = core::array::from_fn(|i| i as f32 * 0.5 - 3.0);
            let rows = &rows[..16 * n];
            let mut points = [f32::NAN; 16 * 100];
            point_major::<16>(rows, n, &mut points);
            let mut back = [f32::NAN; 16 * 100];
            channel_major::<16>(&points[..16 * n], n, &mut back);
            assert_eq!(back[..16 * n], rows[..], "n = {n}");
            #[cfg(target_arch = "x86_64")]
            if let Some(avx2) = super::super::dispatch::X86Fma::detect() {
                let mut vector = [f32::NAN; 16 * 100];
                channel_major_avx2::<16>(avx2, &points[..16 * n], n, &mut vector);
                assert_eq!(back.map(f32::to_bits), vector.map(f32::to_bits), "n = {n}");
            }
        }
    }
}
