//! x86_64 Linux without the C runtime: entry point, output and exit through system calls.
//! No instruction counter.

use crate::firmware_main;

// Entry point called by the kernel (no C runtime): clears the frame pointer, aligns the
// stack to 16 bytes as the C ABI expects at a call, and calls `start`.
core::arch::global_asm!(
    ".globl _start",
    "_start:",
    "xor ebp, ebp",
    "and rsp, -16",
    "call {main}",
    "ud2",
    main = sym start,
);

/// Runs the image once and exits with its status.
extern "C" fn start() -> ! {
    exit(firmware_main(None))
}

/// Writes `text` to standard output with the `write` system call.
pub fn print(text: &str) {
    // SAFETY: `write(1, ptr, len)` reads `len` bytes of `text`, which is valid for them.
    unsafe {
        core::arch::asm!(
            "syscall",
            inlateout("rax") 1usize => _,
            in("rdi") 1usize,
            in("rsi") text.as_ptr(),
            in("rdx") text.len(),
            lateout("rcx") _,
            lateout("r11") _,
            options(nostack)
        );
    }
}

/// Ends the process with the Linux `exit` system call.
pub fn exit(code: i32) -> ! {
    // SAFETY: the exit system call takes one integer argument and never returns.
    unsafe {
        core::arch::asm!("syscall", in("rax") 60, in("rdi") code, options(noreturn));
    }
}

/// The prebuilt `libcore` references this symbol; with `panic = "abort"` it is never called.
#[no_mangle]
pub extern "C" fn rust_eh_personality() {}
