/* hal_posix.c - the HAL on Linux: a file of A-scans, a flash file, a pty or stdio. */
#define _POSIX_C_SOURCE 200809L
#define _DEFAULT_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <poll.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <time.h>
#include <unistd.h>

#include "posix_hal.h"
#include "spiel_proto.h"

#define SCANS_MAGIC "SPAS"
#define SCANS_HEADER 20u
#define FLASH_SIZE 8192u
#define FLASH_SECTOR 4096u

static const uint8_t *scan_data; /* mapped scans file */
static uint32_t n_acq, cursor;
static uint16_t n_channels, n_samples;
static uint32_t sample_rate;
static uint32_t trigger_mask;
static uint16_t trigger_samples;
static const uint8_t *current; /* the acquisition last triggered */
static int current_read;       /* a channel of it was read */
static int flash_fd = -1;
static int in_fd, out_fd;
static int out_blocked;
static long flash_cut = -1, flash_fail = -1, flash_ops;
static char **saved_argv;
static uint64_t boot_ns;
static hal_board_info_t info;
static char serial_buf[17];

static uint64_t now_ns(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (uint64_t)ts.tv_sec * 1000000000u + (uint64_t)ts.tv_nsec;
}

int posix_hal_open(const char *scans, const char *flash, const char *serial, int in, int out,
                   long cut, long fail, char **argv)
{
    struct stat sb;
    int fd = open(scans, O_RDONLY | O_CLOEXEC);
    const uint8_t *p;
    if (fd < 0 || fstat(fd, &sb) != 0) {
        fprintf(stderr, "%s: %s\n", scans, strerror(errno));
        return -1;
    }
    if ((size_t)sb.st_size < SCANS_HEADER) {
        fprintf(stderr, "%s: not a scans file (too short)\n", scans);
        return -1;
    }
    p = mmap(NULL, (size_t)sb.st_size, PROT_READ, MAP_PRIVATE, fd, 0);
    close(fd);
    if (p == MAP_FAILED) {
        fprintf(stderr, "%s: %s\n", scans, strerror(errno));
        return -1;
    }
    n_channels = sp_le_get_u16(p + 6);
    n_samples = sp_le_get_u16(p + 8);
    n_acq = sp_le_get_u32(p + 12);
    sample_rate = sp_le_get_u32(p + 16);
    if (memcmp(p, SCANS_MAGIC, 4) != 0 || sp_le_get_u16(p + 4) != 1 || n_channels == 0 ||
        n_channels > 32 || n_samples == 0 || n_acq == 0 ||
        (uint64_t)sb.st_size != SCANS_HEADER + (uint64_t)n_acq * n_channels * n_samples * 2u) {
        fprintf(stderr, "%s: not a version-1 scans file or its size does not match\n", scans);
        return -1;
    }
    scan_data = p + SCANS_HEADER;
    flash_fd = open(flash, O_RDWR | O_CREAT | O_CLOEXEC, 0644);
    if (flash_fd < 0 || fstat(flash_fd, &sb) != 0) {
        fprintf(stderr, "%s: %s\n", flash, strerror(errno));
        return -1;
    }
    if ((uint64_t)sb.st_size < FLASH_SIZE) { /* a new flash is erased (all 0xFF) */
        uint8_t ff[256];
        off_t at;
        memset(ff, 0xFF, sizeof ff);
        for (at = sb.st_size; at < (off_t)FLASH_SIZE; at += (off_t)sizeof ff) {
            if (pwrite(flash_fd, ff, sizeof ff, at) != (ssize_t)sizeof ff) {
                fprintf(stderr, "%s: %s\n", flash, strerror(errno));
                return -1;
            }
        }
    }
    in_fd = in;
    out_fd = out;
    fcntl(in_fd, F_SETFL, fcntl(in_fd, F_GETFL) | O_NONBLOCK);
    fcntl(out_fd, F_SETFL, fcntl(out_fd, F_GETFL) | O_NONBLOCK);
    flash_cut = cut;
    flash_fail = fail;
    saved_argv = argv;
    boot_ns = now_ns();
    snprintf(serial_buf, sizeof serial_buf, "%s", serial);
    info.firmware_version = "1.0.0+posix";
    info.serial = serial_buf;
    info.board_name = "spiel-posix";
    info.usb_vid = 0x1209;
    info.usb_pid = 0x0001;
    info.hw_revision = 1;
    info.n_channels = (uint8_t)n_channels;
    info.emitter_channel = 0;
    info.adc_bits = 16;
    info.max_samples = n_samples;
    info.emitter_freq_hz = 175000;
    info.max_sample_rate_hz = 100000;
    info.default_n_samples = n_samples;
    info.default_sample_rate_hz = sample_rate;
    return 0;
}

