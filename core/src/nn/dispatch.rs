//! Kernel selection at run time: one build runs on every CPU of its architecture and uses
//! the fused multiply-add instruction and the widest vectors the CPU has.
//!
//! The kernels that round with fused multiply-adds (the linear layer, instance norm) are
//! generic over [`Fma`] and entered through [`with_fma`], which hands them an [`X86Fma`]
//! inside a function compiled for AVX2, FMA and F16C (and, on a CPU with AVX-512 VNNI, one
//! compiled for AVX-512 too, whose token also picks the 512-bit integer kernel) when the CPU
//! has them (checked once with `cpuid` and `xgetbv`, which work in `no_std`, and cached), and
//! [`Portable`] otherwise. A fused multiply-add is exactly specified and the integer sums
//! are exact, so every variant gives the same bits (see [`super::fma`]).
//!
//! This module knows no kernel: one with vector variants of its own (the integer kernel,
//! instance norm's sums, the transposes) picks them with the kernel set's x86-64 tokens
//! ([`Fma::x86_avx2`], [`Fma::x86_avx512`]) in a trait of its own over every [`Fma`]
//! ([`super::integer::IntegerVariants`], [`super::norm::NormVariants`],
//! [`super::transpose::TransposeVariants`]).

use core::sync::atomic::{AtomicU8, Ordering};

use super::fma::mul_add;

/// The CPU's multiply-add instructions: a fused multiply-add `a * b + c` with a single
/// rounding (the f32 kernels) and its vector lanes; also its exact f16 <-> f32 conversions
/// (Sinkhorn's f16 cost rows), and on x86-64 the tokens with which a kernel picks its vector
/// variant (such as the integer kernel's exact int16 pair multiply-adds).
pub trait Fma: Copy {
    /// Whether the CPU has 32 vector registers of 16 f32 lanes (AVX-512): the f32 linear
    /// kernel then accumulates two register blocks side by side and attention's register
    /// tiles are 16 lanes wide; the same sums either way.
    const WIDE_REGISTERS: bool = false;

    /// `a * b + c`, rounded once.
    fn mul_add(self, a: f32, b: f32, c: f32) -> f32;

    /// `acc[t] = w * x[t] + acc[t]` in every lane, each rounded once (the f32 linear
    /// kernel's register rows). The default is one [`Fma::mul_add`] per lane (vectorised by
    /// the compiler on x86-64 inside [`with_fma`]); on AArch64 NEON's `fmla` on 4 lanes at a
    /// time, which `asm!`'s scalar `fmadd` would keep the compiler from doing. Exact, so
    /// every path gives the same bits.
    #[inline(always)]
    fn mul_add_lanes<const L: usize>(self, w: f32, x: &[f32; L], acc: &mut [f32; L]) {
        #[cfg(all(target_arch = "aarch64", target_feature = "neon"))]
        if L.is_multiple_of(4) {
            return mul_add_lanes_neon(w, x, acc);
        }
        for (a, &xt) in acc.iter_mut().zip(x) {
            *a = self.mul_add(w, xt, *a);
        }
    }

    /// `acc[t] = acc[t] + w * x[t]` in every lane, the product and the sum each rounded
    /// (attention's register tiles, unfused as the reference computes them). The default is
    /// a loop the compiler vectorises; x86-64 multiplies and adds 8 (AVX2) or 16 (AVX-512)
    /// lanes explicitly (the compiler's own choice there vectorises across the tile's rows,
    /// with gathers). Exact IEEE operations, so every path gives the same bits.
    #[inline(always)]
    fn add_products<const L: usize>(self, w: f32, x: &[f32; L], acc: &mut [f32; L]) {
        add_products(w, x, acc);
    }

    /// `acc[t] = acc[t] + x[t]` in every lane (attention's messages added block after
    /// block). The default is a loop; x86-64 adds 8 or 16 lanes explicitly (the compiler's
    /// own choice there vectorises across the tile's rows, with gathers and scatters).
    #[inline(always)]
    fn add_lanes<const L: usize>(self, x: &[f32; L], acc: &mut [f32; L]) {
        add_lanes(x, acc);
    }

