//! Cortex-M7 on QEMU's `mps2-an500` board (cortex-m-rt): `memory.x` places the image in
//! the board's SSRAM1 at 0, `.bss` and the stack in SSRAM2/3 at 0x2000_0000 and the
//! workspace in its 16 MiB PSRAM at 0x6000_0000; semihosting prints and exits; SysTick,
//! run from the CPU clock with a wrap interrupt, counts instructions.

use core::sync::atomic::{AtomicU32, Ordering};

use cortex_m_rt::entry;

pub use crate::semihosting::{exit, print};
use crate::{firmware_main, Counter};

/// SysTick control and status register.
const SYST_CSR: *mut u32 = 0xE000_E010 as *mut u32;
/// SysTick reload value register.
const SYST_RVR: *mut u32 = 0xE000_E014 as *mut u32;
/// SysTick current value register.
const SYST_CVR: *mut u32 = 0xE000_E018 as *mut u32;
/// SysTick counts down from this (24 bits) and then wraps.
#[cfg(not(feature = "pc-profile"))]
const RELOAD: u32 = 0x00FF_FFFF;
/// SysTick wraps (and the profiler samples) every `RELOAD + 1` ticks.
#[cfg(feature = "pc-profile")]
const RELOAD: u32 = pc_profile::PERIOD_TICKS - 1;
/// CSR: enable, interrupt on wrap, clocked by the processor clock.
const ENABLE_TICKINT_CPUCLK: u32 = 0b111;
/// Iterations of the calibration loop (two instructions each).
const CALIBRATION_ITERATIONS: u32 = 2_000_000;

/// SysTick wraps since the counter started.
static WRAPS: AtomicU32 = AtomicU32::new(0);

#[cfg(feature = "pc-profile")]
#[path = "pc_profile.rs"]
mod pc_profile;

#[cfg(not(feature = "pc-profile"))]
#[cortex_m_rt::exception]
fn SysTick() {
    WRAPS.fetch_add(1, Ordering::Relaxed);
}

/// SysTick ticks, extended past 24 bits by the wrap count.
fn ticks() -> u64 {
    loop {
        let wraps = WRAPS.load(Ordering::Relaxed);
        // SAFETY: reading SysTick's current value register has no side effect.
        let current = unsafe { SYST_CVR.read_volatile() } & RELOAD;
        if WRAPS.load(Ordering::Relaxed) == wraps {
            // The wrap interrupt comes as the count reaches 0, so 0 starts a period.
            let in_period = (RELOAD - current + 1) & RELOAD;
            return u64::from(wraps) * (u64::from(RELOAD) + 1) + u64::from(in_period);
        }
    }
}

/// Starts SysTick from the processor clock, interrupting at every wrap.
fn start_systick() {
    // SAFETY: the SysTick registers exist on every Cortex-M; this image is their only user.
    unsafe {
        SYST_RVR.write_volatile(RELOAD);
        SYST_CVR.write_volatile(0);
        SYST_CSR.write_volatile(ENABLE_TICKINT_CPUCLK);
    }
}

/// `iterations` turns of a two-instruction loop (`subs`, `bne`).
fn known_loop(iterations: u32) {
    // SAFETY: the loop only counts a register down to zero.
    unsafe {
        core::arch::asm!(
            "2:",
            "subs {n}, #1",
            "bne 2b",
            n = inout(reg) iterations => _,
            options(nomem, nostack)
        );
    }
}

/// Instructions per SysTick tick, times 2^16, measured by [`calibrate`].
static INSTRUCTIONS_PER_TICK_Q16: AtomicU32 = AtomicU32::new(0);

/// Starts SysTick and measures how many instructions a tick is against [`known_loop`]
/// (under `-icount shift=0` a constant: QEMU's virtual clock advances 1 ns per
/// instruction; 40 on the 25 MHz `mps2-an500`).
fn calibrate() -> u32 {
    start_systick();
    let before = ticks();
    known_loop(CALIBRATION_ITERATIONS);
    let elapsed = (ticks() - before).max(1);
    let q16 = ((2 * u64::from(CALIBRATION_ITERATIONS)) << 16) / elapsed;
    u32::try_from(q16).unwrap_or(u32::MAX)
}

/// SysTick scaled to instructions.
struct SysTickCounter;

impl Counter for SysTickCounter {
    fn instructions(&self) -> u64 {
        let q16 = INSTRUCTIONS_PER_TICK_Q16.load(Ordering::Relaxed);
        ((u128::from(ticks()) * u128::from(q16)) >> 16) as u64
    }

    fn clock(&self) -> &dyn gomatch::Clock {
        self
    }
}

impl gomatch::Clock for SysTickCounter {
    fn now_us(&self) -> u64 {
        self.instructions() / 1000
    }
}

#[entry]
fn main() -> ! {
    let q16 = calibrate();
    INSTRUCTIONS_PER_TICK_Q16.store(q16, Ordering::Relaxed);
    crate::print(format_args!("SysTick: {q16}/65536 instructions per tick"));
    let code = firmware_main(Some(&SysTickCounter));
    #[cfg(feature = "pc-profile")]
    pc_profile::print_samples();
    exit(code)
}
