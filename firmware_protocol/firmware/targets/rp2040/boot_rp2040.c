/*
 * boot_rp2040.c - the boot stage of the RP2040 target: the program boot2 starts (vector table
 * at 0x10000100), never updated itself. It starts the clocks (the watchdog tick too), then asks
 * the core's boot_start() (boot.c) which image to run: a pending test becomes a trial, an
 * unconfirmed trial is rolled back, a slot whose length, CRC-32C or SHA-256 does not check is
 * never chosen; the chosen image is installed flash to flash into the execution region
 * (nothing is copied when it is already there) and, for a trial, the watchdog is armed. Then it
 * runs the application in place: VTOR, MSP and the reset handler from the vector table at
 * 0x10011000. The application learns the slot from two watchdog scratch words.
 */
#include <stdint.h>

#include "spiel_boot.h"
#include "hardware/structs/scb.h"
#include "hardware/structs/watchdog.h"
#include "rp2040_board.h"

#define APP_BASE (XIP_BASE + RP2040_EXEC_OFF + RP2040_SECTOR)
#define APP_SIZE (RP2040_AREA_SIZE - RP2040_SECTOR)

extern uint32_t __data_load__, __data_start__, __data_end__, __bss_start__, __bss_end__;
extern uint32_t __stack_top__;
void boot_reset(void);
static void boot_fault(void);

/* The application's vector table: the initial SP in SRAM and a Thumb reset handler inside it. */
static int runnable(uint32_t sp, uint32_t pc, uint32_t body_size)
{
    return sp > SRAM_BASE && sp <= SRAM_END && (sp & 7u) == 0 && (pc & 1u) && pc > APP_BASE &&
           pc < APP_BASE + body_size;
}

void boot_reset(void)
{
    uint32_t *src = &__data_load__, *dst = &__data_start__, sp, pc, body = APP_SIZE;
    uint8_t head[SP_IMAGE_HEADER_SIZE];
    int slot;
    while (dst < &__data_end__) {
        *dst++ = *src++;
    }
    for (dst = &__bss_start__; dst < &__bss_end__;) {
        *dst++ = 0;
    }
    hw_clear_bits(&watchdog_hw->ctrl, WATCHDOG_CTRL_ENABLE_BITS); /* armed again for a trial */
    /* 125 MHz for the image check and copy; the watchdog's 1 MHz tick from the crystal */
    rp2040_clocks_start();

    slot = boot_start(SPIEL_FW_WATCHDOG_MS);
    if (slot >= 0 && hal_image_read(SPIEL_IMAGE_EXEC, 0, head, sizeof head) == 0) {
        sp_image_header_t h;
        sp_image_header_unpack(head, &h);
        body = h.body_size;
    }
    sp = *(const uint32_t *)APP_BASE;
    pc = *(const uint32_t *)(APP_BASE + 4u);
    if (slot < 0 || !runnable(sp, pc, body)) {
        /* nothing to run (no bootable slot: put a UF2 on the board through BOOTSEL); a trial
         * that is not an image of this layout stays unconfirmed: the watchdog rolls it back */
        boot_fault();
    }
    watchdog_hw->scratch[0] = RP2040_HANDOFF_MAGIC;
    watchdog_hw->scratch[1] = (uint32_t)slot;
    scb_hw->vtor = APP_BASE;
    __asm volatile("msr msp, %0\n\tbx %1" ::"r"(sp), "r"(pc) : "memory");
    for (;;) {
    }
}

static void boot_fault(void)
{
    for (;;) {
        __asm volatile("wfi");
    }
}

/* Required by the SDK files the boot stage links (flash.c): stop rather than go on. */
void hard_assertion_failure(void);
void hard_assertion_failure(void)
{
    boot_fault();
}

typedef void (*vector_t)(void);

/* The boot stage takes no interrupt: the initial SP, the reset handler, the faults. */
__attribute__((section(".vectors"), used)) const vector_t boot_vectors[16] = {
    (vector_t)(uintptr_t)&__stack_top__,
    boot_reset,
    boot_fault, boot_fault, 0, 0, 0, 0, 0, 0, 0, boot_fault, 0, 0, boot_fault, boot_fault,
};
