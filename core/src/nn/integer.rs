//! Integer kernel of the per-point linear layer for int8 weights, in the style of CMSIS-NN's
//! `arm_nn_mat_mult_kernel_s16`: int8 weights times int16 activations, summed exactly in
//! 32-bit integers, then scaled in f32.
//!
//! Each point's input is quantized per group `g` of [`GROUP`] channels (of one part of a
//! concatenated input): `q = round(x * 32767 / max_g|x|)`, with the scale
//! `s_g[i] = max_g|x| / 32767` per point and group. Output `r` at point `i` is
//! `(sum_g (sum_{k in g} W[r][k] q[k][i]) * s_g[i]) * row_scale[r] + bias[r]`, the groups
//! added in f32 in order. Products pair up along `k` (`w[k] q[k] + w[k+1] q[k+1]`: x86's
//! `vpmaddwd`, Cortex-M's `SMLAD`), and each sum is exact: `|w| <= 128`, `|q| <= 32767` and
//! at most [`MAX_INPUT`] = 512 products stay below 2^31. Integer sums do not depend on their
//! order, so every block shape, vector width and instruction set gives the same bits.

use super::blocking;
use super::dispatch::Fma;
use super::operands::{Input, WeightRows};
use crate::limits::MAX_INPUT;

/// Points quantized together: one tile of the input, reused by every output row.
pub const TILE: usize = 16;
/// Output rows of one register block ([`blocking`]).
pub const ROWS: usize = blocking::INT8_ROWS;
/// Points of one register block.
pub const POINTS: usize = blocking::INT8_POINTS;
/// Chains of running maxima when quantizing ([`blocking`]).
const QUANTIZE_MAX_CHAINS: usize = blocking::QUANTIZE_MAX_CHAINS;
/// Largest quantized activation magnitude.
const Q_MAX: f32 = 32767.0;
/// Weight pairs one panel holds ([`blocking`]).
const PANEL_PAIRS: usize = blocking::INT8_PANEL_PAIRS;
/// Most rows of a panel.
const PANEL_MAX_ROWS: usize = blocking::INT8_PANEL_MAX_ROWS;
/// `1.5 * 2^23`: adding and subtracting it rounds to the nearest integer (ties to even).
const ROUNDER: f32 = 12_582_912.0;

/// Two consecutive channels (input `k` and `k + 1`) of one weight row or one point.
pub type Pair = [i16; 2];
/// One channel pair of a register block's weight rows.
pub type WeightPairs = [Pair; ROWS];
/// One channel pair of a tile's points.
pub type TilePairs = [Pair; TILE];
/// The sums of one register block.
pub type BlockSums = [[i32; POINTS]; ROWS];

/// The integer kernel's steps with the instructions of a kernel set ([`Fma`]): each step's
/// vector variant where the set has its instructions, else its portable code (exact integer
/// sums and the same f32 steps, so every variant gives the same bits). Every [`Fma`] has
/// them.
pub trait IntegerVariants: Fma {
    /// The integer kernel's register block at point `p` of a tile ([`block_sums`], with NEON
    /// on AArch64 and `smlad` on ARMv7E-M; exact, so every implementation gives the same
    /// sums).
    #[inline(always)]
    fn pair_sums(self, w: &[WeightPairs], x: &[TilePairs], p: usize) -> BlockSums {
        #[cfg(all(target_arch = "aarch64", target_feature = "neon"))]
        return block_sums_neon(w, x, p);
        #[cfg(all(feature = "arm-dsp", target_arch = "arm"))]
        return block_sums_dsp(w, x, p);
        #[cfg(not(any(
            all(target_arch = "aarch64", target_feature = "neon"),
            all(feature = "arm-dsp", target_arch = "arm")
        )))]
        block_sums(w, x, p)
    }

    /// [`scaled_group_sums`]: one row block of the integer kernel over a tile, with the rows'
    /// scales and biases ([`scaled_group_sums_avx512`] or [`scaled_group_sums_avx2`] on
    /// x86-64, which keep the outputs in registers).
    #[inline(always)]
    fn scaled_group_sums(
        self,
        w: &[WeightPairs],
        affine: &BlockAffine,
        tile: QuantizedTile<'_>,
    ) -> OutputBlock {
        #[cfg(target_arch = "x86_64")]
        if let Some(avx512) = self.x86_avx512() {
            let [y] = scaled_group_sums_avx512(avx512, [w], [affine], tile);
            return y;
        }
        #[cfg(target_arch = "x86_64")]
        if let Some(avx2) = self.x86_avx2() {
            return scaled_group_sums_avx2(avx2, w, affine, tile);
        }
        scaled_group_sums(self, w, affine, tile)
    }

    /// [`IntegerVariants::scaled_group_sums`] of two consecutive row blocks (`w` holds both,
    /// `pairs` each; used where [`Fma::WIDE_REGISTERS`]: AVX-512 shares each tile load
    /// between the two, the same sums).
    #[inline(always)]
    fn scaled_group_sums_pair(
        self,
        w: &[WeightPairs],
        pairs: usize,
        affine: [&BlockAffine; 2],
        tile: QuantizedTile<'_>,
    ) -> [OutputBlock; 2] {
        #[cfg(target_arch = "x86_64")]
        if let Some(avx512) = self.x86_avx512() {
            let (first, second) = w.split_at(pairs.min(w.len()));
            return scaled_group_sums_avx512(avx512, [first, second], affine, tile);
        }
        scaled_group_sums_pair(self, w, pairs, affine, tile)
    }

    /// [`interleave_pairs`]: int8 weight rows laid out as the integer kernel's
    /// register-block slots ([`interleave_pairs_sse41`] on x86-64; a pure permutation, so
    /// every path gives the same slots).
    #[inline(always)]
    fn interleave_pairs(self, rows: [&[u8]; ROWS], out: &mut [WeightPairs]) {
        #[cfg(target_arch = "x86_64")]
        if let Some(avx2) = self.x86_avx2() {
            return interleave_pairs_sse41(avx2, rows, out);
        }
        interleave_pairs(rows, out);
    }
}

impl<F: Fma> IntegerVariants for F {}

/// Weight panels and activation tiles on 4-byte boundaries, so that the Cortex-M7 kernel
/// reads two pairs with one `ldrd` (which faults on an unaligned address).
#[repr(C, align(4))]
pub struct WordAligned<T>(pub T);

