/*
 * spiel_boot.h - what a target's boot stage uses of the portable core (with
 * -DSPIEL_FW_UPDATE=1): the boot choice over the two image slots and the boot record
 * (PROTOCOL.md 14.3), the install into the execution region, the watchdog for a trial.
 *
 * A boot stage is a separate small program, never updated itself. It links core/boot.c,
 * core/verify.c, core/sha256.c, ../c/spiel_proto.c and the vendored Ed25519 verifier, with its
 * target's spiel_hal.h image functions, and then:
 *
 *     int slot = boot_start(SPIEL_FW_WATCHDOG_MS);   -1: no bootable slot
 *     read the installed header (hal_image_read(SPIEL_IMAGE_EXEC, 0, ...)) and jump
 *
 * The core's private interfaces (core/core.h) are not for targets.
 */
#ifndef SPIEL_BOOT_H
#define SPIEL_BOOT_H

#include <stdint.h>

#include "spiel_hal.h"
#include "spiel_proto.h"

#ifdef __cplusplus
extern "C" {
#endif

/* How long the boot stage's watchdog waits for a kick once a trial image runs. */
#ifndef SPIEL_FW_WATCHDOG_MS
#define SPIEL_FW_WATCHDOG_MS 2000u
#endif

#if SPIEL_FW_UPDATE
/* The boot stage's whole decision: the slot to run chosen from the boot record (a pending
 * test becomes a trial, an unconfirmed trial rolls back, only a slot whose image checks and is
 * signed by the built-in key is chosen), the install into SPIEL_IMAGE_EXEC (copying targets,
 * SPIEL_FW_EXEC_COPY; a trial whose install fails is rolled back), and the watchdog started
 * (watchdog_ms) before a trial runs. The slot to run, or -1: the built-in image (with
 * SPIEL_FW_FACTORY) or the recovery loader. */
int boot_start(uint32_t watchdog_ms);

/* 1: the boot record says `slot` runs as an unconfirmed trial. */
int boot_is_trial(int slot);

/* 0 when the slot holds a complete image whose header, CRC-32C and SHA-256 check; then its
 * total size, CRC-32C of the whole image and version (NUL-terminated) when asked for (each
 * pointer may be NULL). */
int image_check(int slot, uint32_t *size, uint32_t *crc, char version[17]);
#endif

#ifdef __cplusplus
}
#endif
#endif /* SPIEL_BOOT_H */
