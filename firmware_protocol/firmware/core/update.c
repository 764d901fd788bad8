/* update.c - the firmware update of the portable core (PROTOCOL.md 14.3, with
 * -DSPIEL_FW_UPDATE=1 and the HAL's image slots): FW_INFO/BEGIN/WRITE/VERIFY/TEST/CONFIRM, and
 * while a trial image runs, its self-test and the watchdog kick. Calls only the units below it
 * (boot.c, verify.c, sha256.c, link.c). No allocation. */
#include <string.h>

#include "core.h"

#define FW_MIN_PAYLOAD 128u /* FW_INFO's answer is 74 bytes: firmware update needs this link */

#if SPIEL_FW_UPDATE
static struct {
    int upload_slot;      /* -1: no upload open */
    uint32_t expect_size, expect_crc, written;
    uint8_t expect_sha[32];
    int verified;
    int running;          /* slot running now, -1 none */
    uint8_t boot_state;
    uint32_t erased_to;   /* the upload slot is erased in [0, erased_to): sector by sector */
    uint8_t unit_buf[SPIEL_FW_UNIT_MAX]; /* the upload's bytes short of a program unit */
    uint32_t unit_fill;
    uint8_t selftest;     /* SP_SELFTEST_*: a trial's self-test (FW_INFO byte 3) */
    uint64_t selftest_deadline, trial_end;
    /* FW_VERIFY with SP_FW_VERIFY_ASYNC: answered BUSY, checked in update_tick once the answer
     * is out (a slow part hashes and checks a signature for seconds), the result kept for the
     * next FW_VERIFY until the upload changes */
    uint8_t verify_job; /* VERIFY_NONE, VERIFY_PENDING, VERIFY_DONE */
    uint64_t verify_at;
    uint16_t verify_code, verify_len;
    const char *verify_text;
    uint8_t verify_out[43];
    /* FW_INFO's image_check of each slot (a hash of the whole slot), kept until the upload
     * writes that slot: nothing else changes a slot while the application runs */
    struct {
        uint8_t known, ok;
        uint32_t size, crc;
        char version[17];
    } memo[2];
} fw;

static uint32_t trial_window_ms = SPIEL_FW_TRIAL_WINDOW_MS;
#define SELFTEST_TIMEOUT_US 1000000u /* the first acquisition must complete within 1 s */
enum { VERIFY_NONE, VERIFY_PENDING, VERIFY_DONE };
#define VERIFY_DEFER_US 20000u /* the BUSY answer leaves before the check blocks the loop */
static int fw_verify(uint8_t *out, uint16_t *code, const char **text);
#endif

void spiel_device_set_trial_window_ms(uint32_t ms)
{
#if SPIEL_FW_UPDATE
    trial_window_ms = ms;
#else
    (void)ms;
#endif
}

void update_init(void)
{
#if SPIEL_FW_UPDATE
    boot_record_t r;
    memset(&fw, 0, sizeof fw);
    fw.upload_slot = -1;
    fw.running = hal_image_running();
    boot_record_read(&r);
    fw.boot_state = (r.state == SP_BOOT_TRIAL && (int)r.trial == fw.running)
                        ? (uint8_t)SP_BOOT_TRIAL : (uint8_t)SP_BOOT_CONFIRMED;
    /* a trial proves itself: the sensor answers and one acquisition completes */
    fw.selftest = fw.boot_state == SP_BOOT_TRIAL ? (uint8_t)SP_SELFTEST_PENDING
                                                 : (uint8_t)SP_SELFTEST_NONE;
    fw.trial_end = hal_time_us() + (uint64_t)trial_window_ms * 1000u;
#endif
}

int update_offered(void)
{
#if SPIEL_FW_UPDATE
    return hal_image_slot_size() != 0 && spiel_link.max_payload >= FW_MIN_PAYLOAD;
#else
    return 0;
#endif
}

#if SPIEL_FW_UPDATE
static void selftest_done(uint8_t result, const char *why)
{
    fw.selftest = result;
    if (result == SP_SELFTEST_FAILED) {
        link_log(SP_LOG_ERROR, why);
        link_reboot_after_ms(SP_REBOOT_NORMAL, 2000u); /* the boot stage rolls the trial back */
    } else {
        link_log(SP_LOG_NOTICE, "self-test passed");
    }
}