/// [`super::linear::linear`] for int8 weights on a set of at least
/// [`super::linear::SMALL_SET`] points (the caller checked that `w.int8_row` answers).
///
/// Rows are unpacked a panel at a time (each weight once per call). For each tile of
/// [`TILE`] points, the input is quantized one group of [`GROUP`] channels at a time (each
/// group has its own point scales; a part of a concatenated input starts a fresh pair and
/// group) into one tile of all the input's pairs; then each row block of the panel passes
/// over the tile group by group, and each group's exact sum, times its point scales, is
/// added to the block's outputs in f32, group after group ([`IntegerVariants::scaled_group_sums`]).
#[inline(always)]
pub fn linear_int8<F: Fma, W: WeightRows>(
    fma: F,
    w: &W,
    input: &Input<'_>,
    rows: core::ops::Range<usize>,
    mut emit: impl FnMut(usize, usize, &[f32]),
) {
    let layout = PairLayout::of(input);
    let pairs = layout.pairs();
    let panel_len = (PANEL_PAIRS / pairs.max(1) / ROWS * ROWS).clamp(ROWS, PANEL_MAX_ROWS);
    let mut panel = WordAligned([[[0i16; 2]; ROWS]; PANEL_PAIRS / ROWS]);
    let mut affine = [BlockAffine::ZERO; PANEL_MAX_ROWS / ROWS];
    let mut tile = WordAligned([[[0i16; 2]; TILE]; MAX_PAIRS]);
    let mut groups = [ScaledGroup::EMPTY; MAX_GROUPS];
    let n = input.points();
    let mut p0 = rows.start;
    while p0 < rows.end {
        let count = panel_len.min(rows.end - p0);
        let panel_rows = PanelRows { p0, count, pairs };
        panel_rows.unpack(fma, w, &layout, &mut panel.0, &mut affine);
        let mut i0 = 0;
        while i0 < n {
            let len = TILE.min(n - i0);
            let mut group_count = 0;
            for (slot, group) in groups.iter_mut().zip(layout.groups()) {
                let pairs = &mut tile.0[group.pairs.clone()];
                let scales = quantize_group(input, &group, i0, len, pairs);
                *slot = ScaledGroup {
                    pairs: (group.pairs.start, group.pairs.end),
                    scales,
                };
                group_count += 1;
            }
            let quantized = QuantizedTile {
                pairs: &tile.0,
                groups: &groups[..group_count],
            };
            let points = i0..i0 + len;
            let mut r = 0;
            while r < count {
                let at = r / ROWS;
                let block = at * pairs;
                if F::WIDE_REGISTERS && r + ROWS < count {
                    let blocks = &panel.0[block..block + 2 * pairs];
                    let affine = [&affine[at], &affine[at + 1]];
                    let [first, second] =
                        fma.scaled_group_sums_pair(blocks, pairs, affine, quantized);
                    panel_rows.emit(r, &first, &points, &mut emit);
                    panel_rows.emit(r + ROWS, &second, &points, &mut emit);
                    r += 2 * ROWS;
                } else {
                    let w = &panel.0[block..block + pairs];
                    let y = fma.scaled_group_sums(w, &affine[at], quantized);
                    panel_rows.emit(r, &y, &points, &mut emit);
                    r += ROWS;
                }
            }
            i0 += len;
        }
        p0 += count;
    }
}

/// One tile of a layer input, quantized: all its pairs, and its groups in order.
#[derive(Clone, Copy)]
pub struct QuantizedTile<'a> {
    /// The tile's pairs (`[pair][point]`).
    pub pairs: &'a [TilePairs],
    /// The groups, in order.
    pub groups: &'a [ScaledGroup],
}

/// The outputs of one row block over a tile, before the row scales.
pub type OutputBlock = [[f32; TILE]; ROWS];

/// One group of a quantized tile: its pairs (`start..end` of a row block's and the tile's
/// pairs) and its point scales.
#[derive(Clone, Copy)]
pub struct ScaledGroup {
    /// First pair and one past the last.
    pub pairs: (usize, usize),
    /// Each point's scale.
    pub scales: [f32; TILE],
}

impl ScaledGroup {
    /// No pairs.
    const EMPTY: Self = ScaledGroup {
        pairs: (0, 0),
        scales: [0.0; TILE],
    };

    /// The pairs as a range.
    #[inline(always)]
    pub fn range(&self) -> core::ops::Range<usize> {
        self.pairs.0..self.pairs.1
    }
}

/// Most pairs of a layer input: [`MAX_INPUT`] channels in up to three parts, each rounded up
/// to even.
const MAX_PAIRS: usize = MAX_INPUT / 2 + 2;
/// Most groups of a layer input: one per [`GROUP`] channels of each part, plus each part's
/// partial last group.
const MAX_GROUPS: usize = MAX_INPUT / GROUP + 3;

/// The outputs of one row block over a tile: for each group, in order, its exact sums
/// ([`IntegerVariants::pair_sums`]) times its point scales, added in f32 to outputs that start at zero
/// (`y += sum as f32 * scale`), then each row's `y * scale + bias` (`affine`).
#[inline(always)]
pub fn scaled_group_sums<F: Fma>(
    fma: F,
    w: &[WeightPairs],
    affine: &BlockAffine,
    tile: QuantizedTile<'_>,
) -> OutputBlock {
    let mut y = [[0.0f32; TILE]; ROWS];
    for group in tile.groups {
        let (w, x) = (&w[group.range()], &tile.pairs[group.range()]);
        for p in (0..TILE).step_by(POINTS) {
            let sums = fma.pair_sums(w, x, p);
            for (yr, row_sums) in y.iter_mut().zip(&sums) {
                let out = yr[p..p + POINTS].iter_mut().zip(row_sums);
                for ((yt, &sum), &scale) in out.zip(&group.scales[p..p + POINTS]) {
                    *yt += sum as f32 * scale;
                }
            }
        }
    }
    affine.apply(&mut y);
    y
}

/// [`IntegerVariants::scaled_group_sums`] of two consecutive row blocks: `w` holds both,
/// `pairs` each.
#[inline(always)]
pub fn scaled_group_sums_pair<F: Fma>(
    fma: F,
    w: &[WeightPairs],
    pairs: usize,
    affine: [&BlockAffine; 2],
    tile: QuantizedTile<'_>,
) -> [OutputBlock; 2] {
    let (first, second) = w.split_at(pairs.min(w.len()));
    [
        fma.scaled_group_sums(first, affine[0], tile),
        fma.scaled_group_sums(second, affine[1], tile),
    ]
}