void posix_hal_wait(uint32_t us)
{
    struct pollfd pfd[2];
    int n = 1;
    pfd[0].fd = in_fd;
    pfd[0].events = POLLIN;
    pfd[0].revents = 0;
    if (out_blocked) { /* a frame waits for room: wake when the host has read some (the core
                          * reads no request before that frame is out, so not on input) */
        if (out_fd == in_fd) {
            pfd[0].events = POLLOUT;
        } else {
            pfd[1].fd = out_fd;
            pfd[1].events = POLLOUT;
            pfd[1].revents = 0;
            n = 2;
        }
        if (us == 0 || us > 5000u) {
            us = 5000u;
        }
    }
    if (us == 0) {
        return;
    }
    /* poll counts whole milliseconds: rounded up, a pulse due in 0.3 ms fired up to 1 ms late
     * (a stream started at a time of the board's clock missed its slot). Whole milliseconds
     * wait in poll (input wakes it), the last one in nanosleep once nothing is pending. */
    if (poll(pfd, (nfds_t)n, (int)(us / 1000u)) > 0) {
        if (pfd[0].revents & (POLLHUP | POLLERR)) {
            usleep(1000); /* nobody has the pty open: do not spin */
        }
        return;
    }
    if (us < 1000u) {
        struct timespec rest;
        rest.tv_sec = 0;
        rest.tv_nsec = (long)us * 1000L;
        nanosleep(&rest, NULL);
    }
}

/* ---- transport ---------------------------------------------------------------------------- */

size_t hal_transport_read(uint8_t *buf, size_t cap)
{
    ssize_t n = read(in_fd, buf, cap);
    if (n == 0 && in_fd == 0) {
        exit(0); /* stdin closed: the host is gone */
    }
    return n > 0 ? (size_t)n : 0;
}

size_t hal_transport_write(const uint8_t *buf, size_t len)
{
    ssize_t n = write(out_fd, buf, len);
    out_blocked = n < (ssize_t)len; /* the pty (or pipe) is full: the host is not reading */
    return n > 0 ? (size_t)n : 0;
}

uint64_t hal_time_us(void)
{
    return (now_ns() - boot_ns) / 1000u;
}

/* ---- measurement -------------------------------------------------------------------------- */

static int no_sensor;

void posix_hal_no_sensor(void)
{
    no_sensor = 1;
}

int hal_acq_trigger(uint32_t channel_mask, uint16_t samples)
{
    if (no_sensor) {
        return -1; /* --no-sensor: nothing answers */
    }
    /* no shift by 32 (undefined; x86 shifts by 0 and refused every trigger of 32 channels) */
    if (samples > n_samples || channel_mask == 0 ||
        (n_channels < 32 && (channel_mask >> n_channels) != 0)) {
        return -1;
    }
    trigger_mask = channel_mask;
    trigger_samples = samples;
    if (current != NULL && current_read) {
        cursor = (cursor + 1) % n_acq; /* the recordings in order, looped */
    }
    /* an acquisition triggered but never read (a STREAM_STOP came first) is measured again:
     * every recording reaches the host once, in order */
    current = scan_data + (size_t)cursor * n_channels * n_samples * 2u;
    current_read = 0;
    return 0;
}

int hal_acq_ready(void)
{
    return current != NULL;
}

int hal_acq_read(uint8_t channel, uint16_t *samples, uint16_t n)
{
    uint16_t i;
    const uint8_t *row;
    if (current == NULL || channel >= n_channels || !(trigger_mask & (1u << channel)) ||
        n > trigger_samples) {
        return -1;
    }
    row = current + (size_t)channel * n_samples * 2u;
    current_read = 1;
    for (i = 0; i < n; i++) {
        samples[i] = sp_le_get_u16(row + 2u * i);
    }
    return 0;
}

#if SPIEL_IQ_SAMPLES
/* I/Q of a recording that holds envelopes only: the amplitude as i, q = 0 (phase 0). A front
 * end with real I/Q (SonicLib's ch_get_iq_data) fills both. */
int hal_acq_read_iq(uint8_t channel, uint16_t *qi, uint16_t n)
{
    uint16_t i;
    if (2u * (uint32_t)n > 8192u || hal_acq_read(channel, qi + n, n) != 0) {
        return -1;
    }
    for (i = 0; i < n; i++) {
        uint16_t a = qi[n + i];
        qi[2u * i] = 0;                                 /* q */
        qi[2u * i + 1u] = a > 32767u ? 32767u : a;      /* i */
    }
    return 0;
}
#endif

