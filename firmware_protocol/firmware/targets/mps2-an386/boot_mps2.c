/*
 * boot_mps2.c - the boot stage of the mps2-an386 target: a separate small program at address 0,
 * where the Cortex-M4 fetches its reset vector, never updated itself (MCUboot's "RAM load"
 * mode). It asks the core's boot_choose() (boot.c) which image to run: a pending test becomes a
 * trial (recorded before the jump), an unconfirmed trial is rolled back, a slot whose length,
 * CRC-32C or SHA-256 does not check is never chosen. The chosen slot's body is copied to the
 * execution region EXEC_BASE (every image is linked for it, so one build fits either slot) and
 * run: VTOR, MSP and the reset handler from its vector table. Without a bootable slot the
 * built-in (factory) image already at EXEC_BASE runs; under qemu the loader puts it there at
 * every reset (-kernel firmware.elf holds both programs); on a board it is a third flash region
 * copied the same way. The application learns the slot from two words at HANDOFF_ADDR.
 */
#include <stdint.h>

#include "spiel_boot.h"
#include "mps2.h"

extern uint32_t _sidata, _sdata, _edata, _sbss, _ebss, _estack;
void boot_reset(void);
static void boot_fault(void);

/* An application vector table: the initial SP inside the application's RAM and a Thumb reset
 * handler inside the image. */
static int runnable(uint32_t sp, uint32_t pc, uint32_t body_size)
{
    return sp > APP_RAM_BASE && sp <= APP_RAM_BASE + APP_RAM_SIZE && (sp & 7u) == 0 &&
           (pc & 1u) && pc > EXEC_BASE && pc < EXEC_BASE + body_size;
}

void boot_reset(void)
{
    uint32_t *src = &_sidata, *dst = &_sdata, sp, pc, body = EXEC_SIZE;
    uint8_t head[SP_IMAGE_HEADER_SIZE];
    int slot;
    while (dst < &_edata) {
        *dst++ = *src++;
    }
    for (dst = &_sbss; dst < &_ebss;) {
        *dst++ = 0;
    }
    /* the choice, the flash-to-flash install into the execution region, the watchdog for a
     * trial (boot.c); -1: the built-in image (qemu's loader restored it at this reset) */
    slot = boot_start(SPIEL_FW_WATCHDOG_MS);
    if (slot >= 0 && hal_image_read(SPIEL_IMAGE_EXEC, 0, head, sizeof head) == 0) {
        sp_image_header_t h;
        sp_image_header_unpack(head, &h);
        body = h.body_size;
    }
    sp = REG32(EXEC_BASE);
    pc = REG32(EXEC_BASE + 4u);
    if (!runnable(sp, pc, body)) {
        /* not an image of this layout: a trial stays unconfirmed, so a reset rolls it back
         * (the watchdog would too); without a trial there is nothing to run */
        if (slot >= 0) {
            SCB_AIRCR = AIRCR_VECTKEY | AIRCR_SYSRESETREQ;
        }
        boot_fault();
    }
    REG32(HANDOFF_ADDR) = HANDOFF_MAGIC;
    REG32(HANDOFF_ADDR + 4u) = slot < 0 ? HANDOFF_FACTORY : (uint32_t)slot;
    SCB_VTOR = EXEC_BASE;
    dsb();
    isb();
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

typedef void (*vector_t)(void);

/* The boot stage takes no interrupt: the initial SP, the reset handler, the faults. */
__attribute__((section(".isr_vector"), used)) const vector_t boot_vectors[16] = {
    (vector_t)(uintptr_t)&_estack,
    boot_reset,
    boot_fault, boot_fault, boot_fault, boot_fault, boot_fault,
    0, 0, 0, 0,
    boot_fault, boot_fault, 0, boot_fault, boot_fault,
};