    /// The AVX2 token where this kernel set has AVX2, FMA and F16C: a kernel with an AVX2
    /// variant runs it with the token ([`X86Fma`]), else its portable code.
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    fn x86_avx2(self) -> Option<X86Fma> {
        None
    }

    /// The AVX-512 token where this kernel set has AVX-512 F, BW, VL and VNNI besides.
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    fn x86_avx512(self) -> Option<X86Fma<true>> {
        None
    }

    /// `out[i] = bits[i]` read as an f16 (`out` as long as `bits`), exact for every finite
    /// value ([`f16_to_f32`]; F16C's `vcvtph2ps` on x86-64).
    #[inline(always)]
    fn widen_f16(self, bits: &[u16], out: &mut [f32]) {
        for (o, &b) in out.iter_mut().zip(bits) {
            #[cfg(all(feature = "arm-fma", target_arch = "arm"))]
            {
                *o = f16_to_f32_vfp(b);
            }
            #[cfg(not(all(feature = "arm-fma", target_arch = "arm")))]
            {
                *o = f16_to_f32(b);
            }
        }
    }

    /// `out[i]` = the f16 bits of `values[i]` rounded to nearest, ties to even (`out` as
    /// long as `values`), the same bits for every value that is not a NaN (`half`'s conversion;
    /// F16C's `vcvtps2ph` on x86-64).
    #[inline(always)]
    fn narrow_f16(self, values: &[f32], out: &mut [u16]) {
        for (o, &x) in out.iter_mut().zip(values) {
            *o = f32_to_f16(x);
        }
    }
}

/// [`Fma::add_products`] as a loop (in the index form the compiler vectorises lane by lane).
#[inline(always)]
fn add_products<const L: usize>(w: f32, x: &[f32; L], acc: &mut [f32; L]) {
    for l in 0..L {
        acc[l] += w * x[l];
    }
}

/// [`Fma::add_lanes`] as a loop.
#[inline(always)]
fn add_lanes<const L: usize>(x: &[f32; L], acc: &mut [f32; L]) {
    for l in 0..L {
        acc[l] += x[l];
    }
}

/// `f32 -> f16` rounded to nearest, ties to even (IEEE 754 `convertFormat`; overflow to
/// infinity), in software (`half`).
#[inline(always)]
fn f32_to_f16(x: f32) -> u16 {
    half::f16::from_f32(x).to_bits()
}

/// [`f16_to_f32`] with the FPU's `vcvtb.f32.f16` (Cortex-M4F/M7 FPUs have it; the core's
/// `arm-fma` feature declares such an FPU): exact for every finite f16, as the software
/// conversion.
#[cfg(all(feature = "arm-fma", target_arch = "arm"))]
#[inline(always)]
#[allow(unsafe_code)]
fn f16_to_f32_vfp(bits: u16) -> f32 {
    let mut x = f32::from_bits(u32::from(bits));
    // SAFETY: `vcvtb.f32.f16` reads the low half of the given FPU register and writes the
    // same register; the `arm-fma` feature declares an FPv4/FPv5 FPU, which has it.
    unsafe {
        core::arch::asm!(
            "vcvtb.f32.f16 {x}, {x}",
            x = inout(sreg) x,
            options(pure, nomem, nostack, preserves_flags)
        );
    }
    x
}

/// [`Fma::mul_add_lanes`] with NEON (`L` a multiple of 4): `vfmaq_f32` is `fmla`, a fused
/// multiply-add per lane.
#[cfg(all(target_arch = "aarch64", target_feature = "neon"))]
#[inline(always)]
#[allow(unsafe_code)]
fn mul_add_lanes_neon<const L: usize>(w: f32, x: &[f32; L], acc: &mut [f32; L]) {
    use core::arch::aarch64::{vdupq_n_f32, vfmaq_f32, vld1q_f32, vst1q_f32};
    for (a, x) in acc.chunks_exact_mut(4).zip(x.chunks_exact(4)) {
        // SAFETY: the build enables NEON (checked by the `cfg`); `a` and `x` hold 4 f32
        // each, read and written through their own pointers.
        unsafe {
            let sum = vfmaq_f32(vld1q_f32(a.as_ptr()), vdupq_n_f32(w), vld1q_f32(x.as_ptr()));
            vst1q_f32(a.as_mut_ptr(), sum);
        }
    }
}