static void selftest_step(uint64_t now)
{
    const hal_board_info_t *b = hal_board_info();
    if (fw.selftest == SP_SELFTEST_PENDING && !spiel_link.streaming) {
        uint16_t cap = link_sample_capacity(), n = b->default_n_samples;
        uint32_t mask = b->n_channels >= 32u ? 0xFFFFFFFFu : (1u << b->n_channels) - 1u;
        if (n > cap) {
            n = cap;
        }
        if (n == 0 || b->n_channels == 0 || hal_acq_trigger(mask, n) != 0) {
            selftest_done(SP_SELFTEST_FAILED, "self-test failed: the sensor refused a trigger");
            return;
        }
        fw.selftest = SP_SELFTEST_RUNNING;
        fw.selftest_deadline = now + SELFTEST_TIMEOUT_US;
    } else if (fw.selftest == SP_SELFTEST_RUNNING) {
        uint16_t cap = link_sample_capacity(), n = b->default_n_samples, ch;
        uint16_t *buf = spiel_samples;
        if (!hal_acq_ready()) {
            if (now >= fw.selftest_deadline) {
                selftest_done(SP_SELFTEST_FAILED, "self-test failed: no acquisition within 1 s");
            }
            return;
        }
        if (n > cap) {
            n = cap;
        }
        for (ch = 0; ch < b->n_channels; ch++) {
            if (hal_acq_read((uint8_t)ch, buf, n) != 0) {
                selftest_done(SP_SELFTEST_FAILED, "self-test failed: a channel did not read");
                return;
            }
        }
        selftest_done(SP_SELFTEST_PASSED, NULL);
    }
}
#endif

void update_tick(uint64_t now)
{
#if SPIEL_FW_UPDATE
    if (fw.verify_job == VERIFY_PENDING && now >= fw.verify_at) {
        int n = fw_verify(fw.verify_out, &fw.verify_code, &fw.verify_text);
        fw.verify_len = (uint16_t)n;
        fw.verify_job = VERIFY_DONE;
        fw.verified = 0; /* FW_TEST only after the host has been told (update_verify) */
        now = hal_time_us(); /* the check took time: the trial window is judged after it */
    }
    if (fw.boot_state == SP_BOOT_TRIAL) {
        selftest_step(now);
        /* an unconfirmed trial stops kicking once its self-test failed or its window passed:
         * the watchdog resets it and the boot stage rolls it back, with nobody there */
        if (fw.selftest == SP_SELFTEST_FAILED || now >= fw.trial_end) {
            return;
        }
    }
    hal_watchdog_kick();
#else
    (void)now;
#endif
}

int update_selftest_busy(void)
{
#if SPIEL_FW_UPDATE
    return fw.selftest == SP_SELFTEST_PENDING || fw.selftest == SP_SELFTEST_RUNNING;
#else
    return 0;
#endif
}

int update_uploading(void)
{
#if SPIEL_FW_UPDATE
    return fw.upload_slot >= 0;
#else
    return 0;
#endif
}

uint32_t update_error_flags(void)
{
    uint32_t f = 0;
#if SPIEL_FW_UPDATE
    if (fw.boot_state == SP_BOOT_TRIAL) {
        f |= SP_EFLAG_TRIAL_IMAGE;
    }
    if (fw.selftest == SP_SELFTEST_FAILED) {
        f |= SP_EFLAG_SENSOR;
    }
#endif
    return f;
}

uint64_t update_next_us(uint64_t now)
{
    uint64_t wake = now + 50000u;
#if SPIEL_FW_UPDATE
    if (fw.verify_job == VERIFY_PENDING && fw.verify_at < wake) {
        wake = fw.verify_at;
    }
#endif
    return wake;
}

/* ---- firmware update ------------------------------------------------------------------ */

