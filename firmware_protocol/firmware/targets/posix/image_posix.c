/* image_posix.c - the posix target's firmware image slots (PROTOCOL.md 14.3): two files
 * slot0.img and slot1.img and the boot record file boot.rec in one folder (--images DIR),
 * and the bootloader's jump: the chosen slot's body (an executable: this program, or any
 * other) is written to DIR/run<N> and executed in place of the loader, with SPIEL_FW_SLOT=N
 * in its environment; a reset executes the loader again (SPIEL_FW_LOADER).
 * Fault injection: --image-cut N kills the process (SIGKILL) in the middle of the N-th image
 * operation (0-based: erase, write, record write; half of a write done). */
#define _POSIX_C_SOURCE 200809L
#define _DEFAULT_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <limits.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

#include "core.h"
#include "posix_hal.h"

#if SPIEL_FW_UPDATE

#define IMAGE_SLOT_SIZE (4u * 1024u * 1024u)
#define RECORD_AREA 32u

static char dir[PATH_MAX - 32];
static long image_cut = -1, image_ops;
static int running = -1;

static void slot_path(int slot, char *out, size_t cap)
{
    if (slot == 2) {
        snprintf(out, cap, "%s/boot.rec", dir);
    } else {
        snprintf(out, cap, "%s/slot%d.img", dir, slot);
    }
}

static void operation(int slot, uint32_t offset, const uint8_t *data, uint32_t len)
{
    if (image_ops++ == image_cut) {
        if (data != NULL && len > 1) { /* half of it reaches the flash */
            char path[PATH_MAX];
            int fd;
            slot_path(slot, path, sizeof path);
            fd = open(path, O_WRONLY | O_CREAT, 0644);
            if (fd >= 0) {
                if (pwrite(fd, data, len / 2, offset) < 0) {
                    perror("image");
                }
                fsync(fd);
                close(fd);
            }
        }
        raise(SIGKILL);
    }
}

int posix_image_open(const char *images, long cut)
{
    struct stat sb;
    const char *ops = getenv("SPIEL_FW_IMAGE_OPS");
    if (stat(images, &sb) != 0 || !S_ISDIR(sb.st_mode) || strlen(images) >= sizeof dir) {
        fprintf(stderr, "%s: not a folder\n", images);
        return -1;
    }
    snprintf(dir, sizeof dir, "%s", images);
    image_cut = cut;
    if (ops != NULL) { /* counted since power-on, across resets */
        image_ops = strtol(ops, NULL, 10);
    }
    return 0;
}

void posix_image_before_exec(void)
{
    char n[24];
    snprintf(n, sizeof n, "%ld", image_ops);
    setenv("SPIEL_FW_IMAGE_OPS", n, 1);
}

uint32_t hal_image_slot_size(void)
{
    return dir[0] ? IMAGE_SLOT_SIZE : 0u;
}

int hal_image_running(void)
{
    return running;
}

int hal_image_erase(int slot)
{
    char path[PATH_MAX];
    int fd;
    if (slot < 0 || slot > 2 || !dir[0]) {
        return -1;
    }
    operation(slot, 0, NULL, 0);
    slot_path(slot, path, sizeof path);
    fd = open(path, O_WRONLY | O_CREAT | O_TRUNC, 0644); /* erased: nothing (reads as 0xFF) */
    if (fd < 0) {
        return -1;
    }
    fsync(fd);
    close(fd);
    return 0;
}

int hal_image_write(int slot, uint32_t offset, const uint8_t *data, uint32_t len)
{
    char path[PATH_MAX];
    int fd, ok;
    uint32_t cap = slot == 2 ? RECORD_AREA : IMAGE_SLOT_SIZE;
    if (slot < 0 || slot > 2 || !dir[0] || offset > cap || len > cap - offset) {
        return -1;
    }
    operation(slot, offset, data, len);
    slot_path(slot, path, sizeof path);
    fd = open(path, O_WRONLY | O_CREAT, 0644);
    if (fd < 0) {
        return -1;
    }
    ok = pwrite(fd, data, len, offset) == (ssize_t)len && fsync(fd) == 0;
    close(fd);
    return ok ? 0 : -1;
}

int hal_image_read(int slot, uint32_t offset, uint8_t *data, uint32_t len)
{
    char path[PATH_MAX];
    int fd;
    ssize_t n;
    if (slot < 0 || slot > 2 || !dir[0]) {
        return -1;
    }
    memset(data, 0xFF, len);
    slot_path(slot, path, sizeof path);
    fd = open(path, O_RDONLY);
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

/* The bootloader: choose a slot (the record updated) and execute its body; returns only when
 * no slot holds a bootable image (the caller runs as the recovery loader) or exec failed. */
void posix_image_boot(char **argv)
{
    char path[PATH_MAX], tmp[PATH_MAX], self[PATH_MAX], num[16];
    uint8_t buf[4096];
    uint8_t head[SP_IMAGE_HEADER_SIZE];
    sp_image_header_t h;
    uint32_t off;
    ssize_t n;
    int fd, slot = boot_choose();
    if (slot < 0) {
        fprintf(stderr, "spiel_fw_posix: no bootable image: recovery loader\n");
        return;
    }
    if (hal_image_read(slot, 0, head, sizeof head) != 0) { /* else head is unset */
        fprintf(stderr, "spiel_fw_posix: slot %d unreadable: recovery loader\n", slot);
        return;
    }
    sp_image_header_unpack(head, &h);
    snprintf(path, sizeof path, "%s/run%d", dir, slot);
    snprintf(tmp, sizeof tmp, "%s/run%d.tmp", dir, slot);
    fd = open(tmp, O_WRONLY | O_CREAT | O_TRUNC, 0755);
    if (fd < 0) {
        perror(tmp);
        return;
    }
    for (off = 0; off < h.body_size; off += (uint32_t)n) {
        uint32_t want = h.body_size - off < sizeof buf ? h.body_size - off : (uint32_t)sizeof buf;
        if (hal_image_read(slot, SP_IMAGE_HEADER_SIZE + off, buf, want) != 0 ||
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
    n = readlink("/proc/self/exe", self, sizeof self - 1);
    if (n > 0 && getenv("SPIEL_FW_LOADER") == NULL) {
        self[n] = 0;
        setenv("SPIEL_FW_LOADER", self, 1);
    }
    snprintf(num, sizeof num, "%d", slot);
    setenv("SPIEL_FW_SLOT", num, 1);
    posix_image_before_exec();
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

#endif /* SPIEL_FW_UPDATE */