/// Channels that share one point scale. 15 bits of a point's largest value over a whole
/// layer input were too coarse (instance norms amplify the rounding): int8 match agreement
/// 0.936 on the 300 x 500 reference fixture, 0.952 with groups of 32 (docs/evaluation.md,
/// "Conformance").
pub const GROUP: usize = 32;

/// Where each input part's channel pairs lie: part `p` holds pairs
/// `start[p]..start[p + 1]` (its channels rounded up to even).
struct PairLayout {
    channels: [usize; 3],
    start: [usize; 4],
}

impl PairLayout {
    #[inline(always)]
    fn of(input: &Input<'_>) -> Self {
        let mut channels = input.part_channels();
        let mut start = [0; 4];
        let mut total = 0;
        for (p, c) in channels.iter_mut().enumerate() {
            *c = (*c).min(MAX_INPUT - total);
            total += *c;
            start[p + 1] = start[p] + c.div_ceil(2);
        }
        PairLayout { channels, start }
    }

    /// The groups, in order.
    #[inline(always)]
    fn groups(&self) -> impl Iterator<Item = Group> + '_ {
        (0..3).flat_map(move |part| {
            let (channels, start) = (self.channels[part], self.start[part]);
            (0..channels).step_by(GROUP).map(move |first| {
                let last = (first + GROUP).min(channels);
                Group {
                    part,
                    channels: first..last,
                    pairs: start + first / 2..start + last.div_ceil(2),
                }
            })
        })
    }

    /// All pairs.
    #[inline(always)]
    fn pairs(&self) -> usize {
        self.start[3]
    }

    /// The pair ranges of the parts.
    #[inline(always)]
    fn ranges(&self) -> impl Iterator<Item = core::ops::Range<usize>> + '_ {
        (0..3).map(|p| self.start[p]..self.start[p + 1])
    }
}

/// Up to [`GROUP`] channels of one input part that share point scales, and their pairs.
struct Group {
    part: usize,
    channels: core::ops::Range<usize>,
    pairs: core::ops::Range<usize>,
}

/// The scale and bias of each row of a register block: output `y * scale + bias`.
#[derive(Clone, Copy)]
pub struct BlockAffine {
    /// Each row's scale.
    pub scale: [f32; ROWS],
    /// Each row's bias.
    pub bias: [f32; ROWS],
}

impl BlockAffine {
    const ZERO: Self = BlockAffine {
        scale: [0.0; ROWS],
        bias: [0.0; ROWS],
    };

    /// `y * scale + bias` of each row.
    #[inline(always)]
    fn apply(&self, y: &mut OutputBlock) {
        for ((yr, &scale), &bias) in y.iter_mut().zip(&self.scale).zip(&self.bias) {
            for yt in yr.iter_mut() {
                *yt = *yt * scale + bias;
            }
        }
    }
}

/// Rows `p0..p0 + count` of a panel of `pairs` pairs per row.
struct PanelRows {
    p0: usize,
    count: usize,
    pairs: usize,
}

impl PanelRows {
    /// Unpacks the rows into `panel`, interleaved by row block (`[pair][ROWS]`; zero past
    /// `count` and in each odd part's pad), with their scales and biases. A block's part
    /// whose rows all hold its even number of channels is interleaved by
    /// [`IntegerVariants::interleave_pairs`]; any other part lane by lane.
    #[inline(always)]
    fn unpack<F: Fma, W: WeightRows>(
        &self,
        fma: F,
        w: &W,
        layout: &PairLayout,
        panel: &mut [WeightPairs],
        affine: &mut [BlockAffine],
    ) {
        let pairs = self.pairs;
        for r0 in (0..self.count).step_by(ROWS) {
            let lanes = &mut panel[r0 / ROWS * pairs..(r0 / ROWS + 1) * pairs];
            let mut bytes: [&[u8]; ROWS] = core::array::from_fn(|lane| {
                let r = r0 + lane;
                if r < self.count {
                    affine[r0 / ROWS].scale[lane] = w.scale(self.p0 + r);
                    affine[r0 / ROWS].bias[lane] = w.bias(self.p0 + r);
                    w.int8_row(self.p0 + r).unwrap_or(&[])
                } else {
                    &[]
                }
            });
            for (range, &channels) in layout.ranges().zip(&layout.channels) {
                let parts = bytes.map(|b| b.split_at(channels.min(b.len())));
                bytes = parts.map(|(_, rest)| rest);
                let part = parts.map(|(part, _)| part);
                let slots = &mut lanes[range];
                if channels % 2 == 0 && part.iter().all(|b| b.len() == channels) {
                    fma.interleave_pairs(part, slots);
                } else {
                    for (lane, row) in part.iter().enumerate() {
                        let mut chunks = row.chunks(2);
                        for slot in slots.iter_mut() {
                            slot[lane] = match chunks.next() {
                                Some(&[a, b]) => pair(a, b),
                                Some(&[a]) => pair(a, 0),
                                _ => [0, 0],
                            };
                        }
                    }
                }
            }
        }
    }

    /// Emits the outputs `y` of the row block of panel rows `r..` (those below `count`) at
    /// `points`. A function, not a closure, so that it is inlined into the caller's kernel
    /// set (an outlined closure runs on the baseline instructions).
    #[inline(always)]
    fn emit(
        &self,
        r: usize,
        y: &OutputBlock,
        points: &core::ops::Range<usize>,
        emit: &mut impl FnMut(usize, usize, &[f32]),
    ) {
        for (r, yr) in (r..self.count).zip(y) {
            emit(self.p0 + r, points.start, &yr[..points.len()]);
        }
    }
}

/// `out[q][lane]` = channels `2q` and `2q + 1` of `rows[lane]` (int8, as pairs of `i16`),
/// for every `q < out.len()`; `rows[lane]` holds `2 * out.len()` channels.
#[inline(always)]
pub fn interleave_pairs(rows: [&[u8]; ROWS], out: &mut [WeightPairs]) {
    for (q, slot) in out.iter_mut().enumerate() {
        for (slot_pair, row) in slot.iter_mut().zip(&rows) {
            *slot_pair = match row.get(2 * q..2 * q + 2) {
                Some(&[a, b]) => pair(a, b),
                _ => [0, 0],
            };
        }
    }
}

/// Two int8 weights (stored as bytes) as a channel pair.
#[inline(always)]
fn pair(a: u8, b: u8) -> Pair {
    [i16::from(a as i8), i16::from(b as i8)]
}

