//! Instruction-count profile of the Cortex-M7 image (feature `pc-profile`, a development
//! tool run by `firmware/profile.sh`): SysTick interrupts every [`PERIOD_TICKS`] ticks
//! (under `-icount shift=0`, 40 instructions a tick on the `mps2-an500`), the handler keeps
//! the interrupted program counter, and the image prints the samples at its end. Unlike
//! host-side sampling of QEMU, whose wall time per instruction differs between integer and
//! floating-point code, every sample stands for the same number of instructions.

use core::sync::atomic::{AtomicU32, AtomicUsize, Ordering};

/// SysTick ticks between samples: 100,000 instructions at 40 a tick.
pub const PERIOD_TICKS: u32 = 2_500;
/// Most samples kept (a 5e9-instruction query takes about 50,000).
const CAPACITY: usize = 131_072;

/// The interrupted program counters.
static SAMPLES: [AtomicU32; CAPACITY] = [const { AtomicU32::new(0) }; CAPACITY];
/// Samples taken (may pass [`CAPACITY`]; those past it are counted, not kept).
static TAKEN: AtomicUsize = AtomicUsize::new(0);

/// The SysTick handler: the exception frame the hardware pushed on the main stack (the
/// image never switches to the process stack) holds the interrupted PC in its 7th word.
#[unsafe(naked)]
#[unsafe(no_mangle)]
pub extern "C" fn SysTick() {
    core::arch::naked_asm!("mrs r0, msp", "b {record}", record = sym record);
}

/// Counts the wrap and keeps the PC of the exception `frame`.
extern "C" fn record(frame: *const u32) {
    super::WRAPS.fetch_add(1, Ordering::Relaxed);
    // SAFETY: `frame` is the hardware-stacked exception frame (r0-r3, r12, lr, pc, xpsr).
    let pc = unsafe { frame.add(6).read_volatile() };
    let taken = TAKEN.fetch_add(1, Ordering::Relaxed);
    if let Some(slot) = SAMPLES.get(taken) {
        slot.store(pc, Ordering::Relaxed);
    }
}

/// Prints the samples, one `pc HEX` line each, after a `pc-samples` header.
pub fn print_samples() {
    let taken = TAKEN.load(Ordering::Relaxed);
    crate::print(format_args!(
        "pc-samples: {taken} every {PERIOD_TICKS} ticks"
    ));
    for sample in &SAMPLES[..taken.min(CAPACITY)] {
        crate::print(format_args!("pc {:x}", sample.load(Ordering::Relaxed)));
    }
}
