/* config_store.c - the config in two flash slots, power-cut safe (PROTOCOL.md section 9).
 *
 * Slot i occupies [i * slot_size, (i + 1) * slot_size) of the HAL flash region; slot_size is
 * SPIEL_SLOT_META_SIZE + SPIEL_CONFIG_MAX rounded up to whole sectors. A commit erases the
 * inactive slot, writes the data in pages, then the 16-byte metadata LAST, then reads the slot
 * back. Until the metadata is complete and its CRC matches, the slot is not valid, so a
 * power cut at any flash operation leaves the old slot active (or the new one, once whole).
 */
#include <string.h>

#include "core.h"

static uint32_t slot_size;
static uint32_t capacity;
static int active = -1;
static cfg_slot_t slots[2];

static int count_error(int rc)
{
    if (rc != 0) {
        spiel_stats.flash_errors++;
    }
    return rc;
}

/* Read and check one slot's metadata and data CRC. */
static void scan_slot(int i, cfg_slot_t *s)
{
    uint8_t meta[SPIEL_SLOT_META_SIZE], buf[64];
    uint32_t base = (uint32_t)i * slot_size, magic, done, crc = 0;
    memset(s, 0, sizeof *s);
    if (count_error(hal_flash_read(base, meta, sizeof meta)) != 0) {
        return;
    }
    magic = sp_le_get_u32(meta);
    s->generation = sp_le_get_u32(meta + 4);
    s->length = sp_le_get_u32(meta + 8);
    s->crc = sp_le_get_u32(meta + 12);
    if (magic != SPIEL_SLOT_MAGIC || s->length > capacity) {
        s->generation = s->length = s->crc = 0;
        return;
    }
    for (done = 0; done < s->length; done += (uint32_t)sizeof buf) {
        uint32_t n = s->length - done < sizeof buf ? s->length - done : (uint32_t)sizeof buf;
        if (count_error(hal_flash_read(base + SPIEL_SLOT_META_SIZE + done, buf, n)) != 0) {
            return;
        }
        crc = sp_crc32c(crc, buf, n);
    }
    s->valid = (uint8_t)(crc == s->crc);
}

/* a is after b in u32 serial arithmetic */
static int newer(uint32_t a, uint32_t b)
{
    return a != b && (uint32_t)(a - b) < 0x80000000u;
}

static void choose_active(void)
{
    scan_slot(0, &slots[0]);
    scan_slot(1, &slots[1]);
    if (slots[0].valid && slots[1].valid) {
        active = newer(slots[1].generation, slots[0].generation) ? 1 : 0;
    } else if (slots[0].valid) {
        active = 0;
    } else if (slots[1].valid) {
        active = 1;
    } else {
        active = -1;
    }
}

int cfg_init(void)
{
    uint32_t sector = hal_flash_sector_size();
    uint32_t need = SPIEL_SLOT_META_SIZE + SPIEL_CONFIG_MAX;
    if (sector == 0) {
        sector = 1;
    }
    slot_size = (need + sector - 1) / sector * sector;
    capacity = SPIEL_CONFIG_MAX;
    if (hal_flash_size() < 2 * slot_size) {
        capacity = 0;
        active = -1;
        memset(slots, 0, sizeof slots);
        return -1;
    }
    choose_active();
    return 0;
}

int cfg_active(void)
{
    return active;
}

void cfg_slot(int slot, cfg_slot_t *out)
{
    *out = slots[slot & 1];
}

uint32_t cfg_capacity(void)
{
    return capacity;
}

uint32_t cfg_active_length(void)
{
    return active < 0 ? 0 : slots[active].length;
}

int cfg_read_active(uint32_t offset, uint8_t *out, uint32_t len)
{
    if (active < 0 || offset > slots[active].length || len > slots[active].length - offset) {
        return -1;
    }
    return count_error(
        hal_flash_read((uint32_t)active * slot_size + SPIEL_SLOT_META_SIZE + offset, out, len));
}

uint16_t cfg_commit(const uint8_t *data, uint32_t len, cfg_slot_t *done, int *slot)
{
    int target = active < 0 ? 0 : 1 - active;
    uint32_t generation = active < 0 ? 1u : slots[active].generation + 1u;
    uint32_t base = (uint32_t)target * slot_size, off;
    uint8_t meta[SPIEL_SLOT_META_SIZE];
    uint32_t crc = sp_crc32c(0, data, len);
    cfg_slot_t check;
    if (len > capacity) {
        return SP_ERR_TOO_LARGE;
    }
    if (count_error(hal_flash_erase(base, slot_size)) != 0) {
        return SP_ERR_FLASH_WRITE_FAILED;
    }
    for (off = 0; off < len; off += SPIEL_FLASH_PAGE) {
        uint32_t n = len - off < SPIEL_FLASH_PAGE ? len - off : SPIEL_FLASH_PAGE;
        if (count_error(hal_flash_write(base + SPIEL_SLOT_META_SIZE + off, data + off, n)) != 0) {
            return SP_ERR_FLASH_WRITE_FAILED;
        }
    }
    sp_le_put_u32(meta, SPIEL_SLOT_MAGIC);
    sp_le_put_u32(meta + 4, generation);
    sp_le_put_u32(meta + 8, len);
    sp_le_put_u32(meta + 12, crc);
    if (count_error(hal_flash_write(base, meta, sizeof meta)) != 0) {
        return SP_ERR_FLASH_WRITE_FAILED;
    }
    scan_slot(target, &check);
    if (!check.valid || check.generation != generation || check.length != len ||
        check.crc != crc) {
        slots[target] = check;
        return SP_ERR_FLASH_VERIFY_FAILED;
    }
    slots[target] = check;
    active = target;
    *done = check;
    *slot = target;
    return SP_ERR_OK;
}

void cfg_settings(hal_settings_t *out)
{
    const hal_board_info_t *info = hal_board_info();
    uint8_t raw[SP_CONFIG_HEADER_SIZE];
    sp_config_header_t h;
    uint32_t length = cfg_active_length();
    memset(out, 0, sizeof *out);
    out->n_samples = info->default_n_samples;
    out->sample_rate_hz = info->default_sample_rate_hz;
    if (active < 0 || length < SP_CONFIG_HEADER_SIZE || cfg_read_active(0, raw, sizeof raw) != 0) {
        return;
    }
    sp_config_header_unpack(raw, &h);
    if (memcmp(h.magic, SP_CONFIG_MAGIC, SP_CONFIG_MAGIC_SIZE) != 0 ||
        h.version != SP_CONFIG_VERSION || h.header_size < SP_CONFIG_HEADER_SIZE ||
        /* in u64: a toml_length near 2^32 must not wrap the sum round to the length */
        (uint64_t)h.header_size + h.toml_length != length || h.n_samples == 0 ||
        !(h.sample_rate_hz >= 1.0f && h.sample_rate_hz <= 1.0e7f)) {
        return; /* not a blob this firmware can use: factory defaults */
    }
    out->from_config = 1;
    out->n_samples = h.n_samples;
    out->decimation = h.decimation;
    out->pulse_cycles = h.pulse_cycles;
    out->blind_zone_samples = h.blind_zone_samples;
    out->sample_rate_hz = (uint32_t)(h.sample_rate_hz + 0.5f);
    out->carrier_hz = h.carrier_hz;
    out->gain_db = h.gain_db;
    out->acquisition_rate_hz = h.acquisition_rate_hz;
}
