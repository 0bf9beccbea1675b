//! Per-point linear layer (a 1x1 convolution) on channel-major features:
//! `y[r][i] = scale[r] * sum_k W[r][k] x[k][i] + bias[r]`.
//!
//! Weights are decoded [`ROW_BLOCK`] rows at a time into f32 and reused over all points,
//! so each stored weight is read once per call (cheap zero-copy reading of f16/int8 from
//! flash). The inner block keeps `ROW_BLOCK x COL_BLOCK` accumulators in registers; the
//! sum over `k` runs in order for every output with fused multiply-adds, as the
//! reference's BLAS does, so results neither depend on SIMD width nor differ from the
//! reference's f32 products. On sets of fewer than [`SMALL_SET`] points the reference's
//! BLAS takes its small-matrix path instead (bias first, separate multiply and add), and
//! so does this kernel.

use super::blocking;
use super::dispatch::{with_fma, Fma, Kernel};
use super::integer::linear_int8;
use super::operands::{Input, WeightRows};

/// Output rows computed together.
pub const ROW_BLOCK: usize = 4;
/// Points computed together ([`blocking`]).
pub const COL_BLOCK: usize = blocking::LINEAR_POINTS;
pub use crate::limits::MAX_INPUT;
/// Fewest points of a set on which the reference's BLAS sums with fused multiply-adds
/// and the bias last; on smaller sets it starts from the bias and multiplies and adds
/// separately (measured on the reference fixtures, see docs/evaluation.md, "Conformance
/// with the reference").
pub const SMALL_SET: usize = 12;

/// Output rows of the f32 kernel's register block ([`blocking`]).
const KERNEL_ROWS: usize = blocking::LINEAR_ROWS;
/// Decoded weights kept at once (8 KiB of stack, or one register block of the widest
/// layer if that is more): a panel of `PANEL_FLOATS / cols` rows.
pub const PANEL_FLOATS: usize = if KERNEL_ROWS * MAX_INPUT > 2048 {
    KERNEL_ROWS * MAX_INPUT
} else {
    2048
};
/// Most rows of a panel (a multiple of [`KERNEL_ROWS`]).
const PANEL_MAX_ROWS: usize = 64 / KERNEL_ROWS * KERNEL_ROWS;
/// Points per tile: the input tile (`cols x TILE_POINTS`) stays in cache while every row
/// of the panel passes over it.
const TILE_POINTS: usize = 64;

/// Most output rows a panel holds for a layer of `cols` inputs (a multiple of
/// [`KERNEL_ROWS`]).
fn panel_rows(cols: usize) -> usize {
    (PANEL_FLOATS / cols.max(1) / KERNEL_ROWS * KERNEL_ROWS).clamp(KERNEL_ROWS, PANEL_MAX_ROWS)
}

/// The larger of two scratch buffers (the one [`chunk_rows`] gets more rows from).
pub fn larger<'a>(a: &'a mut [f32], b: &'a mut [f32]) -> &'a mut [f32] {
    if a.len() >= b.len() {
        a
    } else {
        b
    }
}

/// Output rows to compute per call when they must wait in a scratch of `scratch` values
/// for `n` points: as many as fit (fewer calls, so fewer passes over the input), at least
/// [`ROW_BLOCK`].
pub fn chunk_rows(scratch: usize, n: usize) -> usize {
    (scratch / n.max(1) / ROW_BLOCK * ROW_BLOCK).max(ROW_BLOCK)
}