/// Exact f16 -> f32 for every finite f16 (normal, subnormal, zero), branch-free so a row
/// converts with vector instructions (infinities and NaN, which a Sinkhorn cost never is,
/// map to finite values).
#[inline(always)]
pub fn f16_to_f32(bits: u16) -> f32 {
    let sign = u32::from(bits & 0x8000) << 16;
    let magnitude = u32::from(bits & 0x7FFF);
    // Normal: rebias the exponent from 15 to 127 ((127 - 15) << 23 = 0x3800_0000).
    let normal = f32::from_bits(((magnitude << 13) + 0x3800_0000) | sign);
    // Subnormal or zero: mantissa * 2^-24, exact in f32.
    let small = f32::from_bits((magnitude as f32 * 5.960_464_5e-8).to_bits() | sign);
    if magnitude >= 0x0400 {
        normal
    } else {
        small
    }
}

/// [`super::fma::mul_add`]: the instruction where the build enables it, else libm's exact
/// routine.
#[derive(Clone, Copy)]
pub struct Portable;

impl Fma for Portable {
    #[inline(always)]
    fn mul_add(self, a: f32, b: f32, c: f32) -> f32 {
        mul_add(a, b, c)
    }
}

/// The x86-64 FMA instruction and 256-bit vectors; with `AVX512` also the AVX-512 VNNI
/// integer kernel (and the compiler's 512-bit vectors around it). A value exists only on a
/// CPU with AVX2, FMA and F16C, and with `AVX512` only on one that also has AVX-512 F, BW, VL
/// and VNNI (it is made by [`X86Fma::detect`] and [`with_fma`]), which makes its use sound.
#[cfg(target_arch = "x86_64")]
#[derive(Clone, Copy)]
pub struct X86Fma<const AVX512: bool = false>(());

/// The kernels [`with_fma`] may pick, narrowest first.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
#[repr(u8)]
pub enum KernelSet {
    /// [`Portable`] (NEON or the Cortex-M DSP and FPU instructions where the build enables them).
    Portable = 1,
    /// x86-64 AVX2, FMA and F16C.
    Avx2 = 2,
    /// x86-64 AVX-512 F, BW, VL and VNNI besides.
    Avx512 = 3,
}

/// [`KernelSet::Avx512`] as [`kernel_set`] returns it.
#[cfg(target_arch = "x86_64")]
const SET_AVX512: u8 = KernelSet::Avx512 as u8;
/// [`KernelSet::Avx2`] as [`kernel_set`] returns it.
#[cfg(target_arch = "x86_64")]
const SET_AVX2: u8 = KernelSet::Avx2 as u8;

/// What this CPU has: 0 not checked yet, else a [`KernelSet`].
#[cfg(target_arch = "x86_64")]
static DETECTED: AtomicU8 = AtomicU8::new(0);
/// The widest [`KernelSet`] allowed ([`limit_kernels`]).
static LIMIT: AtomicU8 = AtomicU8::new(KernelSet::Avx512 as u8);

/// Every later kernel call uses at most `widest`, even where the CPU has more (to check the
/// narrower variants on such a CPU: the results are the same bits); [`KernelSet::Avx512`]
/// lifts the limit.
pub fn limit_kernels(widest: KernelSet) {
    LIMIT.store(widest as u8, Ordering::Relaxed);
}

/// The kernels of this CPU within the limit.
#[cfg(target_arch = "x86_64")]
fn kernel_set() -> u8 {
    let detected = match DETECTED.load(Ordering::Relaxed) {
        0 => {
            let detected = cpu_kernel_set() as u8;
            DETECTED.store(detected, Ordering::Relaxed);
            detected
        }
        known => known,
    };
    detected.min(LIMIT.load(Ordering::Relaxed))
}

