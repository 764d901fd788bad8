/*
 * image_mps2.c - the firmware image slots of the mps2-an386 target (PROTOCOL.md 14.3), shared
 * by the boot stage (boot_mps2.c) and the application: slots 0 and 1 are two 1 MiB regions of
 * the persistent PSRAM, slot 2 the boot record area (two sectors: the core erases a copy's
 * sector just before it programs it), slot 3 the execution region the boot stage installs the
 * chosen image into. NOR rules: erase in 4 KiB sectors, program in 8-byte units. Every erase
 * and write is one flash operation of nor_mps2.c (its power-cut hook). The watchdog too.
 */
#include <string.h>

#include "mps2.h"
#include "spiel_hal.h"
#include "spiel_proto.h"

int mps2_image_version(char version[17]);

uint32_t hal_image_slot_size(void)
{
    return IMAGE_SLOT_SIZE;
}

uint32_t hal_image_sector_size(void)
{
    return NOR_SECTOR;
}

uint32_t hal_image_program_unit(void)
{
    return IMAGE_UNIT;
}

/* The absolute address of an area's byte `offset` when [offset, offset + len) lies inside it,
 * else 0. Slot 3 (the boot stage's execution region): the header sector, then EXEC_BASE. */
static uint32_t area_addr(int slot, uint32_t offset, uint32_t len)
{
    uint32_t base, size;
    if (slot == 0 || slot == 1) {
        base = PSRAM_BASE + SLOT0_OFF + (uint32_t)slot * IMAGE_SLOT_SIZE;
        size = IMAGE_SLOT_SIZE;
    } else if (slot == SPIEL_IMAGE_RECORD) {
        base = PSRAM_BASE + BOOT_REC_OFF;
        size = 2u * NOR_SECTOR;
    } else if (slot == SPIEL_IMAGE_EXEC) {
        base = EXEC_HDR_ADDR;
        size = NOR_SECTOR + IMAGE_SLOT_SIZE;
    } else {
        return 0;
    }
    return offset <= size && len <= size - offset ? base + offset : 0u;
}

int hal_image_erase(int slot, uint32_t offset, uint32_t len)
{
    uint32_t at = area_addr(slot, offset, len);
    return at != 0 ? flash_erase_at(at, len) : -1;
}

int hal_image_write(int slot, uint32_t offset, const uint8_t *data, uint32_t len)
{
    uint32_t at = area_addr(slot, offset, len);
    if (at == 0 || offset % IMAGE_UNIT != 0 || len % IMAGE_UNIT != 0) {
        return -1; /* ECC flash: whole program units only */
    }
    return flash_write_at(at, data, len);
}

int hal_image_read(int slot, uint32_t offset, uint8_t *data, uint32_t len)
{
    uint32_t at = area_addr(slot, offset, len);
    if (at == 0) {
        return -1;
    }
    flash_read_at(at, data, len);
    return 0;
}

/* The watchdog: armed by the boot stage before a trial; the application kicks it. */
void hal_watchdog_start(uint32_t timeout_ms)
{
    WDOG_LOCK = WDOG_UNLOCK;
    /* the reset comes at the second expiry without a kick: half the timeout each */
    WDOG_LOAD = (MPS2_SYSCLK_HZ / 1000u) * (timeout_ms / 2u);
    WDOG_CTRL = WDOG_CTRL_RESEN; /* no interrupt (the NMI would go to the image's table) */
    WDOG_LOCK = 0;
}

void hal_watchdog_kick(void)
{
    if (WDOG_CTRL & WDOG_CTRL_RESEN) {
        WDOG_LOCK = WDOG_UNLOCK;
        WDOG_INTCLR = 1u; /* clears the expiry and reloads the counter */
        WDOG_LOCK = 0;
    }
}

int hal_image_running(void)
{
    uint32_t slot = REG32(HANDOFF_ADDR + 4u);
    return REG32(HANDOFF_ADDR) == HANDOFF_MAGIC && slot <= 1u ? (int)slot : -1;
}

/* The running slot's version text (its image header): 0, or -1 for the built-in image. */
int mps2_image_version(char version[17])
{
    uint8_t head[SP_IMAGE_HEADER_SIZE];
    sp_image_header_t h;
    int slot = hal_image_running();
    if (slot < 0 || hal_image_read(slot, 0, head, sizeof head) != 0) {
        return -1;
    }
    sp_image_header_unpack(head, &h);
    memcpy(version, h.version, 16);
    version[16] = 0;
    return 0;
}
