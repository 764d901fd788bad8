/* v2.c - protocol version 2 of the portable core (PROTOCOL.md section 14): TIME_SYNC,
 * TELEMETRY with HEARTBEAT and LOG frames, and (with -DSPIEL_FW_UPDATE=1 and the HAL's image
 * slots) the firmware update FW_INFO/BEGIN/WRITE/VERIFY/TEST/CONFIRM. No allocation. */
#include <string.h>

#include "core.h"

#define LOG_QUEUE 8u
#define LOG_TEXT 64u
#define HEARTBEAT_DEFAULT_MS 1000u
#define FW_MIN_PAYLOAD 128u /* FW_INFO's answer is 74 bytes: firmware update needs this link */

static struct {
    uint16_t heartbeat_ms;
    uint8_t log_level, log_per_s;
    uint64_t next_beat;
    uint64_t tokens_at;   /* when the log tokens were last refilled */
    uint32_t tokens_milli;
    uint8_t head, count;
    uint32_t dropped;
    struct {
        uint8_t level;
        char text[LOG_TEXT + 1];
    } q[LOG_QUEUE];
#if SPIEL_FW_UPDATE
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
    /* FW_VERIFY with SP_FW_VERIFY_ASYNC: answered BUSY, checked in v2_tick once the answer
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
#endif
} v2;

#if SPIEL_FW_UPDATE
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

void v2_init(void)
{
    memset(&v2, 0, sizeof v2);
    v2.heartbeat_ms = SPIEL_PROTOCOL_MAX >= 2 ? HEARTBEAT_DEFAULT_MS : 0u;
    v2.log_level = SP_LOG_INFO;
    v2.log_per_s = 20;
    v2.tokens_milli = 20000u;
    v2.next_beat = hal_time_us() + (uint64_t)v2.heartbeat_ms * 1000u;
#if SPIEL_FW_UPDATE
    {
        boot_record_t r;
        v2.upload_slot = -1;
        v2.running = hal_image_running();
        boot_record_read(&r);
        v2.boot_state = (r.state == SP_BOOT_TRIAL && (int)r.trial == v2.running)
                            ? (uint8_t)SP_BOOT_TRIAL : (uint8_t)SP_BOOT_CONFIRMED;
        /* a trial proves itself: the sensor answers and one acquisition completes */
        v2.selftest = v2.boot_state == SP_BOOT_TRIAL ? (uint8_t)SP_SELFTEST_PENDING
                                                     : (uint8_t)SP_SELFTEST_NONE;
        v2.trial_end = hal_time_us() + (uint64_t)trial_window_ms * 1000u;
    }
#endif
}

#if SPIEL_FW_UPDATE
static void selftest_done(uint8_t result, const char *why)
{
    v2.selftest = result;
    if (result == SP_SELFTEST_FAILED) {
        v2_log(SP_LOG_ERROR, why);
        core_reboot_after_ms(2000u); /* the boot stage rolls the trial back */
    } else {
        v2_log(SP_LOG_NOTICE, "self-test passed");
    }
}

