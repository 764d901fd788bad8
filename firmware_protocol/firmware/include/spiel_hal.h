/*
 * spiel_hal.h - the hardware abstraction layer of the spiel-edge reference firmware.
 *
 * This is the ONLY header between the portable core (the files in core/) and a target
 * (targets/<name>/). A target implements every function below; the core calls them from
 * spiel_device_poll() only, never from an interrupt. None of them may block for long: the
 * transport calls return at once, flash calls take as long as the flash needs (a commit is
 * allowed about 3 s in total, PROTOCOL.md section 10).
 *
 * The first block (transport .. system) is fixed and shared by every target; the second
 * block holds the functions the core adds, each documented where it is declared.
 */
#ifndef SPIEL_HAL_H
#define SPIEL_HAL_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

/* ---- fixed signatures ------------------------------------------------------------------ */

/* Transport: never blocks. */
size_t hal_transport_read(uint8_t *buf, size_t cap);        /* bytes read now; 0 if none */
size_t hal_transport_write(const uint8_t *buf, size_t len); /* bytes accepted now (<= len) */
/* Clock. */
uint64_t hal_time_us(void);                                 /* monotonic us since boot */
/* Measurement: trigger all channels of channel_mask, then read each channel's samples. */
int hal_acq_trigger(uint32_t channel_mask, uint16_t n_samples); /* 0 ok, <0 error */
int hal_acq_ready(void);                                    /* 1 when the measurement is done */
int hal_acq_read(uint8_t channel, uint16_t *samples, uint16_t n_samples); /* 0 ok */
/* Flash: a byte-addressed region [0, hal_flash_size()) erased in sectors. 0 ok, <0 error. */
uint32_t hal_flash_size(void);
uint32_t hal_flash_sector_size(void);
int hal_flash_erase(uint32_t addr, uint32_t len);
int hal_flash_write(uint32_t addr, const uint8_t *data, uint32_t len);
int hal_flash_read(uint32_t addr, uint8_t *data, uint32_t len);
/* System. */
void hal_reset(int to_bootloader);                          /* does not return */
uint32_t hal_random(void);

/* ---- added by the core ----------------------------------------------------------------- */

/* What the board is: constant for the life of the firmware. Strings are NUL-terminated,
 * at most 16 bytes of UTF-8 (longer ones are cut on the wire). Channel ids are physical:
 * channel i is bit i of every channel_mask, 0 .. n_channels - 1. */
typedef struct {
    const char *firmware_version; /* HELLO firmware_version, e.g. "1.0.0+posix" */
    const char *serial;           /* HELLO serial: the board's serial number */
    const char *board_name;       /* DEVICE_INFO board_name */
    uint16_t usb_vid, usb_pid;    /* HELLO usb_vid/usb_pid (0 if none) */
    uint16_t hw_revision;         /* DEVICE_INFO hw_revision */
    uint8_t n_channels;           /* channels that listen (emitter included), <= 32 */
    uint8_t emitter_channel;      /* the channel whose transducer also emits; 0xFF: none */
    uint8_t adc_bits;             /* DEVICE_INFO adc_bits */
    uint16_t max_samples;         /* samples per channel per acquisition the HAL can capture */
    uint32_t emitter_freq_hz;     /* DEVICE_INFO emitter_freq_hz */
    uint32_t max_sample_rate_hz;  /* DEVICE_INFO max_sample_rate_hz */
    /* Factory defaults, used when no valid config slot exists (PROTOCOL.md 9.1). */
    uint16_t default_n_samples;   /* STREAM_START n_samples 0 resolves to this */
    uint32_t default_sample_rate_hz; /* integer Hz (PROTOCOL.md 13.1) */
} hal_board_info_t;

const hal_board_info_t *hal_board_info(void);

/* Board temperature in 0.01 degC (DEVICE_INFO temperature_cdeg; 0 if unknown). */
int16_t hal_temperature_cdeg(void);

/* The acquisition settings in force: the active config's blob header (PROTOCOL.md 13.1)
 * when a valid slot holds a usable blob, else the factory defaults. */
typedef struct {
    uint8_t from_config;          /* 1: the active config slot; 0: factory defaults */
    uint16_t n_samples;           /* default samples per channel */
    uint16_t decimation;          /* 0 with factory defaults: the target's own */
    uint16_t pulse_cycles;        /* 0 with factory defaults */
    uint16_t blind_zone_samples;
    uint32_t sample_rate_hz;      /* integer Hz, as STREAM_DATA carries it */
    float carrier_hz, gain_db, acquisition_rate_hz; /* 0 with factory defaults */
} hal_settings_t;

/* Called at boot and after every successful CONFIG_COMMIT, never while a stream runs: a
 * target whose front end takes these settings (sample rate, gain, pulse) applies them before
 * the next hal_acq_trigger; one that cannot, ignores them. */
void hal_apply_settings(const hal_settings_t *settings);


/* ---- added for protocol version 2 (PROTOCOL.md 14.3): firmware image slots ---------------- */

