/* image_posix.c - the posix target's firmware image areas (PROTOCOL.md 14.3) in one folder
 * (--images DIR), with NOR flash rules checked on every call: slot0.img and slot1.img (4 MiB
 * each), boot.rec (the boot record area, two sectors) and exec.img (the execution region the
 * boot stage copies the chosen image into, flash to flash: header sector, then the body).
 * Sectors of 4 KiB; erase sets 0xFF in whole sectors; a write covers whole program units
 * (--program-unit N, default 8 as on ECC flash) of erased bytes only, and fails otherwise.
 * A file that does not exist reads as erased.
 * The boot stage (posix_image_boot) runs boot_start(): the record updated, the image installed
 * in exec.img, and for a trial the watchdog started; then the installed body is written to
 * DIR/run<N> and executed in place of the loader with SPIEL_FW_SLOT=N (a reset executes the
 * loader again: SPIEL_FW_LOADER).
 * The watchdog: the loader forks before a trial; the parent (the process the test started:
 * its death is the board's power going) watches a pipe that the image kicks, and when no kick
 * comes in time it kills the image and executes the loader again: a reset, with no power
 * cycle. A reset the image asks for goes through the same parent.
 * Fault injection: --image-cut N kills the board (SIGKILL) in the middle of the N-th image
 * operation (0-based: each erase and write, counted since power-on in DIR/.image_ops; half of
 * a write or an erase done). */
#define _POSIX_C_SOURCE 200809L
#define _DEFAULT_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <limits.h>
#include <poll.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/prctl.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>

#include "spiel_boot.h"
#include "posix_hal.h"

#if SPIEL_FW_UPDATE

#define IMAGE_SLOT_SIZE (4u * 1024u * 1024u)
#define SECTOR 4096u
#define RECORD_AREA (2u * SECTOR)

static char dir[PATH_MAX - 32];
static long image_cut = -1;
static int running = -1;
static uint32_t unit = 8;
static int wdt_fd = -1; /* the image's end of the watchdog pipe */

static void area_path(int slot, char *out, size_t cap)
{
    if (slot == SPIEL_IMAGE_RECORD) {
        snprintf(out, cap, "%s/boot.rec", dir);
    } else if (slot == SPIEL_IMAGE_EXEC) {
        snprintf(out, cap, "%s/exec.img", dir);
    } else {
        snprintf(out, cap, "%s/slot%d.img", dir, slot);
    }
}

static uint32_t area_size(int slot)
{
    return slot == SPIEL_IMAGE_RECORD ? RECORD_AREA
           : slot == SPIEL_IMAGE_EXEC ? SECTOR + IMAGE_SLOT_SIZE
                                      : IMAGE_SLOT_SIZE;
}

static int area_ok(int slot, uint32_t offset, uint32_t len)
{
    return dir[0] && slot >= 0 && slot <= SPIEL_IMAGE_EXEC && offset <= area_size(slot) &&
           len <= area_size(slot) - offset;
}

/* Count one operation (persistently, since power-on); 1 when this one is to be cut. */
static int operation(void)
{
    char path[PATH_MAX];
    long ops = 0;
    int fd;
    snprintf(path, sizeof path, "%s/.image_ops", dir);
    fd = open(path, O_RDWR | O_CREAT | O_CLOEXEC, 0644);
    if (fd < 0) {
        return 0;
    }
    if (pread(fd, &ops, sizeof ops, 0) != (ssize_t)sizeof ops) {
        ops = 0;
    }
    ops++;
    if (pwrite(fd, &ops, sizeof ops, 0) != (ssize_t)sizeof ops) {
        perror("image ops");
    }
    close(fd);
    return ops - 1 == image_cut;
}

/* --image-cut: the board loses power: the whole board, the watchdog's parent included */
static void power_cut(void)
{
    if (wdt_fd >= 0) {
        kill(getppid(), SIGKILL);
    }
    raise(SIGKILL);
}

static int put(int slot, uint32_t offset, const uint8_t *data, uint32_t len)
{
    char path[PATH_MAX];
    int fd, ok;
    area_path(slot, path, sizeof path);
    fd = open(path, O_WRONLY | O_CREAT | O_CLOEXEC, 0644);
    if (fd < 0) {
        return -1;
    }
    /* no fsync: a power cut here is a SIGKILL, and the page cache outlives the process */
    ok = pwrite(fd, data, len, offset) == (ssize_t)len;
    close(fd);
    return ok ? 0 : -1;
}

