/* main.c - the posix target: the reference firmware as a Linux program.
 *
 *   spiel_fw_posix --scans FILE --flash FILE [--pty] [--link PATH] [--serial S]
 *                  [--flash-cut N] [--flash-fail N]
 *
 * The transport is a pseudo-terminal (--pty: its slave path is printed on stdout, as
 * `spiel-edge simulate --pty` does) or stdin/stdout. A-scans come from a scans file
 * (tools/release/firmware_scans.py writes one from spiel-csv recordings or the vendored subset),
 * looped in order; the flash is a file. A reset re-executes the program on the same pty.
 * Fault injection for tests: --flash-cut N kills the process (SIGKILL) in the middle of the
 * N-th flash operation (0-based: erase or write; half of it done), --flash-fail N makes the
 * N-th one fail.
 * Firmware update (protocol 2): --images DIR holds the image slots and the boot record
 * (image_posix.c); the program then starts as the bootloader and runs the chosen image.
 * --program-unit N (default 8): the image flash's program unit; --watchdog-ms N: the
 * watchdog the boot stage starts before a trial image; --trial-window-ms N: how long an
 * unconfirmed trial keeps kicking it; --no-sensor: the front end refuses every trigger (a
 * sensorless board: a trial's self-test fails). */
#define _XOPEN_SOURCE 600
#define _DEFAULT_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <poll.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <termios.h>
#include <unistd.h>

#include "posix_hal.h"
#include "spiel_boot.h"
#include "spiel_device.h"

static void usage(void)
{
    fprintf(stderr, "usage: spiel_fw_posix --scans FILE --flash FILE [--pty] [--link PATH] "
                    "[--serial S] [--flash-cut N] [--flash-fail N] [--images DIR] "
                    "[--image-cut N] [--program-unit N] [--watchdog-ms N] "
                    "[--trial-window-ms N] [--no-sensor]\n");
    exit(2);
}

static int open_pty(void)
{
    struct termios t;
    int fd = posix_openpt(O_RDWR | O_NOCTTY);
    if (fd < 0 || grantpt(fd) != 0 || unlockpt(fd) != 0) {
        perror("pty");
        exit(1);
    }
    if (tcgetattr(fd, &t) == 0) {
        cfmakeraw(&t);
        tcsetattr(fd, TCSANOW, &t);
    }
    return fd;
}

int main(int argc, char **argv)
{
    const char *scans = NULL, *flash = NULL, *link = NULL, *serial = "POSIX0001";
    const char *images = NULL;
    long cut = -1, fail = -1, image_cut = -1, unit = 8, watchdog_ms = SPIEL_FW_WATCHDOG_MS;
    long trial_window_ms = SPIEL_FW_TRIAL_WINDOW_MS;
    int use_pty = 0, i, in_fd = 0, out_fd = 1, slave = -1;
    const char *inherited = getenv("SPIEL_FW_PTY_FD");
    for (i = 1; i < argc; i++) {
        const char *a = argv[i];
        const char *v = i + 1 < argc ? argv[i + 1] : NULL;
        if (strcmp(a, "--pty") == 0) {
            use_pty = 1;
            continue;
        }
        if (strcmp(a, "--no-sensor") == 0) {
            posix_hal_no_sensor();
            continue;
        }
        if (v == NULL) {
            usage();
        }
        if (strcmp(a, "--scans") == 0) {
            scans = v;
        } else if (strcmp(a, "--flash") == 0) {
            flash = v;
        } else if (strcmp(a, "--link") == 0) {
            link = v;
        } else if (strcmp(a, "--serial") == 0) {
            serial = v;
        } else if (strcmp(a, "--flash-cut") == 0) {
            cut = strtol(v, NULL, 0);
        } else if (strcmp(a, "--flash-fail") == 0) {
            fail = strtol(v, NULL, 0);
        } else if (strcmp(a, "--images") == 0) {
            images = v;
        } else if (strcmp(a, "--image-cut") == 0) {
            image_cut = strtol(v, NULL, 0);
        } else if (strcmp(a, "--program-unit") == 0) {
            unit = strtol(v, NULL, 0);
        } else if (strcmp(a, "--watchdog-ms") == 0) {
            watchdog_ms = strtol(v, NULL, 0);
        } else if (strcmp(a, "--trial-window-ms") == 0) {
            trial_window_ms = strtol(v, NULL, 0);
        } else {
            usage();
        }
        i++;
    }
    if (scans == NULL || flash == NULL) {
        usage();
    }
    if (watchdog_ms <= 0 || watchdog_ms > 600000 || trial_window_ms < 0 || unit <= 0 ||
        unit > 0xFFFF) {
        usage();
    }
    spiel_device_set_trial_window_ms((uint32_t)trial_window_ms);
    /* the pty first: the boot stage passes it on to the image it starts (and keeps it over a
     * watchdog reset), so the port stays where it was */
    if (use_pty) {
        if (inherited != NULL) { /* a reset: the same pty */
            in_fd = out_fd = atoi(inherited);
        } else {
            char *name, fd[16];
            in_fd = out_fd = open_pty();
            name = ptsname(in_fd);
            /* keep the slave open too, so the pty survives a host that closes and reopens */
            slave = open(name, O_RDWR | O_NOCTTY);
            if (link != NULL) {
                char tmp[4096];
                snprintf(tmp, sizeof tmp, "%s.tmp%ld", link, (long)getpid());
                unlink(tmp);
                if (symlink(name, tmp) != 0 || rename(tmp, link) != 0) {
                    perror("--link");
                    return 1;
                }
            }
            printf("%s\n", name);
            fflush(stdout);
            snprintf(fd, sizeof fd, "%d", in_fd);
            setenv("SPIEL_FW_PTY_FD", fd, 1);
        }
    }
    if (images != NULL) {
#if SPIEL_FW_UPDATE
        if (posix_image_open(images, image_cut, (uint32_t)unit) != 0) {
            return 1;
        }
        if (getenv("SPIEL_FW_SLOT") == NULL) {
            /* the bootloader: returns only without a bootable image */
            posix_image_boot(argv, (uint32_t)watchdog_ms);
        }
#else
        (void)image_cut;
        fprintf(stderr, "--images needs a build with -DSPIEL_FW_UPDATE=1\n");
        return 2;
#endif
    }
    (void)slave;
    if (posix_hal_open(scans, flash, serial, in_fd, out_fd, cut, fail, argv) != 0) {
        return 1;
    }
#if SPIEL_FW_UPDATE
    if (images != NULL) {
        static char version[17];
        posix_image_started(version);
        posix_hal_set_firmware_version(version);
    }
#endif
    spiel_device_init();
    for (;;) {
        uint32_t idle;
        spiel_device_poll();
        idle = spiel_device_idle_us();
        posix_hal_wait(idle); /* returns at once when idle is 0, unless output is blocked */
    }
}
