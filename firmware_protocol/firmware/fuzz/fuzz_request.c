/*
 * fuzz_request.c - libFuzzer harness of the device's request decoder: the whole portable core
 * (core/ over ../c/spiel_proto.c, built with -DSPIEL_FW_UPDATE=1 -DSPIEL_FW_EXEC_COPY=1
 * -DSPIEL_IQ_SAMPLES=1) on an in-memory HAL with config flash, two firmware image slots, a boot
 * record area and an execution region (NOR with ECC: 512-byte sectors, 8-byte program units),
 * fed one input per power-on. A reset (REBOOT, FW_TEST) runs the core's boot stage (boot_start:
 * the choice, the flash-to-flash install, the trial's watchdog) and boots the core again on the
 * same flash and slots; the input goes on (at most 8 resets).
 *
 *   make TARGET=fuzz            clang -fsanitize=fuzzer,address,undefined
 *   python -m tools.release.firmware_fuzz --runs 10000000
 *
 * Input: byte 0 chooses how the rest is read, bytes 1..3 shape the HAL:
 *   bit 0 of byte 0   0: raw transport bytes;  1: records framed here with a valid CRC, so
 *                     the fuzzer reaches every request's payload parser, fed one at a time:
 *                     u8 type index (types[] below), u8 flags, u8 seq step, u16 length,
 *                     length bytes
 *   bit 1             boot with a committed config in flash (else an erased flash)
 *   bit 2             the transport takes at most byte 3 + 1 bytes per write (backpressure)
 *   bit 3             image slot 0 holds a valid image (the confirmed one, running); else
 *                     both slots are erased and the recovery loader runs (running slot -1)
 *   byte 1            bytes per transport read (0: all available)
 *   byte 2            0xFF: nothing fails; 0x00..0x7F: that erase or write (config flash and
 *                     image slots counted together, 0-based) fails (a failing slot write
 *                     programs half its bytes first, a failing erase erases half the
 *                     range); 0x80..0xFE: image read (byte 2 & 0x7F) fails
 * Between reads the core is polled and the clock moves on, so streams are scheduled, sent,
 * overrun and stopped. Oracles beyond the sanitizers:
 *   - everything the device writes decodes as valid frames (no CRC, COBS, length or flag error
 *     in the host's decoder);
 *   - the core never erases or writes the running slot, never reads or writes outside an
 *     area, erases whole sectors only and programs whole units of erased bytes only (ECC NOR);
 *   - a trial image is never started without the watchdog;
 *   - framed records: the answers to FW_* requests agree with the requests (a model of the
 *     upload): FW_BEGIN's size in [96, slot_size], never the running slot; FW_WRITE answered
 *     OK only within the size FW_BEGIN announced; FW_VERIFY's size, CRC-32C and SHA-256 are
 *     FW_BEGIN's and those of the slot's bytes; FW_TEST's slot is the verified one; FW_INFO
 *     names the running slot. Retries answered from the device's cache are not checked;
 *   - the boot stage (when no failure was injected): after FW_TEST it boots the tested slot,
 *     and a reset of an unconfirmed trial rolls back to the other slot when that one checks.
 * The harness counts its own inputs: "spiel_fuzz: inputs N" at exit, and every million.
 */
#include <setjmp.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "core.h" /* white-box: the core's SHA-256 and SPIEL_FW_TARGET (fuzz.mk adds -Icore) */
#include "spiel_device.h"
#include "spiel_hal.h"
#include "spiel_proto.h"

#if !SPIEL_FW_UPDATE || !SPIEL_IQ_SAMPLES
#error "the harness implements the image slots and I/Q: build with -DSPIEL_FW_UPDATE=1 -DSPIEL_IQ_SAMPLES=1"
#endif

#define FLASH_SIZE 0x4000u /* two 8 KiB slots: 4 KiB sectors, SPIEL_CONFIG_MAX 4080 */
#define FLASH_SECTOR 0x1000u

static uint8_t flash[FLASH_SIZE], flash_erased[FLASH_SIZE], flash_seeded[FLASH_SIZE];
static const uint8_t *in_data;
static size_t in_len, in_pos, read_step;
static size_t tx_budget; /* 0: unlimited */
static uint32_t store_ops, store_fail_at; /* erases and writes: config flash and images */
static uint32_t image_reads, read_fail_at;
static int failed;                          /* an injected failure happened in this input */
static uint64_t now_us;
static uint32_t rng_state;
static jmp_buf reset_jump;
static int in_input;
static sp_decoder_t out_decoder;
static unsigned long long inputs;