/// Computes output rows `rows` of `w` applied to `input` and hands each finished block of
/// up to [`COL_BLOCK`] points to `emit(row, first_point, values)` (`values.len()` is the
/// number of valid points), in no particular order. int8 layers on sets of at least
/// [`SMALL_SET`] points run on the integer kernel ([`super::integer`]); everything else on
/// the f32 one described here. The caller keeps
/// `w.cols() == input.channels() <= MAX_INPUT` and every part long enough for its rows
/// (a part too short reads as zeros).
///
/// Rows are decoded a panel at a time (each weight once per call), interleaved by row
/// block (`[input][ROW_BLOCK]`) so the inner loop reads the weights of a block with one
/// load; for each tile of points, every row block of the panel passes over the cached
/// input tile. Each output sums over the inputs in order. Runs with the CPU's FMA
/// instruction where it has one ([`with_fma`]); the bits are the same either way.
pub fn linear<W: WeightRows>(
    w: &W,
    input: &Input<'_>,
    rows: core::ops::Range<usize>,
    emit: impl FnMut(usize, usize, &[f32]),
) {
    let call = LinearCall {
        w,
        input,
        rows,
        emit,
    };
    // Two entries, so that each kernel's buffers have a stack frame of their own.
    if call.is_integer() {
        with_fma(IntegerKernel(call));
    } else {
        with_fma(FloatKernel(call));
    }
}

/// The arguments of one [`linear`] call.
struct LinearCall<'k, 'a, W, E> {
    w: &'k W,
    input: &'k Input<'a>,
    rows: core::ops::Range<usize>,
    emit: E,
}

impl<W: WeightRows, E> LinearCall<'_, '_, W, E> {
    /// Whether the call runs on the integer kernel: int8 weights on a set of at least
    /// [`SMALL_SET`] points.
    #[inline(always)]
    fn is_integer(&self) -> bool {
        self.input.set >= SMALL_SET && self.w.int8_row(self.rows.start).is_some()
    }
}

/// A [`LinearCall`] on the f32 kernel.
struct FloatKernel<'k, 'a, W, E>(LinearCall<'k, 'a, W, E>);

impl<W: WeightRows, E: FnMut(usize, usize, &[f32])> Kernel<()> for FloatKernel<'_, '_, W, E> {
    #[inline(always)]
    fn run<F: Fma>(self, fma: F) {
        let c = self.0;
        linear_f32(fma, c.w, c.input, c.rows, c.emit);
    }
}

/// A [`LinearCall`] on the integer kernel.
struct IntegerKernel<'k, 'a, W, E>(LinearCall<'k, 'a, W, E>);

impl<W: WeightRows, E: FnMut(usize, usize, &[f32])> Kernel<()> for IntegerKernel<'_, '_, W, E> {
    #[inline(always)]
    fn run<F: Fma>(self, fma: F) {
        let c = self.0;
        linear_int8(fma, c.w, c.input, c.rows, c.emit);
    }
}

/// [`linear`] with the given [`Fma`].
#[inline(always)]
pub fn linear_with<F: Fma, W: WeightRows>(
    fma: F,
    w: &W,
    input: &Input<'_>,
    rows: core::ops::Range<usize>,
    emit: impl FnMut(usize, usize, &[f32]),
) {
    let call = LinearCall {
        w,
        input,
        rows,
        emit,
    };
    if call.is_integer() {
        IntegerKernel(call).run(fma);
    } else {
        FloatKernel(call).run(fma);
    }
}

