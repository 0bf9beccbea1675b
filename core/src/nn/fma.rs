//! Fused multiply-add `a * b + c` with a single rounding (IEEE 754 `fusedMultiplyAdd`).
//!
//! The reference's BLAS accumulates every dot product with FMA instructions, in input
//! order, and its normalisation kernels apply `x * alpha + beta` fused; using the same
//! operation reproduces its f32 results bit for bit instead of within a few ulps (see
//! docs/evaluation.md, "Conformance with the reference"). The result is exactly specified,
//! so the hardware instruction and the software fallback give identical bits: host and
//! device agree whichever is used.

/// `a * b + c`, rounded once: the FMA instruction when the build enables it.
#[cfg(all(target_arch = "x86_64", target_feature = "fma"))]
#[inline(always)]
#[allow(unsafe_code)]
pub fn mul_add(a: f32, b: f32, c: f32) -> f32 {
    use core::arch::x86_64::{_mm_cvtss_f32, _mm_fmadd_ss, _mm_set_ss};
    // SAFETY: the `fma` target feature is enabled for the whole build (checked by the
    // `cfg` above), so the instruction exists on every CPU this code runs on; the
    // intrinsics only touch registers.
    unsafe { _mm_cvtss_f32(_mm_fmadd_ss(_mm_set_ss(a), _mm_set_ss(b), _mm_set_ss(c))) }
}

/// `a * b + c`, rounded once: `vfma.f32` of the Cortex-M7's FPv5 FPU, enabled by the core's
/// `arm-fma` feature. Stable Rust cannot test `target_feature = "vfp4"`, so the feature is
/// the switch. It needs `thumbv7em-none-eabihf` with `-C target-cpu=cortex-m7`: Rust's
/// `sreg` operands require the double-precision `vfp2` feature, which a Cortex-M4F
/// (single-precision FPv4, which has the instruction too) lacks, so those builds use libm.
#[cfg(all(feature = "arm-fma", target_arch = "arm"))]
#[inline(always)]
#[allow(unsafe_code)]
pub fn mul_add(a: f32, b: f32, c: f32) -> f32 {
    let mut acc = c;
    // SAFETY: `vfma.f32` only reads and writes the three FPU registers given; the
    // `arm-fma` feature declares that the target has an FPv4/FPv5 FPU.
    unsafe {
        core::arch::asm!(
            "vfma.f32 {acc}, {a}, {b}",
            acc = inout(sreg) acc,
            a = in(sreg) a,
            b = in(sreg) b,
            options(pure, nomem, nostack, preserves_flags)
        );
    }
    acc
}

/// `a * b + c`, rounded once: AArch64's `fmadd` (every AArch64 core with the FP unit),
/// enabled by the core's `arm-fma` feature.
#[cfg(all(feature = "arm-fma", target_arch = "aarch64"))]
#[inline(always)]
#[allow(unsafe_code)]
pub fn mul_add(a: f32, b: f32, c: f32) -> f32 {
    let result: f32;
    // SAFETY: `fmadd` only reads and writes the FP registers given; the `arm-fma` feature
    // declares a target with the FP unit (`aarch64-unknown-none`, not `-softfloat`).
    unsafe {
        core::arch::asm!(
            "fmadd {r:s}, {a:s}, {b:s}, {c:s}",
            r = lateout(vreg) result,
            a = in(vreg) a,
            b = in(vreg) b,
            c = in(vreg) c,
            options(pure, nomem, nostack, preserves_flags)
        );
    }
    result
}

/// `a * b + c`, rounded once: libm's exact routine (software, or the instruction where
/// libm finds one) on builds without a hardware path above.
#[cfg(not(any(
    all(target_arch = "x86_64", target_feature = "fma"),
    all(feature = "arm-fma", any(target_arch = "arm", target_arch = "aarch64"))
)))]
#[inline(always)]
pub fn mul_add(a: f32, b: f32, c: f32) -> f32 {
    libm::fmaf(a, b, c)
}

#[cfg(test)]
mod tests {
    use super::mul_add;

    #[test]
    fn rounds_once() {
        // (1 + 2^-12)^2 = 1 + 2^-11 + 2^-24: the last term survives only without the
        // intermediate rounding of the product.
        let a = 1.0 + f32::EPSILON * 2048.0;
        let exact = mul_add(a, a, -1.0);
        assert_eq!(exact, 2.0f32.powi(-11) + 2.0f32.powi(-24));
        assert_eq!(a * a - 1.0, 2.0f32.powi(-11));
    }

    #[test]
    fn agrees_with_libm_everywhere() {
        let values = [
            0.0f32,
            -0.0,
            1.5,
            -3.25,
            1e-30,
            7e30,
            f32::MIN_POSITIVE,
            0.1,
            -0.7,
        ];
        for &a in &values {
            for &b in &values {
                for &c in &values {
                    assert_eq!(mul_add(a, b, c).to_bits(), libm::fmaf(a, b, c).to_bits());
                }
            }
        }
    }
}
