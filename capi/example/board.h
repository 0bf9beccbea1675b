/* The board of the C example: QEMU's mps2-an500 (Cortex-M7), its output and exit through
   semihosting, and an instruction counter (SysTick under QEMU's -icount shift=0). */
#ifndef GOMATCH_EXAMPLE_BOARD_H
#define GOMATCH_EXAMPLE_BOARD_H

#include <stdint.h>

/* Writes a zero-terminated string to the host's console. */
void board_print(const char *text);
/* Ends the program: QEMU exits with `status`. */
_Noreturn void board_exit(int status);
/* Starts the counter; returns its calibration (instructions per SysTick tick, times 2^16). */
uint32_t board_start_counter(void);
/* Instructions since the counter started (exact under -icount shift=0). */
uint64_t board_instructions(void);

#endif /* GOMATCH_EXAMPLE_BOARD_H */