/// The f32 kernel of [`linear`].
#[inline(always)]
fn linear_f32<F: Fma, W: WeightRows>(
    fma: F,
    w: &W,
    input: &Input<'_>,
    rows: core::ops::Range<usize>,
    mut emit: impl FnMut(usize, usize, &[f32]),
) {
    debug_assert_eq!(w.cols(), input.channels());
    let small_set = input.set < SMALL_SET;
    let k = w.cols().min(MAX_INPUT);
    let panel_len = panel_rows(k);
    let mut panel = [[0.0f32; KERNEL_ROWS]; PANEL_FLOATS / KERNEL_ROWS];
    let mut decoded = [0.0f32; MAX_INPUT];
    let mut scale = [0.0f32; PANEL_MAX_ROWS];
    let mut bias = [0.0f32; PANEL_MAX_ROWS];
    let n = input.n;
    let mut p0 = rows.start;
    while p0 < rows.end {
        let count = panel_len.min(rows.end - p0);
        for r in 0..count.next_multiple_of(KERNEL_ROWS) {
            let lanes = &mut panel[r / KERNEL_ROWS * k..(r / KERNEL_ROWS + 1) * k];
            let lane = r % KERNEL_ROWS;
            if r < count {
                w.decode(p0 + r, &mut decoded[..k]);
                for (slot, &x) in lanes.iter_mut().zip(&decoded[..k]) {
                    slot[lane] = x;
                }
                scale[r] = w.scale(p0 + r);
                bias[r] = w.bias(p0 + r);
            } else {
                lanes.iter_mut().for_each(|slot| slot[lane] = 0.0);
            }
        }
        let mut t0 = 0;
        while t0 < n {
            let t1 = (t0 + TILE_POINTS).min(n);
            let mut r = 0;
            while r < count {
                let live = KERNEL_ROWS.min(count - r);
                let weights = &panel[r / KERNEL_ROWS * k..(r / KERNEL_ROWS + 1) * k];
                let mut i0 = t0;
                while i0 < t1 {
                    let pair = F::WIDE_REGISTERS && !small_set && i0 + 2 * COL_BLOCK <= t1;
                    let len = if pair {
                        2 * COL_BLOCK
                    } else {
                        COL_BLOCK.min(t1 - i0)
                    };
                    if small_set {
                        let rows = r..r + KERNEL_ROWS;
                        let acc =
                            small_block(weights, input, i0, len, &scale[rows.clone()], &bias[rows]);
                        for (b, a) in acc.iter().enumerate().take(live) {
                            emit(p0 + r + b, i0, &a[..len]);
                        }
                    } else {
                        let mut emit_block =
                            |at: usize, acc: &[[f32; COL_BLOCK]; KERNEL_ROWS], len| {
                                for (b, a) in acc.iter().enumerate().take(live) {
                                    let (s, o) = (scale[r + b], bias[r + b]);
                                    let values: [f32; COL_BLOCK] =
                                        core::array::from_fn(|t| a[t] * s + o);
                                    emit(p0 + r + b, at, &values[..len]);
                                }
                            };
                        if pair {
                            let [first, second] =
                                blocks::<F, true, 2>(fma, weights, input, i0, COL_BLOCK);
                            emit_block(i0, &first, COL_BLOCK);
                            emit_block(i0 + COL_BLOCK, &second, COL_BLOCK);
                        } else if len == COL_BLOCK {
                            emit_block(
                                i0,
                                &blocks::<F, true, 1>(fma, weights, input, i0, len)[0],
                                len,
                            );
                        } else {
                            emit_block(
                                i0,
                                &blocks::<F, false, 1>(fma, weights, input, i0, len)[0],
                                len,
                            );
                        }
                    }
                    i0 += len;
                }
                r += live;
            }
            t0 = t1;
        }
        p0 += count;
    }
}

/// Accumulates `B` side-by-side `KERNEL_ROWS x COL_BLOCK` blocks (points `i0..` and, for
/// `B = 2`, the next [`COL_BLOCK`]) over all input channels, in order; `w[k]` holds the
/// blocks' weights of input `k`. The accumulators stay in registers (two blocks where the
/// CPU has 32 vector registers: [`Fma::WIDE_REGISTERS`]). `len` counts the first block's
/// points (every block but a lone last one is full).
#[inline(always)]
fn blocks<F: Fma, const FULL: bool, const B: usize>(
    fma: F,
    w: &[[f32; KERNEL_ROWS]],
    input: &Input<'_>,
    i0: usize,
    len: usize,
) -> [[[f32; COL_BLOCK]; KERNEL_ROWS]; B] {
    let mut acc = [[[0.0f32; COL_BLOCK]; KERNEL_ROWS]; B];
    let mut weights = w.iter();
    let first = input.start + i0;
    let stride = input.stride;
    for (part, &rows) in input.parts.iter().zip(&input.rows) {
        // `rest` starts at the current channel's first point.
        let mut rest = part.get(first..).unwrap_or(&[]);
        for wk in weights.by_ref().take(rows) {
            let mut x = [[0.0f32; COL_BLOCK]; B];
            if FULL {
                for (b, xb) in x.iter_mut().enumerate() {
                    let points = rest.get(b * COL_BLOCK..).unwrap_or(&[]);
                    if let Some(values) = points.first_chunk::<COL_BLOCK>() {
                        *xb = *values;
                    }
                }
            } else {
                for (xt, &v) in x[0][..len].iter_mut().zip(rest) {
                    *xt = v;
                }
            }
            rest = rest.get(stride..).unwrap_or(&[]);
            for (ab, xb) in acc.iter_mut().zip(&x) {
                for (a, &wb) in ab.iter_mut().zip(wk) {
                    fma.mul_add_lanes(wb, xb, a);
                }
            }
        }
    }
    acc
}