int posix_image_open(const char *images, long cut, uint32_t program_unit)
{
    struct stat sb;
    if (stat(images, &sb) != 0 || !S_ISDIR(sb.st_mode) || strlen(images) >= sizeof dir) {
        fprintf(stderr, "%s: not a folder\n", images);
        return -1;
    }
    if (program_unit == 0 || program_unit > SPIEL_FW_UNIT_MAX ||
        (program_unit & (program_unit - 1u)) != 0) {
        fprintf(stderr, "--program-unit must be a power of two, 1..%u\n", SPIEL_FW_UNIT_MAX);
        return -1;
    }
    snprintf(dir, sizeof dir, "%s", images);
    image_cut = cut;
    unit = program_unit;
    if (getenv("SPIEL_FW_POWERED") == NULL) { /* power-on: the operation count starts at 0 */
        char path[PATH_MAX];
        snprintf(path, sizeof path, "%s/.image_ops", dir);
        unlink(path);
        setenv("SPIEL_FW_POWERED", "1", 1);
    }
    if (getenv("SPIEL_FW_WDT_FD") != NULL) {
        wdt_fd = atoi(getenv("SPIEL_FW_WDT_FD"));
    }
    return 0;
}

uint32_t hal_image_slot_size(void)
{
    return dir[0] ? IMAGE_SLOT_SIZE : 0u;
}

uint32_t hal_image_sector_size(void)
{
    return SECTOR;
}

uint32_t hal_image_program_unit(void)
{
    return unit;
}

int hal_image_running(void)
{
    return running;
}

int hal_image_erase(int slot, uint32_t offset, uint32_t len)
{
    static uint8_t ff[SECTOR];
    uint32_t at;
    if (!area_ok(slot, offset, len) || offset % SECTOR != 0 || len % SECTOR != 0) {
        return -1;
    }
    memset(ff, 0xFF, sizeof ff);
    if (operation()) { /* half of the first sector erased */
        put(slot, offset, ff, SECTOR / 2u);
        power_cut();
    }
    for (at = offset; at < offset + len; at += SECTOR) {
        if (put(slot, at, ff, SECTOR) != 0) {
            return -1;
        }
    }
    return 0;
}

int hal_image_read(int slot, uint32_t offset, uint8_t *data, uint32_t len)
{
    char path[PATH_MAX];
    int fd;
    ssize_t n;
    if (!area_ok(slot, offset, len)) {
        return -1;
    }
    memset(data, 0xFF, len);
    area_path(slot, path, sizeof path);
    fd = open(path, O_RDONLY | O_CLOEXEC);
    if (fd < 0) {
        return 0; /* never written: erased */
    }
    n = pread(fd, data, len, offset);
    close(fd);
    if (n < 0) {
        return -1;
    }
    if ((uint32_t)n < len) {
        memset(data + n, 0xFF, len - (uint32_t)n);
    }
    return 0;
}

int hal_image_write(int slot, uint32_t offset, const uint8_t *data, uint32_t len)
{
    static uint8_t old[64 * 1024];
    uint32_t i;
    if (!area_ok(slot, offset, len) || len > sizeof old || offset % unit != 0 ||
        len % unit != 0 || hal_image_read(slot, offset, old, len) != 0) {
        return -1;
    }
    for (i = 0; i < len; i++) {
        if (old[i] != 0xFF) { /* ECC flash: a unit is programmed once after its erase */
            fprintf(stderr, "spiel_fw_posix: area %d offset %u programmed twice\n", slot,
                    (unsigned)(offset + i));
            return -1;
        }
    }
    if (operation()) {
        put(slot, offset, data, len / 2u);
        power_cut();
    }
    return put(slot, offset, data, len);
}

/* ---- the watchdog ------------------------------------------------------------------------ */

static uint64_t ms_now(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (uint64_t)ts.tv_sec * 1000u + (uint64_t)ts.tv_nsec / 1000000u;
}

static char **loader_argv;

static void reexec_loader(void)
{
    const char *loader = getenv("SPIEL_FW_LOADER");
    unsetenv("SPIEL_FW_SLOT");
    unsetenv("SPIEL_FW_WDT_FD");
    execv(loader != NULL ? loader : "/proc/self/exe", loader_argv);
    perror("re-exec");
    exit(1);
}

/* The parent's side: until the image resets (a byte 'R'), dies, or stops kicking. */
static void watch(pid_t child, int rfd, uint32_t timeout_ms)
{
    uint64_t deadline = ms_now() + timeout_ms;
    for (;;) {
        struct pollfd p = {rfd, POLLIN, 0};
        uint64_t now = ms_now();
        int status = 0;
        char c;
        ssize_t n;
        if (now >= deadline) {
            fprintf(stderr, "spiel_fw_posix: watchdog: no kick for %u ms: reset\n",
                    (unsigned)timeout_ms);
            kill(child, SIGKILL);
            waitpid(child, &status, 0);
            close(rfd);
            reexec_loader();
        }
        if (poll(&p, 1, (int)(deadline - now)) <= 0) {
            continue;
        }
        n = read(rfd, &c, 1);
        if (n == 1 && c == 'K') {
            deadline = ms_now() + timeout_ms;
            continue;
        }
        if (n < 0 && errno == EINTR) {
            continue;
        }
        waitpid(child, &status, 0);
        close(rfd);
        if (WIFEXITED(status) && WEXITSTATUS(status) == 3 && !(n == 1 && c == 'R')) {
            exit(3); /* REBOOT to the bootloader: this target has none */
        }
        /* hal_reset in the image, or the image crashed or ended: a reset, as a fault handler
         * (or the watchdog) resets a board */
        if (!(n == 1 && c == 'R')) {
            fprintf(stderr, "spiel_fw_posix: the image ended (status %d): reset\n", status);
        }
        reexec_loader();
    }
}