#define IMAGE_SLOT 2048u  /* bytes per image slot: small, so that inputs fill one */
#define IMAGE_SECTOR 512u /* erase unit: a slot is 4 sectors, erased as the upload goes */
#define IMAGE_UNIT 8u     /* program unit (ECC flash): whole units of erased bytes only */
#define RECORD_AREA (2u * IMAGE_SECTOR) /* slot 2: the boot record's two copies */
#define EXEC_AREA (IMAGE_SECTOR + IMAGE_SLOT) /* slot 3: the boot stage's copy */
#define MAX_RESETS 8u     /* resets per input */

static uint8_t slots[2][IMAGE_SLOT], record_area[RECORD_AREA], exec_area[EXEC_AREA];
static int watchdog_started;
static uint8_t image0[IMAGE_SLOT]; /* a valid image for slot 0 (mode bit 3) */
static int image_running;          /* the slot the boot stage chose: 0, 1, -1 none */
static unsigned resets;

static void fail_check(const char *what)
{
    fprintf(stderr, "spiel_fuzz: %s\n", what);
    abort();
}

/* ---- the in-memory HAL ----------------------------------------------------------------- */

size_t hal_transport_read(uint8_t *buf, size_t cap)
{
    size_t n = in_len - in_pos;
    if (read_step && n > read_step) {
        n = read_step;
    }
    if (n > cap) {
        n = cap;
    }
    memcpy(buf, in_data + in_pos, n);
    in_pos += n;
    return n;
}

static void check_output(const sp_frame_t *f);

size_t hal_transport_write(const uint8_t *buf, size_t len)
{
    size_t i, n = tx_budget && len > tx_budget ? tx_budget : len;
    for (i = 0; i < n; i++) {
        sp_frame_t f;
        if (sp_decoder_feed(&out_decoder, buf[i], &f)) {
            check_output(&f);
        }
    }
    return n;
}

uint64_t hal_time_us(void)
{
    return now_us;
}

static uint32_t trig_mask;
static uint16_t trig_samples;

int hal_acq_trigger(uint32_t channel_mask, uint16_t n_samples)
{
    if (channel_mask == 0 || (channel_mask >> 4) != 0 || n_samples == 0 || n_samples > 64) {
        return -1;
    }
    trig_mask = channel_mask;
    trig_samples = n_samples;
    return 0;
}

int hal_acq_read_iq(uint8_t channel, uint16_t *qi, uint16_t n_samples)
{
    uint16_t i;
    if (channel >= 4 || !(trig_mask & (1u << channel)) || n_samples > trig_samples ||
        2u * (uint32_t)n_samples > SPIEL_MAX_SAMPLES) {
        return -1;
    }
    for (i = 0; i < n_samples; i++) {
        qi[2u * i] = (uint16_t)(0x8000u + i);      /* q: negative values too */
        qi[2u * i + 1u] = (uint16_t)(i * 131u + channel); /* i */
    }
    return 0;
}

int hal_acq_ready(void)
{
    return 1;
}

int hal_acq_read(uint8_t channel, uint16_t *samples, uint16_t n_samples)
{
    uint16_t i;
    if (channel >= 4 || !(trig_mask & (1u << channel)) || n_samples > trig_samples) {
        return -1;
    }
    for (i = 0; i < n_samples; i++) {
        samples[i] = (uint16_t)(i * 257u + channel);
    }
    return 0;
}

uint32_t hal_flash_size(void)
{
    return FLASH_SIZE;
}

uint32_t hal_flash_sector_size(void)
{
    return FLASH_SECTOR;
}

static int storage_fails(void)
{
    if (store_ops++ == store_fail_at) {
        failed = 1;
        return 1;
    }
    return 0;
}

int hal_flash_erase(uint32_t addr, uint32_t len)
{
    if (addr > FLASH_SIZE || len > FLASH_SIZE - addr || addr % FLASH_SECTOR || len % FLASH_SECTOR) {
        return -1;
    }
    if (storage_fails()) {
        return -1;
    }
    memset(flash + addr, 0xFF, len);
    return 0;
}