/// One block on a set of fewer than [`SMALL_SET`] points, as the reference's BLAS sums
/// there: each output starts from its bias and adds the products of the dequantized
/// weights (`scale x W`), one rounding for the product and one for the sum. `scale` and
/// `bias` hold the block's [`KERNEL_ROWS`] rows.
fn small_block(
    w: &[[f32; KERNEL_ROWS]],
    input: &Input<'_>,
    i0: usize,
    len: usize,
    scale: &[f32],
    bias: &[f32],
) -> [[f32; COL_BLOCK]; KERNEL_ROWS] {
    let mut acc = [[0.0f32; COL_BLOCK]; KERNEL_ROWS];
    for (a, &b) in acc.iter_mut().zip(bias) {
        *a = [b; COL_BLOCK];
    }
    let mut weights = w.iter();
    for (part, &rows) in input.parts.iter().zip(&input.rows) {
        let mut rest = part.get(input.start + i0..).unwrap_or(&[]);
        for wk in weights.by_ref().take(rows) {
            for ((a, &wb), &s) in acc.iter_mut().zip(wk).zip(scale) {
                let wb = wb * s;
                for (at, &x) in a[..len].iter_mut().zip(rest) {
                    *at += wb * x;
                }
            }
            rest = rest.get(input.stride..).unwrap_or(&[]);
        }
    }
    acc
}

/// Writes `values` of `row` at points `i0..` of a channel-major matrix of `n` points. A full
/// block of [`COL_BLOCK`] values is copied inline; a shorter one (a set's last points) out of
/// line, so that the compiler does not merge both into one variable-length `memcpy` call.
#[inline(always)]
pub fn store(out: &mut [f32], n: usize, row: usize, i0: usize, values: &[f32]) {
    let at = row * n + i0;
    match (
        out.get_mut(at..)
            .and_then(|d| d.first_chunk_mut::<COL_BLOCK>()),
        values.first_chunk::<COL_BLOCK>(),
    ) {
        (Some(d), Some(v)) if values.len() == COL_BLOCK => *d = *v,
        _ => store_short(out, at, values),
    }
}

/// [`store`]'s copy of a short block.
#[inline(never)]
fn store_short(out: &mut [f32], at: usize, values: &[f32]) {
    out[at..at + values.len()].copy_from_slice(values);
}

/// Adds `values` of `row` at points `i0..` of a channel-major matrix of `n` points.
#[inline(always)]
pub fn accumulate(out: &mut [f32], n: usize, row: usize, i0: usize, values: &[f32]) {
    for (o, v) in out[row * n + i0..row * n + i0 + values.len()]
        .iter_mut()
        .zip(values)
    {
        *o += v;
    }
}

