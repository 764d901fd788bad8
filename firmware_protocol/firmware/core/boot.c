/* boot.c - firmware image checks, the boot record, the boot choice and the boot stage's
 * flash-to-flash install (PROTOCOL.md 14.3): MCUboot's test/confirm model.
 * The record is kept twice in HAL area SPIEL_IMAGE_RECORD, copy k at offset k * sector, each
 * erased just before it is written, alternately, so a cut while one is written leaves the
 * other. A copy is 32 bytes: magic "SPB2", generation, confirmed, trial, state, flags (0),
 * security_counter (anti-rollback: kept as read, 0 until a signing build sets it), 12 reserved
 * bytes (0), CRC-32C of the 28 bytes before. */
#include <string.h>

#include "core.h"

#if SPIEL_FW_UPDATE

#define RECORD_MAGIC 0x32425053u /* "SPB2" */
#define RECORD_SIZE 32u

static int read_copy(int copy, uint32_t *gen, boot_record_t *r)
{
    uint8_t b[RECORD_SIZE];
    uint32_t at = (uint32_t)copy * hal_image_sector_size();
    if (hal_image_read(SPIEL_IMAGE_RECORD, at, b, RECORD_SIZE) != 0 ||
        sp_le_get_u32(b) != RECORD_MAGIC || sp_crc32c(0, b, 28) != sp_le_get_u32(b + 28)) {
        return -1;
    }
    *gen = sp_le_get_u32(b + 4);
    r->confirmed = b[8];
    r->trial = b[9];
    r->state = b[10];
    r->security_counter = sp_le_get_u32(b + 12);
    return 0;
}

static int newest(uint32_t *gen, boot_record_t *r)
{
    uint32_t g0 = 0, g1 = 0;
    boot_record_t r0, r1;
    int ok0 = read_copy(0, &g0, &r0) == 0, ok1 = read_copy(1, &g1, &r1) == 0;
    if (!ok0 && !ok1) {
        return -1;
    }
    if (ok0 && (!ok1 || (int32_t)(g0 - g1) > 0)) {
        *gen = g0, *r = r0;
    } else {
        *gen = g1, *r = r1;
    }
    return 0;
}

void boot_record_read(boot_record_t *r)
{
    uint32_t gen;
    if (newest(&gen, r) != 0) {
        r->security_counter = 0;
    } else if (r->confirmed <= 1u || r->confirmed == BOOT_NO_SLOT) {
        return;
    }
    r->confirmed = SPIEL_FW_FACTORY ? BOOT_NO_SLOT : 0u; /* the built-in image, or slot 0 */
    r->trial = BOOT_NO_SLOT;
    r->state = SP_BOOT_CONFIRMED;
}

int boot_record_write(const boot_record_t *r)
{
    uint8_t b[RECORD_SIZE];
    uint32_t gen = 0, sector = hal_image_sector_size(), at;
    boot_record_t old;
    if (newest(&gen, &old) != 0) {
        gen = 0;
    }
    gen++;
    memset(b, 0, sizeof b);
    sp_le_put_u32(b, RECORD_MAGIC);
    sp_le_put_u32(b + 4, gen);
    b[8] = r->confirmed;
    b[9] = r->trial;
    b[10] = r->state;
    sp_le_put_u32(b + 12, r->security_counter);
    sp_le_put_u32(b + 28, sp_crc32c(0, b, 28));
    at = (gen % 2u) * sector;
    if (hal_image_erase(SPIEL_IMAGE_RECORD, at, sector) != 0) {
        return -1;
    }
    return hal_image_write(SPIEL_IMAGE_RECORD, at, b, RECORD_SIZE);
}