/* A target that implements these builds the core with -DSPIEL_FW_UPDATE=1; the core then
 * offers FIRMWARE_UPDATE. Slots 0 and 1 hold images (header + body, PROTOCOL.md 14.3), slot 2
 * is the boot record area (at least 32 bytes); the bootloader (the target's start-up code,
 * using boot_choose() of the core) runs the image of the slot the record names. */
#ifndef SPIEL_FW_UPDATE
#define SPIEL_FW_UPDATE 0
#endif
/* A target that also has a built-in (factory) image outside the two slots, run when no slot
 * holds a bootable image, builds with -DSPIEL_FW_FACTORY=1: without a boot record the built-in
 * image is the confirmed one (FW_INFO confirmed_slot 0xFF), so an unconfirmed trial started
 * from it rolls back to it. Without it slot 0 holds the first image. */
#ifndef SPIEL_FW_FACTORY
#define SPIEL_FW_FACTORY 0
#endif
/* I/Q samples (PROTOCOL.md 14.4): a target whose front end gives I/Q pairs (SonicLib's
 * ch_get_iq_data) builds with -DSPIEL_IQ_SAMPLES=1 and implements this; the core then accepts
 * STREAM_START sample_format I16_IQ. Fills qi[0 .. 2n) with q0 i0 q1 i1 ... (two's complement
 * int16 in uint16_t), like hal_acq_read. 0 ok. */
#ifndef SPIEL_IQ_SAMPLES
#define SPIEL_IQ_SAMPLES 0
#endif
#if SPIEL_IQ_SAMPLES
int hal_acq_read_iq(uint8_t channel, uint16_t *qi, uint16_t n_samples);
#endif

#if SPIEL_FW_UPDATE
/* Image slots on NOR flash (a real part's constraints, PROTOCOL.md 14.3 "Flash layout"):
 *   slot 0, 1             the two image slots, hal_image_slot_size() bytes each;
 *   SPIEL_IMAGE_RECORD    the boot record area: two copies, copy k at offset k * sector size,
 *                         each erased by the core just before it is written (>= 2 sectors);
 *   SPIEL_IMAGE_EXEC      the execution region of a target whose boot stage copies the chosen
 *                         image flash to flash (SPIEL_FW_EXEC_COPY, boot_start() in boot.c):
 *                         its first sector holds the installed image's header (written last),
 *                         the body starts at offset hal_image_sector_size(), where the
 *                         application is linked. Used by the boot stage only.
 * Erase: whole sectors only (offset and len multiples of hal_image_sector_size()); the core
 * erases the slot being written one sector at a time as the upload reaches it, so no request
 * waits for more than one sector erase (2.4-32 s for a 1 MiB slot of real NOR flash).
 * Write: offset and len multiples of hal_image_program_unit(), into erased bytes only (ECC
 * flash programs each unit once: 8 bytes on STM32G0/L4, 32 on H7); the core buffers the
 * upload's chunks to whole units and pads the last one with 0xFF. */
#define SPIEL_IMAGE_RECORD 2
#define SPIEL_IMAGE_EXEC 3
#define SPIEL_FW_UNIT_MAX 32u               /* the largest program unit the core buffers */
uint32_t hal_image_slot_size(void);         /* bytes an image slot holds (a sector multiple) */
uint32_t hal_image_sector_size(void);       /* erase unit of every area: power of two, >= 64 */
uint32_t hal_image_program_unit(void);      /* program unit: power of two, 1..SPIEL_FW_UNIT_MAX */
int hal_image_erase(int slot, uint32_t offset, uint32_t len); /* whole sectors; 0 ok, <0 error */
int hal_image_write(int slot, uint32_t offset, const uint8_t *data, uint32_t len);
int hal_image_read(int slot, uint32_t offset, uint8_t *data, uint32_t len); /* erased: 0xFF */
int hal_image_running(void);                /* the slot running now: 0, 1, -1 none */
/* (-1: the built-in image with SPIEL_FW_FACTORY, else the recovery loader) */

/* The watchdog (PROTOCOL.md 14.3 "Trial images"). The boot stage starts it just before it
 * jumps to a trial image (boot_start()); once started it cannot be stopped until the next
 * reset, and a reset it causes runs the boot stage, which rolls the unconfirmed trial back.
 * The core kicks it from spiel_device_poll(): while the trial runs only until its self-test
 * has failed or the trial window (SPIEL_FW_TRIAL_WINDOW_MS) has passed unconfirmed; after
 * FW_CONFIRM always. A board whose watchdog was not started ignores the kicks. */
void hal_watchdog_start(uint32_t timeout_ms);
void hal_watchdog_kick(void);
#endif
/* A copying boot stage (mps2-an386, posix): the chosen image is copied into SPIEL_IMAGE_EXEC
 * before it runs, so an image never has to fit in RAM. */
#ifndef SPIEL_FW_EXEC_COPY
#define SPIEL_FW_EXEC_COPY 0
#endif

#ifdef __cplusplus
}
#endif
#endif /* SPIEL_HAL_H */
