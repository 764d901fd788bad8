/* core.h - internal interfaces between the files of the portable core (not for targets). */
#ifndef SPIEL_CORE_H
#define SPIEL_CORE_H

#include <stdint.h>

#include "spiel_device.h"
#include "spiel_hal.h"

/* The flash slot metadata (PROTOCOL.md 9.1): magic, generation, length, CRC-32C of the data,
 * four u32 little-endian at the start of the slot, written last. */
#define SPIEL_SLOT_MAGIC 0x53504346u
#define SPIEL_SLOT_META_SIZE 16u
#define SPIEL_FLASH_PAGE 256u /* bytes per hal_flash_write of a commit */

typedef struct {
    uint8_t valid;
    uint32_t generation, length, crc;
} cfg_slot_t;

/* config_store.c: two slots in the HAL flash region; staging in RAM. */
int cfg_init(void);                    /* 0, or <0 when the flash is too small for two slots */
int cfg_active(void);                  /* 0, 1, or -1 (none valid: factory defaults) */
void cfg_slot(int slot, cfg_slot_t *out);
uint32_t cfg_capacity(void);           /* max_length */
uint32_t cfg_active_length(void);
int cfg_read_active(uint32_t offset, uint8_t *out, uint32_t len); /* 0 ok */
/* Write staging[0:len] to the inactive slot and make it active: SP_ERR_OK, or
 * SP_ERR_FLASH_WRITE_FAILED / SP_ERR_FLASH_VERIFY_FAILED (the old slot stays active). */
uint16_t cfg_commit(const uint8_t *data, uint32_t len, cfg_slot_t *done, int *slot);
/* The settings in force: the active blob's header when it is usable, else the defaults. */
void cfg_settings(hal_settings_t *out);

extern spiel_device_stats_t spiel_stats;

#endif