int image_check(int slot, uint32_t *size, uint32_t *crc, char version[17])
{
    uint8_t head[SP_IMAGE_HEADER_SIZE], buf[128], sha[32];
    sp_image_header_t h;
    sha256_t s;
    uint32_t off, body_crc = 0, all_crc;
    if (hal_image_read(slot, 0, head, sizeof head) != 0) {
        return -1;
    }
    sp_image_header_unpack(head, &h);
    if (memcmp(h.magic, SP_IMAGE_MAGIC, 4) != 0 ||
        sp_crc32c(0, head, SP_IMAGE_HEADER_SIZE - 4u) != h.header_crc ||
        h.header_version != SP_IMAGE_HEADER_VERSION || h.header_size != SP_IMAGE_HEADER_SIZE ||
        /* in u64: a slot smaller than the header must not wrap the bound */
        (uint64_t)h.body_size + SP_IMAGE_HEADER_SIZE + image_trailer_size(&h) >
            hal_image_slot_size()) {
        return -1;
    }
    all_crc = sp_crc32c(0, head, SP_IMAGE_HEADER_SIZE);
    sha256_init(&s);
    for (off = 0; off < h.body_size;) {
        uint32_t n = h.body_size - off < sizeof buf ? h.body_size - off : (uint32_t)sizeof buf;
        if (hal_image_read(slot, SP_IMAGE_HEADER_SIZE + off, buf, n) != 0) {
            return -1;
        }
        body_crc = sp_crc32c(body_crc, buf, n);
        all_crc = sp_crc32c(all_crc, buf, n);
        sha256_update(&s, buf, n);
        off += n;
    }
    sha256_final(&s, sha);
    if (body_crc != h.body_crc || memcmp(sha, h.body_sha256, 32) != 0) {
        return -1;
    }
    if (image_trailer_size(&h)) { /* the signature trailer: in the image's size and CRC */
        if (hal_image_read(slot, SP_IMAGE_HEADER_SIZE + h.body_size, buf, SP_SIG_TRAILER_SIZE) !=
            0) {
            return -1;
        }
        all_crc = sp_crc32c(all_crc, buf, SP_SIG_TRAILER_SIZE);
    }
    if (size) {
        *size = SP_IMAGE_HEADER_SIZE + h.body_size + image_trailer_size(&h);
    }
    if (crc) {
        *crc = all_crc;
    }
    if (version) {
        memcpy(version, h.version, 16);
        version[16] = 0;
    }
    return 0;
}

/* 1: the slot may be started: its image checks (image_check) and is signed by the built-in key
 * with a security counter at or above the floor (verify.c's image_auth). */
static int image_bootable(int slot, uint32_t floor)
{
    const char *why;
    return image_check(slot, NULL, NULL, NULL) == 0 &&
           image_auth(slot, floor, NULL, &why) == SP_ERR_OK;
}

int boot_choose(void)
{
    boot_record_t r, w;
    int choice;
    boot_record_read(&r);
    choice = r.confirmed == BOOT_NO_SLOT ? -1 : (int)r.confirmed; /* -1: the built-in image */
    w = r;
    w.confirmed = r.confirmed;
    w.trial = BOOT_NO_SLOT;
    w.state = SP_BOOT_CONFIRMED;
    if (r.state == SP_BOOT_TEST_PENDING && r.trial <= 1u) {
        if (image_bootable(r.trial, r.security_counter)) { /* intact, signed, no downgrade */
            w.trial = r.trial;
            w.state = SP_BOOT_TRIAL; /* the record first, then the jump: a cut rolls back */
            choice = r.trial;
        }
        boot_record_write(&w);
    } else if (r.state == SP_BOOT_TRIAL) { /* reset before FW_CONFIRM: roll back */
        boot_record_write(&w);
    }
    if (choice < 0) {
        return -1;
    }
    if (!image_bootable(choice, r.security_counter)) {
        int other = 1 - choice;
        if (!image_bootable(other, r.security_counter)) {
            return -1;
        }
        w.confirmed = (uint8_t)other;
        w.trial = BOOT_NO_SLOT;
        w.state = SP_BOOT_CONFIRMED;
        boot_record_write(&w);
        choice = other;
    }
    return choice;
}