int hal_flash_write(uint32_t addr, const uint8_t *data, uint32_t len)
{
    uint32_t i;
    if (addr > FLASH_SIZE || len > FLASH_SIZE - addr) {
        return -1;
    }
    if (storage_fails()) {
        return -1;
    }
    for (i = 0; i < len; i++) {
        flash[addr + i] &= data[i];
    }
    return 0;
}

int hal_flash_read(uint32_t addr, uint8_t *data, uint32_t len)
{
    if (addr > FLASH_SIZE || len > FLASH_SIZE - addr) {
        return -1;
    }
    memcpy(data, flash + addr, len);
    return 0;
}

void hal_reset(int to_bootloader)
{
    (void)to_bootloader;
    if (in_input) {
        longjmp(reset_jump, 1); /* the board restarts: power_on(), then the input goes on */
    }
    abort();
}

uint32_t hal_random(void)
{
    rng_state = rng_state * 1664525u + 1013904223u;
    return rng_state;
}

static const hal_board_info_t board = {
    "1.0.0+fuzz", "FUZZ0001", "spiel-c fuzz", 0, 0, 1, 4, 0, 16, 64, 175000u, 400000u, 64,
    22000u,
};

const hal_board_info_t *hal_board_info(void)
{
    return &board;
}

int16_t hal_temperature_cdeg(void)
{
    return 2100;
}

void hal_apply_settings(const hal_settings_t *settings)
{
    (void)settings;
}

/* ---- firmware image slots (SPIEL_FW_UPDATE): slots 0 and 1 behave as NOR flash (a write
 * only clears bits; erase sets 0xFF), slot 2 (the boot record) as the mps2 target's: a write
 * replaces one copy (its own sector, erased first). ---------------------------------------- */

static uint32_t area_cap(int slot)
{
    return slot == SPIEL_IMAGE_RECORD ? RECORD_AREA : slot == SPIEL_IMAGE_EXEC ? EXEC_AREA
                                                                             : IMAGE_SLOT;
}

static uint8_t *image_area(int slot, uint32_t offset, uint32_t len)
{
    uint32_t cap = area_cap(slot);
    if (slot < 0 || slot > SPIEL_IMAGE_EXEC || offset > cap || len > cap - offset) {
        fprintf(stderr, "spiel_fuzz: image slot %d accessed outside it: offset %lu, %lu bytes\n",
                slot, (unsigned long)offset, (unsigned long)len);
        abort();
    }
    return slot == SPIEL_IMAGE_RECORD ? record_area + offset
           : slot == SPIEL_IMAGE_EXEC ? exec_area + offset
                                      : slots[slot] + offset;
}

uint32_t hal_image_slot_size(void)
{
    return IMAGE_SLOT;
}

uint32_t hal_image_sector_size(void)
{
    return IMAGE_SECTOR;
}

uint32_t hal_image_program_unit(void)
{
    return IMAGE_UNIT;
}

int hal_image_running(void)
{
    return image_running;
}

void hal_watchdog_start(uint32_t timeout_ms)
{
    (void)timeout_ms;
    watchdog_started = 1;
}

void hal_watchdog_kick(void)
{
}

/* NOR flash with ECC: erase whole sectors (a cut leaves the first half erased), program whole
 * units of erased bytes once (a cut programs half of them). */
int hal_image_erase(int slot, uint32_t offset, uint32_t len)
{
    uint8_t *area = image_area(slot, offset, len);
    if (offset % IMAGE_SECTOR != 0 || len % IMAGE_SECTOR != 0 || len == 0) {
        fail_check("the core erased a range that is not whole sectors");
    }
    if (slot == image_running) {
        fail_check("the core erased the running slot");
    }
    if (storage_fails()) {
        memset(area, 0xFF, len / 2u);
        return -1;
    }
    memset(area, 0xFF, len);
    return 0;
}