/// [`interleave_pairs`] with SSE4.1 (x86-64, `ROWS` = 4): four pairs of the four rows at a
/// time, transposed as 16-bit pairs (`punpcklwd`, `punpck*dq`), then each slot's 8 bytes
/// sign-extended (`pmovsxbw`) and stored; the tail as [`interleave_pairs`].
#[cfg(target_arch = "x86_64")]
#[inline(always)]
#[allow(unsafe_code)]
pub fn interleave_pairs_sse41(
    _avx2: super::dispatch::X86Fma,
    rows: [&[u8]; ROWS],
    out: &mut [WeightPairs],
) {
    use core::arch::x86_64::{
        _mm_cvtepi8_epi16, _mm_loadl_epi64, _mm_srli_si128, _mm_storeu_si128, _mm_unpackhi_epi32,
        _mm_unpacklo_epi16, _mm_unpacklo_epi32,
    };
    const { assert!(ROWS == 4) };
    let quads = out.len() / 4;
    let fits = rows.iter().all(|r| r.len() >= 8 * quads);
    if !fits {
        return interleave_pairs(rows, out);
    }
    let (body, tail) = out.split_at_mut(4 * quads);
    for (c, slots) in body.chunks_exact_mut(4).enumerate() {
        // SAFETY: an `X86Fma` exists only on a CPU with AVX2 (so SSE4.1). Each load reads
        // 8 bytes of a row at `8c` (`8c + 8 <= 8 * quads <= len`, checked above); each
        // store writes 16 bytes (one `WeightPairs` of 4 `[i16; 2]`) into `slots`, which
        // holds 4; `loadl`/`storeu` need no alignment.
        unsafe {
            let load = |row: &[u8]| _mm_loadl_epi64(row.as_ptr().add(8 * c).cast());
            let low = _mm_unpacklo_epi16(load(rows[0]), load(rows[1]));
            let high = _mm_unpacklo_epi16(load(rows[2]), load(rows[3]));
            let first = _mm_unpacklo_epi32(low, high);
            let second = _mm_unpackhi_epi32(low, high);
            let blocks = [
                first,
                _mm_srli_si128::<8>(first),
                second,
                _mm_srli_si128::<8>(second),
            ];
            for (slot, bytes) in slots.iter_mut().zip(blocks) {
                _mm_storeu_si128(slot.as_mut_ptr().cast(), _mm_cvtepi8_epi16(bytes));
            }
        }
    }
    let rest = rows.map(|r| r.get(8 * quads..).unwrap_or(&[]));
    interleave_pairs(rest, tail);
}

/// Quantizes points `i0..i0 + len` of `group`'s channels into `tile` (`[pair][point]`, zero
/// in the pad of an odd last channel) and returns the group's point scales (`max|x| / 32767`
/// over its channels, 0 for an all-zero point). A part too short reads as zeros, as in the
/// f32 kernel. A full tile is read in place (the part's values found once for the group);
/// a short one is first copied, zero-padded.
#[inline(always)]
fn quantize_group(
    input: &Input<'_>,
    group: &Group,
    i0: usize,
    len: usize,
    tile: &mut [TilePairs],
) -> [f32; TILE] {
    let channel = |c: usize| input.channel(group.part, c, i0, len);
    // Channels lie one after the other: when the last has the whole tile, all have.
    let last = group.channels.end.saturating_sub(1);
    if channel(last).first_chunk::<TILE>().is_some() {
        let first = group.channels.start;
        let (values, stride) = input.channels_from(group.part, first, i0);
        quantize_channels(group, tile, |c| {
            let row = values.get((c - first) * stride..);
            row.and_then(|v| v.first_chunk::<TILE>())
                .unwrap_or(&[0.0; TILE])
        })
    } else {
        let mut values = [[0.0f32; TILE]; GROUP];
        for (row, c) in values.iter_mut().zip(group.channels.clone()) {
            *row = padded(channel(c));
        }
        let first = group.channels.start;
        quantize_channels(group, tile, |c| &values[c - first])
    }
}

/// [`quantize_group`] on the tile values of each channel of `group`, `values(c)`.
#[inline(always)]
fn quantize_channels<'a>(
    group: &Group,
    tile: &mut [TilePairs],
    values: impl Fn(usize) -> &'a [f32; TILE],
) -> [f32; TILE] {
    // Up to two running maxima (even and odd channels, `blocking::QUANTIZE_MAX_CHAINS`),
    // so that two chains of `max` are in flight; the maximum is exact, so the same value.
    let (mut even, mut odd) = ([0.0f32; TILE], [0.0f32; TILE]);
    for c in group.channels.clone().step_by(QUANTIZE_MAX_CHAINS) {
        running_max_abs(&mut even, values(c));
        if QUANTIZE_MAX_CHAINS == 2 && c + 1 < group.channels.end {
            running_max_abs(&mut odd, values(c + 1));
        }
    }
    let max_abs: [f32; TILE] = core::array::from_fn(|t| larger(even[t], odd[t]));
    let inverse = max_abs.map(|m| if m > 0.0 { Q_MAX / m } else { 0.0 });
    for (slot, c) in tile.iter_mut().zip(group.channels.clone().step_by(2)) {
        let even = quantized(values(c), &inverse);
        let odd = if c + 1 < group.channels.end {
            quantized(values(c + 1), &inverse)
        } else {
            [0; TILE]
        };
        *slot = interleave(even, odd);
    }
    max_abs.map(|m| m / Q_MAX)
}

/// `m[t] = max(m[t], |x[t]|)` (NaNs skipped).
#[inline(always)]
fn running_max_abs(m: &mut [f32; TILE], x: &[f32; TILE]) {
    for (m, v) in m.iter_mut().zip(x) {
        let v = v.abs();
        *m = if v > *m { v } else { *m };
    }
}

/// The larger of two values that are not NaN.
#[inline(always)]
fn larger(a: f32, b: f32) -> f32 {
    if b > a {
        b
    } else {
        a
    }
}

/// One channel's tile values times each point's inverse scale, quantized.
#[inline(always)]
fn quantized(x: &[f32; TILE], inverse: &[f32; TILE]) -> [i16; TILE] {
    core::array::from_fn(|t| quantize(x[t] * inverse[t]))
}

/// A channel's values at one tile's points, zero past the end.
#[inline(always)]
fn padded(values: &[f32]) -> [f32; TILE] {
    let mut x = [0.0; TILE];
    for (xt, &v) in x.iter_mut().zip(values) {
        *xt = v;
    }
    x
}

