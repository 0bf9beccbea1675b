//! Self-check of the build's fused multiply-add: the matcher's `mul_add` (the hardware
//! instruction where the build enables it: `vfma.f32`, `fmadd`, x86 FMA) must give the same
//! bits as libm's exact `fmaf` over many random triples, or the image's numbers would not
//! be the host's.

use gomatch::nn::fma::mul_add;
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
/// rounding decides the last bits.
pub fn run() -> Result<(), Mismatch> {
    let mut rng = SplitMix64::new(0x05EE_DF3A);
    for i in 0..TRIPLES {
        let operands = if i % 2 == 0 {
            arbitrary(&mut rng)
        } else {
            cancelling(&mut rng)
        };
        let [a, b, c] = operands.map(f32::from_bits);
        let got = mul_add(a, b, c);
        let expected = libm::fmaf(a, b, c);
        // NaN payloads are not specified the same way by every FPU and libm.
        let same = got.to_bits() == expected.to_bits() || (got.is_nan() && expected.is_nan());
        if !same {
            return Err(Mismatch {
                operands,
                got: got.to_bits(),
                expected: expected.to_bits(),
            });
        }
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
    let moderate = |bits: u64| {
        // Sign and mantissa random, exponent within 2^-16 .. 2^15.
        let sign_mantissa = (bits as u32) & 0x807F_FFFF;
        let exponent = 111 + (bits >> 32) as u32 % 32;
        f32::from_bits(sign_mantissa | exponent << 23)
    };
    let a = moderate(rng.next_u64());
    let b = moderate(rng.next_u64());
    let nudge = rng.below(9) as i32 - 4;
    let c = (-(a * b)).to_bits().wrapping_add_signed(nudge);
    [a.to_bits(), b.to_bits(), c]
}
