//! Square root, correctly rounded (IEEE 754 `squareRoot`), as an operation the compiler
//! knows: on x86-64 SSE's `sqrtss` through its intrinsic, which the compiler encodes to
//! match the surrounding code (VEX inside the AVX2 kernels) and may vectorise, instead of
//! libm's `asm!` block, whose legacy SSE encoding among AVX code took a quarter of the time
//! of an N = 1024 match in the cost matrix. Correct rounding makes every implementation
//! give the same bits.

/// `sqrt(x)`, correctly rounded.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
#[allow(unsafe_code, unused_unsafe)]
pub fn sqrt(x: f32) -> f32 {
    use core::arch::x86_64::{_mm_cvtss_f32, _mm_set_ss, _mm_sqrt_ss};
    // SAFETY: SSE is part of every x86-64 CPU; the intrinsics only touch registers.
    unsafe { _mm_cvtss_f32(_mm_sqrt_ss(_mm_set_ss(x))) }
}

/// `sqrt(x)`, correctly rounded.
#[cfg(not(target_arch = "x86_64"))]
#[inline(always)]
pub fn sqrt(x: f32) -> f32 {
    libm::sqrtf(x)
}

/// [`sqrt`] of an f64 (`sqrtsd` on x86-64).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
#[allow(unsafe_code, unused_unsafe)]
pub fn sqrt_f64(x: f64) -> f64 {
    use core::arch::x86_64::{_mm_cvtsd_f64, _mm_set_sd, _mm_sqrt_pd};
    // SAFETY: SSE2 is part of every x86-64 CPU; the intrinsics only touch registers.
    unsafe { _mm_cvtsd_f64(_mm_sqrt_pd(_mm_set_sd(x))) }
}

/// [`sqrt`] of an f64.
#[cfg(not(target_arch = "x86_64"))]
#[inline(always)]
pub fn sqrt_f64(x: f64) -> f64 {
    libm::sqrt(x)
}

#[cfg(test)]
mod tests {
    use super::{sqrt, sqrt_f64};

    #[test]
    fn same_bits_as_libm() {
        let specials = [
            0.0f32,
            -0.0,
            1e-30,
            1.0,
            2.0,
            f32::MIN_POSITIVE,
            1e-45,
            f32::MAX,
        ];
        let mut x = 1.0e-6f32;
        let sweep = core::iter::from_fn(|| {
            x *= 1.000_37;
            (x < 1.0e6).then_some(x)
        });
        for v in specials.into_iter().chain(sweep) {
            assert_eq!(sqrt(v).to_bits(), libm::sqrtf(v).to_bits(), "{v:e}");
            let wide = f64::from(v) * 1.1;
            assert_eq!(
                sqrt_f64(wide).to_bits(),
                libm::sqrt(wide).to_bits(),
                "{wide:e}"
            );
        }
        assert!(sqrt(-1.0).is_nan() && sqrt(f32::NAN).is_nan() && sqrt_f64(-1.0).is_nan());
    }
}