/// Channels `2p` and `2p + 1` of a tile's points as pairs.
#[inline(always)]
fn interleave(even: [i16; TILE], odd: [i16; TILE]) -> TilePairs {
    core::array::from_fn(|t| [even[t], odd[t]])
}

/// `v` clamped to `±Q_MAX` (NaN to `-Q_MAX`) and rounded to the nearest integer (ties to
/// even): after adding [`ROUNDER`] the integer sits in the low mantissa bits, so integer
/// arithmetic on the bit patterns reads it off (no float-to-int conversion, which
/// vectorises poorly).
#[inline(always)]
fn quantize(v: f32) -> i16 {
    let v = if v >= -Q_MAX { v } else { -Q_MAX };
    let v = if v <= Q_MAX { v } else { Q_MAX };
    ((v + ROUNDER).to_bits() as i32 - ROUNDER.to_bits() as i32) as i16
}

/// `ROWS x POINTS` sums starting at point `p` of the tile; the accumulators stay in registers.
#[inline(always)]
pub fn block_sums(w: &[WeightPairs], x: &[TilePairs], p: usize) -> BlockSums {
    let mut acc = [[0i32; POINTS]; ROWS];
    for (wk, xk) in w.iter().zip(x) {
        let Some(points) = xk.get(p..).and_then(|s| s.first_chunk::<POINTS>()) else {
            continue;
        };
        for (a, &wr) in acc.iter_mut().zip(wk) {
            for (at, &xt) in a.iter_mut().zip(points) {
                *at = multiply_accumulate(*at, wr, xt);
            }
        }
    }
    acc
}

/// One channel pair of the Cortex-M7 register block (the template of [`block_sums_dsp`]'s
/// `asm!`): the two rows' weights and the two points with one `ldrd` each, four `smlad`.
#[cfg(all(feature = "arm-dsp", target_arch = "arm"))]
macro_rules! smlad_pair {
    () => {
        concat!(
            "ldrd {w0}, {w1}, [{wp}], #8\n",
            "ldrd {x0}, {x1}, [{xp}], #{stride}\n",
            "smlad {a00}, {w0}, {x0}, {a00}\n",
            "smlad {a01}, {w0}, {x1}, {a01}\n",
            "smlad {a10}, {w1}, {x0}, {a10}\n",
            "smlad {a11}, {w1}, {x1}, {a11}"
        )
    };
}

/// [`block_sums`] with ARMv7E-M's `smlad` in a loop of its own (the core's `arm-dsp`
/// feature): per channel pair one `ldrd` of the two rows' weights, one `ldrd` of the two
/// points and four `smlad`, four pairs a turn (6.5 instructions a pair; one `ldr` per word
/// and a pair a turn took 10). Slices not on 4-byte boundaries (see [`WordAligned`]) take the
/// portable [`block_sums`].
#[cfg(all(feature = "arm-dsp", target_arch = "arm"))]
#[inline(always)]
#[allow(unsafe_code)]
pub fn block_sums_dsp(w: &[WeightPairs], x: &[TilePairs], p: usize) -> BlockSums {
    const { assert!(ROWS == 2 && POINTS == 2) };
    let pairs = w.len().min(x.len());
    let unaligned = (w.as_ptr() as usize | x.as_ptr() as usize) & 3 != 0;
    if p + POINTS > TILE || pairs == 0 || unaligned {
        return block_sums(w, x, p);
    }
    let (mut a00, mut a01, mut a10, mut a11) = (0i32, 0i32, 0i32, 0i32);
    // SAFETY: the loop reads `pairs` weight pairs of two rows (8 bytes each, from `w`) and,
    // for each, points `p` and `p + 1` of one tile pair (`x[k][p..p + 2]`, in bounds as
    // `p + 2 <= TILE`), walking `x` by its 64-byte stride: all inside the two slices, whose
    // starts are 4-byte aligned (checked above; every offset is a multiple of 4), as `ldrd`
    // requires. `smlad` only touches the registers given (and may set the sticky Q flag,
    // which nothing reads); the `arm-dsp` feature declares an ARMv7E-M target, which has
    // the instruction. The count's two low bits are taken before the loop: each `lsrs` moves
    // one into the carry and sets Z when no turn of four is left (`ldrd` and `smlad` keep
    // the flags).
    unsafe {
        core::arch::asm!(
            "lsrs {n}, {n}, #1",
            "bcc 3f",
            smlad_pair!(),
            "3:",
            "lsrs {n}, {n}, #1",
            "bcc 4f",
            smlad_pair!(),
            smlad_pair!(),
            "4:",
            "beq 5f",
            "2:",
            smlad_pair!(),
            smlad_pair!(),
            smlad_pair!(),
            smlad_pair!(),
            "subs {n}, {n}, #1",
            "bne 2b",
            "5:",
            stride = const core::mem::size_of::<TilePairs>(),
            wp = inout(reg) w.as_ptr() => _,
            xp = inout(reg) x.as_ptr().cast::<Pair>().add(p) => _,
            n = inout(reg) pairs => _,
            w0 = out(reg) _,
            w1 = out(reg) _,
            x0 = out(reg) _,
            x1 = out(reg) _,
            a00 = inout(reg) a00,
            a01 = inout(reg) a01,
            a10 = inout(reg) a10,
            a11 = inout(reg) a11,
            options(nostack, readonly)
        );
    }
    [[a00, a01], [a10, a11]]
}