/// Writes `values` of channel `row` for points `i0..` into a point-major matrix of
/// `channels` per point.
#[inline(always)]
pub fn store_point_major(out: &mut [f32], channels: usize, row: usize, i0: usize, values: &[f32]) {
    for (t, &v) in values.iter().enumerate() {
        out[(i0 + t) * channels + row] = v;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::weights::Precision;

    struct Dense<'a> {
        w: &'a [f32],
        rows: usize,
        cols: usize,
        bias: &'a [f32],
    }

    impl WeightRows for Dense<'_> {
        fn rows(&self) -> usize {
            self.rows
        }
        fn cols(&self) -> usize {
            self.cols
        }
        fn decode(&self, row: usize, out: &mut [f32]) {
            out.copy_from_slice(&self.w[row * self.cols..(row + 1) * self.cols]);
        }
        fn scale(&self, _row: usize) -> f32 {
            1.0
        }
        fn bias(&self, row: usize) -> f32 {
            self.bias[row]
        }
        fn int8_row(&self, _row: usize) -> Option<&[u8]> {
            None
        }
    }

    /// 5 outputs (a partial row block) x 3 inputs on 11 points (a partial column block),
    /// with small integers so the expected result is exact.
    #[test]
    fn matches_the_definition_on_partial_blocks() {
        let (rows, cols, n) = (5, 3, 11);
        let w: [f32; 15] = core::array::from_fn(|i| (i as f32) - 7.0);
        let bias = [0.5, -1.0, 2.0, 0.0, 3.0];
        let x: [f32; 33] = core::array::from_fn(|i| ((i * 7) % 5) as f32 - 2.0);
        let dense = Dense {
            w: &w,
            rows,
            cols,
            bias: &bias,
        };
        let mut out = [0.0f32; 55];
        linear(&dense, &Input::one(&x, cols, n), 0..rows, |r, i0, v| {
            store(&mut out, n, r, i0, v)
        });
        for r in 0..rows {
            for i in 0..n {
                let expected: f32 = (0..cols)
                    .map(|k| w[r * cols + k] * x[k * n + i])
                    .sum::<f32>()
                    + bias[r];
                assert_eq!(out[r * n + i], expected, "row {r} point {i}");
            }
        }
    }

    /// Both summation paths, bit for bit, on values whose rounding tells them apart: fused
    /// multiply-adds in order then the bias on a set of [`SMALL_SET`] points, bias first with
    /// separate multiply and add on a smaller set (and on a tile of such a set).
    #[test]
    fn sums_as_the_reference_blas_on_large_and_small_sets() {
        let (rows, cols) = (3, 5);
        let w: [f32; 15] = core::array::from_fn(|i| 1.0 / (i as f32 + 3.0) - 0.21);
        let bias = [0.7f32, -1.3, 0.1];
        let dense = Dense {
            w: &w,
            rows,
            cols,
            bias: &bias,
        };
        let x: [f32; 5 * SMALL_SET] = core::array::from_fn(|i| libm::sinf(i as f32 * 1.7) * 3.0);
        let fused = |r: usize, i: usize, n: usize| {
            (0..cols).fold(0.0f32, |acc, k| {
                libm::fmaf(w[r * cols + k], x[k * n + i], acc)
            }) + bias[r]
        };
        let plain = |r: usize, i: usize, n: usize| {
            (0..cols).fold(bias[r], |acc, k| acc + w[r * cols + k] * x[k * n + i])
        };
        let mut paths_differ = false;
        for n in [SMALL_SET, SMALL_SET - 1] {
            let mut out = [0.0f32; 3 * SMALL_SET];
            linear(
                &dense,
                &Input::one(&x[..cols * n], cols, n),
                0..rows,
                |r, i0, v| store(&mut out, n, r, i0, v),
            );
            let mut tile = [0.0f32; 3 * 2];
            let window = Input::one(&x[..cols * n], cols, n).columns(3, 2);
            linear(&dense, &window, 0..rows, |r, i0, v| {
                store(&mut tile, 2, r, i0, v)
            });
            for r in 0..rows {
                for i in 0..n {
                    let expected = if n < SMALL_SET {
                        plain(r, i, n)
                    } else {
                        fused(r, i, n)
                    };
                    assert_eq!(
                        out[r * n + i].to_bits(),
                        expected.to_bits(),
                        "n {n} row {r} point {i}"
                    );
                    paths_differ |= plain(r, i, n) != fused(r, i, n);
                }
                assert_eq!(tile[r * 2..r * 2 + 2], out[r * n + 3..r * n + 5]);
            }
        }
        assert!(paths_differ, "the test values do not tell the paths apart");
    }

    /// The dispatched kernels (the FMA instruction where the CPU has it; AVX-512's pairs of
    /// register blocks where it has that) and the portable one (libm's exact `fmaf` on
    /// builds without the instruction) give the same bits, on full tiles, full and partial
    /// pairs of blocks and a lone partial block.
    #[test]
    fn dispatched_and_portable_kernels_agree_bit_for_bit() {
        use super::super::dispatch::{limit_kernels, KernelSet};
        const ROWS: usize = 9;
        const COLS: usize = 37;
        const N: usize = 109;
        let w: [f32; ROWS * COLS] = core::array::from_fn(|i| libm::sinf(i as f32 * 0.37) * 0.3);
        let bias: [f32; ROWS] = core::array::from_fn(|i| i as f32 * 0.1 - 0.4);
        let x: [f32; COLS * N] = core::array::from_fn(|i| libm::cosf(i as f32 * 1.3) * 2.0);
        let dense = Dense {
            w: &w,
            rows: ROWS,
            cols: COLS,
            bias: &bias,
        };
        let input = Input::one(&x, COLS, N);
        let mut portable = [0.0f32; ROWS * N];
        linear_with(
            super::super::dispatch::Portable,
            &dense,
            &input,
            0..ROWS,
            |r, i0, v| store(&mut portable, N, r, i0, v),
        );
        for set in [KernelSet::Avx2, KernelSet::Avx512] {
            limit_kernels(set);
            let mut dispatched = [f32::NAN; ROWS * N];
            linear(&dense, &input, 0..ROWS, |r, i0, v| {
                store(&mut dispatched, N, r, i0, v)
            });
            assert_eq!(dispatched.map(f32::to_bits), portable.map(f32::to_bits));
        }
    }

    #[test]
    fn concatenated_parts_and_column_windows_agree_with_one_matrix() {
        let (cols, n) = (4, 9);
        let w: [f32; 8] = [1.0, -2.0, 0.5, 3.0, 2.0, 1.0, -1.0, 0.25];
        let x: [f32; 36] = core::array::from_fn(|i| (i % 7) as f32);
        let dense = Dense {
            w: &w,
            rows: 2,
            cols,
            bias: &[0.0, 1.0],
        };
        let mut whole = [0.0f32; 18];
        linear(&dense, &Input::one(&x, cols, n), 0..2, |r, i0, v| {
            store(&mut whole, n, r, i0, v)
        });
        let (a, b) = x.split_at(n);
        let mut split = [0.0f32; 18];
        linear(&dense, &Input::two((a, 1), (b, 3), n), 0..2, |r, i0, v| {
            store(&mut split, n, r, i0, v)
        });
        assert_eq!(whole, split);
        let mut window = [0.0f32; 6];
        let input = Input::one(&x, cols, n).columns(4, 3);
        linear(&dense, &input, 0..2, |r, i0, v| {
            store(&mut window, 3, r, i0, v)
        });
        for r in 0..2 {
            assert_eq!(window[r * 3..r * 3 + 3], whole[r * n + 4..r * n + 7]);
        }
    }

    #[test]
    fn int8_layer_applies_its_row_scale() {
        let weights = [2u8, 0xFE]; // 2, -2
        let scales = 0.25f32.to_le_bytes();
        let bias = 1.0f32.to_le_bytes();
        let linear_layer =
            crate::weights::tests_support::linear(1, 2, Precision::Int8, &weights, &scales, &bias);
        let x = [3.0f32, 1.0];
        let mut out = [0.0f32; 1];
        linear(&linear_layer, &Input::one(&x, 2, 1), 0..1, |_, _, v| {
            out[0] = v[0]
        });
        assert_eq!(out[0], 0.25 * (2.0 * 3.0 - 2.0 * 1.0) + 1.0);
    }
}