#if SPIEL_FW_UPDATE
static void put_slot(uint8_t *p, int slot)
{
    uint32_t size = 0, crc = 0;
    char version[17] = {0};
    uint8_t state = SP_SLOT_EMPTY;
    if (!fw.memo[slot].known) {
        fw.memo[slot].ok = image_check(slot, &fw.memo[slot].size, &fw.memo[slot].crc,
                                       fw.memo[slot].version) == 0;
        fw.memo[slot].known = 1;
    }
    if (fw.memo[slot].ok) {
        size = fw.memo[slot].size;
        crc = fw.memo[slot].crc;
        memcpy(version, fw.memo[slot].version, sizeof version);
        state = SP_SLOT_VERIFIED;
    } else if (slot == fw.upload_slot && fw.written) {
        state = SP_SLOT_PARTIAL;
        size = fw.written;
    } else {
        uint8_t magic[4];
        if (hal_image_read(slot, 0, magic, 4) == 0 && memcmp(magic, SP_IMAGE_MAGIC, 4) == 0) {
            state = SP_SLOT_INVALID;
        }
    }
    p[0] = state;
    memset(p + 1, 0, 16);
    memcpy(p + 1, version, strlen(version));
    sp_le_put_u32(p + 17, size);
    sp_le_put_u32(p + 21, crc);
}

int update_info(const uint8_t *p, uint16_t len, uint8_t *out, uint16_t *code, const char **text)
{
    (void)p, (void)len, (void)code, (void)text;
    boot_record_t r;
    boot_record_read(&r);
    out[0] = fw.running < 0 ? (uint8_t)0xFF : (uint8_t)fw.running;
    out[1] = r.state == SP_BOOT_TEST_PENDING ? (uint8_t)SP_BOOT_TEST_PENDING : fw.boot_state;
    out[2] = r.confirmed;
    out[3] = fw.selftest;
    sp_le_put_u32(out + 4, hal_image_slot_size());
    memset(out + 8, 0, 16);
    memcpy(out + 8, SPIEL_FW_TARGET, strlen(SPIEL_FW_TARGET));
    put_slot(out + 24, 0);
    put_slot(out + 49, 1);
    return SP_FW_INFO_SIZE;
}

/* CRC-32C and SHA-256 of slot[0 .. size) */
static int slot_digest(int slot, uint32_t size, uint32_t *crc, uint8_t sha[32])
{
    uint8_t buf[128];
    uint32_t off = 0, c = 0;
    sha256_t s;
    sha256_init(&s);
    while (off < size) {
        uint32_t n = size - off < sizeof buf ? size - off : (uint32_t)sizeof buf;
        if (hal_image_read(slot, off, buf, n) != 0) {
            return -1;
        }
        c = sp_crc32c(c, buf, n);
        sha256_update(&s, buf, n);
        off += n;
    }
    sha256_final(&s, sha);
    *crc = c;
    return 0;
}

int update_begin(const uint8_t *p, uint16_t len, uint8_t *out, uint16_t *code, const char **text)
{
    uint8_t in[10] = {0};
    uint32_t size;
    boot_record_t r;
    int slot;
    memcpy(in, p, len < sizeof in ? len : sizeof in);
    size = sp_le_get_u32(in);
    if (spiel_link.streaming) {
        *code = SP_ERR_BAD_STATE, *text = "stop the stream before a firmware update";
        return 0;
    }
    if (fw.boot_state == SP_BOOT_TRIAL) {
        *code = SP_ERR_BAD_STATE, *text = "running a trial image: confirm it or reset first";
        return 0;
    }
    if (sp_le_get_u16(in + 8) != 32u || len < 10u + 32u) {
        *code = SP_ERR_INVALID, *text = "sha256 must be 32 bytes";
        return 0;
    }
    if (size > hal_image_slot_size()) {
        *code = SP_ERR_TOO_LARGE, *text = "image larger than the slot";
        return 0;
    }
    if (size < SP_IMAGE_HEADER_SIZE) {
        *code = SP_ERR_INVALID, *text = "an image is at least its 96-byte header";
        return 0;
    }
    boot_record_read(&r);
    /* never the running slot, nor the confirmed one while the built-in image runs */
    slot = fw.running >= 0 ? 1 - fw.running : r.confirmed == 0u ? 1 : 0;
    if (r.state == SP_BOOT_TEST_PENDING) { /* cancel: the slot it names is about to change */
        r.state = SP_BOOT_CONFIRMED;
        r.trial = BOOT_NO_SLOT;
        if (boot_record_write(&r) != 0) {
            *code = SP_ERR_FLASH_WRITE_FAILED, *text = "boot record write failed";
            return 0;
        }
    }
    fw.upload_slot = -1;
    fw.verified = 0;
    fw.verify_job = VERIFY_NONE;
    fw.memo[slot].known = 0;
    /* only the header's sector now (the old image is gone at once); the rest as the upload
     * reaches it, one sector per FW_WRITE at most: no request waits for a whole slot erase */
    if (hal_image_erase(slot, 0, hal_image_sector_size()) != 0) {
        spiel_stats.flash_errors++;
        *code = SP_ERR_FLASH_WRITE_FAILED, *text = "slot erase failed";
        return 0;
    }
    fw.upload_slot = slot;
    fw.expect_size = size;
    fw.expect_crc = sp_le_get_u32(in + 4);
    memcpy(fw.expect_sha, p + 10, 32);
    fw.written = 0;
    fw.erased_to = hal_image_sector_size();
    fw.unit_fill = 0;
    link_log(SP_LOG_INFO, "firmware upload started");
    out[0] = (uint8_t)slot;
    sp_le_put_u32(out + 1, hal_image_slot_size());
    return 5;
}

