/*
 * image_mps2.c - the firmware image slots of the mps2-an386 target (PROTOCOL.md 14.3), shared
 * by the boot stage (boot_mps2.c) and the application: slots 0 and 1 are two 1 MiB regions of
 * the persistent PSRAM, slot 2 the boot record area. The core writes its two 16-byte record
 * copies in place, alternately; on NOR each copy has a sector of its own, erased just before
 * the copy is programmed, so a cut there spoils only the copy being written (boot.c keeps the
 * other). Every erase and write is one flash operation of nor_mps2.c (its power-cut hook).
 */
#include <string.h>

#include "mps2.h"
#include "spiel_hal.h"
#include "spiel_proto.h"

int mps2_image_version(char version[17]);

#define RECORD_COPY 16u

uint32_t hal_image_slot_size(void)
{
    return IMAGE_SLOT_SIZE;
}

static int slot_range(int slot, uint32_t offset, uint32_t len)
{
    return (slot == 0 || slot == 1) && offset <= IMAGE_SLOT_SIZE &&
           len <= IMAGE_SLOT_SIZE - offset;
}

static uint32_t slot_off(int slot, uint32_t offset)
{
    return SLOT0_OFF + (uint32_t)slot * IMAGE_SLOT_SIZE + offset;
}

/* the record area's byte `offset` (0 .. 31): copy offset / 16 in its own sector */
static uint32_t record_off(uint32_t offset)
{
    return BOOT_REC_OFF + (offset / RECORD_COPY) * NOR_SECTOR + offset % RECORD_COPY;
}

int hal_image_erase(int slot)
{
    if (slot == 2) {
        return nor_erase(BOOT_REC_OFF, 2u * NOR_SECTOR);
    }
    return slot_range(slot, 0, IMAGE_SLOT_SIZE) ? nor_erase(slot_off(slot, 0), IMAGE_SLOT_SIZE)
                                                : -1;
}

int hal_image_write(int slot, uint32_t offset, const uint8_t *data, uint32_t len)
{
    if (slot == 2) { /* one whole copy or part of one */
        uint32_t copy = offset / RECORD_COPY;
        if (len == 0 || copy > 1u || offset % RECORD_COPY + len > RECORD_COPY) {
            return -1;
        }
        if (nor_erase(BOOT_REC_OFF + copy * NOR_SECTOR, NOR_SECTOR) != 0) {
            return -1;
        }
        return nor_write(record_off(offset), data, len);
    }
    return slot_range(slot, offset, len) ? nor_write(slot_off(slot, offset), data, len) : -1;
}

int hal_image_read(int slot, uint32_t offset, uint8_t *data, uint32_t len)
{
    if (slot == 2) {
        uint32_t i;
        if (offset > 2u * RECORD_COPY || len > 2u * RECORD_COPY - offset) {
            return -1;
        }
        for (i = 0; i < len; i++) {
            nor_read(record_off(offset + i), data + i, 1u);
        }
        return 0;
    }
    if (!slot_range(slot, offset, len)) {
        return -1;
    }
    nor_read(slot_off(slot, offset), data, len);
    return 0;
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