static void selftest_step(uint64_t now)
{
    const hal_board_info_t *b = hal_board_info();
    if (v2.selftest == SP_SELFTEST_PENDING && !core_streaming()) {
        uint16_t cap = 0, n = b->default_n_samples;
        uint32_t mask = b->n_channels >= 32u ? 0xFFFFFFFFu : (1u << b->n_channels) - 1u;
        (void)core_sample_buffer(&cap);
        if (n > cap) {
            n = cap;
        }
        if (n == 0 || b->n_channels == 0 || hal_acq_trigger(mask, n) != 0) {
            selftest_done(SP_SELFTEST_FAILED, "self-test failed: the sensor refused a trigger");
            return;
        }
        v2.selftest = SP_SELFTEST_RUNNING;
        v2.selftest_deadline = now + SELFTEST_TIMEOUT_US;
    } else if (v2.selftest == SP_SELFTEST_RUNNING) {
        uint16_t cap = 0, n = b->default_n_samples, ch;
        uint16_t *buf = core_sample_buffer(&cap);
        if (!hal_acq_ready()) {
            if (now >= v2.selftest_deadline) {
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

void v2_tick(uint64_t now)
{
#if SPIEL_FW_UPDATE
    if (v2.verify_job == VERIFY_PENDING && now >= v2.verify_at) {
        int n = fw_verify(v2.verify_out, &v2.verify_code, &v2.verify_text);
        v2.verify_len = (uint16_t)n;
        v2.verify_job = VERIFY_DONE;
        v2.verified = 0; /* FW_TEST only after the host has been told (fw_verify_request) */
        now = hal_time_us(); /* the check took time: the trial window is judged after it */
    }
    if (v2.boot_state == SP_BOOT_TRIAL) {
        selftest_step(now);
        /* an unconfirmed trial stops kicking once its self-test failed or its window passed:
         * the watchdog resets it and the boot stage rolls it back, with nobody there */
        if (v2.selftest == SP_SELFTEST_FAILED || now >= v2.trial_end) {
            return;
        }
    }
    hal_watchdog_kick();
#else
    (void)now;
#endif
}

int v2_selftest_busy(void)
{
#if SPIEL_FW_UPDATE
    return v2.selftest == SP_SELFTEST_PENDING || v2.selftest == SP_SELFTEST_RUNNING;
#else
    return 0;
#endif
}

uint32_t v2_capabilities(void)
{
    uint32_t caps = SP_CAP_TIME_SYNC | SP_CAP_TELEMETRY | SP_CAP_START_AT;
#if SPIEL_FW_UPDATE
    if (hal_image_slot_size() != 0 && core_max_payload() >= FW_MIN_PAYLOAD) {
        caps |= SP_CAP_FIRMWARE_UPDATE;
    }
#endif
    return caps;
}

void v2_log(uint8_t level, const char *text)
{
    size_t n;
    uint8_t at;
    if (level > v2.log_level) {
        return;
    }
    if (v2.count == LOG_QUEUE) {
        v2.dropped++;
        return;
    }
    at = (uint8_t)((v2.head + v2.count) % LOG_QUEUE);
    n = strlen(text);
    if (n > LOG_TEXT) {
        n = LOG_TEXT;
    }
    v2.q[at].level = level;
    memcpy(v2.q[at].text, text, n);
    v2.q[at].text[n] = 0;
    v2.count++;
}

/* ---- TIME_SYNC, TELEMETRY ------------------------------------------------------------- */

static uint16_t time_sync(const uint8_t *p, uint16_t len, uint8_t *out)
{
    uint8_t in[8] = {0};
    memcpy(in, p, len < sizeof in ? len : sizeof in);
    memcpy(out, in, 8); /* host_time_us, echoed */
    sp_le_put_u64(out + 8, hal_time_us());
    sp_le_put_u32(out + 16, core_boot_id());
    return 20;
}

static uint16_t telemetry(const uint8_t *p, uint16_t len, uint8_t *out)
{
    uint8_t in[4] = {0};
    memcpy(in, p, len < sizeof in ? len : sizeof in);
    v2.heartbeat_ms = sp_le_get_u16(in);
    if (v2.heartbeat_ms != 0 && v2.heartbeat_ms < 50u) {
        v2.heartbeat_ms = 50u;
    }
    v2.log_level = in[2] > SP_LOG_DEBUG ? (uint8_t)SP_LOG_DEBUG : in[2];
    v2.log_per_s = in[3];
    v2.next_beat = hal_time_us() + (uint64_t)v2.heartbeat_ms * 1000u;
    sp_le_put_u16(out, v2.heartbeat_ms);
    out[2] = v2.log_level;
    out[3] = v2.log_per_s;
    return 4;
}

static uint32_t error_flags(void)
{
    uint32_t f = 0;
    if (spiel_stats.flash_errors) {
        f |= SP_EFLAG_FLASH;
    }
    if (cfg_active() < 0) {
        f |= SP_EFLAG_DEFAULT_CONFIG;
    }
    if (v2.dropped) {
        f |= SP_EFLAG_LOG_DROPPED;
    }
#if SPIEL_FW_UPDATE
    if (v2.boot_state == SP_BOOT_TRIAL) {
        f |= SP_EFLAG_TRIAL_IMAGE;
    }
    if (v2.selftest == SP_SELFTEST_FAILED) {
        f |= SP_EFLAG_SENSOR;
    }
#endif
    return f;
}

uint16_t v2_due(uint64_t now, uint8_t *out, uint16_t *out_len)
{
    if (core_version() < 2) {
        return 0;
    }
    if (v2.heartbeat_ms && now >= v2.next_beat) {
        uint8_t state = core_streaming() ? (uint8_t)SP_BOARD_STREAMING : (uint8_t)SP_BOARD_IDLE;
#if SPIEL_FW_UPDATE
        if (v2.upload_slot >= 0) {
            state = SP_BOARD_UPDATING;
        }
#endif
        v2.next_beat = now + (uint64_t)v2.heartbeat_ms * 1000u;
        sp_le_put_u32(out, (uint32_t)(now / 1000u));
        out[4] = state;
        out[5] = 0;
        sp_le_put_u16(out + 6, v2.heartbeat_ms);
        sp_le_put_u32(out + 8, error_flags());
        sp_le_put_u32(out + 12, core_boot_id());
        sp_le_put_u64(out + 16, now);
        *out_len = SP_HEARTBEAT_SIZE;
        return SP_MSG_HEARTBEAT;
    }
    if (v2.count && v2.log_per_s) {
        /* token bucket: log_per_s lines a second, at most that many at once */
        uint64_t gained = (now - v2.tokens_at) * v2.log_per_s / 1000u; /* milli-tokens */
        uint32_t cap = (uint32_t)v2.log_per_s * 1000u;
        v2.tokens_at = now;
        v2.tokens_milli = gained >= cap || v2.tokens_milli + gained >= cap
                              ? cap : v2.tokens_milli + (uint32_t)gained;
        if (v2.tokens_milli >= 1000u) {
            size_t n = strlen(v2.q[v2.head].text);
            if (n + 15u > core_max_payload()) { /* the link's limit (at least 64) */
                n = core_max_payload() - 15u;
            }
            v2.tokens_milli -= 1000u;
            out[0] = v2.q[v2.head].level;
            sp_le_put_u32(out + 1, v2.dropped);
            sp_le_put_u64(out + 5, now);
            sp_le_put_u16(out + 13, (uint16_t)n);
            memcpy(out + 15, v2.q[v2.head].text, n);
            v2.dropped = 0;
            v2.head = (uint8_t)((v2.head + 1u) % LOG_QUEUE);
            v2.count--;
            *out_len = (uint16_t)(15u + n);
            return SP_MSG_LOG;
        }
    }
    return 0;
}

uint64_t v2_next_us(uint64_t now)
{
    uint64_t wake = now + 50000u;
    if (core_version() < 2) {
        return wake;
    }
    if (v2.heartbeat_ms && v2.next_beat < wake) {
        wake = v2.next_beat;
    }
    if (v2.count && v2.log_per_s && now + 1000000u / v2.log_per_s < wake) {
        wake = now + 1000000u / v2.log_per_s;
    }
#if SPIEL_FW_UPDATE
    if (v2.verify_job == VERIFY_PENDING && v2.verify_at < wake) {
        wake = v2.verify_at;
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
    if (!v2.memo[slot].known) {
        v2.memo[slot].ok = image_check(slot, &v2.memo[slot].size, &v2.memo[slot].crc,
                                       v2.memo[slot].version) == 0;
        v2.memo[slot].known = 1;
    }
    if (v2.memo[slot].ok) {
        size = v2.memo[slot].size;
        crc = v2.memo[slot].crc;
        memcpy(version, v2.memo[slot].version, sizeof version);
        state = SP_SLOT_VERIFIED;
    } else if (slot == v2.upload_slot && v2.written) {
        state = SP_SLOT_PARTIAL;
        size = v2.written;
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

static uint16_t fw_info(uint8_t *out)
{
    boot_record_t r;
    boot_record_read(&r);
    out[0] = v2.running < 0 ? (uint8_t)0xFF : (uint8_t)v2.running;
    out[1] = r.state == SP_BOOT_TEST_PENDING ? (uint8_t)SP_BOOT_TEST_PENDING : v2.boot_state;
    out[2] = r.confirmed;
    out[3] = v2.selftest;
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

static int fw_begin(const uint8_t *p, uint16_t len, uint8_t *out, uint16_t *code,
                    const char **text)
{
    uint8_t in[10] = {0};
    uint32_t size;
    boot_record_t r;
    int slot;
    memcpy(in, p, len < sizeof in ? len : sizeof in);
    size = sp_le_get_u32(in);
    if (core_streaming()) {
        *code = SP_ERR_BAD_STATE, *text = "stop the stream before a firmware update";
        return 0;
    }
    if (v2.boot_state == SP_BOOT_TRIAL) {
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
    slot = v2.running >= 0 ? 1 - v2.running : r.confirmed == 0u ? 1 : 0;
    if (r.state == SP_BOOT_TEST_PENDING) { /* cancel: the slot it names is about to change */
        r.state = SP_BOOT_CONFIRMED;
        r.trial = BOOT_NO_SLOT;
        if (boot_record_write(&r) != 0) {
            *code = SP_ERR_FLASH_WRITE_FAILED, *text = "boot record write failed";
            return 0;
        }
    }
    v2.upload_slot = -1;
    v2.verified = 0;
    v2.verify_job = VERIFY_NONE;
    v2.memo[slot].known = 0;
    /* only the header's sector now (the old image is gone at once); the rest as the upload
     * reaches it, one sector per FW_WRITE at most: no request waits for a whole slot erase */
    if (hal_image_erase(slot, 0, hal_image_sector_size()) != 0) {
        spiel_stats.flash_errors++;
        *code = SP_ERR_FLASH_WRITE_FAILED, *text = "slot erase failed";
        return 0;
    }
    v2.upload_slot = slot;
    v2.expect_size = size;
    v2.expect_crc = sp_le_get_u32(in + 4);
    memcpy(v2.expect_sha, p + 10, 32);
    v2.written = 0;
    v2.erased_to = hal_image_sector_size();
    v2.unit_fill = 0;
    v2_log(SP_LOG_INFO, "firmware upload started");
    out[0] = (uint8_t)slot;
    sp_le_put_u32(out + 1, hal_image_slot_size());
    return 5;
}

/* Program [at, at + len) of the upload slot (whole units), erasing each sector first as the
 * upload reaches it. */
static int program(uint32_t at, const uint8_t *data, uint32_t len)
{
    uint32_t sector = hal_image_sector_size();
    v2.memo[v2.upload_slot].known = 0;
    while ((uint64_t)at + len > v2.erased_to) {
        if (v2.erased_to >= hal_image_slot_size() ||
            hal_image_erase(v2.upload_slot, v2.erased_to, sector) != 0) {
            return -1;
        }
        v2.erased_to += sector;
    }
    return hal_image_write(v2.upload_slot, at, data, len);
}

/* The upload's next n bytes: whole program units go to flash, the rest waits in unit_buf
 * (flushed, padded with 0xFF, when the image is complete). */
static int upload_bytes(const uint8_t *d, uint32_t n)
{
    uint32_t unit = hal_image_program_unit();
    uint32_t base = v2.written - v2.unit_fill; /* unit-aligned: where unit_buf goes */
    if (unit == 0 || unit > SPIEL_FW_UNIT_MAX) {
        return -1;
    }
    if (v2.unit_fill) {
        uint32_t take = unit - v2.unit_fill < n ? unit - v2.unit_fill : n;
        memcpy(v2.unit_buf + v2.unit_fill, d, take);
        v2.unit_fill += take;
        d += take;
        n -= take;
        if (v2.unit_fill < unit) {
            return 0;
        }
        if (program(base, v2.unit_buf, unit) != 0) {
            return -1;
        }
        base += unit;
        v2.unit_fill = 0;
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
    memcpy(v2.unit_buf, d, n);
    v2.unit_fill = n;
    return 0;
}

static int upload_flush(void)
{
    uint32_t unit = hal_image_program_unit();
    if (v2.unit_fill == 0) {
        return 0;
    }
    memset(v2.unit_buf + v2.unit_fill, 0xFF, unit - v2.unit_fill);
    if (program(v2.written - v2.unit_fill, v2.unit_buf, unit) != 0) {
        return -1;
    }
    v2.unit_fill = 0;
    return 0;
}

static int fw_write(const uint8_t *p, uint16_t len, uint8_t *out, uint16_t *code,
                    const char **text)
{
    uint32_t off;
    uint16_t n;
    if (v2.upload_slot < 0) {
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
    if ((uint64_t)off + n > v2.expect_size) { /* u64: an offset near 2^32 must not wrap */
        *code = SP_ERR_TOO_LARGE, *text = "past the announced size";
        return 0;
    }
    if (off + n <= v2.written) { /* a repeated chunk: already there */
        sp_le_put_u32(out, v2.written);
        return 4;
    }
    if (off != v2.written) {
        *code = SP_ERR_INVALID, *text = "offset is not the bytes written so far";
        return 0;
    }
    v2.verified = 0;
    v2.verify_job = VERIFY_NONE;
    if (upload_bytes(p + 6, n) != 0) {
        v2.upload_slot = -1; /* the bytes buffered are lost: FW_BEGIN again */
        spiel_stats.flash_errors++;
        *code = SP_ERR_FLASH_WRITE_FAILED, *text = "slot write failed";
        return 0;
    }
    v2.written = off + n;
    sp_le_put_u32(out, v2.written);
    return 4;
}

static int fw_verify(uint8_t *out, uint16_t *code, const char **text)
{
    uint32_t crc, size;
    uint8_t sha[32];
    char version[17];
    int slot = v2.upload_slot;
    if (slot < 0) {
        *code = SP_ERR_BAD_STATE, *text = "no upload: send FW_BEGIN";
        return 0;
    }
    if (v2.written != v2.expect_size) {
        *code = SP_ERR_BAD_STATE, *text = "image incomplete";
        return 0;
    }
    if (upload_flush() != 0) {
        v2.upload_slot = -1;
        spiel_stats.flash_errors++;
        *code = SP_ERR_FLASH_WRITE_FAILED, *text = "slot write failed";
        return 0;
    }
    if (slot_digest(slot, v2.expect_size, &crc, sha) != 0) {
        *code = SP_ERR_FLASH_VERIFY_FAILED, *text = "slot read failed";
        return 0;
    }
    if (crc != v2.expect_crc || memcmp(sha, v2.expect_sha, 32) != 0) {
        *code = SP_ERR_CORRUPT, *text = "CRC-32C or SHA-256 differs from FW_BEGIN's";
        v2_log(SP_LOG_ERROR, "firmware verify failed: digest mismatch");
        return 0;
    }
    if (image_check(slot, &size, NULL, version) != 0) {
        *code = SP_ERR_INVALID, *text = "not a valid image (header, size or body digest)";
        v2_log(SP_LOG_ERROR, "firmware verify failed: image header");
        return 0;
    }
    { /* signed by the built-in key, not below the record's security counter (14.6); before
       * the size check, so a truncated signature is named as such */
        boot_record_t r;
        boot_record_read(&r);
        *code = image_auth(slot, r.security_counter, NULL, text);
        if (*code == SP_ERR_OK && size > v2.expect_size) {
            *code = SP_ERR_FW_BAD_SIGNATURE, *text = "signature trailer truncated";
        } else if (*code == SP_ERR_OK && size < v2.expect_size) {
            *code = SP_ERR_INVALID, *text = "bytes after the image's end";
        }
        if (*code != SP_ERR_OK) {
            v2_log(SP_LOG_ERROR, "firmware verify failed: signature or security counter");
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
    v2.verified = 1;
    out[0] = (uint8_t)slot;
    sp_le_put_u32(out + 1, v2.expect_size);
    sp_le_put_u32(out + 5, crc);
    sp_le_put_u16(out + 9, 32);
    memcpy(out + 11, sha, 32);
    return 43;
}

/* FW_VERIFY: checked within the request, or (SP_FW_VERIFY_ASYNC) BUSY until v2_tick has
 * checked, then the result, as often as asked, until FW_BEGIN or new FW_WRITE bytes */
static int fw_verify_request(const uint8_t *p, uint16_t len, uint8_t *out, uint16_t *code,
                             const char **text)
{
    if (len == 0 || !(p[0] & SP_FW_VERIFY_ASYNC)) {
        v2.verify_job = VERIFY_NONE;
        return fw_verify(out, code, text);
    }
    if (v2.verify_job == VERIFY_DONE) {
        v2.verified = v2.verify_code == SP_ERR_OK;
        *code = v2.verify_code;
        *text = v2.verify_text;
        memcpy(out, v2.verify_out, v2.verify_len);
        return v2.verify_len;
    }
    if (v2.verify_job == VERIFY_NONE) {
        v2.verify_job = VERIFY_PENDING;
        v2.verify_at = hal_time_us() + VERIFY_DEFER_US;
    }
    *code = SP_ERR_BUSY, *text = "checking the image: ask again";
    return 0;
}

static int fw_test(const uint8_t *p, uint16_t len, uint8_t *out, uint16_t *code,
                   const char **text)
{
    uint8_t in[2] = {0};
    boot_record_t r;
    memcpy(in, p, len < sizeof in ? len : sizeof in);
    if (!v2.verified || v2.upload_slot < 0) {
        *code = SP_ERR_BAD_STATE, *text = "no verified image: FW_VERIFY first";
        return 0;
    }
    boot_record_read(&r);
    r.trial = (uint8_t)v2.upload_slot;
    r.state = SP_BOOT_TEST_PENDING;
    if (boot_record_write(&r) != 0) {
        spiel_stats.flash_errors++;
        *code = SP_ERR_FLASH_WRITE_FAILED, *text = "boot record write failed";
        return 0;
    }
    out[0] = (uint8_t)v2.upload_slot;
    v2.upload_slot = -1;
    v2.verify_job = VERIFY_NONE; /* no result for an upload that ended */
    core_reboot_after_ms(sp_le_get_u16(in));
    return 1;
}

static int fw_confirm(uint8_t *out, uint16_t *code, const char **text)
{
    if (v2.running < 0) {
        *code = SP_ERR_BAD_STATE, *text = "no image is running";
        return 0;
    }
    if (v2.boot_state == SP_BOOT_TRIAL && v2.selftest != SP_SELFTEST_PASSED) {
        *code = SP_ERR_BAD_STATE;
        *text = v2.selftest == SP_SELFTEST_FAILED ? "the self-test failed: the trial rolls back"
                                                  : "the self-test has not passed yet";
        return 0;
    }
    if (v2.boot_state == SP_BOOT_TRIAL) {
        boot_record_t r;
        boot_record_read(&r);
        r.confirmed = (uint8_t)v2.running;
        r.trial = BOOT_NO_SLOT;
        r.state = SP_BOOT_CONFIRMED;
        /* anti-rollback: in the same record write as the confirmation (one power-cut-safe
         * step), the floor rises to the confirmed image's counter */
        r.security_counter = image_counter_floor(v2.running, r.security_counter);
        if (boot_record_write(&r) != 0) {
            spiel_stats.flash_errors++;
            *code = SP_ERR_FLASH_WRITE_FAILED, *text = "boot record write failed";
            return 0;
        }
        v2.boot_state = SP_BOOT_CONFIRMED;
        v2_log(SP_LOG_NOTICE, "firmware confirmed");
    }
    out[0] = (uint8_t)v2.running;
    out[1] = v2.boot_state;
    return 2;
}
#endif

int v2_request(uint16_t msg_type, const uint8_t *p, uint16_t len, uint8_t *out,
               uint16_t *out_len, uint16_t *code, const char **text)
{
    int n = -1;
    *code = 0;
    *text = "";
    switch (msg_type) {
    case SP_MSG_TIME_SYNC:
        n = time_sync(p, len, out);
        break;
    case SP_MSG_TELEMETRY:
        n = telemetry(p, len, out);
        break;
#if SPIEL_FW_UPDATE
    case SP_MSG_FW_INFO:
    case SP_MSG_FW_BEGIN:
    case SP_MSG_FW_WRITE:
    case SP_MSG_FW_VERIFY:
    case SP_MSG_FW_TEST:
    case SP_MSG_FW_CONFIRM:
        if (hal_image_slot_size() == 0 || core_max_payload() < FW_MIN_PAYLOAD) {
            return 0;
        }
        n = msg_type == SP_MSG_FW_INFO     ? fw_info(out)
            : msg_type == SP_MSG_FW_BEGIN  ? fw_begin(p, len, out, code, text)
            : msg_type == SP_MSG_FW_WRITE  ? fw_write(p, len, out, code, text)
            : msg_type == SP_MSG_FW_VERIFY ? fw_verify_request(p, len, out, code, text)
            : msg_type == SP_MSG_FW_TEST   ? fw_test(p, len, out, code, text)
                                           : fw_confirm(out, code, text);
        break;
#endif
    default:
        return 0;
    }
    *out_len = (uint16_t)n;
    return 1;
}