void hal_watchdog_start(uint32_t timeout_ms)
{
    int fds[2];
    pid_t child;
    char num[16];
    if (pipe(fds) != 0) {
        perror("watchdog");
        return;
    }
    fflush(stdout);
    child = fork();
    if (child < 0) {
        perror("watchdog");
        close(fds[0]);
        close(fds[1]);
        return;
    }
    if (child > 0) {
        close(fds[1]);
        fcntl(fds[0], F_SETFD, FD_CLOEXEC);
        watch(child, fds[0], timeout_ms); /* does not return */
    }
    close(fds[0]);
    prctl(PR_SET_PDEATHSIG, SIGKILL); /* the board's power is the parent */
    snprintf(num, sizeof num, "%d", fds[1]);
    setenv("SPIEL_FW_WDT_FD", num, 1);
    wdt_fd = fds[1];
}

void hal_watchdog_kick(void)
{
    static uint64_t last;
    uint64_t now;
    if (wdt_fd < 0) {
        return;
    }
    now = ms_now();
    if (now - last >= 50u) {
        if (write(wdt_fd, "K", 1) != 1) {
            wdt_fd = -1;
        }
        last = now;
    }
}

/* A reset of an image started under the watchdog goes through its parent. */
void posix_image_reset(void)
{
    if (wdt_fd >= 0) {
        if (write(wdt_fd, "R", 1) == 1) {
            _exit(0);
        }
    }
}

/* ---- the boot stage ------------------------------------------------------------------------ */

/* Choose and install a slot, start the watchdog for a trial, and execute the installed body;
 * returns only when no slot holds a bootable image (the caller runs as the recovery loader)
 * or exec failed. */
void posix_image_boot(char **argv, uint32_t watchdog_ms)
{
    char path[PATH_MAX], tmp[PATH_MAX], self[PATH_MAX], num[16];
    uint8_t buf[4096];
    uint8_t head[SP_IMAGE_HEADER_SIZE];
    sp_image_header_t h;
    uint32_t off;
    ssize_t n;
    int fd, slot;
    loader_argv = argv;
    n = readlink("/proc/self/exe", self, sizeof self - 1);
    if (n > 0 && getenv("SPIEL_FW_LOADER") == NULL) {
        self[n] = 0;
        setenv("SPIEL_FW_LOADER", self, 1);
    }
    slot = boot_start(watchdog_ms);
    if (slot < 0) {
        fprintf(stderr, "spiel_fw_posix: no bootable image: recovery loader\n");
        return;
    }
    if (hal_image_read(SPIEL_IMAGE_EXEC, 0, head, sizeof head) != 0) { /* else head is unset */
        fprintf(stderr, "spiel_fw_posix: execution region unreadable: recovery loader\n");
        return;
    }
    sp_image_header_unpack(head, &h);
    snprintf(path, sizeof path, "%s/run%d", dir, slot);
    snprintf(tmp, sizeof tmp, "%s/run%d.tmp", dir, slot);
    fd = open(tmp, O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0755);
    if (fd < 0) {
        perror(tmp);
        return;
    }
    for (off = 0; off < h.body_size; off += (uint32_t)n) {
        uint32_t want = h.body_size - off < sizeof buf ? h.body_size - off : (uint32_t)sizeof buf;
        if (hal_image_read(SPIEL_IMAGE_EXEC, SECTOR + off, buf, want) != 0 ||
            (n = write(fd, buf, want)) != (ssize_t)want) {
            perror(tmp);
            close(fd);
            return;
        }
    }
    close(fd);
    if (rename(tmp, path) != 0) {
        perror(path);
        return;
    }
    snprintf(num, sizeof num, "%d", slot);
    setenv("SPIEL_FW_SLOT", num, 1);
    execv(path, argv);
    perror(path);
}

/* After the jump: the running slot and its version text (NUL-terminated, at most 16). */
int posix_image_started(char version[17])
{
    const char *s = getenv("SPIEL_FW_SLOT");
    uint8_t head[SP_IMAGE_HEADER_SIZE];
    sp_image_header_t h;
    running = s ? atoi(s) : -1;
    if (running < 0 || running > 1) {
        running = -1;
        snprintf(version, 17, "recovery");
        return -1;
    }
    if (hal_image_read(running, 0, head, sizeof head) != 0) { /* else head is unset */
        snprintf(version, 17, "unknown");
        return running;
    }
    sp_image_header_unpack(head, &h);
    memcpy(version, h.version, 16);
    version[16] = 0;
    return running;
}

#else
void posix_image_reset(void)
{
}
#endif /* SPIEL_FW_UPDATE */