/// The widest [`KernelSet`] this CPU and its OS support: `cpuid` leaf 1 (FMA, OSXSAVE, AVX,
/// F16C) and leaf 7 (AVX2; AVX-512 F, BW, VL, VNNI), and `xgetbv` for the registers the OS
/// saves (SSE and AVX state; the opmask and all 512 bits of the 32 vector registers) (Intel
/// SDM vol. 1, 14.3 "Detection of Intel AVX instructions", 15.2 "Detection of AVX-512
/// foundation instructions").
#[cfg(target_arch = "x86_64")]
#[allow(unsafe_code, unused_unsafe)]
fn cpu_kernel_set() -> KernelSet {
    use core::arch::x86_64::{__cpuid, __cpuid_count, _xgetbv};
    const LEAF1_ECX: u32 = (1 << 12) | (1 << 27) | (1 << 28) | (1 << 29); // FMA, OSXSAVE, AVX, F16C
    const AVX2_EBX: u32 = 1 << 5;
    const AVX512_EBX: u32 = (1 << 16) | (1 << 30) | (1 << 31); // F, BW, VL
    const AVX512_VNNI_ECX: u32 = 1 << 11;
    const XMM_YMM_STATE: u64 = 0b110;
    const OPMASK_ZMM_STATE: u64 = 0b1110_0110;
    // SAFETY: every x86-64 CPU has `cpuid`.
    let (max_leaf, leaf1) = unsafe { (__cpuid(0).eax, __cpuid(1)) };
    if max_leaf < 7 || leaf1.ecx & LEAF1_ECX != LEAF1_ECX {
        return KernelSet::Portable;
    }
    // SAFETY: OSXSAVE (checked above) means the OS enabled `xgetbv`; leaf 7 exists
    // (`max_leaf >= 7`).
    let (xcr0, leaf7) = unsafe { (_xgetbv(0), __cpuid_count(7, 0)) };
    let has = |state: u64, ebx: u32, ecx: u32| {
        xcr0 & state == state && leaf7.ebx & ebx == ebx && leaf7.ecx & ecx == ecx
    };
    if !has(XMM_YMM_STATE, AVX2_EBX, 0) {
        KernelSet::Portable
    } else if has(OPMASK_ZMM_STATE, AVX512_EBX, AVX512_VNNI_ECX) {
        KernelSet::Avx512
    } else {
        KernelSet::Avx2
    }
}

#[cfg(target_arch = "x86_64")]
impl X86Fma {
    /// The token if this CPU has AVX2, FMA and F16C and the OS saves the AVX registers (and
    /// [`limit_kernels`] allows them).
    pub fn detect() -> Option<Self> {
        (kernel_set() >= SET_AVX2).then_some(X86Fma(()))
    }

    /// The AVX-512 token if this CPU has AVX-512 F, BW, VL and VNNI besides, the OS saves
    /// their registers and [`limit_kernels`] allows them.
    pub fn detect_avx512() -> Option<X86Fma<true>> {
        (kernel_set() >= SET_AVX512).then_some(X86Fma(()))
    }
}

#[cfg(target_arch = "x86_64")]
impl<const AVX512: bool> X86Fma<AVX512> {
    /// The AVX2 token (every AVX-512 CPU has AVX2).
    #[inline(always)]
    pub fn avx2(self) -> X86Fma {
        X86Fma(())
    }

    /// The AVX-512 token if this one is.
    #[inline(always)]
    pub fn avx512(self) -> Option<X86Fma<true>> {
        AVX512.then_some(X86Fma(()))
    }
}

#[cfg(target_arch = "x86_64")]
impl<const AVX512: bool> Fma for X86Fma<AVX512> {
    const WIDE_REGISTERS: bool = AVX512;

    #[inline(always)]
    fn x86_avx2(self) -> Option<X86Fma> {
        Some(self.avx2())
    }

