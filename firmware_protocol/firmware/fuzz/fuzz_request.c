/*
 * fuzz_request.c - libFuzzer harness of the device's request decoder: the whole portable core
 * (core/ over ../c/spiel_proto.c) on an in-memory HAL, fed one input per boot.
 *
 *   make TARGET=fuzz            clang -fsanitize=fuzzer,address,undefined
 *   python -m tools.release.firmware_fuzz --runs 10000000
 *
 * Input: byte 0 chooses how the rest is read, bytes 1..3 shape the HAL:
 *   bit 0 of byte 0   0: raw transport bytes;  1: records framed here with a valid CRC, so
 *                     the fuzzer reaches every request's payload parser:
 *                     u8 type index, u8 flags, u8 seq step, u16 length, length bytes
 *   bit 1             boot with a committed config in flash (else an erased flash)
 *   bit 2             the transport takes at most byte 3 + 1 bytes per write (backpressure)
 *   byte 1            bytes per transport read (0: all available)
 *   byte 2            the flash operation that fails (0xFF: none)
 * Between reads the core is polled and the clock moves on, so streams are scheduled, sent,
 * overrun and stopped. Oracle beyond the sanitizers: everything the device writes must decode
 * as valid frames (no CRC, COBS, length or flag error in the host's decoder).
 * The harness counts its own inputs: "spiel_fuzz: inputs N" at exit, and every million.
 */
#include <setjmp.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "spiel_device.h"
#include "spiel_hal.h"
#include "spiel_proto.h"

#define FLASH_SIZE 0x4000u /* two 8 KiB slots: 4 KiB sectors, SPIEL_CONFIG_MAX 4080 */
#define FLASH_SECTOR 0x1000u

static uint8_t flash[FLASH_SIZE], flash_erased[FLASH_SIZE], flash_seeded[FLASH_SIZE];
static const uint8_t *in_data;
static size_t in_len, in_pos, read_step;
static size_t tx_budget; /* 0: unlimited */
static uint32_t flash_ops, flash_fail_at;
static uint64_t now_us;
static uint32_t rng_state;
static jmp_buf reset_jump;
static int in_input;
static sp_decoder_t out_decoder;
static unsigned long long inputs;

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

size_t hal_transport_write(const uint8_t *buf, size_t len)
{
    size_t i, n = tx_budget && len > tx_budget ? tx_budget : len;
    for (i = 0; i < n; i++) {
        sp_frame_t f;
        (void)sp_decoder_feed(&out_decoder, buf[i], &f);
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

static int flash_fails(void)
{
    return flash_ops++ == flash_fail_at;
}

int hal_flash_erase(uint32_t addr, uint32_t len)
{
    if (addr > FLASH_SIZE || len > FLASH_SIZE - addr || addr % FLASH_SECTOR || len % FLASH_SECTOR) {
        return -1;
    }
    if (flash_fails()) {
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
    if (flash_fails()) {
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
        longjmp(reset_jump, 1); /* the board restarts: this input ends */
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

/* ---- driving the core ------------------------------------------------------------------- */

static void poll_for(unsigned rounds, uint32_t step_us)
{
    unsigned i;
    for (i = 0; i < rounds; i++) {
        spiel_device_poll();
        now_us += step_us;
    }
}

static void feed(const uint8_t *data, size_t len, uint32_t step_us)
{
    in_data = data;
    in_len = len;
    in_pos = 0;
    while (in_pos < in_len) {
        spiel_device_poll();
        now_us += step_us;
    }
    poll_for(8, step_us);
}

static uint8_t wire[SP_MAX_WIRE];
static uint8_t framed[1u << 16];

static const uint16_t types[] = {
    SP_MSG_HELLO, SP_MSG_DEVICE_INFO, SP_MSG_PING, SP_MSG_REBOOT, SP_MSG_STREAM_START,
    SP_MSG_STREAM_STOP, SP_MSG_STREAM_STATUS, SP_MSG_CONFIG_READ, SP_MSG_CONFIG_WRITE,
    SP_MSG_CONFIG_COMMIT, SP_MSG_CONFIG_STATUS, SP_MSG_ERROR, SP_MSG_STREAM_DATA, 0x0006u,
    0x0007u, 0x0008u, 0x0009u, 0x000Au, 0x0014u, 0x0024u, 0x0025u, 0x0030u, 0x0031u, 0x0032u,
    0x0033u, 0x0034u, 0x0040u, 0x8A01u, 0xFFFFu,
};

/* Frame the records of a structured input; returns the framed length. */
static size_t frame_records(const uint8_t *p, size_t n)
{
    size_t out = 0;
    uint16_t seq = 1;
    while (n >= 5) {
        uint16_t type = types[p[0] % (sizeof types / sizeof types[0])];
        uint8_t flags = (uint8_t)(p[1] & SP_KNOWN_FLAGS);
        uint16_t len = (uint16_t)(p[3] | (p[4] << 8)), w;
        seq = (uint16_t)(seq + p[2]);
        p += 5;
        n -= 5;
        if (len > n) {
            len = (uint16_t)n;
        }
        w = (uint16_t)sp_frame_encode(type, seq, flags, 0, p, len, wire, sizeof wire);
        if (w == 0 || out + w > sizeof framed) {
            break;
        }
        memcpy(framed + out, wire, w);
        out += w;
        p += len;
        n -= len;
    }
    return out;
}

static void boot(const uint8_t *image)
{
    memcpy(flash, image, FLASH_SIZE);
    sp_decoder_init(&out_decoder);
    now_us = 1000;
    rng_state = 12345u;
    flash_ops = 0;
    spiel_device_init();
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
    boot(flash_erased);
    flash_fail_at = 0xFFFFFFFFu;
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
    seed_config();
    atexit(report);
    return 0;
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    uint8_t mode;
    uint32_t step_us;
    const uint8_t *body;
    size_t body_len;
    if (++inputs % 1000000u == 0) { /* a count that survives an interrupted run */
        fprintf(stderr, "spiel_fuzz: inputs %llu so far\n", inputs);
    }
    if (size < 4) {
        return 0;
    }
    mode = data[0];
    read_step = data[1];
    tx_budget = (mode & 4u) ? (size_t)data[3] + 1u : 0u;
    flash_fail_at = data[2] == 0xFF ? 0xFFFFFFFFu : data[2];
    step_us = 50u + 997u * (data[3] & 0x3Fu); /* 50 us .. 63 ms per poll */
    body = data + 4;
    body_len = size - 4;
    boot((mode & 2u) ? flash_seeded : flash_erased);
    if (mode & 1u) {
        body_len = frame_records(body, body_len);
        body = framed;
    }
    in_input = 1;
    if (setjmp(reset_jump) == 0) {
        feed(body, body_len, step_us);
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