int boot_is_trial(int slot)
{
    boot_record_t r;
    boot_record_read(&r);
    return slot >= 0 && r.state == SP_BOOT_TRIAL && (int)r.trial == slot;
}

#if SPIEL_FW_EXEC_COPY
/* Copy the slot's image into the execution region, flash to flash, through a buffer of one
 * read (no image in RAM): the header sector erased first, then each body sector erased and
 * programmed as the copy reaches it, the copy read back and checked against the header's
 * CRC-32C and SHA-256, the header programmed last. A region whose header equals the slot's is
 * already installed (nothing is written: no wear at every boot). A power cut anywhere leaves
 * no header or another one, so the next boot copies again: idempotent. 0 ok, -1 failed. */
static uint8_t copy_buf[256];

int boot_install(int slot)
{
    uint8_t head[SP_IMAGE_HEADER_SIZE], have[SP_IMAGE_HEADER_SIZE], sha[32];
    sp_image_header_t h;
    sha256_t s;
    uint32_t sector = hal_image_sector_size(), unit = hal_image_program_unit(), off, crc = 0;
    if (hal_image_read(slot, 0, head, sizeof head) != 0) {
        return -1;
    }
    sp_image_header_unpack(head, &h);
    if (unit == 0 || unit > SPIEL_FW_UNIT_MAX || SP_IMAGE_HEADER_SIZE % unit != 0) {
        return -1;
    }
    if (hal_image_read(SPIEL_IMAGE_EXEC, 0, have, sizeof have) == 0 &&
        memcmp(have, head, sizeof head) == 0) {
        return 0; /* installed (the header is written last) */
    }
    if (hal_image_erase(SPIEL_IMAGE_EXEC, 0, sector) != 0) {
        return -1;
    }
    for (off = 0; off < h.body_size;) {
        uint32_t n = h.body_size - off < sizeof copy_buf ? h.body_size - off
                                                         : (uint32_t)sizeof copy_buf;
        uint32_t padded = (n + unit - 1u) / unit * unit;
        if (off % sector == 0 &&
            hal_image_erase(SPIEL_IMAGE_EXEC, sector + off, sector) != 0) {
            return -1;
        }
        memset(copy_buf, 0xFF, sizeof copy_buf);
        if (hal_image_read(slot, SP_IMAGE_HEADER_SIZE + off, copy_buf, n) != 0 ||
            hal_image_write(SPIEL_IMAGE_EXEC, sector + off, copy_buf, padded) != 0) {
            return -1;
        }
        off += n;
    }
    sha256_init(&s);
    for (off = 0; off < h.body_size;) {
        uint32_t n = h.body_size - off < sizeof copy_buf ? h.body_size - off
                                                         : (uint32_t)sizeof copy_buf;
        if (hal_image_read(SPIEL_IMAGE_EXEC, sector + off, copy_buf, n) != 0) {
            return -1;
        }
        crc = sp_crc32c(crc, copy_buf, n);
        sha256_update(&s, copy_buf, n);
        off += n;
    }
    sha256_final(&s, sha);
    if (crc != h.body_crc || memcmp(sha, h.body_sha256, 32) != 0) {
        return -1;
    }
    return hal_image_write(SPIEL_IMAGE_EXEC, 0, head, sizeof head);
}
#endif

int boot_start(uint32_t watchdog_ms)
{
    int slot = boot_choose(), tries;
#if SPIEL_FW_EXEC_COPY
    /* an install that fails (a flash fault): a trial is rolled back (boot_choose() again sees
     * TRIAL), a confirmed image is tried once more, then the built-in image or recovery */
    for (tries = 0; slot >= 0 && boot_install(slot) != 0; tries++) {
        if (tries == 1) {
            return -1;
        }
        slot = boot_choose();
    }
#else
    (void)tries;
#endif
    if (boot_is_trial(slot)) {
        hal_watchdog_start(watchdog_ms);
    }
    return slot;
}

#endif