/* Program [at, at + len) of the upload slot (whole units), erasing each sector first as the
 * upload reaches it. */
static int program(uint32_t at, const uint8_t *data, uint32_t len)
{
    uint32_t sector = hal_image_sector_size();
    fw.memo[fw.upload_slot].known = 0;
    while ((uint64_t)at + len > fw.erased_to) {
        if (fw.erased_to >= hal_image_slot_size() ||
            hal_image_erase(fw.upload_slot, fw.erased_to, sector) != 0) {
            return -1;
        }
        fw.erased_to += sector;
    }
    return hal_image_write(fw.upload_slot, at, data, len);
}

/* The upload's next n bytes: whole program units go to flash, the rest waits in unit_buf
 * (flushed, padded with 0xFF, when the image is complete). */
static int upload_bytes(const uint8_t *d, uint32_t n)
{
    uint32_t unit = hal_image_program_unit();
    uint32_t base = fw.written - fw.unit_fill; /* unit-aligned: where unit_buf goes */
    if (unit == 0 || unit > SPIEL_FW_UNIT_MAX) {
        return -1;
    }
    if (fw.unit_fill) {
        uint32_t take = unit - fw.unit_fill < n ? unit - fw.unit_fill : n;
        memcpy(fw.unit_buf + fw.unit_fill, d, take);
        fw.unit_fill += take;
        d += take;
        n -= take;
        if (fw.unit_fill < unit) {
            return 0;
        }
        if (program(base, fw.unit_buf, unit) != 0) {
            return -1;
        }
        base += unit;
        fw.unit_fill = 0;
    }
    if (n >= unit) {
        uint32_t whole = n / unit * unit;
        if (program(base, d, whole) != 0) {
            return -1;
        }
        base += whole;
        d += whole;
        n -= whole;
    }
    memcpy(fw.unit_buf, d, n);
    fw.unit_fill = n;
    return 0;
}

static int upload_flush(void)
{
    uint32_t unit = hal_image_program_unit();
    if (fw.unit_fill == 0) {
        return 0;
    }
    memset(fw.unit_buf + fw.unit_fill, 0xFF, unit - fw.unit_fill);
    if (program(fw.written - fw.unit_fill, fw.unit_buf, unit) != 0) {
        return -1;
    }
    fw.unit_fill = 0;
    return 0;
}