    #[inline(always)]
    fn x86_avx512(self) -> Option<X86Fma<true>> {
        self.avx512()
    }

    #[inline(always)]
    #[allow(unsafe_code)]
    fn mul_add(self, a: f32, b: f32, c: f32) -> f32 {
        use core::arch::x86_64::{_mm_cvtss_f32, _mm_fmadd_ss, _mm_set_ss};
        // SAFETY: an `X86Fma` exists only when `detect` found the FMA instruction; the
        // intrinsics only touch registers.
        unsafe { _mm_cvtss_f32(_mm_fmadd_ss(_mm_set_ss(a), _mm_set_ss(b), _mm_set_ss(c))) }
    }

    #[inline(always)]
    #[allow(unsafe_code)]
    fn add_products<const L: usize>(self, w: f32, x: &[f32; L], acc: &mut [f32; L]) {
        use core::arch::x86_64::{
            _mm256_add_ps, _mm256_loadu_ps, _mm256_mul_ps, _mm256_set1_ps, _mm256_storeu_ps,
            _mm512_add_ps, _mm512_loadu_ps, _mm512_mul_ps, _mm512_set1_ps, _mm512_storeu_ps,
        };
        match (L, self.avx512()) {
            // SAFETY: an `X86Fma<true>` exists only on a CPU with AVX-512 F; `x` and `acc`
            // hold 16 f32 (64 bytes) each, read and written unaligned.
            (16, Some(_avx512)) => unsafe {
                let product = _mm512_mul_ps(_mm512_set1_ps(w), _mm512_loadu_ps(x.as_ptr()));
                let sum = _mm512_add_ps(_mm512_loadu_ps(acc.as_ptr()), product);
                _mm512_storeu_ps(acc.as_mut_ptr(), sum);
            },
            // SAFETY: an `X86Fma` exists only on a CPU with AVX2; `x` and `acc` hold 8 f32
            // (32 bytes) each, read and written unaligned.
            (8, _) => unsafe {
                let product = _mm256_mul_ps(_mm256_set1_ps(w), _mm256_loadu_ps(x.as_ptr()));
                let sum = _mm256_add_ps(_mm256_loadu_ps(acc.as_ptr()), product);
                _mm256_storeu_ps(acc.as_mut_ptr(), sum);
            },
            _ => add_products(w, x, acc),
        }
    }

    #[inline(always)]
    #[allow(unsafe_code)]
    fn add_lanes<const L: usize>(self, x: &[f32; L], acc: &mut [f32; L]) {
        use core::arch::x86_64::{
            _mm256_add_ps, _mm256_loadu_ps, _mm256_storeu_ps, _mm512_add_ps, _mm512_loadu_ps,
            _mm512_storeu_ps,
        };
        match (L, self.avx512()) {
            // SAFETY: an `X86Fma<true>` exists only on a CPU with AVX-512 F; `x` and `acc`
            // hold 16 f32 (64 bytes) each, read and written unaligned.
            (16, Some(_avx512)) => unsafe {
                let sum = _mm512_add_ps(_mm512_loadu_ps(acc.as_ptr()), _mm512_loadu_ps(x.as_ptr()));
                _mm512_storeu_ps(acc.as_mut_ptr(), sum);
            },
            // SAFETY: an `X86Fma` exists only on a CPU with AVX2; `x` and `acc` hold 8 f32
            // (32 bytes) each, read and written unaligned.
            (8, _) => unsafe {
                let sum = _mm256_add_ps(_mm256_loadu_ps(acc.as_ptr()), _mm256_loadu_ps(x.as_ptr()));
                _mm256_storeu_ps(acc.as_mut_ptr(), sum);
            },
            _ => add_lanes(x, acc),
        }
    }

