/* posix_hal.h - setup of the posix target's HAL (not part of the portable HAL). */
#ifndef POSIX_HAL_H
#define POSIX_HAL_H

#include "spiel_hal.h"

/* Map the scans file, open (create) the flash file, remember the transport fds, fault
 * injection (-1: none) and argv (for the re-exec of a reset). 0 ok, else a message on
 * stderr and -1. */
int posix_hal_open(const char *scans, const char *flash, const char *serial, int in_fd,
                   int out_fd, long flash_cut, long flash_fail, char **argv);
/* Sleep until the transport is readable or `us` microseconds have passed (0: return at
 * once), or, while a write found the transport full, until it is writable again (at most
 * 5 ms): a firmware whose host stopped reading does not spin. */
void posix_hal_wait(uint32_t us);

/* Firmware image slots (image_posix.c, PROTOCOL.md 14.3): --images DIR and --image-cut N. */
int posix_image_open(const char *images, long cut, uint32_t program_unit);
/* the bootloader (boot_start: choice, install, watchdog); returns only without an image */
void posix_image_boot(char **argv, uint32_t watchdog_ms);
int posix_image_started(char version[17]); /* the running slot (-1 none) and its version */
void posix_image_reset(void); /* an image under the watchdog: the reset goes through it */
void posix_hal_no_sensor(void); /* --no-sensor: every trigger is refused */
/* The firmware version HELLO reports (default "1.0.0+posix"). */
void posix_hal_set_firmware_version(const char *version);

#endif