int update_write(const uint8_t *p, uint16_t len, uint8_t *out, uint16_t *code, const char **text)
{
    uint32_t off;
    uint16_t n;
    if (fw.upload_slot < 0) {
        *code = SP_ERR_BAD_STATE, *text = "no upload: send FW_BEGIN";
        return 0;
    }
    if (len < 6u) {
        *code = SP_ERR_INVALID, *text = "short FW_WRITE";
        return 0;
    }
    off = sp_le_get_u32(p);
    n = sp_le_get_u16(p + 4);
    if ((uint32_t)n + 6u > len) {
        *code = SP_ERR_INVALID, *text = "data shorter than its length";
        return 0;
    }
    if ((uint64_t)off + n > fw.expect_size) { /* u64: an offset near 2^32 must not wrap */
        *code = SP_ERR_TOO_LARGE, *text = "past the announced size";
        return 0;
    }
    if (off + n <= fw.written) { /* a repeated chunk: already there */
        sp_le_put_u32(out, fw.written);
        return 4;
    }
    if (off != fw.written) {
        *code = SP_ERR_INVALID, *text = "offset is not the bytes written so far";
        return 0;
    }
    fw.verified = 0;
    fw.verify_job = VERIFY_NONE;
    if (upload_bytes(p + 6, n) != 0) {
        fw.upload_slot = -1; /* the bytes buffered are lost: FW_BEGIN again */
        spiel_stats.flash_errors++;
        *code = SP_ERR_FLASH_WRITE_FAILED, *text = "slot write failed";
        return 0;
    }
    fw.written = off + n;
    sp_le_put_u32(out, fw.written);
    return 4;
}

static int fw_verify(uint8_t *out, uint16_t *code, const char **text)
{
    uint32_t crc, size;
    uint8_t sha[32];
    char version[17];
    int slot = fw.upload_slot;
    if (slot < 0) {
        *code = SP_ERR_BAD_STATE, *text = "no upload: send FW_BEGIN";
        return 0;
    }
    if (fw.written != fw.expect_size) {
        *code = SP_ERR_BAD_STATE, *text = "image incomplete";
        return 0;
    }
    if (upload_flush() != 0) {
        fw.upload_slot = -1;
        spiel_stats.flash_errors++;
        *code = SP_ERR_FLASH_WRITE_FAILED, *text = "slot write failed";
        return 0;
    }
    if (slot_digest(slot, fw.expect_size, &crc, sha) != 0) {
        *code = SP_ERR_FLASH_VERIFY_FAILED, *text = "slot read failed";
        return 0;
    }
    if (crc != fw.expect_crc || memcmp(sha, fw.expect_sha, 32) != 0) {
        *code = SP_ERR_CORRUPT, *text = "CRC-32C or SHA-256 differs from FW_BEGIN's";
        link_log(SP_LOG_ERROR, "firmware verify failed: digest mismatch");
        return 0;
    }
    if (image_check(slot, &size, NULL, version) != 0) {
        *code = SP_ERR_INVALID, *text = "not a valid image (header, size or body digest)";
        link_log(SP_LOG_ERROR, "firmware verify failed: image header");
        return 0;
    }
    { /* signed by the built-in key, not below the record's security counter (14.6); before
       * the size check, so a truncated signature is named as such */
        boot_record_t r;
        boot_record_read(&r);
        *code = image_auth(slot, r.security_counter, NULL, text);
        if (*code == SP_ERR_OK && size > fw.expect_size) {
            *code = SP_ERR_FW_BAD_SIGNATURE, *text = "signature trailer truncated";
        } else if (*code == SP_ERR_OK && size < fw.expect_size) {
            *code = SP_ERR_INVALID, *text = "bytes after the image's end";
        }
        if (*code != SP_ERR_OK) {
            link_log(SP_LOG_ERROR, "firmware verify failed: signature or security counter");
            return 0;
        }
    }
    {
        uint8_t head[SP_IMAGE_HEADER_SIZE];
        sp_image_header_t h;
        if (hal_image_read(slot, 0, head, sizeof head) != 0) { /* else head is unset */
            *code = SP_ERR_FLASH_VERIFY_FAILED, *text = "slot read failed";
            return 0;
        }
        sp_image_header_unpack(head, &h);
        if (strncmp((const char *)h.target, SPIEL_FW_TARGET, 16) != 0) {
            *code = SP_ERR_UNSUPPORTED, *text = "image for another target";
            return 0;
        }
        if (h.min_protocol > SPIEL_PROTOCOL_MAX || h.max_protocol < 1u) {
            *code = SP_ERR_UNSUPPORTED, *text = "image speaks no protocol version of ours";
            return 0;
        }
    }
    fw.verified = 1;
    out[0] = (uint8_t)slot;
    sp_le_put_u32(out + 1, fw.expect_size);
    sp_le_put_u32(out + 5, crc);
    sp_le_put_u16(out + 9, 32);
    memcpy(out + 11, sha, 32);
    return 43;
}