/// [`scaled_group_sums`] with AVX2: `vpmaddwd` (`_mm256_madd_epi16`: eight pair products
/// summed into 32-bit lanes per instruction) for each group's sums over a whole tile (a
/// register block is a tile), converted, scaled and added to the outputs in registers.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
#[allow(unsafe_code)]
pub fn scaled_group_sums_avx2(
    _avx2: super::dispatch::X86Fma,
    w: &[WeightPairs],
    affine: &BlockAffine,
    quantized: QuantizedTile<'_>,
) -> OutputBlock {
    use core::arch::x86_64::{
        __m256i, _mm256_add_epi32, _mm256_add_ps, _mm256_cvtepi32_ps, _mm256_loadu_ps,
        _mm256_loadu_si256, _mm256_madd_epi16, _mm256_mul_ps, _mm256_set1_epi32, _mm256_set1_ps,
        _mm256_setzero_ps, _mm256_setzero_si256, _mm256_storeu_ps,
    };
    const HALF: usize = TILE / 2;
    const { assert!(POINTS == 16 && TILE == 16) };
    let mut y = [[0.0f32; TILE]; ROWS];
    // SAFETY: an `X86Fma` exists only on a CPU with AVX2 (see `dispatch`). Each integer load
    // reads 8 pairs (32 bytes) of a `[Pair; 16]` (64 bytes) at pair 0 or 8, each float load
    // 8 `f32` of a `[f32; 16]` at 0 or 8, and each store writes 8 `f32` into a `[f32; 16]`
    // at 0 or 8: all in bounds; `loadu`/`storeu` need no alignment.
    unsafe {
        let mut out = [[_mm256_setzero_ps(); 2]; ROWS];
        for group in quantized.groups {
            let pairs = w.get(group.range()).unwrap_or(&[]);
            let tile = quantized.pairs.get(group.range()).unwrap_or(&[]);
            let mut acc = [[_mm256_setzero_si256(); 2]; ROWS];
            for (wk, xk) in pairs.iter().zip(tile) {
                let points: [__m256i; 2] =
                    [0, HALF].map(|at| _mm256_loadu_si256(xk.as_ptr().add(at).cast()));
                for (a, wr) in acc.iter_mut().zip(wk) {
                    let weights = _mm256_set1_epi32(pair_bits(*wr));
                    for (lane, &xs) in a.iter_mut().zip(&points) {
                        *lane = _mm256_add_epi32(*lane, _mm256_madd_epi16(weights, xs));
                    }
                }
            }
            let scale = [0, HALF].map(|at| _mm256_loadu_ps(group.scales.as_ptr().add(at)));
            for (o, a) in out.iter_mut().zip(&acc) {
                for ((o, &a), &s) in o.iter_mut().zip(a).zip(&scale) {
                    *o = _mm256_add_ps(*o, _mm256_mul_ps(_mm256_cvtepi32_ps(a), s));
                }
            }
        }
        for (((row, o), &scale), &bias) in
            y.iter_mut().zip(&out).zip(&affine.scale).zip(&affine.bias)
        {
            let (scale, bias) = (_mm256_set1_ps(scale), _mm256_set1_ps(bias));
            for (at, &lane) in [0, HALF].into_iter().zip(o) {
                let lane = _mm256_add_ps(_mm256_mul_ps(lane, scale), bias);
                _mm256_storeu_ps(row.as_mut_ptr().add(at), lane);
            }
        }
    }
    y
}

/// [`scaled_group_sums`] of `B` row blocks with AVX-512 VNNI: `vpdpwssd`
/// (`_mm512_dpwssd_epi32`: sixteen pair products added to 32-bit lanes per instruction, the
/// whole tile, with no separate add) for each group's sums, each tile load serving every
/// block (two blocks are eight chains in flight; integer sums do not depend on their order),
/// then converted, scaled and added to the outputs in registers as
/// [`scaled_group_sums_avx2`] does.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
#[allow(unsafe_code)]
pub fn scaled_group_sums_avx512<const B: usize>(
    _avx512: super::dispatch::X86Fma<true>,
    blocks: [&[WeightPairs]; B],
    affine: [&BlockAffine; B],
    quantized: QuantizedTile<'_>,
) -> [OutputBlock; B] {
    use core::arch::x86_64::{
        _mm512_add_ps, _mm512_cvtepi32_ps, _mm512_dpwssd_epi32, _mm512_loadu_ps,
        _mm512_loadu_si512, _mm512_mul_ps, _mm512_set1_epi32, _mm512_set1_ps, _mm512_setzero_ps,
        _mm512_setzero_si512, _mm512_storeu_ps,
    };
    const { assert!(POINTS == 16 && TILE == 16) };
    let mut y = [[[0.0f32; TILE]; ROWS]; B];
    // SAFETY: an `X86Fma<true>` exists only on a CPU with AVX-512 F, BW, VL and VNNI (see
    // `dispatch`). Each integer load reads one `[Pair; 16]` (64 bytes), each float load one
    // `[f32; 16]` and each store writes one `[f32; 16]`: all in bounds; `loadu`/`storeu` need
    // no alignment.
    unsafe {
        let mut out = [[_mm512_setzero_ps(); ROWS]; B];
        for group in quantized.groups {
            let tile = quantized.pairs.get(group.range()).unwrap_or(&[]);
            let weights = blocks.map(|b| b.get(group.range()).unwrap_or(&[]));
            let len = weights.iter().fold(tile.len(), |len, w| len.min(w.len()));
            let mut acc = [[_mm512_setzero_si512(); ROWS]; B];
            for (k, xk) in tile[..len].iter().enumerate() {
                let points = _mm512_loadu_si512(xk.as_ptr().cast());
                for (acc, w) in acc.iter_mut().zip(&weights) {
                    for (a, wr) in acc.iter_mut().zip(&w[k]) {
                        *a = _mm512_dpwssd_epi32(*a, _mm512_set1_epi32(pair_bits(*wr)), points);
                    }
                }
            }
            let scale = _mm512_loadu_ps(group.scales.as_ptr());
            for (out, acc) in out.iter_mut().zip(&acc) {
                for (o, &sums) in out.iter_mut().zip(acc) {
                    *o = _mm512_add_ps(*o, _mm512_mul_ps(_mm512_cvtepi32_ps(sums), scale));
                }
            }
        }
        for ((y, out), affine) in y.iter_mut().zip(&out).zip(affine) {
            let rows = y.iter_mut().zip(out).zip(&affine.scale).zip(&affine.bias);
            for (((row, &o), &scale), &bias) in rows {
                let o = _mm512_add_ps(
                    _mm512_mul_ps(o, _mm512_set1_ps(scale)),
                    _mm512_set1_ps(bias),
                );
                _mm512_storeu_ps(row.as_mut_ptr(), o);
            }
        }
    }
    y
}

