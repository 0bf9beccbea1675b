/* Start-up code of the C example on QEMU's mps2-an500 (Cortex-M7), as cortex-m-rt does it for
   the Rust firmware (firmware/src/mps2.rs): the vector table, the reset handler (FPU on,
   .data copied, .bss zeroed, main called), semihosting output and exit, and SysTick counting
   instructions. */
#include <stdint.h>
#include <string.h>

#include "board.h"

extern int main(void);
extern uint32_t _stack_top, _sidata, _sdata, _edata, _sbss, _ebss;

/* Coprocessor access control: CP10 and CP11 (the FPU) full access. */
#define SCB_CPACR (*(volatile uint32_t *)0xE000ED88u)
/* SysTick control and status, reload and current value registers. */
#define SYST_CSR (*(volatile uint32_t *)0xE000E010u)
#define SYST_RVR (*(volatile uint32_t *)0xE000E014u)
#define SYST_CVR (*(volatile uint32_t *)0xE000E018u)
/* SysTick counts down from this (24 bits), then wraps and interrupts. */
#define SYST_RELOAD 0x00FFFFFFu
/* Semihosting operations and the exit reason of a program that ended by itself. */
#define SYS_WRITE0 0x04u
#define SYS_EXIT_EXTENDED 0x20u
#define ADP_STOPPED_APPLICATION_EXIT 0x20026u

/* Runs before anything may use the FPU: this function is integer code only. */
__attribute__((noreturn)) void reset_handler(void) {
  SCB_CPACR |= 0xFu << 20;
  __asm__ volatile("dsb\n\tisb" ::: "memory");
  uint32_t *src = &_sidata;
  for (uint32_t *dst = &_sdata; dst < &_edata;) *dst++ = *src++;
  for (uint32_t *dst = &_sbss; dst < &_ebss;) *dst++ = 0;
  board_exit(main());
}

static volatile uint32_t systick_wraps;

void systick_handler(void) { systick_wraps++; }

/* Any other exception (a HardFault: a bug, or the library's panic trap): exit with 101 as the
   Rust firmware's panic handler does. */
static void fault_handler(void) { board_exit(101); }

/* Initial stack pointer, reset, NMI, HardFault, MemManage, BusFault, UsageFault, 4 reserved,
   SVCall, DebugMonitor, reserved, PendSV, SysTick. */
__attribute__((section(".vector_table"), used)) static void (*const vector_table[16])(void) = {
    (void (*)(void))&_stack_top, (void (*)(void))reset_handler, fault_handler, fault_handler,
    fault_handler, fault_handler, fault_handler, 0, 0, 0, 0, fault_handler, fault_handler, 0,
    fault_handler, systick_handler,
};

static uint32_t semihost(uint32_t op, const void *arg) {
  register uint32_t r0 __asm__("r0") = op;
  register const void *r1 __asm__("r1") = arg;
  __asm__ volatile("bkpt 0xab" : "+r"(r0) : "r"(r1) : "memory");
  return r0;
}

void board_print(const char *text) { semihost(SYS_WRITE0, text); }

_Noreturn void board_exit(int status) {
  const uint32_t block[2] = {ADP_STOPPED_APPLICATION_EXIT, (uint32_t)status};
  semihost(SYS_EXIT_EXTENDED, block);
  for (;;) {
  }
}

/* SysTick ticks since the counter started, extended past 24 bits by the wraps. */
static uint64_t ticks(void) {
  for (;;) {
    uint32_t wraps = systick_wraps;
    uint32_t current = SYST_CVR & SYST_RELOAD;
    if (systick_wraps == wraps) {
      uint32_t in_period = (SYST_RELOAD - current + 1) & SYST_RELOAD;
      return (uint64_t)wraps * (SYST_RELOAD + 1ull) + in_period;
    }
  }
}

static uint32_t instructions_per_tick_q16;

uint32_t board_start_counter(void) {
  SYST_RVR = SYST_RELOAD;
  SYST_CVR = 0;
  SYST_CSR = 0x7; /* enable, interrupt on wrap, processor clock */
  /* Calibration: 2,000,000 turns of a two-instruction loop. */
  uint32_t iterations = 2000000;
  uint64_t before = ticks();
  __asm__ volatile("1:\n\tsubs %0, #1\n\tbne 1b" : "+r"(iterations)::"cc");
  uint64_t elapsed = ticks() - before;
  if (elapsed == 0) elapsed = 1;
  instructions_per_tick_q16 = (uint32_t)(((2ull * 2000000u) << 16) / elapsed);
  return instructions_per_tick_q16;
}

uint64_t board_instructions(void) {
  /* ticks * q16 >> 16 without overflow for any realistic count (2^48 ticks). */
  uint64_t t = ticks();
  return (t >> 16) * instructions_per_tick_q16 + (((t & 0xFFFFu) * instructions_per_tick_q16) >> 16);
}
