/*
 * flash_rp2040.c - the RP2040 target's flash: erase in 4 KiB sectors, program in 256-byte
 * pages, read through XIP.
 *
 * On a board (the default build) the Pico SDK's hardware_flash does the work: its functions
 * run from RAM with interrupts off, since the flash cannot be read (so no code can run from it)
 * while it is erased or programmed. Only this path touches a real flash chip.
 *
 * The emulator (rp2040js, build with -DRP2040_EMU_FLASH=1: firmware-emu.elf of target.mk) has
 * no QSPI command interface; its flash is an array it lets the CPU store into through the XIP
 * window. So the emulator build erases by storing 0xFF words and programs by clearing bits with
 * byte stores, which is what NOR does. On real silicon such stores reach the XIP cache at most,
 * never the flash: the emulator build must not be flashed onto a board (it would lose its
 * config at every power cycle), which is why the UF2 is made from the default build alone.
 */
#include <string.h>

#include "hardware/flash.h"
#include "hardware/sync.h"
#include "hardware/regs/addressmap.h"
#include "rp2040_board.h"

#ifndef RP2040_EMU_FLASH
#define RP2040_EMU_FLASH 0
#endif

static int in_flash(uint32_t off, uint32_t len)
{
    /* the boot stage is never written: only the areas behind it (rp2040_board.h) */
    return off >= RP2040_BOOT_SIZE && off <= RP2040_FLASH_BYTES && len <= RP2040_FLASH_BYTES - off;
}

#if RP2040_EMU_FLASH

static void page_program(uint32_t page_off, const uint8_t *page)
{
    volatile uint8_t *xip = (volatile uint8_t *)(uintptr_t)(XIP_BASE + page_off);
    uint32_t i;
    for (i = 0; i < RP2040_PAGE; i++) {
        xip[i] = (uint8_t)(xip[i] & page[i]); /* programming only clears bits */
    }
}

static void sectors_erase(uint32_t off, uint32_t len)
{
    volatile uint32_t *xip = (volatile uint32_t *)(uintptr_t)(XIP_BASE + off);
    uint32_t i;
    for (i = 0; i < len / 4u; i++) {
        xip[i] = 0xFFFFFFFFu;
    }
}

const char *rp2040_serial(void)
{
    return "RP2040-EMU-0001";
}

#else

static void page_program(uint32_t page_off, const uint8_t *page)
{
    uint32_t irq = save_and_disable_interrupts();
    flash_range_program(page_off, page, RP2040_PAGE);
    restore_interrupts(irq);
}

static void sectors_erase(uint32_t off, uint32_t len)
{
    uint32_t irq = save_and_disable_interrupts();
    flash_range_erase(off, len);
    restore_interrupts(irq);
}

const char *rp2040_serial(void)
{
    static char text[2 * FLASH_UNIQUE_ID_SIZE_BYTES + 1];
    if (text[0] == 0) {
        static const char hex[] = "0123456789ABCDEF";
        uint8_t id[FLASH_UNIQUE_ID_SIZE_BYTES];
        uint32_t irq = save_and_disable_interrupts();
        unsigned i;
        flash_get_unique_id(id);
        restore_interrupts(irq);
        for (i = 0; i < FLASH_UNIQUE_ID_SIZE_BYTES; i++) {
            text[2 * i] = hex[id[i] >> 4];
            text[2 * i + 1] = hex[id[i] & 15u];
        }
    }
    return text;
}

#endif

int rp2040_flash_erase(uint32_t off, uint32_t len)
{
    if (!in_flash(off, len) || off % RP2040_SECTOR != 0 || len % RP2040_SECTOR != 0) {
        return -1;
    }
    if (len > 0) {
        sectors_erase(off, len);
    }
    return 0;
}

int rp2040_flash_program(uint32_t off, const uint8_t *data, uint32_t len)
{
    static uint8_t page[RP2040_PAGE]; /* static: flash_range_program reads it from RAM */
    if (!in_flash(off, len)) {
        return -1;
    }
    while (len > 0) {
        uint32_t start = off % RP2040_PAGE;
        uint32_t n = RP2040_PAGE - start < len ? RP2040_PAGE - start : len;
        memset(page, 0xFF, sizeof page); /* 0xFF programs nothing: the page's other bytes stay */
        memcpy(page + start, data, n);
        page_program(off - start, page);
        off += n;
        data += n;
        len -= n;
    }
    return 0;
}

void rp2040_flash_read(uint32_t off, uint8_t *data, uint32_t len)
{
    memcpy(data, (const uint8_t *)(uintptr_t)(XIP_BASE + off), len);
}