/// [`block_sums`] with AArch64 NEON: `smlal`/`smlal2` multiply four points' pairs by the
/// row's pair (each lane one product, even lanes channel `k`, odd lanes `k + 1`), and one
/// `addp` at the end adds each point's two lanes. A block is a whole tile (`p` is 0), done
/// in two halves of 8 points so that the 16 accumulators stay in registers.
#[cfg(all(target_arch = "aarch64", target_feature = "neon"))]
#[inline(always)]
#[allow(unsafe_code)]
pub fn block_sums_neon(w: &[WeightPairs], x: &[TilePairs], p: usize) -> BlockSums {
    use core::arch::aarch64::{
        int16x8_t, int32x4_t, vdupq_n_s32, vget_low_s16, vld1q_s16, vmlal_high_s16, vmlal_s16,
        vpaddq_s32, vreinterpretq_s16_s32, vst1q_s32,
    };
    const HALF: usize = POINTS / 2;
    debug_assert_eq!((p, POINTS, TILE), (0, 16, 16));
    let mut sums = [[0i32; POINTS]; ROWS];
    // SAFETY: NEON is enabled (`cfg` above). Each load reads 4 pairs (16 bytes) of a
    // `[Pair; 16]` at pair 0, 4, 8 or 12, and each store writes 4 `i32` into a `[i32; 16]`
    // at 0, 4, 8 or 12: all in bounds; `ld1`/`st1` need only the elements' alignment.
    unsafe {
        for half in [0, HALF] {
            let zero = vdupq_n_s32(0);
            let (mut even, mut odd): ([[int32x4_t; 2]; ROWS], [[int32x4_t; 2]; ROWS]) =
                ([[zero; 2]; ROWS], [[zero; 2]; ROWS]);
            for (wk, xk) in w.iter().zip(x) {
                let points: [int16x8_t; 2] =
                    [0, 4].map(|at| vld1q_s16(xk.as_ptr().add(half + at).cast()));
                for ((e, o), wr) in even.iter_mut().zip(odd.iter_mut()).zip(wk) {
                    let weights = vreinterpretq_s16_s32(vdupq_n_s32(pair_bits(*wr)));
                    for ((e, o), &xs) in e.iter_mut().zip(o.iter_mut()).zip(&points) {
                        *e = vmlal_s16(*e, vget_low_s16(xs), vget_low_s16(weights));
                        *o = vmlal_high_s16(*o, xs, weights);
                    }
                }
            }
            for ((row, e), o) in sums.iter_mut().zip(&even).zip(&odd) {
                for (at, (&e, &o)) in [0, 4].into_iter().zip(e.iter().zip(o)) {
                    vst1q_s32(row.as_mut_ptr().add(half + at), vpaddq_s32(e, o));
                }
            }
        }
    }
    sums
}

/// A pair as one 32-bit word: channel `k` in the low half, as `vpmaddwd` and `smlad` read it.
#[cfg(any(
    target_arch = "x86_64",
    all(target_arch = "aarch64", target_feature = "neon")
))]
#[inline(always)]
fn pair_bits(pair: Pair) -> i32 {
    (u32::from(pair[0] as u16) | u32::from(pair[1] as u16) << 16) as i32
}

/// `acc + w[0] x[0] + w[1] x[1]` (no overflow: each product is below 2^22, and the sums of
/// a layer below 2^31).
#[inline(always)]
fn multiply_accumulate(acc: i32, w: Pair, x: Pair) -> i32 {
    acc.wrapping_add(i32::from(w[0]) * i32::from(x[0]) + i32::from(w[1]) * i32::from(x[1]))
}

#[cfg(test)]
mod tests {
    use super::super::dispatch::{limit_kernels, KernelSet, Portable};
    use super::super::linear::{linear, linear_with, store, SMALL_SET};
    use super::*;
    use crate::weights::{tests_support, Precision};

    /// A layer of `ROWS_ x COLS` int8 weights from `sin`, scales and biases from `cos`.
    struct Layer {
        weights: [u8; 9 * 37],
        scales: [u8; 9 * 4],
        bias: [u8; 9 * 4],
    }

    const ROWS_: usize = 9;
    const COLS: usize = 37;

    impl Layer {
        /// The layer as the kernel reads it.
        fn linear(&self) -> crate::weights::Linear<'_> {
            tests_support::linear(
                ROWS_,
                COLS,
                Precision::Int8,
                &self.weights,
                &self.scales,
                &self.bias,
            )
        }

        /// Row `r`'s scale.
        fn scale(&self, r: usize) -> f32 {
            f32::from_le_bytes(self.scales[r * 4..r * 4 + 4].try_into().unwrap())
        }