int hal_image_write(int slot, uint32_t offset, const uint8_t *data, uint32_t len)
{
    uint8_t *area = image_area(slot, offset, len);
    uint32_t i, n = len;
    if (slot == image_running) {
        fail_check("the core wrote the running slot");
    }
    if (offset % IMAGE_UNIT != 0 || len % IMAGE_UNIT != 0) {
        fail_check("the core programmed a part of a program unit");
    }
    for (i = 0; i < len; i++) {
        if (area[i] != 0xFF && !failed) {
            fail_check("the core programmed a unit twice without an erase");
        }
    }
    if (storage_fails()) {
        n = len / 2; /* half of it reaches the flash */
    }
    for (i = 0; i < n; i++) {
        area[i] &= data[i];
    }
    return n == len ? 0 : -1;
}

int hal_image_read(int slot, uint32_t offset, uint8_t *data, uint32_t len)
{
    const uint8_t *area = image_area(slot, offset, len);
    if (image_reads++ == read_fail_at) {
        failed = 1;
        return -1;
    }
    memcpy(data, area, len);
    return 0;
}

/* Its signature trailer by the development key (keys/dev.key, the default FW_KEY; Ed25519 is
 * deterministic: tests/protocol_v2/test_v2_signing_posix.py makes it again and compares). */
static const uint8_t image0_trailer[SP_SIG_TRAILER_SIZE] = {
    0x53, 0x50, 0x53, 0x47, 0x01, 0x00, 0x40, 0x00, 0x2e, 0xf2, 0x88, 0x43,
    0x16, 0xb5, 0xbc, 0x8c, 0x26, 0x89, 0x18, 0x8d, 0x90, 0x26, 0xf1, 0xfe,
    0x6e, 0x25, 0x6e, 0x60, 0xb0, 0xb1, 0x02, 0x8c, 0x3b, 0x67, 0xb1, 0x22,
    0x6d, 0x35, 0x0c, 0x18, 0x67, 0xaf, 0xfa, 0xe4, 0x0b, 0x6b, 0x50, 0x7e,
    0x30, 0x42, 0xb8, 0x03, 0xc6, 0x24, 0xab, 0x75, 0x8a, 0x09, 0x59, 0x73,
    0x5e, 0xac, 0x12, 0xe8, 0x7d, 0xc1, 0xb6, 0xcf, 0xd4, 0xa0, 0x34, 0xd2,
    0xbb, 0x11, 0xc6, 0x7f, 0xf8, 0x48, 0x3c, 0x0c};

/* A valid image for slot 0 (target SPIEL_FW_TARGET, protocols 1-2, a 160-byte body, signed
 * by the development key). */
static void make_image0(void)
{
    uint8_t body[160];
    sp_image_header_t h;
    sha256_t s;
    uint32_t i;
    for (i = 0; i < sizeof body; i++) {
        body[i] = (uint8_t)(i * 7u + 1u);
    }
    memset(&h, 0, sizeof h);
    memcpy(h.magic, SP_IMAGE_MAGIC, 4);
    h.header_version = SP_IMAGE_HEADER_VERSION;
    h.header_size = SP_IMAGE_HEADER_SIZE;
    memcpy(h.version, "1.0.0+fuzz", 10);
    memcpy(h.target, SPIEL_FW_TARGET, strlen(SPIEL_FW_TARGET));
    h.min_protocol = 1;
    h.max_protocol = 2;
    h.flags = SP_IMAGE_FLAG_SIGNED;
    h.body_size = sizeof body;
    h.body_crc = sp_crc32c(0, body, sizeof body);
    sha256_init(&s);
    sha256_update(&s, body, sizeof body);
    sha256_final(&s, h.body_sha256);
    memset(image0, 0xFF, sizeof image0);
    sp_image_header_pack(&h, image0);
    h.header_crc = sp_crc32c(0, image0, SP_IMAGE_HEADER_SIZE - 4u);
    sp_image_header_pack(&h, image0);
    memcpy(image0 + SP_IMAGE_HEADER_SIZE, body, sizeof body);
    memcpy(image0 + SP_IMAGE_HEADER_SIZE + sizeof body, image0_trailer, sizeof image0_trailer);
}

/* ---- the oracle's model of the host side: the request being fed, the device's retry cache,
 * the upload and the boot record ---------------------------------------------------------- */

/* make TARGET=fuzz CFLAGS_EXTRA=-DSPIEL_FUZZ_TRACE=1: the harness prints every answer it
 * matched to a framed request, and every boot, on stderr (to see how deep a seed goes). */