/* FW_VERIFY: checked within the request, or (SP_FW_VERIFY_ASYNC) BUSY until update_tick has
 * checked, then the result, as often as asked, until FW_BEGIN or new FW_WRITE bytes */
int update_verify(const uint8_t *p, uint16_t len, uint8_t *out, uint16_t *code, const char **text)
{
    if (len == 0 || !(p[0] & SP_FW_VERIFY_ASYNC)) {
        fw.verify_job = VERIFY_NONE;
        return fw_verify(out, code, text);
    }
    if (fw.verify_job == VERIFY_DONE) {
        fw.verified = fw.verify_code == SP_ERR_OK;
        *code = fw.verify_code;
        *text = fw.verify_text;
        memcpy(out, fw.verify_out, fw.verify_len);
        return fw.verify_len;
    }
    if (fw.verify_job == VERIFY_NONE) {
        fw.verify_job = VERIFY_PENDING;
        fw.verify_at = hal_time_us() + VERIFY_DEFER_US;
    }
    *code = SP_ERR_BUSY, *text = "checking the image: ask again";
    return 0;
}

int update_test(const uint8_t *p, uint16_t len, uint8_t *out, uint16_t *code, const char **text)
{
    uint8_t in[2] = {0};
    boot_record_t r;
    memcpy(in, p, len < sizeof in ? len : sizeof in);
    if (!fw.verified || fw.upload_slot < 0) {
        *code = SP_ERR_BAD_STATE, *text = "no verified image: FW_VERIFY first";
        return 0;
    }
    boot_record_read(&r);
    r.trial = (uint8_t)fw.upload_slot;
    r.state = SP_BOOT_TEST_PENDING;
    if (boot_record_write(&r) != 0) {
        spiel_stats.flash_errors++;
        *code = SP_ERR_FLASH_WRITE_FAILED, *text = "boot record write failed";
        return 0;
    }
    out[0] = (uint8_t)fw.upload_slot;
    fw.upload_slot = -1;
    fw.verify_job = VERIFY_NONE; /* no result for an upload that ended */
    link_reboot_after_ms(SP_REBOOT_NORMAL, sp_le_get_u16(in));
    return 1;
}

int update_confirm(const uint8_t *p, uint16_t len, uint8_t *out, uint16_t *code,
                   const char **text)
{
    (void)p, (void)len;
    if (fw.running < 0) {
        *code = SP_ERR_BAD_STATE, *text = "no image is running";
        return 0;
    }
    if (fw.boot_state == SP_BOOT_TRIAL && fw.selftest != SP_SELFTEST_PASSED) {
        *code = SP_ERR_BAD_STATE;
        *text = fw.selftest == SP_SELFTEST_FAILED ? "the self-test failed: the trial rolls back"
                                                  : "the self-test has not passed yet";
        return 0;
    }
    if (fw.boot_state == SP_BOOT_TRIAL) {
        boot_record_t r;
        boot_record_read(&r);
        r.confirmed = (uint8_t)fw.running;
        r.trial = BOOT_NO_SLOT;
        r.state = SP_BOOT_CONFIRMED;
        /* anti-rollback: in the same record write as the confirmation (one power-cut-safe
         * step), the floor rises to the confirmed image's counter */
        r.security_counter = image_counter_floor(fw.running, r.security_counter);
        if (boot_record_write(&r) != 0) {
            spiel_stats.flash_errors++;
            *code = SP_ERR_FLASH_WRITE_FAILED, *text = "boot record write failed";
            return 0;
        }
        fw.boot_state = SP_BOOT_CONFIRMED;
        link_log(SP_LOG_NOTICE, "firmware confirmed");
    }
    out[0] = (uint8_t)fw.running;
    out[1] = fw.boot_state;
    return 2;
}
#endif
