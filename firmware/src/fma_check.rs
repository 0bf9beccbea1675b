//! Self-check of the build's fused multiply-add: the matcher's `mul_add` (the hardware
//! instruction where the build enables it: `vfma.f32`, `fmadd`, x86 FMA) and the linear
//! kernel's `mul_add_lanes` (NEON `fmla` on AArch64) must give the same bits as libm's exact
//! `fmaf` over many random triples, or the image's numbers would not be the host's; and the
//! int8 kernel's register block of this instruction set (`smlad`, NEON, AVX2 through
//! `pair_sums`) must give the portable block's exact sums, and its f16 widening the software
//! conversion's.

use gomatch::nn::dispatch::{f16_to_f32, Fma, Portable};
use gomatch::nn::fma::mul_add;
use gomatch::nn::integer::{
    block_sums, IntegerVariants, TilePairs, WeightPairs, WordAligned, POINTS, TILE,
};
use gomatch::nn::COL_BLOCK;
use gomatch::rng::SplitMix64;

/// Random triples checked.
const TRIPLES: u32 = 100_000;

/// A triple on which `mul_add` and `libm::fmaf` differ.
pub struct Mismatch {
    /// The operands `a, b, c` of `a * b + c`, as bits.
    pub operands: [u32; 3],
    /// `mul_add`'s result, as bits.
    pub got: u32,
    /// `libm::fmaf`'s result, as bits.
    pub expected: u32,
}

/// Checks [`TRIPLES`] triples, half of arbitrary bit patterns (every exponent, subnormals,
/// infinities), half with `c` close to `-a * b` so that the sum cancels and the single
/// rounding decides the last bits; then as many again through `mul_add_lanes`, in rows of
/// [`COL_BLOCK`] lanes sharing one multiplier.
pub fn run() -> Result<(), Mismatch> {
    let mut rng = SplitMix64::new(0x05EE_DF3A);
    for i in 0..TRIPLES {
        let operands = if i % 2 == 0 {
            arbitrary(&mut rng)
        } else {
            cancelling(&mut rng)
        };
        let [a, b, c] = operands.map(f32::from_bits);
        compare(operands, mul_add(a, b, c))?;
    }
    for i in 0..TRIPLES / COL_BLOCK as u32 {
        check_lanes(&mut rng, i % 2 == 0)?;
    }
    Ok(())
}

/// `got` against `libm::fmaf` on `operands`.
fn compare(operands: [u32; 3], got: f32) -> Result<(), Mismatch> {
    let [a, b, c] = operands.map(f32::from_bits);
    let expected = libm::fmaf(a, b, c);
    // NaN payloads are not specified the same way by every FPU and libm.
    if got.to_bits() == expected.to_bits() || (got.is_nan() && expected.is_nan()) {
        return Ok(());
    }
    Err(Mismatch {
        operands,
        got: got.to_bits(),
        expected: expected.to_bits(),
    })
}

/// One `mul_add_lanes` call of the linear kernel's width: one multiplier, a row of
/// arbitrary or cancelling triples sharing it.
fn check_lanes(rng: &mut SplitMix64, arbitrary_lanes: bool) -> Result<(), Mismatch> {
    let triples: [[u32; 3]; COL_BLOCK] = if arbitrary_lanes {
        let w = rng.next_u64() as u32;
        core::array::from_fn(|_| {
            let [_, b, c] = arbitrary(rng);
            [w, b, c]
        })
    } else {
        let w = cancelling(rng)[0];
        core::array::from_fn(|_| cancelling_with(rng, f32::from_bits(w)))
    };
    let x = triples.map(|t| f32::from_bits(t[1]));
    let mut acc = triples.map(|t| f32::from_bits(t[2]));
    Portable.mul_add_lanes(f32::from_bits(triples[0][0]), &x, &mut acc);
    for (operands, got) in triples.into_iter().zip(acc) {
        compare(operands, got)?;
    }
    Ok(())
}

/// Three arbitrary bit patterns.
fn arbitrary(rng: &mut SplitMix64) -> [u32; 3] {
    let bits = rng.next_u64();
    [bits as u32, (bits >> 32) as u32, rng.next_u64() as u32]
}

/// `a`, `b` of moderate magnitude and `c` = `-(a * b)` rounded, nudged by a few ulps.
fn cancelling(rng: &mut SplitMix64) -> [u32; 3] {
    let a = moderate(rng.next_u64());
    cancelling_with(rng, a)
}

/// [`cancelling`] with the multiplier `a` given.
fn cancelling_with(rng: &mut SplitMix64, a: f32) -> [u32; 3] {
    let b = moderate(rng.next_u64());
    let nudge = rng.below(9) as i32 - 4;
    let c = (-(a * b)).to_bits().wrapping_add_signed(nudge);
    [a.to_bits(), b.to_bits(), c]
}

/// Sign and mantissa random, exponent within 2^-16 .. 2^15.
fn moderate(bits: u64) -> f32 {
    let sign_mantissa = (bits as u32) & 0x807F_FFFF;
    let exponent = 111 + (bits >> 32) as u32 % 32;
    f32::from_bits(sign_mantissa | exponent << 23)
}

/// Random blocks checked by [`integer_blocks`].
const BLOCKS: u32 = 2_000;

/// Checks `pair_sums` against the portable [`block_sums`] on [`BLOCKS`] random register
/// blocks: int8 weights, activations over the whole int16 range (both extremes included),
/// 1 to 16 channel pairs, every block's offset in a tile. Returns the first block that
/// differs (its number).
pub fn integer_blocks() -> Result<(), u32> {
    let mut rng = SplitMix64::new(0x1A7E_B10C);
    let extreme = |bits: u64, limit: i16| match bits % 8 {
        0 => limit,
        1 => -limit,
        _ => (bits >> 8) as i16 % limit,
    };
    for block in 0..BLOCKS {
        let pairs = 1 + rng.below(16) as usize;
        let weights: WordAligned<[WeightPairs; 16]> = WordAligned(core::array::from_fn(|_| {
            core::array::from_fn(|_| [0; 2].map(|_| extreme(rng.next_u64(), 127)))
        }));
        let tile: WordAligned<[TilePairs; 16]> = WordAligned(core::array::from_fn(|_| {
            core::array::from_fn(|_| [0; 2].map(|_| extreme(rng.next_u64(), 32767)))
        }));
        let p = POINTS * rng.below((TILE / POINTS) as u32) as usize;
        let (w, x) = (&weights.0[..pairs], &tile.0[..pairs]);
        let (got, want) = (Portable.pair_sums(w, x, p), block_sums(w, x, p));
        // Element by element: `==` on the arrays would call `bcmp`, which the x86_64 image
        // does not have.
        if got
            .iter()
            .flatten()
            .zip(want.iter().flatten())
            .any(|(a, b)| a != b)
        {
            return Err(block);
        }
    }
    Ok(())
}

/// Checks `widen_f16` (the FPU's `vcvtb.f32.f16` on the Cortex-M7) against the software
/// conversion on every finite f16. Returns the first bit pattern that differs.
pub fn f16_widening() -> Result<(), u16> {
    let bits: [u16; 256] = core::array::from_fn(|i| i as u16);
    let mut out = [0.0f32; 256];
    for high in 0..=255u16 {
        let block = bits.map(|low| high << 8 | low);
        Portable.widen_f16(&block, &mut out);
        for (&b, &got) in block.iter().zip(&out) {
            let finite = b & 0x7C00 != 0x7C00;
            if finite && got.to_bits() != f16_to_f32(b).to_bits() {
                return Err(b);
            }
        }
    }
    Ok(())
}