#ifndef SPIEL_FUZZ_TRACE
#define SPIEL_FUZZ_TRACE 0
#endif

#define UNKNOWN (-2) /* a failure made the device's state uncertain: not checked */

static struct {
    int valid;            /* a framed request is being fed, its answer not seen yet */
    uint16_t type, seq;
    const uint8_t *p;     /* its payload */
    uint16_t len;
} fed;

static struct {
    int valid;            /* the device answers (seq, type) from its cache */
    uint16_t seq, type;
} cache_model;

static struct {
    int begun;            /* FW_BEGIN answered OK, the upload not ended since */
    uint32_t size, crc, written;
    uint8_t sha[32];
    int slot;             /* the slot FW_BEGIN answered */
    int verified;         /* the slot FW_VERIFY passed since, -1 none, or UNKNOWN */
    int pending;          /* FW_TEST answered OK: the slot the next boot runs; -1, UNKNOWN */
    int trial;            /* running that unconfirmed trial slot; -1, UNKNOWN */
} up;

static void model_reset(void)
{
    memset(&up, 0, sizeof up);
    up.verified = up.pending = up.trial = -1;
    cache_model.valid = 0;
    fed.valid = 0;
}

static void fw_refused(void)
{
    switch (fed.type) {
    case SP_MSG_FW_BEGIN: /* a failed boot record write or erase: the test may be cancelled */
        if (up.pending >= 0) {
            up.pending = UNKNOWN;
        }
        break;
    case SP_MSG_FW_WRITE: /* a failed slot write clears the verification */
        if (up.verified >= 0) {
            up.verified = UNKNOWN;
        }
        break;
    default:
        break;
    }
}

static void fw_answered(const uint8_t *out, uint16_t n)
{
    switch (fed.type) {
    case SP_MSG_FW_INFO:
        if (n < 8u || out[0] != (image_running < 0 ? 0xFFu : (unsigned)image_running) ||
            sp_le_get_u32(out + 4) != IMAGE_SLOT) {
            fail_check("FW_INFO names another running slot or slot size");
        }
        break;
    case SP_MSG_FW_BEGIN: {
        uint32_t size = sp_le_get_u32(fed.p);
        if (fed.len < 42u || n < 5u) {
            fail_check("FW_BEGIN answered OK to a short request");
        }
        if (size < SP_IMAGE_HEADER_SIZE || size > IMAGE_SLOT || out[0] > 1u ||
            (int)out[0] == image_running || sp_le_get_u32(out + 1) != IMAGE_SLOT) {
            fail_check("FW_BEGIN answered OK: size outside [96, slot_size] or the running slot");
        }
        if (up.trial >= 0) {
            fail_check("FW_BEGIN answered OK while an unconfirmed trial image runs");
        }
        up.begun = 1;
        up.size = size;
        up.crc = sp_le_get_u32(fed.p + 4);
        memcpy(up.sha, fed.p + 10, 32);
        up.slot = out[0];
        up.written = 0;
        up.verified = -1;
        up.pending = -1; /* a pending test is cancelled */
        break;
    }
    case SP_MSG_FW_WRITE: {
        uint64_t end;
        if (fed.len < 6u || n < 4u || !up.begun) {
            fail_check("FW_WRITE answered OK without an upload or to a short request");
        }
        end = (uint64_t)sp_le_get_u32(fed.p) + sp_le_get_u16(fed.p + 4);
        if (end > up.size) {
            fail_check("FW_WRITE answered OK past the image size FW_BEGIN announced");
        }
        if (end > up.written) { /* new bytes (a repeat is answered without writing) */
            up.written = (uint32_t)end;
            up.verified = -1;
        }
        if (sp_le_get_u32(out) != up.written) {
            fail_check("FW_WRITE's written differs from the bytes sent");
        }
        break;
    }
    case SP_MSG_FW_VERIFY: {
        uint8_t sha[32];
        sha256_t s;
        if (!up.begun || n < 43u || out[0] != up.slot || sp_le_get_u32(out + 1) != up.size ||
            up.written != up.size || sp_le_get_u32(out + 5) != up.crc ||
            sp_le_get_u16(out + 9) != 32u || memcmp(out + 11, up.sha, 32) != 0) {
            fail_check("FW_VERIFY answered OK with another slot, size or digest than FW_BEGIN's");
        }
        sha256_init(&s);
        sha256_update(&s, slots[up.slot], up.size);
        sha256_final(&s, sha);
        if (!failed && (memcmp(sha, up.sha, 32) != 0 ||
                        sp_crc32c(0, slots[up.slot], up.size) != up.crc)) {
            fail_check("FW_VERIFY answered OK but the slot's bytes have another digest");
        }
        up.verified = up.slot;
        break;
    }
    case SP_MSG_FW_TEST:
        if (!up.begun || n < 1u || out[0] != up.slot || up.verified == -1 ||
            (up.verified >= 0 && up.verified != up.slot)) {
            fail_check("FW_TEST answered OK without a verified upload of that slot");
        }
        up.pending = up.slot;
        up.begun = 0;
        break;
    case SP_MSG_FW_CONFIRM:
        if (n < 2u || image_running < 0 || out[0] != (unsigned)image_running ||
            out[1] != SP_BOOT_CONFIRMED) {
            fail_check("FW_CONFIRM answered OK but not the running slot, confirmed");
        }
        up.trial = -1;
        break;
    default:
        break;
    }
}

