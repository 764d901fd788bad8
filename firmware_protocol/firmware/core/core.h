/* core.h - internal interfaces between the files of the portable core (not for targets). */
#ifndef SPIEL_CORE_H
#define SPIEL_CORE_H

#include <stdint.h>

#include "spiel_boot.h"
#include "spiel_device.h"
#include "spiel_hal.h"

/* The flash slot metadata (PROTOCOL.md 9.1): magic, generation, length, CRC-32C of the data,
 * four u32 little-endian at the start of the slot, written last. */
#define SPIEL_SLOT_MAGIC 0x53504346u
#define SPIEL_SLOT_META_SIZE 16u
#define SPIEL_FLASH_PAGE 256u /* bytes per hal_flash_write of a commit */

typedef struct {
    uint8_t valid;
    uint32_t generation, length, crc;
} cfg_slot_t;

/* config_store.c: two slots in the HAL flash region; staging in RAM. */
int cfg_init(void);                    /* 0, or <0 when the flash is too small for two slots */
int cfg_active(void);                  /* 0, 1, or -1 (none valid: factory defaults) */
void cfg_slot(int slot, cfg_slot_t *out);
uint32_t cfg_capacity(void);           /* max_length */
uint32_t cfg_active_length(void);
int cfg_read_active(uint32_t offset, uint8_t *out, uint32_t len); /* 0 ok */
/* Write staging[0:len] to the inactive slot and make it active: SP_ERR_OK, or
 * SP_ERR_FLASH_WRITE_FAILED / SP_ERR_FLASH_VERIFY_FAILED (the old slot stays active). */
uint16_t cfg_commit(const uint8_t *data, uint32_t len, cfg_slot_t *done, int *slot);
/* The settings in force: the active blob's header when it is usable, else the defaults. */
void cfg_settings(hal_settings_t *out);

/* ---- the units and their order -------------------------------------------------------------
 * Each unit calls only units below it, never one above (no call circle):
 *   device.c                  the protocol engine: the link, the request table, the stream (top)
 *   telemetry.c, update.c     TIME_SYNC, TELEMETRY, HEARTBEAT, LOG | FW_*, a trial's self-test
 *   boot.c                    the boot record, image checks, the boot choice and install
 *   verify.c                  an image's signature and security counter
 *   config_store.c, sha256.c  the config slots | SHA-256
 *   link.c                    the state they share (bottom)
 * tests/firmware/test_core_layers.py holds them to this order. */

/* link.c: the shared state. */
#define SPIEL_LOG_QUEUE 8u
#define SPIEL_LOG_TEXT 64u
typedef struct {
    uint8_t level;        /* lines above it are not queued (TELEMETRY sets it) */
    uint8_t head, count;
    uint32_t dropped;     /* lines lost to a full queue since the last LOG frame */
    struct {
        uint8_t level;
        char text[SPIEL_LOG_TEXT + 1];
    } q[SPIEL_LOG_QUEUE];
} link_log_t;
typedef struct {
    uint32_t boot_id;
    uint8_t version;      /* the negotiated protocol version (1 before any HELLO) */
    uint16_t max_payload; /* the link's: min(device, host's HELLO) */
    int streaming;        /* 1 while a stream runs (device.c) */
    int reboot_pending, reboot_mode;
    uint64_t reboot_at;
    link_log_t log;
} spiel_link_t;
extern spiel_link_t spiel_link;
extern spiel_device_stats_t spiel_stats;
/* the sample buffer: one channel of the acquisition being sent (free while not streaming) */
extern uint16_t spiel_samples[SPIEL_MAX_SAMPLES];
void link_init(void); /* a new boot_id, version 1, no stream, counters and queue cleared */
uint16_t link_sample_capacity(void);
void link_reboot_after_ms(int mode, uint32_t ms); /* mode: SP_REBOOT_* */
void link_log(uint8_t level, const char *text);   /* queue a LOG line (bounded; drops counted) */

/* A request handler (device.c's request table): the answer's payload in out, its length
 * returned, with *code 0; or *code an SP_ERR_* and *text its detail. */
typedef int (*core_handler_t)(const uint8_t *p, uint16_t len, uint8_t *out, uint16_t *code,
                              const char **text);

