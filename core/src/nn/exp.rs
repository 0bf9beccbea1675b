//! A deterministic, branch-free `exp` that the compiler can vectorise: Cody-Waite range
//! reduction and the Cephes `expf` polynomial, in plain f32 arithmetic (no FMA, no table),
//! so host and device give bit-identical results. Within 2 ulp of `libm::expf` on
//! `[-87.3, 88.3]`; inputs below are clamped (results near 1e-38 instead of 0), which is
//! harmless where it is used: softmax and Sinkhorn terms `exp(x - max)`.

const LOG2_E: f32 = core::f32::consts::LOG2_E;
/// `ln 2` split so that `k * LN2_HI` is exact for the `k` that occur.
const LN2_HI: f32 = 0.693_359_4;
const LN2_LO: f32 = -2.121_944_4e-4;
/// `1.5 * 2^23`: adding and subtracting it rounds to the nearest integer.
const ROUNDER: f32 = 12_582_912.0;
const MIN_INPUT: f32 = -87.336_54;
const MAX_INPUT: f32 = 88.376_26;

/// `e^x` for finite `x` (see the module doc for range and accuracy).
#[inline(always)]
pub fn exp(x: f32) -> f32 {
    let x = x.clamp(MIN_INPUT, MAX_INPUT);
    let shifted = x * LOG2_E + ROUNDER;
    let k = shifted - ROUNDER;
    let k_int = (shifted.to_bits() as i32).wrapping_sub(ROUNDER.to_bits() as i32);
    let r = x - k * LN2_HI - k * LN2_LO;
    let r2 = r * r;
    let mut p = 1.987_569_2e-4f32;
    p = p * r + 1.398_2e-3;
    p = p * r + 8.333_452e-3;
    p = p * r + 4.166_579_6e-2;
    p = p * r + 1.666_666_5e-1;
    p = p * r + 0.5;
    let y = p * r2 + r + 1.0;
    let scale = f32::from_bits(((k_int + 127) << 23) as u32);
    y * scale
}

#[cfg(test)]
mod tests {
    use super::exp;

    fn ulps(a: f32, b: f32) -> u32 {
        (a.to_bits() as i32).abs_diff(b.to_bits() as i32)
    }

    #[test]
    fn within_two_ulp_of_libm_over_the_range() {
        let mut worst = 0;
        let mut x = -87.0f32;
        while x < 88.0 {
            worst = worst.max(ulps(exp(x), libm::expf(x)));
            x += 0.001_37;
        }
        assert!(worst <= 2, "worst error {worst} ulp");
    }

    #[test]
    fn exact_points_and_clamping() {
        assert_eq!(exp(0.0), 1.0);
        assert_eq!(exp(1.0), libm::expf(1.0));
        assert!(exp(-1000.0) < 1.2e-38 && exp(-1000.0) > 0.0);
        assert!(exp(1000.0).is_finite());
    }
}