/* Every frame the device writes: the answer to the framed request being fed is checked. */
static void check_output(const sp_frame_t *f)
{
    const sp_header_t *h = &f->header;
    if (!fed.valid || !(h->flags & SP_FLAG_RESPONSE) || h->seq != fed.seq) {
        return;
    }
    fed.valid = 0;
    if (SPIEL_FUZZ_TRACE) {
        fprintf(stderr, "spiel_fuzz: 0x%04x seq %u: %s %u\n", (unsigned)fed.type,
                (unsigned)fed.seq, (h->flags & SP_FLAG_NACK) ? "error" : "ok, bytes",
                (h->flags & SP_FLAG_NACK) ? (unsigned)sp_le_get_u16(f->payload)
                                          : (unsigned)h->payload_len);
    }
    if (cache_model.valid && cache_model.seq == fed.seq && cache_model.type == fed.type &&
        fed.type != SP_MSG_HELLO) {
        return; /* a retry, answered from the cache (the earlier request's answer) */
    }
    cache_model.valid = h->payload_len <= 64u && fed.type != SP_MSG_HELLO;
    cache_model.seq = fed.seq;
    cache_model.type = fed.type;
    if (h->flags & SP_FLAG_NACK) {
        fw_refused();
    } else {
        fw_answered(f->payload, h->payload_len);
    }
}

/* Power-on or reset: the boot stage (the core's boot_choose) picks the slot, then the core
 * boots; RAM (the upload, the retry cache, the receive buffer) is lost. */
static void power_on(void)
{
    int choice;
    image_running = -1;
    watchdog_started = 0;
    choice = boot_start(2000u); /* the choice, the install into slot 3, the trial's watchdog */
    if (choice >= 0 && boot_is_trial(choice) && !watchdog_started && !failed) {
        fail_check("a trial image was started without the watchdog");
    }
    if (choice >= 0 && image_check(choice, NULL, NULL, NULL) != 0 && !failed) {
        fail_check("the boot stage chose a slot whose image does not check");
    }
    if (!failed && up.pending >= 0 && choice != up.pending) {
        fail_check("the boot stage did not run the slot FW_TEST named");
    }
    if (!failed && up.pending == -1 && up.trial >= 0 && choice == up.trial &&
        image_check(1 - up.trial, NULL, NULL, NULL) == 0 && !failed) {
        fail_check("a reset of an unconfirmed trial image did not roll back");
    }
    if (failed || up.pending == UNKNOWN) {
        up.trial = UNKNOWN;
    } else {
        up.trial = up.pending >= 0 ? choice : -1;
    }
    up.pending = -1;
    up.begun = 0;
    up.verified = -1;
    cache_model.valid = 0;
    fed.valid = 0;
    image_running = choice;
    if (SPIEL_FUZZ_TRACE) {
        fprintf(stderr, "spiel_fuzz: boot (reset %u): slot %d\n", resets, choice);
    }
    spiel_device_init();
}

/* ---- driving the core ------------------------------------------------------------------- */

static void poll_for(unsigned rounds, uint32_t step_us)
{
    unsigned i;
    for (i = 0; i < rounds; i++) {
        spiel_device_poll();
        now_us += step_us;
    }
}

