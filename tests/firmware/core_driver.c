/* Test driver of the portable firmware core (firmware_protocol/firmware/core) with an
 * in-memory HAL: the test feeds request bytes and sets the clock; the driver prints what the
 * device wrote. Commands on stdin, one per line; every command prints exactly one line:
 *   scans <path>       A-scans file (tools/release/firmware_scans.py)     -> ok | error ...
 *   init               power on (spiel_device_init); flash kept  -> ok
 *   time <us>          set the clock                              -> ok
 *   feed <hex>         give the bytes to the transport, poll until the device is idle
 *                                                                 -> out <hex of all it wrote>
 *   poll <n>           poll n times                               -> out <hex>
 *   stats              -> stats frames crc cobs length oversize version flags requests repeated
 *                               acquisitions_sent frames_sent overruns flash_errors
 *   flashfail <k>      the k-th flash operation from now fails    -> ok
 *   acqfail <k>        the k-th hal_acq_read from now fails        -> ok
 * An empty hex string is "-". hal_reset prints nothing and re-initialises (flash kept).
 */
#include <setjmp.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "spiel_device.h"
#include "spiel_hal.h"

#define MAX_IN (1u << 16)
#define MAX_OUT (1u << 22)
#define MAX_SCANS (1u << 21)
#define FLASH_SIZE 8192u

static char line[2 * MAX_IN + 64];
static uint8_t in_buf[MAX_IN];
static size_t in_len, in_pos;
static uint8_t out_buf[MAX_OUT];
static size_t out_len;
static uint8_t scans[MAX_SCANS];
static uint16_t n_ch, n_s;
static uint32_t n_acq, rate, cursor;
static const uint8_t *current;
static uint8_t flash[FLASH_SIZE];
static long flash_ops, flash_fail = -1;
static long acq_reads, acq_fail = -1;
static uint64_t now_us;
static uint32_t rng = 12345u;
static hal_board_info_t info;
static jmp_buf on_reset;

size_t hal_transport_read(uint8_t *buf, size_t cap)
{
    size_t n = in_len - in_pos < cap ? in_len - in_pos : cap;
    memcpy(buf, in_buf + in_pos, n);
    in_pos += n;
    return n;
}

size_t hal_transport_write(const uint8_t *buf, size_t len)
{
    if (out_len + len > MAX_OUT) {
        len = MAX_OUT - out_len;
    }
    memcpy(out_buf + out_len, buf, len);
    out_len += len;
    return len;
}

uint64_t hal_time_us(void) { return now_us; }

int hal_acq_trigger(uint32_t mask, uint16_t n)
{
    if (n > n_s || mask == 0 || (mask >> n_ch) != 0 || n_acq == 0) {
        return -1;
    }
    current = scans + 20 + (size_t)cursor * n_ch * n_s * 2u;
    cursor = (cursor + 1) % n_acq;
    return 0;
}

int hal_acq_ready(void) { return current != NULL; }

int hal_acq_read(uint8_t ch, uint16_t *samples, uint16_t n)
{
    uint16_t i;
    const uint8_t *row = current + (size_t)ch * n_s * 2u;
    if (acq_reads++ == acq_fail) {
        return -1;
    }
    for (i = 0; i < n; i++) {
        samples[i] = (uint16_t)(row[2 * i] | (row[2 * i + 1] << 8));
    }
    return 0;
}

uint32_t hal_flash_size(void) { return FLASH_SIZE; }
uint32_t hal_flash_sector_size(void) { return 4096u; }

static int op(void) { return flash_ops++ == flash_fail ? -1 : 0; }

int hal_flash_erase(uint32_t addr, uint32_t len)
{
    if (addr > FLASH_SIZE || len > FLASH_SIZE - addr || op()) {
        return -1;
    }
    memset(flash + addr, 0xFF, len);
    return 0;
}

