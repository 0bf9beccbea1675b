//! `memcpy`, `memmove` and `memset` for the x86_64 image: the compiler emits calls to them
//! and, linked without any C library, nothing else defines them. They are written with
//! the string instructions in assembly so that the compiler cannot turn them back into
//! calls to themselves. On `*-none-*` targets (Cortex-M, RISC-V) `compiler_builtins`
//! provides these symbols and this module is not needed.

/// Copies `n` bytes from `src` to `dest` (regions must not overlap).
///
/// # Safety
/// `src` must be valid for `n` bytes of reads and `dest` for `n` bytes of writes.
#[no_mangle]
pub unsafe extern "C" fn memcpy(dest: *mut u8, src: *const u8, n: usize) -> *mut u8 {
    // SAFETY: the caller guarantees both regions; `rep movsb` copies forwards and the
    // direction flag is clear by the ABI.
    unsafe {
        core::arch::asm!(
            "rep movsb",
            inout("rcx") n => _,
            inout("rdi") dest => _,
            inout("rsi") src => _,
            options(nostack, preserves_flags)
        );
    }
    dest
}

/// Copies `n` bytes from `src` to `dest`; the regions may overlap.
///
/// # Safety
/// `src` must be valid for `n` bytes of reads and `dest` for `n` bytes of writes.
#[no_mangle]
pub unsafe extern "C" fn memmove(dest: *mut u8, src: *const u8, n: usize) -> *mut u8 {
    if (dest as usize).wrapping_sub(src as usize) >= n {
        // `dest` is before `src` or past its end: a forward copy never overwrites a byte
        // before reading it.
        // SAFETY: as for `memcpy`.
        return unsafe { memcpy(dest, src, n) };
    }
    // `dest` starts inside the source: copy backwards, from the last byte.
    // SAFETY: the caller guarantees both regions; the direction flag is set for the copy
    // and cleared again, as the ABI requires.
    unsafe {
        core::arch::asm!(
            "std",
            "rep movsb",
            "cld",
            inout("rcx") n => _,
            inout("rdi") dest.wrapping_add(n).wrapping_sub(1) => _,
            inout("rsi") src.wrapping_add(n).wrapping_sub(1) => _,
            options(nostack)
        );
    }
    dest
}

/// Sets `n` bytes at `dest` to `value`.
///
/// # Safety
/// `dest` must be valid for `n` bytes of writes.
#[no_mangle]
pub unsafe extern "C" fn memset(dest: *mut u8, value: i32, n: usize) -> *mut u8 {
    // SAFETY: the caller guarantees the region; `rep stosb` stores forwards.
    unsafe {
        core::arch::asm!(
            "rep stosb",
            inout("rcx") n => _,
            inout("rdi") dest => _,
            in("al") value as u8,
            options(nostack, preserves_flags)
        );
    }
    dest
}