    #[inline(always)]
    #[allow(unsafe_code)]
    fn widen_f16(self, bits: &[u16], out: &mut [f32]) {
        use core::arch::x86_64::{_mm256_cvtph_ps, _mm256_storeu_ps, _mm_loadu_si128};
        let out = &mut out[..bits.len()];
        let mut halves = bits.chunks_exact(8);
        let mut floats = out.chunks_exact_mut(8);
        for (h, f) in (&mut halves).zip(&mut floats) {
            // SAFETY: an `X86Fma` exists only when `detect` found F16C; `h` holds 8 f16
            // (16 bytes) and `f` 8 f32 (32 bytes), read and written unaligned.
            unsafe {
                _mm256_storeu_ps(
                    f.as_mut_ptr(),
                    _mm256_cvtph_ps(_mm_loadu_si128(h.as_ptr().cast())),
                )
            }
        }
        for (f, &h) in floats.into_remainder().iter_mut().zip(halves.remainder()) {
            *f = f16_to_f32(h);
        }
    }

    #[inline(always)]
    #[allow(unsafe_code)]
    fn narrow_f16(self, values: &[f32], out: &mut [u16]) {
        use core::arch::x86_64::{
            _mm256_cvtps_ph, _mm256_loadu_ps, _mm_storeu_si128, _MM_FROUND_TO_NEAREST_INT,
        };
        let values = &values[..out.len()];
        let mut floats = values.chunks_exact(8);
        let mut halves = out.chunks_exact_mut(8);
        for (f, h) in (&mut floats).zip(&mut halves) {
            // SAFETY: an `X86Fma` exists only when `detect` found F16C; `f` holds 8 f32
            // (32 bytes) and `h` 8 f16 (16 bytes), read and written unaligned. The immediate
            // rounds to nearest even whatever MXCSR says.
            unsafe {
                _mm_storeu_si128(
                    h.as_mut_ptr().cast(),
                    _mm256_cvtps_ph::<_MM_FROUND_TO_NEAREST_INT>(_mm256_loadu_ps(f.as_ptr())),
                )
            }
        }
        for (h, &f) in halves.into_remainder().iter_mut().zip(floats.remainder()) {
            *h = f32_to_f16(f);
        }
    }
}

/// Runs `kernel` with the best [`Fma`] of this CPU: on x86-64 with AVX2, FMA and F16C inside a
/// function compiled for them (so the kernel, inlined there, uses 256-bit FMA
/// instructions), with AVX-512 VNNI besides inside one compiled for those too, else with
/// [`Portable`]. `kernel` must be `#[inline(always)]`-able code
/// (a closure calling the generic kernel).
#[inline(always)]
pub fn with_fma<R>(kernel: impl Kernel<R>) -> R {
    // One read of the cached set (`X86Fma::detect*` each read it again; inlined into every
    // kernel call, a second read measured slower).
    #[cfg(target_arch = "x86_64")]
    match kernel_set() {
        SET_AVX512 => return run_avx512(X86Fma(()), kernel),
        SET_AVX2 => return run_avx2_fma(X86Fma(()), kernel),
        _ => {}
    }
    run_portable(kernel)
}

/// Runs `kernel` with [`Portable`] in a frame of its own (so that callers do not carry the
/// kernel's buffers in theirs next to the AVX2 variant's).
#[inline(never)]
fn run_portable<R>(kernel: impl Kernel<R>) -> R {
    kernel.run(Portable)
}

/// A kernel generic over its [`Fma`] (a closure cannot be generic, hence the trait).
pub trait Kernel<R> {
    /// Runs the kernel with `fma`.
    fn run<F: Fma>(self, fma: F) -> R;
}

/// Runs `kernel` compiled for AVX2, FMA and F16C.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
#[allow(unsafe_code)]
fn run_avx2_fma<R>(fma: X86Fma, kernel: impl Kernel<R>) -> R {
    #[target_feature(enable = "avx2,fma,f16c")]
    unsafe fn avx2_fma<R>(fma: X86Fma, kernel: impl Kernel<R>) -> R {
        kernel.run(fma)
    }
    // SAFETY: `fma` proves the CPU has AVX2, FMA and F16C.
    unsafe { avx2_fma(fma, kernel) }
}