int hal_flash_write(uint32_t addr, const uint8_t *data, uint32_t len)
{
    uint32_t i;
    if (addr > FLASH_SIZE || len > FLASH_SIZE - addr || op()) {
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
    longjmp(on_reset, 1);
}

uint32_t hal_random(void)
{
    rng = rng * 1103515245u + 12345u;
    return rng;
}

#if SPIEL_FW_UPDATE
/* Firmware image areas in memory (-DSPIEL_FW_UPDATE=1): two erased 64 KiB slots, the boot
 * record area, slot 0 named as the one running (as on the virtual board), NOR rules
 * (whole sectors erased, program units of erased bytes only). The watchdog is not started. */
#define IMG_SECTOR 4096u
#define IMG_SLOT (16u * IMG_SECTOR)
#define IMG_UNIT 8u
static uint8_t images[3][IMG_SLOT];
static int images_ready;

static uint8_t *image_area(int slot, uint32_t offset, uint32_t len)
{
    uint32_t size = slot == SPIEL_IMAGE_RECORD ? 2u * IMG_SECTOR : IMG_SLOT;
    if (!images_ready) {
        memset(images, 0xFF, sizeof images);
        images_ready = 1;
    }
    if (slot < 0 || slot > SPIEL_IMAGE_RECORD || offset > size || len > size - offset) {
        return NULL;
    }
    return images[slot] + offset;
}

uint32_t hal_image_slot_size(void) { return IMG_SLOT; }
uint32_t hal_image_sector_size(void) { return IMG_SECTOR; }
uint32_t hal_image_program_unit(void) { return IMG_UNIT; }
int hal_image_running(void) { return 0; }
void hal_watchdog_start(uint32_t timeout_ms) { (void)timeout_ms; }
void hal_watchdog_kick(void) {}

int hal_image_erase(int slot, uint32_t offset, uint32_t len)
{
    uint8_t *area = image_area(slot, offset, len);
    if (area == NULL || offset % IMG_SECTOR || len % IMG_SECTOR) {
        return -1;
    }
    memset(area, 0xFF, len);
    return 0;
}

int hal_image_write(int slot, uint32_t offset, const uint8_t *data, uint32_t len)
{
    uint8_t *area = image_area(slot, offset, len);
    uint32_t i;
    if (area == NULL || offset % IMG_UNIT || len % IMG_UNIT) {
        return -1;
    }
    for (i = 0; i < len; i++) {
        if (area[i] != 0xFF) {
            return -1;
        }
        area[i] = data[i];
    }
    return 0;
}

int hal_image_read(int slot, uint32_t offset, uint8_t *data, uint32_t len)
{
    const uint8_t *area = image_area(slot, offset, len);
    if (area == NULL) {
        return -1;
    }
    memcpy(data, area, len);
    return 0;
}
#endif

const hal_board_info_t *hal_board_info(void) { return &info; }
int16_t hal_temperature_cdeg(void) { return 2000; }
void hal_apply_settings(const hal_settings_t *s) { (void)s; }

static size_t parse_hex(const char *s, uint8_t *dst, size_t cap)
{
    size_t n = 0;
    if (strcmp(s, "-") == 0) {
        return 0;
    }
    while (s[0] && s[1] && s[0] != '\n' && n < cap) {
        unsigned v;
        if (sscanf(s, "%2x", &v) != 1) {
            break;
        }
        dst[n++] = (uint8_t)v;
        s += 2;
    }
    return n;
}

static void print_out(void)
{
    size_t i;
    fputs("out ", stdout);
    if (out_len == 0) {
        fputs("-", stdout);
    }
    for (i = 0; i < out_len; i++) {
        printf("%02x", out_buf[i]);
    }
    fputs("\n", stdout);
    out_len = 0;
}

static int load_scans(const char *path)
{
    FILE *f = fopen(path, "rb");
    size_t n;
    if (!f) {
        return -1;
    }
    n = fread(scans, 1, sizeof scans, f);
    fclose(f);
    if (n < 20 || memcmp(scans, "SPAS", 4) != 0) {
        return -1;
    }
    n_ch = (uint16_t)(scans[6] | scans[7] << 8);
    n_s = (uint16_t)(scans[8] | scans[9] << 8);
    n_acq = (uint32_t)scans[12] | (uint32_t)scans[13] << 8 | (uint32_t)scans[14] << 16 |
            (uint32_t)scans[15] << 24;
    rate = (uint32_t)scans[16] | (uint32_t)scans[17] << 8 | (uint32_t)scans[18] << 16 |
           (uint32_t)scans[19] << 24;
    if (20u + (size_t)n_acq * n_ch * n_s * 2u > n) {
        return -1;
    }
    info.firmware_version = "1.0.0+driver";
    info.serial = "DRIVER0001";
    info.board_name = "spiel-driver";
    info.usb_vid = 0x1209;
    info.usb_pid = 0x0001;
    info.hw_revision = 1;
    info.n_channels = (uint8_t)n_ch;
    info.emitter_channel = 0;
    info.adc_bits = 16;
    info.max_samples = n_s;
    info.emitter_freq_hz = 175000;
    info.max_sample_rate_hz = 100000;
    info.default_n_samples = n_s;
    info.default_sample_rate_hz = rate;
    return 0;
}

static void boot(void)
{
    current = NULL;
    cursor = 0;
    in_len = in_pos = 0;
    spiel_device_init();
}

int main(void)
{
    memset(flash, 0xFF, sizeof flash);
    while (fgets(line, sizeof line, stdin)) {
        char *arg = strchr(line, ' ');
        if (arg) {
            *arg++ = 0;
        } else {
            line[strcspn(line, "\n")] = 0;
        }
        if (setjmp(on_reset)) { /* hal_reset during this command: power on again */
            boot();
            print_out();
            fflush(stdout);
            continue;
        }
        if (strcmp(line, "scans") == 0) {
            arg[strcspn(arg, "\n")] = 0;
            puts(load_scans(arg) == 0 ? "ok" : "error scans");
        } else if (strcmp(line, "init") == 0) {
            boot();
            puts("ok");
        } else if (strcmp(line, "time") == 0) {
            now_us = strtoull(arg, NULL, 10);
            puts("ok");
        } else if (strcmp(line, "flashfail") == 0) {
            flash_fail = flash_ops + strtol(arg, NULL, 10);
            puts("ok");
        } else if (strcmp(line, "acqfail") == 0) {
            acq_fail = acq_reads + strtol(arg, NULL, 10);
            puts("ok");
        } else if (strcmp(line, "feed") == 0) {
            int idle = 0, guard = 0;
            in_len = parse_hex(arg, in_buf, sizeof in_buf);
            in_pos = 0;
            while (guard++ < 1000000 && idle < 2) { /* idle twice: nothing left to do now */
                size_t before = out_len, pos = in_pos;
                spiel_device_poll();
                idle = (out_len == before && in_pos == pos) ? idle + 1 : 0;
            }
            print_out();
        } else if (strcmp(line, "poll") == 0) {
            long k, n = strtol(arg, NULL, 10);
            for (k = 0; k < n; k++) {
                spiel_device_poll();
            }
            print_out();
        } else if (strcmp(line, "stats") == 0) {
            const spiel_device_stats_t *s = spiel_device_stats();
            printf("stats %u %u %u %u %u %u %u %u %u %u %u %u %u\n", s->rx.frames, s->rx.crc,
                   s->rx.cobs, s->rx.length, s->rx.oversize, s->rx.version, s->rx.flags,
                   s->requests, s->repeated, s->acquisitions_sent, s->frames_sent, s->overruns,
                   s->flash_errors);
        } else {
            puts("error unknown command");
        }
        fflush(stdout);
    }
    return 0;
}