        /// Row `r`'s bias.
        fn bias(&self, r: usize) -> f32 {
            f32::from_le_bytes(self.bias[r * 4..r * 4 + 4].try_into().unwrap())
        }
    }

    fn layer() -> Layer {
        let mut scales = [0u8; 9 * 4];
        let mut bias = [0u8; 9 * 4];
        for r in 0..ROWS_ {
            scales[r * 4..r * 4 + 4].copy_from_slice(&(0.01 + 0.002 * r as f32).to_le_bytes());
            bias[r * 4..r * 4 + 4].copy_from_slice(&libm::cosf(r as f32).to_le_bytes());
        }
        let weights = core::array::from_fn(|i| (libm::sinf(i as f32 * 0.61) * 127.0) as i8 as u8);
        Layer {
            weights,
            scales,
            bias,
        }
    }

    /// The definition in the module doc, written out point by point with `i64` sums.
    fn expected(layer: &Layer, x: &[f32], n: usize, r: usize, i: usize) -> f32 {
        let mut y = 0.0f32;
        for first in (0..COLS).step_by(GROUP) {
            let group = first..(first + GROUP).min(COLS);
            let max_abs = group.clone().fold(0.0f32, |m, k| m.max(x[k * n + i].abs()));
            let inv = if max_abs > 0.0 { Q_MAX / max_abs } else { 0.0 };
            let sum: i64 = group
                .map(|k| {
                    let w = i64::from(layer.weights[r * COLS + k] as i8);
                    let q = libm::rintf(x[k * n + i] * inv).clamp(-Q_MAX, Q_MAX) as i64;
                    w * q
                })
                .sum();
            y += sum as f32 * (max_abs / Q_MAX);
        }
        y * layer.scale(r) + layer.bias(r)
    }

    struct Interleave<'a>([&'a [u8]; ROWS], &'a mut [WeightPairs]);

    impl super::super::dispatch::Kernel<()> for Interleave<'_> {
        fn run<F: Fma>(self, fma: F) {
            fma.interleave_pairs(self.0, self.1);
        }
    }

    /// Rows of 0 to 21 pairs (whole groups of four pairs and tails), every byte value: the
    /// dispatched interleave (SSE4.1 where the CPU has it) puts channels `2q`, `2q + 1` of
    /// row `lane` at slot `q`, lane `lane`, sign-extended, and writes nothing past `out`.
    #[test]
    fn weight_pairs_interleave_by_definition_on_every_path() {
        let bytes: std::vec::Vec<u8> = (0..4 * 42).map(|i| (i * 97 + 13) as u8).collect();
        for pairs in 0..=21 {
            let rows: [&[u8]; ROWS] =
                core::array::from_fn(|lane| &bytes[lane * 42..lane * 42 + 2 * pairs]);
            let mut out = std::vec![[[7i16; 2]; ROWS]; pairs + 1];
            super::super::dispatch::with_fma(Interleave(rows, &mut out[..pairs]));
            for (q, slot) in out[..pairs].iter().enumerate() {
                for (lane, pair) in slot.iter().enumerate() {
                    let channel = |c: usize| i16::from(rows[lane][c] as i8);
                    assert_eq!(*pair, [channel(2 * q), channel(2 * q + 1)], "{pairs} {q}");
                }
            }
            assert_eq!(out[pairs], [[7; 2]; ROWS], "wrote past the slots");
        }
    }

    /// 9 rows (a partial row block) x 37 inputs (an odd count) on 45 points (a partial tile),
    /// one point all zero: the dispatched kernels (AVX2 and AVX-512 VNNI where the CPU has
    /// them), the portable one
    /// (NEON on AArch64) and the definition agree bit for bit, and the result is within the
    /// activations' rounding of the f32 product.
    #[test]
    fn integer_kernel_follows_its_definition_on_every_path() {
        const N: usize = 45;
        let layer = layer();
        let linear_layer = layer.linear();
        let mut x: [f32; COLS * N] = core::array::from_fn(|i| libm::cosf(i as f32 * 1.3) * 2.0);
        for k in 0..COLS {
            x[k * N + 7] = 0.0;
        }
        let input = Input::one(&x, COLS, N);
        let mut portable = [0.0f32; ROWS_ * N];
        linear_with(Portable, &linear_layer, &input, 0..ROWS_, |r, i0, v| {
            store(&mut portable, N, r, i0, v)
        });
        let mut dispatched = [0.0f32; ROWS_ * N];
        for set in [KernelSet::Avx2, KernelSet::Avx512] {
            limit_kernels(set);
            linear(&linear_layer, &input, 0..ROWS_, |r, i0, v| {
                store(&mut dispatched, N, r, i0, v)
            });
            assert_eq!(dispatched.map(f32::to_bits), portable.map(f32::to_bits));
        }
        for r in 0..ROWS_ {
            let scale = layer.scale(r);
            for i in 0..N {
                let got = dispatched[r * N + i];
                assert_eq!(got.to_bits(), expected(&layer, &x, N, r, i).to_bits());
                let float: f32 = (0..COLS)
                    .map(|k| f32::from(layer.weights[r * COLS + k] as i8) * x[k * N + i])
                    .sum::<f32>()
                    * scale
                    + layer.bias(r);
                assert!(
                    (got - float).abs() < 1e-3,
                    "row {r} point {i}: {got} vs {float}"
                );
            }
        }
        const { assert!(N >= SMALL_SET) };
    }

    /// A concatenated input of three parts on their own scales (one of odd width), a window
    /// of its points, a row sub-range and a column slice of the layer: every output is
    /// within the activations' rounding of the f32 kernel's.
    #[test]
    fn parts_windows_and_slices_stay_close_to_the_f32_kernel() {
        const N: usize = 40;
        let layer = layer();
        let linear_layer = layer.linear();
        let (a_rows, b_rows, c_rows) = (10, 13, 14);
        let a: [f32; 10 * N] = core::array::from_fn(|i| libm::sinf(i as f32) * 100.0);
        let b: [f32; 13 * N] = core::array::from_fn(|i| libm::cosf(i as f32 * 0.3) * 0.01);
        let c: [f32; 14 * N] = core::array::from_fn(|i| libm::sinf(i as f32 * 2.1));
        let input =
            Input::parts([&a, &b, &c], [a_rows, b_rows, c_rows], N).columns(5, SMALL_SET + 3);
        let slice = super::super::operands::ColumnSlice {
            layer: &linear_layer,
            start: a_rows,
            cols: b_rows + c_rows,
        };
        let tail = Input::two((&b, b_rows), (&c, c_rows), N);
        let float = |row: usize, point: usize, first: usize, parts: &[(&[f32], usize)]| {
            let mut k = first;
            let mut sum = 0.0f64;
            for (x, rows) in parts {
                for ch in 0..*rows {
                    let w = f64::from(layer.weights[row * COLS + k] as i8);
                    sum += w * f64::from(x[ch * N + point]);
                    k += 1;
                }
            }
            sum * f64::from(layer.scale(row))
        };
        let bias = |row: usize| f64::from(layer.bias(row));
        let mut checked = 0;
        linear(&linear_layer, &input, 3..ROWS_, |r, i0, v| {
            for (t, &got) in v.iter().enumerate() {
                let want = float(
                    r,
                    5 + i0 + t,
                    0,
                    &[(&a, a_rows), (&b, b_rows), (&c, c_rows)],
                ) + bias(r);
                // Each part's rounding: half a step of its largest value per channel.
                assert!(
                    (f64::from(got) - want).abs() < 0.05,
                    "row {r}: {got} vs {want}"
                );
                checked += 1;
            }
        });
        linear(&slice, &tail, 0..ROWS_, |r, i0, v| {
            for (t, &got) in v.iter().enumerate() {
                let want = float(r, i0 + t, a_rows, &[(&b, b_rows), (&c, c_rows)]);
                assert!(
                    (f64::from(got) - want).abs() < 1e-3,
                    "slice row {r}: {got} vs {want}"
                );
                checked += 1;
            }
        });
        assert_eq!(checked, (ROWS_ - 3) * (SMALL_SET + 3) + ROWS_ * N);
    }

    /// The largest magnitudes (weights -128, activations at full scale, 512 inputs) sum
    /// without overflow.
    #[test]
    fn the_widest_layer_at_full_scale_does_not_overflow() {
        let weights = [0x80u8; MAX_INPUT];
        let scales = 1.0f32.to_le_bytes();
        let linear_layer =
            tests_support::linear(1, MAX_INPUT, Precision::Int8, &weights, &scales, &[]);
        let x = [-3.0f32; MAX_INPUT * SMALL_SET];
        let mut out = [0.0f32; SMALL_SET];
        linear(
            &linear_layer,
            &Input::one(&x, MAX_INPUT, SMALL_SET),
            0..1,
            |_, i0, v| out[i0..i0 + v.len()].copy_from_slice(v),
        );
        let exact = 128.0 * 3.0 * MAX_INPUT as f32;
        assert!(out.iter().all(|&y| (y - exact).abs() < 0.1), "{out:?}");
    }
}
