/*
 * startup.c - reset handler and vector table of the mps2-an386 target (Cortex-M4F).
 *
 * Linked at 0 (the bring-up image) or at EXEC_BASE (the application the boot stage jumps to).
 * The reset handler points VTOR at this table, copies .data from its load address, zeroes .bss, turns the FPU on
 * (CPACR) and calls main(). Faults end in fault_handler(), which resets the board (a real
 * port would log the fault first).
 */
#include <stdint.h>

#include "mps2.h"

extern uint32_t _sidata, _sdata, _edata, _sbss, _ebss, _estack;
extern int main(void);
void reset_handler(void);
void fault_handler(void);
void default_handler(void);
void uart0_rx_handler(void); /* hal_mps2.c */
void uart0_tx_handler(void); /* hal_mps2.c */
void timer0_handler(void);   /* hal_mps2.c */
void timer1_handler(void);   /* hal_mps2.c */

typedef void (*vector_t)(void);

extern const vector_t vector_table[];

void reset_handler(void)
{
    uint32_t *src = &_sidata, *dst = &_sdata;
    SCB_VTOR = (uint32_t)(uintptr_t)vector_table; /* the boot stage set it too; a debugger may not */
    while (dst < &_edata) {
        *dst++ = *src++;
    }
    for (dst = &_sbss; dst < &_ebss;) {
        *dst++ = 0;
    }
    SCB_CPACR |= (0xFu << 20); /* CP10 and CP11 full access: the FPU */
    dsb();
    __asm volatile("isb 0xF" ::: "memory");
    (void)main();
    for (;;) {
    }
}

void fault_handler(void)
{
    SCB_AIRCR = AIRCR_VECTKEY | AIRCR_SYSRESETREQ;
    for (;;) {
    }
}

void default_handler(void)
{
    for (;;) {
    }
}

#define N_IRQ 32

/* Entry 0 is the initial stack pointer, then the 15 system exceptions, then the IRQs. */
__attribute__((section(".isr_vector"), used)) const vector_t vector_table[16 + N_IRQ] = {
    (vector_t)(uintptr_t)&_estack,
    reset_handler,
    fault_handler, /* NMI */
    fault_handler, /* HardFault */
    fault_handler, /* MemManage */
    fault_handler, /* BusFault */
    fault_handler, /* UsageFault */
    0, 0, 0, 0,
    default_handler, /* SVCall */
    default_handler, /* DebugMonitor */
    0,
    default_handler, /* PendSV */
    default_handler, /* SysTick */
    /* IRQs of the AN385/AN386 image */
    uart0_rx_handler, /* 0: UART0 RX */
    uart0_tx_handler, /* 1: UART0 TX */
    default_handler, default_handler, default_handler, default_handler, default_handler,
    default_handler,
    timer0_handler, /* 8: timer 0 */
    timer1_handler, /* 9: timer 1 */
    default_handler, default_handler, default_handler, default_handler,
    default_handler, default_handler, default_handler, default_handler, default_handler,
    default_handler, default_handler, default_handler, default_handler, default_handler,
    default_handler, default_handler, default_handler, default_handler, default_handler,
    default_handler, default_handler, default_handler,
};