/* ---- flash -------------------------------------------------------------------------------- */

uint32_t hal_flash_size(void)
{
    return FLASH_SIZE;
}

uint32_t hal_flash_sector_size(void)
{
    return FLASH_SECTOR;
}

/* Fault injection: 1 when this operation is to fail, and the power cut (half done, then
 * SIGKILL) when it is the one to be cut. */
static int operation(uint32_t addr, const uint8_t *data, uint32_t len, int erase)
{
    long op = flash_ops++;
    if (op == flash_fail) {
        return 1;
    }
    if (op == flash_cut) {
        uint8_t buf[FLASH_SECTOR];
        uint32_t half = len / 2, i;
        if (pread(flash_fd, buf, half, addr) == (ssize_t)half) {
            for (i = 0; i < half; i++) {
                buf[i] = erase ? 0xFF : (uint8_t)(buf[i] & data[i]);
            }
            if (pwrite(flash_fd, buf, half, addr) != (ssize_t)half) {
                perror("flash");
            }
        }
        fsync(flash_fd);
        raise(SIGKILL);
    }
    return 0;
}

static int in_range(uint32_t addr, uint32_t len)
{
    return addr <= FLASH_SIZE && len <= FLASH_SIZE - addr;
}

int hal_flash_erase(uint32_t addr, uint32_t len)
{
    uint8_t ff[FLASH_SECTOR];
    uint32_t at;
    if (!in_range(addr, len) || addr % FLASH_SECTOR || len % FLASH_SECTOR) {
        return -1;
    }
    if (operation(addr, NULL, len > FLASH_SECTOR ? FLASH_SECTOR : len, 1)) {
        return -1;
    }
    memset(ff, 0xFF, sizeof ff);
    for (at = addr; at < addr + len; at += FLASH_SECTOR) {
        if (pwrite(flash_fd, ff, FLASH_SECTOR, at) != (ssize_t)FLASH_SECTOR) {
            return -1;
        }
    }
    return 0;
}

int hal_flash_write(uint32_t addr, const uint8_t *data, uint32_t len)
{
    uint8_t buf[FLASH_SECTOR];
    uint32_t i;
    if (!in_range(addr, len) || len > sizeof buf) {
        return -1;
    }
    if (operation(addr, data, len, 0)) {
        return -1;
    }
    if (pread(flash_fd, buf, len, addr) != (ssize_t)len) {
        return -1;
    }
    for (i = 0; i < len; i++) {
        buf[i] &= data[i]; /* NOR flash: programming only clears bits */
    }
    return pwrite(flash_fd, buf, len, addr) == (ssize_t)len ? 0 : -1;
}

int hal_flash_read(uint32_t addr, uint8_t *data, uint32_t len)
{
    if (!in_range(addr, len)) {
        return -1;
    }
    return pread(flash_fd, data, len, addr) == (ssize_t)len ? 0 : -1;
}

/* ---- system ------------------------------------------------------------------------------- */

void posix_hal_set_firmware_version(const char *version)
{
    info.firmware_version = version;
}

void hal_reset(int to_bootloader)
{
    char fd[16];
    const char *loader = getenv("SPIEL_FW_LOADER"); /* an image booted by the bootloader */
    if (to_bootloader) {
        fprintf(stderr, "spiel_fw_posix: reset to the bootloader (none in this target): exit\n");
        exit(3);
    }
    snprintf(fd, sizeof fd, "%d", in_fd);
    if (in_fd != 0) {
        setenv("SPIEL_FW_PTY_FD", fd, 1);
    }
    fsync(flash_fd);
    unsetenv("SPIEL_FW_SLOT"); /* a reset runs the bootloader again, which chooses */
    posix_image_reset();       /* under the watchdog: its parent executes the loader */
    execv(loader != NULL ? loader : "/proc/self/exe", saved_argv);
    perror("re-exec");
    exit(1);
}

uint32_t hal_random(void)
{
    uint32_t v = 0;
    int fd = open("/dev/urandom", O_RDONLY);
    if (fd >= 0) {
        if (read(fd, &v, sizeof v) != (ssize_t)sizeof v) {
            v = 0;
        }
        close(fd);
    }
    return v ^ (uint32_t)now_ns();
}

const hal_board_info_t *hal_board_info(void)
{
    return &info;
}

int16_t hal_temperature_cdeg(void)
{
    return 2000;
}

void hal_apply_settings(const hal_settings_t *settings)
{
    (void)settings; /* recordings have one sample rate and length */
}
