/* verify.c - the authenticity of a firmware image (PROTOCOL.md 14.6): the Ed25519 signature in
 * its trailer, over the 96-byte header (which holds the body's size, CRC-32C and SHA-256, so the
 * body is covered once image_check() has matched them), by the public key built in, and the
 * security counter against the boot record's. Verification: vendor/monocypher (RFC 8032). */
#include <string.h>

#include "core.h"

#if SPIEL_FW_UPDATE

#include "monocypher-ed25519.h"

#ifndef SPIEL_FW_KEY_FILE
#error "build with -DSPIEL_FW_KEY_FILE=\"path/key.pub\" (the Makefile's FW_KEY)"
#endif

/* the public key file: 32 bytes as 0x.., under a comment (spiel-edge firmware keygen) */
static const uint8_t fw_key[] = {
#include SPIEL_FW_KEY_FILE
};
/* a key file of more or fewer than 32 bytes fails the build (C would zero-fill a short one) */
typedef char fw_key_is_32_bytes[sizeof fw_key == 32 ? 1 : -1];

uint32_t image_trailer_size(const sp_image_header_t *h)
{
    return (h->flags & SP_IMAGE_FLAG_SIGNED) ? SP_SIG_TRAILER_SIZE : 0u;
}

/* the first 8 bytes of SHA-256(key): names the key in a trailer (a diagnostic, not trusted) */
static void key_id(uint8_t out[8])
{
    uint8_t d[32];
    sha256_t s;
    sha256_init(&s);
    sha256_update(&s, fw_key, sizeof fw_key);
    sha256_final(&s, d);
    memcpy(out, d, 8);
}

uint16_t image_auth(int slot, uint32_t min_counter, uint32_t *counter, const char **why)
{
    uint8_t head[SP_IMAGE_HEADER_SIZE], t[SP_SIG_TRAILER_SIZE], kid[8];
    sp_image_header_t h;
    *why = "";
    if (hal_image_read(slot, 0, head, sizeof head) != 0) {
        *why = "slot read failed";
        return SP_ERR_FLASH_VERIFY_FAILED;
    }
    sp_image_header_unpack(head, &h);
    if (!(h.flags & SP_IMAGE_FLAG_SIGNED)) {
        *why = "unsigned image";
        return SP_ERR_FW_UNSIGNED;
    }
    /* u64: a body size near 2^32 must not wrap the bound */
    if ((uint64_t)SP_IMAGE_HEADER_SIZE + h.body_size + SP_SIG_TRAILER_SIZE >
            hal_image_slot_size() ||
        hal_image_read(slot, SP_IMAGE_HEADER_SIZE + h.body_size, t, sizeof t) != 0 ||
        memcmp(t, SP_SIG_MAGIC, 4) != 0 || t[4] != SP_SIG_TYPE_ED25519 ||
        sp_le_get_u16(t + 6) != 64u) {
        *why = "signature trailer missing or truncated";
        return SP_ERR_FW_BAD_SIGNATURE;
    }
    key_id(kid);
    if (memcmp(t + 8, kid, 8) != 0) {
        *why = "signed by another key";
        return SP_ERR_FW_WRONG_KEY;
    }
    if (crypto_ed25519_check(t + 16, fw_key, head, sizeof head) != 0) {
        *why = "signature does not verify";
        return SP_ERR_FW_BAD_SIGNATURE;
    }
    if (counter) {
        *counter = h.security_counter;
    }
    if (h.security_counter < min_counter) {
        *why = "security counter below the board's";
        return SP_ERR_FW_ROLLBACK;
    }
    return SP_ERR_OK;
}

uint32_t image_counter_floor(int slot, uint32_t floor)
{
    uint8_t head[SP_IMAGE_HEADER_SIZE];
    sp_image_header_t h;
    if (slot < 0 || hal_image_read(slot, 0, head, sizeof head) != 0) {
        return floor;
    }
    sp_image_header_unpack(head, &h);
    return h.security_counter > floor ? h.security_counter : floor;
}

#endif