/* Hand out the rest of in_data (a reset may interrupt it: pump again to go on), then poll. */
static void pump(uint32_t step_us, unsigned tail)
{
    while (in_pos < in_len) {
        spiel_device_poll();
        now_us += step_us;
    }
    poll_for(tail, step_us);
}

static void feed(const uint8_t *data, size_t len, uint32_t step_us)
{
    in_data = data;
    in_len = len;
    in_pos = 0;
    pump(step_us, 8);
}

static uint8_t wire[SP_MAX_WIRE];
static uint8_t framed[1u << 16];

/* The record's type index: tools/release/firmware_fuzz.py (FRAMED_TYPES) mirrors this table. */
static const uint16_t types[] = {
    SP_MSG_HELLO, SP_MSG_DEVICE_INFO, SP_MSG_PING, SP_MSG_REBOOT, SP_MSG_STREAM_START,
    SP_MSG_STREAM_STOP, SP_MSG_STREAM_STATUS, SP_MSG_CONFIG_READ, SP_MSG_CONFIG_WRITE,
    SP_MSG_CONFIG_COMMIT, SP_MSG_CONFIG_STATUS, SP_MSG_ERROR, SP_MSG_STREAM_DATA, 0x0006u,
    0x0007u, 0x0008u, 0x0009u, 0x000Au, 0x0014u, 0x0024u, 0x0025u, 0x0030u, 0x0031u, 0x0032u,
    0x0033u, 0x0034u, 0x0040u, 0x8A01u, 0xFFFFu, SP_MSG_FW_BEGIN, SP_MSG_FW_WRITE,
    SP_MSG_FW_VERIFY, SP_MSG_FW_TEST, SP_MSG_FW_CONFIRM,
};

/* The records of a structured input, framed and fed one at a time (the cursor survives a
 * reset: the record being fed then is lost, like bytes in flight). */
static const uint8_t *rec_p;
static size_t rec_n;
static uint16_t rec_seq;

static void feed_records(uint32_t step_us)
{
    while (rec_n >= 5) {
        const uint8_t *p = rec_p;
        uint16_t type = types[p[0] % (sizeof types / sizeof types[0])];
        uint8_t flags = (uint8_t)(p[1] & SP_KNOWN_FLAGS);
        uint16_t len = (uint16_t)(p[3] | (p[4] << 8));
        size_t w;
        rec_seq = (uint16_t)(rec_seq + p[2]);
        if (len > rec_n - 5) {
            len = (uint16_t)(rec_n - 5);
        }
        rec_p += 5u + len;
        rec_n -= 5u + len;
        w = sp_frame_encode(type, rec_seq, flags, 0, p + 5, len, wire, sizeof wire);
        if (w == 0) {
            rec_n = 0;
            break;
        }
        fed.valid = (flags & (SP_FLAG_RESPONSE | SP_FLAG_STREAM)) == 0;
        fed.type = type;
        fed.seq = rec_seq;
        fed.p = p + 5;
        fed.len = len;
        in_data = wire;
        in_len = w;
        in_pos = 0;
        pump(step_us, 2);
        fed.valid = 0;
    }
    poll_for(8, step_us);
}

