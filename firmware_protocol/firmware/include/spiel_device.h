/*
 * spiel_device.h - the portable device core of the spiel-edge reference firmware.
 *
 * The core speaks firmware_protocol/PROTOCOL.md over the HAL (spiel_hal.h): it answers
 * requests (HELLO, DEVICE_INFO, PING, REBOOT, STREAM_*, CONFIG_*), keeps the config in two
 * flash slots (power-cut safe), schedules acquisitions and streams them. It allocates
 * nothing: all state is static, sized by the build-time limits below.
 *
 * A target's main loop:
 *
 *     spiel_device_init();
 *     for (;;) {
 *         spiel_device_poll();                 never blocks
 *         sleep until input arrives or spiel_device_idle_us() has passed
 *     }
 */
#ifndef SPIEL_DEVICE_H
#define SPIEL_DEVICE_H

#include <stdint.h>

#include "spiel_proto.h"

#ifdef __cplusplus
extern "C" {
#endif

/* ---- build-time limits (override with -D) ---------------------------------------------- */

/* The largest payload the device sends or accepts (HELLO max_payload); RAM: about three
 * buffers of this size (receive, transmit, one payload). At least SPIEL_MIN_PAYLOAD. */
#ifndef SPIEL_MAX_PAYLOAD
#define SPIEL_MAX_PAYLOAD 1024u
#endif
/* The protocol's minimum max_payload (PROTOCOL.md 6.2): every message but STREAM_DATA,
 * PING and CONFIG_READ/WRITE data fits it. */
#define SPIEL_MIN_PAYLOAD 64u
/* The largest config blob (CONFIG_STATUS max_length, the RAM staging buffer); a flash slot
 * holds this plus its 16-byte metadata. */
#ifndef SPIEL_CONFIG_MAX
#define SPIEL_CONFIG_MAX 4080u
#endif
/* The largest samples per channel the core buffers (one channel at a time). */
#ifndef SPIEL_MAX_SAMPLES
#define SPIEL_MAX_SAMPLES 4096u
#endif
/* Highest protocol version this build speaks: 2, or 1 for a version-1 board
 * (-DSPIEL_PROTOCOL_MAX=1). The lowest is always 1. */
#ifndef SPIEL_PROTOCOL_MAX
#define SPIEL_PROTOCOL_MAX 2u
#endif

#if SPIEL_MAX_PAYLOAD < SPIEL_MIN_PAYLOAD || SPIEL_MAX_PAYLOAD > SP_MAX_PAYLOAD
#error "SPIEL_MAX_PAYLOAD must be in [SPIEL_MIN_PAYLOAD, SP_MAX_PAYLOAD]"
#endif

/* ---- API -------------------------------------------------------------------------------- */

/* Boot: a new boot_id (hal_random), no stream, empty staging and response cache, the
 * active config slot chosen from flash (factory defaults when none is valid). */
void spiel_device_init(void);

/* Do what is due now: read what the transport has, answer one request, trigger, read and
 * send acquisitions, reboot when a REBOOT's delay has passed. Never blocks. */
void spiel_device_poll(void);

/* Microseconds the core has nothing to do unless input arrives (0: poll again at once).
 * A target may sleep this long or until its transport has bytes. */
uint32_t spiel_device_idle_us(void);

/* Counters for tests and a target's diagnostics (PROTOCOL.md 6.4 STREAM_STATUS). */
typedef struct {
    uint32_t requests;          /* request frames answered (cache hits included) */
    uint32_t repeated;          /* answered from the last-response cache */
    uint32_t acquisitions_sent; /* since boot */
    uint32_t frames_sent;       /* STREAM_DATA frames, since boot */
    uint32_t overruns;          /* acquisitions skipped, since boot */
    uint32_t flash_errors;      /* HAL flash calls that failed */
    sp_stats_t rx;              /* the receive decoder's counters */
} spiel_device_stats_t;

const spiel_device_stats_t *spiel_device_stats(void);

/* Firmware update (-DSPIEL_FW_UPDATE=1): how long an unconfirmed trial image keeps kicking the
 * watchdog (so that a host that died mid-update leaves no trial behind: it rolls back by
 * itself; the boot stage's watchdog: SPIEL_FW_WATCHDOG_MS in spiel_boot.h). Default below; a target
 * may change the window before spiel_device_init() (the posix target for its tests). */
#ifndef SPIEL_FW_TRIAL_WINDOW_MS
#define SPIEL_FW_TRIAL_WINDOW_MS 60000u
#endif
void spiel_device_set_trial_window_ms(uint32_t ms);

#ifdef __cplusplus
}
#endif
#endif /* SPIEL_DEVICE_H */