/// Runs `kernel` compiled for AVX-512 (F, BW, VL, VNNI) besides AVX2, FMA and F16C.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
#[allow(unsafe_code)]
fn run_avx512<R>(fma: X86Fma<true>, kernel: impl Kernel<R>) -> R {
    #[target_feature(enable = "avx2,fma,f16c,avx512f,avx512bw,avx512vl,avx512vnni")]
    unsafe fn avx512<R>(fma: X86Fma<true>, kernel: impl Kernel<R>) -> R {
        kernel.run(fma)
    }
    // SAFETY: `fma` proves the CPU has all of them.
    unsafe { avx512(fma, kernel) }
}

#[cfg(test)]
mod tests {
    use super::*;

    struct Probe(f32, f32, f32);

    impl Kernel<u32> for Probe {
        fn run<F: Fma>(self, fma: F) -> u32 {
            fma.mul_add(self.0, self.1, self.2).to_bits()
        }
    }

    /// Whichever variant this CPU gets, the result is the single-rounding one.
    #[test]
    fn dispatched_fma_rounds_once_like_libm() {
        let a = 1.0 + f32::EPSILON * 2048.0;
        for (x, y, z) in [(a, a, -1.0), (0.1, -0.7, 1e-30), (7e30, 1.5, -3.25)] {
            let got = with_fma(Probe(x, y, z));
            assert_eq!(got, libm::fmaf(x, y, z).to_bits());
            assert_eq!(Portable.mul_add(x, y, z).to_bits(), got);
        }
    }

    struct Widen<'a>(&'a [u16], &'a mut [f32]);

    impl Kernel<()> for Widen<'_> {
        fn run<F: Fma>(self, fma: F) {
            fma.widen_f16(self.0, self.1);
        }
    }

    /// Every finite f16, converted by the dispatched variant (rows of every length mod 8, so
    /// both the vector body and the tail run) and by the definition, is half's exact value.
    #[test]
    fn f16_rows_widen_exactly() {
        let finite: std::vec::Vec<u16> = (0..=u16::MAX)
            .filter(|&b| half::f16::from_bits(b).is_finite())
            .collect();
        for row in finite.chunks(1021) {
            let mut out = std::vec![f32::NAN; row.len() + 3];
            with_fma(Widen(row, &mut out));
            for (&b, &x) in row.iter().zip(&out) {
                let exact = half::f16::from_bits(b).to_f32().to_bits();
                assert_eq!(x.to_bits(), exact, "{b:#06x}");
                assert_eq!(f16_to_f32(b).to_bits(), exact, "{b:#06x}");
            }
            assert!(
                out[row.len()..].iter().all(|x| x.is_nan()),
                "wrote past the row"
            );
        }
    }

    struct Narrow<'a>(&'a [f32], &'a mut [u16]);

    impl Kernel<()> for Narrow<'_> {
        fn run<F: Fma>(self, fma: F) {
            fma.narrow_f16(self.0, self.1);
        }
    }

    /// Every 61st f32 bit pattern that is not a NaN (normal, subnormal and overflowing
    /// magnitudes, both signs, every rounding case of the low bits), in rows of every
    /// length mod 8: the dispatched variant gives half's bits.
    #[test]
    fn f32_rows_narrow_like_half() {
        let values: std::vec::Vec<f32> = (0..=u32::MAX)
            .step_by(61)
            .map(f32::from_bits)
            .filter(|x| !x.is_nan())
            .collect();
        let mut at = 0;
        for len in (0..).map(|i| 1021 + i % 8) {
            let Some(row) = values.get(at..at + len) else {
                break;
            };
            at += len;
            let mut out = std::vec![0x7e00u16; len + 3];
            with_fma(Narrow(row, &mut out[..len]));
            for (&x, &h) in row.iter().zip(&out) {
                assert_eq!(h, half::f16::from_f32(x).to_bits(), "{x:e}");
            }
            assert!(
                out[len..].iter().all(|&h| h == 0x7e00),
                "wrote past the row"
            );
        }
    }

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn detection_is_stable() {
        assert_eq!(X86Fma::detect().is_some(), X86Fma::detect().is_some());
    }
}