static void boot(const uint8_t *image, int with_image0)
{
    memcpy(flash, image, FLASH_SIZE);
    memset(slots, 0xFF, sizeof slots);
    memset(record_area, 0xFF, sizeof record_area);
    memset(exec_area, 0xFF, sizeof exec_area);
    if (with_image0) {
        memcpy(slots[0], image0, IMAGE_SLOT);
    }
    sp_decoder_init(&out_decoder);
    now_us = 1000;
    rng_state = 12345u;
    store_ops = 0;
    image_reads = 0;
    failed = 0;
    resets = 0;
    model_reset();
    power_on();
}
/* A committed config in flash, made through the protocol itself (CONFIG_WRITE + COMMIT). */
static void seed_config(void)
{
    static const char toml[] = "[board]\nname = \"fuzz\"\n";
    uint8_t blob[SP_CONFIG_HEADER_SIZE + sizeof toml - 1], req[64 + sizeof blob];
    sp_config_header_t h;
    size_t n = 0;
    uint32_t crc;
    memcpy(h.magic, "SPCF", 4);
    h.version = 1;
    h.header_size = SP_CONFIG_HEADER_SIZE;
    h.n_samples = 64;
    h.decimation = 8;
    h.pulse_cycles = 30;
    h.blind_zone_samples = 9;
    h.sample_rate_hz = 22000.0f;
    h.carrier_hz = 175000.0f;
    h.gain_db = 20.0f;
    h.acquisition_rate_hz = 30.0f;
    h.toml_length = sizeof toml - 1;
    sp_config_header_pack(&h, blob);
    memcpy(blob + SP_CONFIG_HEADER_SIZE, toml, sizeof toml - 1);
    crc = sp_crc32c(0, blob, sizeof blob);
    memset(flash_erased, 0xFF, sizeof flash_erased);
    store_fail_at = read_fail_at = 0xFFFFFFFFu;
    boot(flash_erased, 0);
    sp_le_put_u32(req, 0);
    sp_le_put_u16(req + 4, (uint16_t)sizeof blob);
    memcpy(req + 6, blob, sizeof blob);
    n = sp_frame_encode(SP_MSG_CONFIG_WRITE, 1, 0, 0, req, (uint16_t)(6 + sizeof blob), framed,
                        sizeof framed);
    sp_le_put_u32(req, (uint32_t)sizeof blob);
    sp_le_put_u32(req + 4, crc);
    n += sp_frame_encode(SP_MSG_CONFIG_COMMIT, 2, 0, 0, req, 8, framed + n, sizeof framed - n);
    feed(framed, n, 100);
    memcpy(flash_seeded, flash, FLASH_SIZE);
    if (memcmp(flash_seeded, flash_erased, FLASH_SIZE) == 0) {
        fprintf(stderr, "spiel_fuzz: the seed config was not committed\n");
        abort();
    }
}

static void report(void)
{
    fprintf(stderr, "spiel_fuzz: inputs %llu\n", inputs);
}

int LLVMFuzzerInitialize(int *argc, char ***argv);
int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size);

int LLVMFuzzerInitialize(int *argc, char ***argv)
{
    (void)argc;
    (void)argv;
    store_fail_at = read_fail_at = 0xFFFFFFFFu;
    make_image0();
    memcpy(slots[0], image0, IMAGE_SLOT);
    image_running = -1;
    if (image_check(0, NULL, NULL, NULL) != 0) {
        fail_check("the harness's own slot 0 image does not check");
    }
    seed_config();
    atexit(report);
    return 0;
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    uint8_t mode;
    uint32_t step_us;
    if (++inputs % 1000000u == 0) { /* a count that survives an interrupted run */
        fprintf(stderr, "spiel_fuzz: inputs %llu so far\n", inputs);
    }
    if (size < 4) {
        return 0;
    }
    mode = data[0];
    read_step = data[1];
    tx_budget = (mode & 4u) ? (size_t)data[3] + 1u : 0u;
    store_fail_at = data[2] < 0x80u ? data[2] : 0xFFFFFFFFu;
    read_fail_at = data[2] >= 0x80u && data[2] != 0xFFu ? data[2] & 0x7Fu : 0xFFFFFFFFu;
    step_us = 50u + 997u * (data[3] & 0x3Fu); /* 50 us .. 63 ms per poll */
    in_data = data + 4;
    in_len = size - 4;
    in_pos = 0;
    rec_p = data + 4;
    rec_n = size - 4;
    rec_seq = 1;
    boot((mode & 2u) ? flash_seeded : flash_erased, (mode & 8u) != 0);
    in_input = 1;
    if (setjmp(reset_jump) != 0 && ++resets <= MAX_RESETS) { /* the board restarted */
        power_on();
    }
    if (resets <= MAX_RESETS) {
        if (mode & 1u) {
            feed_records(step_us);
        } else {
            pump(step_us, 8);
        }
    }
    in_input = 0;
    /* the oracle: the device never sends a damaged frame */
    if (out_decoder.stats.crc || out_decoder.stats.cobs || out_decoder.stats.length ||
        out_decoder.stats.oversize || out_decoder.stats.version || out_decoder.stats.flags) {
        fprintf(stderr, "spiel_fuzz: the device sent an invalid frame\n");
        abort();
    }
    return 0;
}
