/*
 * image_rp2040.c - the firmware image areas of the RP2040 target (PROTOCOL.md 14.3, the layout
 * in rp2040_board.h), shared by the boot stage (boot_rp2040.c) and the application, and the
 * watchdog the boot stage arms before a trial image. Erase: 4 KiB sectors; program unit: 1 byte
 * (the W25Q16 programs any bytes of a 256-byte page, once each; flash_rp2040.c pads pages).
 */
#include <string.h>

#include "hardware/watchdog.h"
#include "hardware/structs/watchdog.h"
#include "rp2040_board.h"
#include "spiel_hal.h"
#include "spiel_proto.h"

uint32_t hal_image_slot_size(void)
{
    return RP2040_AREA_SIZE;
}

uint32_t hal_image_sector_size(void)
{
    return RP2040_SECTOR;
}

uint32_t hal_image_program_unit(void)
{
    return 1u;
}

/* The flash offset of an area's byte `offset` when [offset, offset + len) lies inside it,
 * else 0 (no area starts at 0: the boot stage is there). */
static uint32_t area_off(int slot, uint32_t offset, uint32_t len)
{
    uint32_t base, size = RP2040_AREA_SIZE;
    if (slot == 0 || slot == 1) {
        base = RP2040_SLOT0_OFF + (uint32_t)slot * RP2040_AREA_SIZE;
    } else if (slot == SPIEL_IMAGE_RECORD) {
        base = RP2040_RECORD_OFF;
        size = 2u * RP2040_SECTOR;
    } else if (slot == SPIEL_IMAGE_EXEC) {
        base = RP2040_EXEC_OFF;
    } else {
        return 0;
    }
    return offset <= size && len <= size - offset ? base + offset : 0u;
}

int hal_image_erase(int slot, uint32_t offset, uint32_t len)
{
    uint32_t at = area_off(slot, offset, len);
    return at != 0 ? rp2040_flash_erase(at, len) : -1;
}

int hal_image_write(int slot, uint32_t offset, const uint8_t *data, uint32_t len)
{
    uint32_t at = area_off(slot, offset, len);
    return at != 0 ? rp2040_flash_program(at, data, len) : -1;
}

int hal_image_read(int slot, uint32_t offset, uint8_t *data, uint32_t len)
{
    uint32_t at = area_off(slot, offset, len);
    if (at == 0) {
        return -1;
    }
    rp2040_flash_read(at, data, len);
    return 0;
}

int hal_image_running(void)
{
    uint32_t slot = watchdog_hw->scratch[1];
    return watchdog_hw->scratch[0] == RP2040_HANDOFF_MAGIC && slot <= 1u ? (int)slot : -1;
}

/* Armed by the boot stage just before a trial image runs; the application kicks it from every
 * poll. The SDK's watchdog_enable() counts in microseconds of the watchdog tick (1 MHz from
 * the crystal, which the boot stage starts first). The SDK's watchdog_update() reloads the
 * value its own watchdog_enable() kept in RAM: the application is another program, so the
 * boot stage leaves the reload value in scratch 2 and the kick writes that. */
void hal_watchdog_start(uint32_t timeout_ms)
{
    /* what the SDK loads: 2 counts per microsecond (RP2040-E1), at most 24 bits (8.3 s) */
    uint64_t load = (uint64_t)timeout_ms * 2000u;
    watchdog_hw->scratch[2] = load > WATCHDOG_LOAD_BITS ? WATCHDOG_LOAD_BITS : (uint32_t)load;
    watchdog_enable(timeout_ms, 1);
}

void hal_watchdog_kick(void)
{
    if (watchdog_hw->ctrl & WATCHDOG_CTRL_ENABLE_BITS) {
        watchdog_hw->load = watchdog_hw->scratch[2];
    }
}

/* The running image's version text (its header in the execution region): 0, or -1. */
int rp2040_image_version(char version[17])
{
    uint8_t head[SP_IMAGE_HEADER_SIZE];
    sp_image_header_t h;
    if (hal_image_running() < 0 || hal_image_read(SPIEL_IMAGE_EXEC, 0, head, sizeof head) != 0) {
        return -1;
    }
    sp_image_header_unpack(head, &h);
    memcpy(version, h.version, 16);
    version[16] = 0;
    return 0;
}
