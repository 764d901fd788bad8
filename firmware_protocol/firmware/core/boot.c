/* boot.c - firmware image checks, the boot record and the boot choice (PROTOCOL.md 14.3):
 * MCUboot's test/confirm model. The record is kept twice in HAL image slot 2 (16 bytes each:
 * magic, generation, confirmed, trial, state, 0, CRC-32C of the 12 bytes before), written
 * alternately, so a cut while one is written leaves the other. */
#include <string.h>

#include "core.h"

#if SPIEL_FW_UPDATE

#define RECORD_MAGIC 0x42545053u /* "SPTB" */
#define RECORD_SIZE 16u
#define RECORD_SLOT 2

static int read_copy(int copy, uint32_t *gen, boot_record_t *r)
{
    uint8_t b[RECORD_SIZE];
    if (hal_image_read(RECORD_SLOT, (uint32_t)copy * RECORD_SIZE, b, RECORD_SIZE) != 0 ||
        sp_le_get_u32(b) != RECORD_MAGIC || sp_crc32c(0, b, 12) != sp_le_get_u32(b + 12)) {
        return -1;
    }
    *gen = sp_le_get_u32(b + 4);
    r->confirmed = b[8];
    r->trial = b[9];
    r->state = b[10];
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
    if (newest(&gen, r) != 0 || (r->confirmed > 1u && r->confirmed != BOOT_NO_SLOT)) {
        r->confirmed = SPIEL_FW_FACTORY ? BOOT_NO_SLOT : 0u; /* the built-in image, or slot 0 */
        r->trial = BOOT_NO_SLOT;
        r->state = SP_BOOT_CONFIRMED;
    }
}

int boot_record_write(const boot_record_t *r)
{
    uint8_t b[RECORD_SIZE];
    uint32_t gen = 0;
    boot_record_t old;
    if (newest(&gen, &old) != 0) {
        gen = 0;
    }
    gen++;
    sp_le_put_u32(b, RECORD_MAGIC);
    sp_le_put_u32(b + 4, gen);
    b[8] = r->confirmed;
    b[9] = r->trial;
    b[10] = r->state;
    b[11] = 0;
    sp_le_put_u32(b + 12, sp_crc32c(0, b, 12));
    return hal_image_write(RECORD_SLOT, (gen % 2u) * RECORD_SIZE, b, RECORD_SIZE);
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

int boot_choose(void)
{
    boot_record_t r, w;
    int choice;
    boot_record_read(&r);
    choice = r.confirmed == BOOT_NO_SLOT ? -1 : (int)r.confirmed; /* -1: the built-in image */
    w.confirmed = r.confirmed;
    w.trial = BOOT_NO_SLOT;
    w.state = SP_BOOT_CONFIRMED;
    if (r.state == SP_BOOT_TEST_PENDING && r.trial <= 1u) {
        if (image_check(r.trial, NULL, NULL, NULL) == 0) {
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
    if (image_check(choice, NULL, NULL, NULL) != 0) {
        int other = 1 - choice;
        if (image_check(other, NULL, NULL, NULL) != 0) {
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

#endif
