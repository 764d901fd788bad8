/* core.h - internal interfaces between the files of the portable core (not for targets). */
#ifndef SPIEL_CORE_H
#define SPIEL_CORE_H

#include <stdint.h>

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

extern spiel_device_stats_t spiel_stats;

/* ---- protocol version 2 (PROTOCOL.md section 14): v2.c, boot.c, sha256.c ------------------ */

typedef struct {
    uint32_t h[8];
    uint64_t total;
    uint8_t buf[64];
    uint32_t fill;
} sha256_t;
void sha256_init(sha256_t *s);
void sha256_update(sha256_t *s, const uint8_t *p, uint32_t n);
void sha256_final(sha256_t *s, uint8_t out[32]);

void v2_init(void);
uint32_t v2_capabilities(void); /* HELLO capability bits offered under version 2 */
/* A version-2 request: returns 1 with the answer's payload in out[0 .. *out_len) and *code 0,
 * or *code an SP_ERR_* and *text its detail; 0 when msg_type is not a version-2 request. */
int v2_request(uint16_t msg_type, const uint8_t *p, uint16_t len, uint8_t *out,
               uint16_t *out_len, uint16_t *code, const char **text);
/* A device-originated frame due now (HEARTBEAT, LOG): its msg_type with the payload in out,
 * or 0. Called only with the transmit buffer empty. */
uint16_t v2_due(uint64_t now, uint8_t *out, uint16_t *out_len);
uint64_t v2_next_us(uint64_t now); /* when v2_due may have a frame (now + 50 ms at most) */
void v2_log(uint8_t level, const char *text); /* queue a LOG line (bounded; drops counted) */
void v2_tick(uint64_t now);   /* every poll: a trial's self-test, the watchdog kick */
int v2_selftest_busy(void);   /* 1 while the self-test's acquisition is in flight */

/* device.c, for v2.c */
uint8_t core_version(void);   /* the negotiated protocol version */
int core_streaming(void);
uint32_t core_boot_id(void);
uint16_t core_max_payload(void); /* the link's: min(device, host's HELLO) */
void core_reboot_after_ms(uint32_t ms);
uint16_t *core_sample_buffer(uint16_t *cap); /* the sample buffer (free while not streaming) */

#ifndef SPIEL_FW_TARGET
#define SPIEL_FW_TARGET "posix" /* the image target this build runs (PROTOCOL.md 14.3) */
#endif

#if SPIEL_FW_UPDATE
/* boot.c: the boot record (two copies, generation + CRC-32C) and the boot choice. */
#define BOOT_NO_SLOT 0xFFu
typedef struct {
    uint8_t confirmed, trial, state; /* state: SP_BOOT_CONFIRMED / _TEST_PENDING / _TRIAL */
    uint32_t security_counter;       /* anti-rollback floor, carried across writes */
} boot_record_t;
void boot_record_read(boot_record_t *r); /* defaults (slot 0 confirmed) when none is valid */
int boot_record_write(const boot_record_t *r);
/* 0 when the slot holds a complete image whose header, CRC-32C and SHA-256 check; then its
 * total size, CRC-32C of the whole image and version (NUL-terminated) when asked for. */
int image_check(int slot, uint32_t *size, uint32_t *crc, char version[17]);
/* At reset: the slot to run (the record updated as PROTOCOL.md 14.3 says), -1: none. */
int boot_choose(void);
int boot_is_trial(int slot); /* 1: the record says `slot` runs as an unconfirmed trial */
#if SPIEL_FW_EXEC_COPY
int boot_install(int slot); /* copy the slot into SPIEL_IMAGE_EXEC (idempotent): 0 ok */
#endif
/* The boot stage's whole decision: boot_choose(), the install (copying targets; a trial whose
 * install fails is rolled back), and the watchdog started (watchdog_ms) before a trial runs.
 * The slot to run, or -1: the built-in image / recovery loader. */
int boot_start(uint32_t watchdog_ms);

/* verify.c (PROTOCOL.md 14.6): bytes of the signature trailer an image's header announces. */
uint32_t image_trailer_size(const sp_image_header_t *h);
/* The slot's signature by the built-in key and its security counter (>= min_counter):
 * SP_ERR_OK, or SP_ERR_FW_UNSIGNED / _FW_BAD_SIGNATURE / _FW_WRONG_KEY / _FW_ROLLBACK (or
 * _FLASH_VERIFY_FAILED) with *why a short reason. Call after image_check() passed (it matches
 * the body to the signed header). *counter: the image's counter, when the signature verifies. */
uint16_t image_auth(int slot, uint32_t min_counter, uint32_t *counter, const char **why);
/* 1: the slot may be started (image_check() and image_auth() pass with this floor). */
int image_bootable(int slot, uint32_t floor);
/* The floor a confirmation of the slot's image leaves: max(floor, its header's counter). */
uint32_t image_counter_floor(int slot, uint32_t floor);
#endif

#endif