/* sha256.c */
typedef struct {
    uint32_t h[8];
    uint64_t total;
    uint8_t buf[64];
    uint32_t fill;
} sha256_t;
void sha256_init(sha256_t *s);
void sha256_update(sha256_t *s, const uint8_t *p, uint32_t n);
void sha256_final(sha256_t *s, uint8_t out[32]);

/* telemetry.c (protocol version 2, PROTOCOL.md 14.1-14.2) */
void telemetry_init(void);
int telemetry_time_sync(const uint8_t *p, uint16_t len, uint8_t *out, uint16_t *code,
                        const char **text);
int telemetry_set(const uint8_t *p, uint16_t len, uint8_t *out, uint16_t *code,
                  const char **text);
/* A device-originated frame due now (HEARTBEAT with the board's state and the error flags
 * of the caller's units, or LOG): its msg_type with the payload in out, or 0. Called only
 * with the transmit buffer empty. */
uint16_t telemetry_due(uint64_t now, uint8_t board_state, uint32_t error_flags, uint8_t *out,
                       uint16_t *out_len);
uint64_t telemetry_next_us(uint64_t now); /* when telemetry_due may have a frame (<= now + 50 ms) */

/* update.c (PROTOCOL.md 14.3): without SPIEL_FW_UPDATE, never offered. */
void update_init(void);
int update_offered(void);   /* 1: the FW_* requests are answered on this link */
void update_tick(uint64_t now); /* every poll: a trial's self-test, the watchdog kick */
int update_selftest_busy(void); /* 1 while the self-test's acquisition is in flight */
int update_uploading(void); /* 1 while an upload is open (HEARTBEAT state UPDATING) */
uint32_t update_error_flags(void); /* SP_EFLAG_TRIAL_IMAGE, SP_EFLAG_SENSOR */
uint64_t update_next_us(uint64_t now);
#if SPIEL_FW_UPDATE
int update_info(const uint8_t *p, uint16_t len, uint8_t *out, uint16_t *code, const char **text);
int update_begin(const uint8_t *p, uint16_t len, uint8_t *out, uint16_t *code, const char **text);
int update_write(const uint8_t *p, uint16_t len, uint8_t *out, uint16_t *code, const char **text);
int update_verify(const uint8_t *p, uint16_t len, uint8_t *out, uint16_t *code, const char **text);
int update_test(const uint8_t *p, uint16_t len, uint8_t *out, uint16_t *code, const char **text);
int update_confirm(const uint8_t *p, uint16_t len, uint8_t *out, uint16_t *code,
                   const char **text);
#endif

#ifndef SPIEL_FW_TARGET
#define SPIEL_FW_TARGET "posix" /* the image target this build runs (PROTOCOL.md 14.3) */
#endif

#if SPIEL_FW_UPDATE
/* boot.c (boot_start, boot_is_trial and image_check: spiel_boot.h): the boot record (two copies, generation + CRC-32C) and the boot choice. */
#define BOOT_NO_SLOT 0xFFu
typedef struct {
    uint8_t confirmed, trial, state; /* state: SP_BOOT_CONFIRMED / _TEST_PENDING / _TRIAL */
    uint32_t security_counter;       /* anti-rollback floor, carried across writes */
} boot_record_t;
void boot_record_read(boot_record_t *r); /* defaults (slot 0 confirmed) when none is valid */
int boot_record_write(const boot_record_t *r);
/* At reset: the slot to run (the record updated as PROTOCOL.md 14.3 says), -1: none. */
int boot_choose(void);
#if SPIEL_FW_EXEC_COPY
int boot_install(int slot); /* copy the slot into SPIEL_IMAGE_EXEC (idempotent): 0 ok */
#endif

/* verify.c (PROTOCOL.md 14.6): bytes of the signature trailer an image's header announces. */
uint32_t image_trailer_size(const sp_image_header_t *h);
/* The slot's signature by the built-in key and its security counter (>= min_counter):
 * SP_ERR_OK, or SP_ERR_FW_UNSIGNED / _FW_BAD_SIGNATURE / _FW_WRONG_KEY / _FW_ROLLBACK (or
 * _FLASH_VERIFY_FAILED) with *why a short reason. Call after image_check() passed (it matches
 * the body to the signed header). *counter: the image's counter, when the signature verifies. */
uint16_t image_auth(int slot, uint32_t min_counter, uint32_t *counter, const char **why);
/* The floor a confirmation of the slot's image leaves: max(floor, its header's counter). */
uint32_t image_counter_floor(int slot, uint32_t floor);
#endif

#endif
