/*
 * startup_rp2040.c - the RP2040 target's start: the vector table (at 0x10000100, right after
 * boot2, where boot2 looks for it), the reset handler (RAM code and data copied, bss cleared)
 * and the two interrupts this firmware takes: the USB controller and timer alarm 0.
 * The Pico SDK's crt0.S and runtime do more (RAM vector table, binary info, multicore, C++):
 * none of it is needed here.
 */
#include <stdint.h>

#include "rp2040_board.h"

extern uint32_t __data_load__, __data_start__, __data_end__, __bss_start__, __bss_end__;
extern uint32_t __stack_top__;
int main(void);
void reset_handler(void);
static void fault(void);
static void unused_irq(void);

void reset_handler(void)
{
    uint32_t *src = &__data_load__, *dst = &__data_start__;
    while (dst < &__data_end__) {
        *dst++ = *src++;
    }
    for (dst = &__bss_start__; dst < &__bss_end__;) {
        *dst++ = 0;
    }
    (void)main();
    for (;;) {
    }
}

static void fault(void)
{
    /* a HardFault: nothing to report to; the watchdog, when armed, restarts the board */
    for (;;) {
        __asm volatile("wfi");
    }
}

static void unused_irq(void)
{
    for (;;) {
        __asm volatile("wfi");
    }
}

/* The sensor layer's interrupts (sensor/chbsp_rp2040.c, built with SONICLIB_DIR): the GPIO
 * bank (the sensors' INT lines) and the two I2C blocks; without it they are never enabled. */
void isr_io_bank0(void) __attribute__((weak, alias("unused_irq")));
void isr_i2c0(void) __attribute__((weak, alias("unused_irq")));
void isr_i2c1(void) __attribute__((weak, alias("unused_irq")));

typedef void (*vector_t)(void);

/* 16 system exceptions, then the RP2040's 32 interrupts (TIMER_IRQ_0 is 0, USBCTRL_IRQ 5). */
__attribute__((section(".vectors"), used)) const vector_t vectors[48] = {
    (vector_t)(uintptr_t)&__stack_top__,
    reset_handler,
    fault, fault, /* NMI, HardFault */
    0, 0, 0, 0, 0, 0, 0,
    fault, /* SVCall */
    0, 0,
    fault, fault, /* PendSV, SysTick */
    isr_timer0, unused_irq, unused_irq, unused_irq, unused_irq, isr_usbctrl,     /* 0-5 */
    unused_irq, unused_irq, unused_irq, unused_irq, unused_irq, unused_irq, unused_irq,
    isr_io_bank0,                                                                  /* 13 */
    unused_irq, unused_irq, unused_irq, unused_irq, unused_irq, unused_irq, unused_irq,
    unused_irq, unused_irq, isr_i2c0, isr_i2c1,                                    /* 23, 24 */
    unused_irq, unused_irq, unused_irq, unused_irq, unused_irq, unused_irq, unused_irq,
};
