//! AArch64 on QEMU's `virt` board (Cortex-A53/A72): own start-up code (`virt.ld` links the
//! whole image into RAM at 0x4020_0000, above the device tree QEMU puts at the base of
//! RAM), semihosting prints and exits, the generic timer's virtual count counts
//! instructions. The MMU stays off (flat physical addresses; every access is
//! Device memory, so the target's `+strict-align` matters); a real board turns it and the
//! caches on.

use core::sync::atomic::{AtomicU64, Ordering};

use crate::{firmware_main, Counter};

pub use crate::semihosting::{exit, print};

/// Iterations of the calibration loop (two instructions each).
const CALIBRATION_ITERATIONS: u64 = 2_000_000;

// Entry point (EL1, MMU off): enables the FP/SIMD unit (CPACR_EL1.FPEN, which Rust code
// needs from its first instruction), sets the stack, zeroes `.bss` and calls `start`.
core::arch::global_asm!(
    ".section .text.boot, \"ax\"",
    ".globl _start",
    "_start:",
    "mov x0, #(3 << 20)",
    "msr cpacr_el1, x0",
    "isb",
    "adrp x0, __stack_top",
    "add x0, x0, :lo12:__stack_top",
    "mov sp, x0",
    "adrp x0, __bss_start",
    "add x0, x0, :lo12:__bss_start",
    "adrp x1, __bss_end",
    "add x1, x1, :lo12:__bss_end",
    "2:",
    "cmp x0, x1",
    "b.hs 3f",
    "str xzr, [x0], #8",
    "b 2b",
    "3:",
    "bl {start}",
    "4:",
    "wfe",
    "b 4b",
    start = sym start,
);

/// The generic timer's virtual count.
fn ticks() -> u64 {
    let count: u64;
    // SAFETY: reading CNTVCT_EL0 has no side effect; EL1 may read it.
    unsafe {
        core::arch::asm!("isb", "mrs {c}, cntvct_el0", c = out(reg) count, options(nomem, nostack));
    }
    count
}

/// `iterations` turns of a two-instruction loop (`subs`, `b.ne`).
fn known_loop(iterations: u64) {
    // SAFETY: the loop only counts a register down to zero.
    unsafe {
        core::arch::asm!(
            "2:",
            "subs {n}, {n}, #1",
            "b.ne 2b",
            n = inout(reg) iterations => _,
            options(nomem, nostack)
        );
    }
}

/// Instructions per timer tick, times 2^16, measured by [`calibrate`].
static INSTRUCTIONS_PER_TICK_Q16: AtomicU64 = AtomicU64::new(0);

/// Measures how many instructions a tick is against [`known_loop`] (under `-icount shift=0`
/// a constant: QEMU's virtual clock advances 1 ns per instruction and the `virt` timer runs
/// at 62.5 MHz, so 16).
fn calibrate() -> u64 {
    let before = ticks();
    known_loop(CALIBRATION_ITERATIONS);
    let elapsed = (ticks() - before).max(1);
    ((2 * CALIBRATION_ITERATIONS) << 16) / elapsed
}

/// The timer count scaled to instructions.
struct TimerCounter;

impl Counter for TimerCounter {
    fn instructions(&self) -> u64 {
        let q16 = INSTRUCTIONS_PER_TICK_Q16.load(Ordering::Relaxed);
        ((u128::from(ticks()) * u128::from(q16)) >> 16) as u64
    }

    fn clock(&self) -> &dyn gomatch::Clock {
        self
    }
}

impl gomatch::Clock for TimerCounter {
    fn now_us(&self) -> u64 {
        self.instructions() / 1000
    }
}

/// Calibrates the counter, runs the image once and exits with its status.
extern "C" fn start() -> ! {
    let q16 = calibrate();
    INSTRUCTIONS_PER_TICK_Q16.store(q16, Ordering::Relaxed);
    crate::print(format_args!(
        "generic timer: {q16}/65536 instructions per tick"
    ));
    exit(firmware_main(Some(&TimerCounter)))
}
