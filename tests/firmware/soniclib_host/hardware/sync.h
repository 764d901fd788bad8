/* host stand-in for the Pico SDK's hardware/sync.h (the harness has no interrupts) */
#ifndef SPIEL_HOST_SYNC_H
#define SPIEL_HOST_SYNC_H
#include <stdint.h>
static inline uint32_t save_and_disable_interrupts(void) { return 0; }
static inline void restore_interrupts(uint32_t s) { (void)s; }
#endif
