//! Arm semihosting (Arm "Semihosting for AArch32 and AArch64", version 2): the debugger or
//! emulator (QEMU with `-semihosting-config enable=on,target=native`) serves text output and
//! the exit status. Cortex-M traps with `bkpt 0xab`, AArch64 with `hlt 0xf000`.

/// `SYS_WRITE0`: writes a zero-terminated string to the debug console.
const SYS_WRITE0: usize = 0x04;
/// `SYS_EXIT_EXTENDED`: ends the program with a reason and an exit status.
const SYS_EXIT_EXTENDED: usize = 0x20;
/// `ADP_Stopped_ApplicationExit`: the program ended by itself (the status is its own).
const ADP_STOPPED_APPLICATION_EXIT: usize = 0x2_0026;

/// Semihosting operation `op` with the parameter (usually a block's address) `arg`.
///
/// # Safety
/// `arg` must be what `op` expects: for a block, its address, valid for the operation.
#[cfg(target_arch = "arm")]
unsafe fn call(op: usize, arg: usize) -> usize {
    let result;
    // SAFETY: the caller passes what the operation expects; the host reads (and for some
    // operations writes) only the memory the operation names.
    unsafe {
        core::arch::asm!("bkpt 0xab", inlateout("r0") op => result, in("r1") arg, options(nostack));
    }
    result
}

/// Semihosting operation `op` with the parameter (usually a block's address) `arg`.
///
/// # Safety
/// `arg` must be what `op` expects: for a block, its address, valid for the operation.
#[cfg(target_arch = "aarch64")]
unsafe fn call(op: usize, arg: usize) -> usize {
    let result;
    // SAFETY: as for the Cortex-M `call`.
    unsafe {
        core::arch::asm!("hlt 0xf000", inlateout("x0") op => result, in("x1") arg, options(nostack));
    }
    result
}

/// Writes `text` to the host's console, in pieces of at most 127 bytes.
pub fn print(text: &str) {
    for piece in text.as_bytes().chunks(127) {
        let mut zero_terminated = [0u8; 128];
        zero_terminated[..piece.len()].copy_from_slice(piece);
        // SAFETY: SYS_WRITE0 reads the string up to its zero, which is inside the buffer.
        unsafe {
            call(SYS_WRITE0, zero_terminated.as_ptr() as usize);
        }
    }
}

/// Ends the program; the emulator exits with `code`.
pub fn exit(code: i32) -> ! {
    let block = [ADP_STOPPED_APPLICATION_EXIT, code as usize];
    // SAFETY: SYS_EXIT_EXTENDED reads the two-word block.
    unsafe {
        call(SYS_EXIT_EXTENDED, block.as_ptr() as usize);
    }
    // Without a semihosting host nothing ends the program: wait here.
    loop {
        core::hint::spin_loop();
    }
}
