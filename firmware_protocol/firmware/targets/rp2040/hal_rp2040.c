/*
 * hal_rp2040.c - spiel_hal.h on the Raspberry Pi Pico (RP2040), over the Pico SDK's hardware
 * layers and TinyUSB.
 *
 * transport  USB CDC-ACM (TinyUSB): read what the CDC receive FIFO holds, write what its
 *            transmit FIFO takes (sized for one acquisition's frames, tusb_config.h) and flush.
 *            While no host holds the port open (DTR low) written bytes are dropped, as a UART
 *            with no one listening would: the core resends nothing on its own, and a stream
 *            left running must not stall the board.
 * clock      the RP2040 timer (1 MHz from the watchdog tick, 64 bits).
 * A-scans    the vendored recordings as constant data (ascans.c, generated as for mps2), in
 *            order and looped, one per measurement that was read; ready after the listening
 *            time n_samples / sample rate. Built with SONICLIB_DIR (RP2040_SONICLIB=1), four
 *            CH101 over TDK SonicLib instead: sensor/sensor_soniclib.c.
 * flash      the config store's 64 KiB at the end of the 2 MiB flash (flash_rp2040.c); the
 *            image areas and the watchdog are image_rp2040.c's.
 * reset      the watchdog (a reboot), or the ROM's USB boot mode (BOOTSEL) for the bootloader.
 */
#include <string.h>

#include "ascans.h"
#include "hardware/clocks.h"
#include "hardware/irq.h"
#include "hardware/resets.h"
#include "hardware/structs/rosc.h"
#include "hardware/structs/timer.h"
#include "hardware/sync.h"
#include "hardware/watchdog.h"
#include "pico/bootrom.h"
#include "rp2040_board.h"
#include "spiel_hal.h"
#include "tusb.h"

/* ---- transport ------------------------------------------------------------------------- */

size_t hal_transport_read(uint8_t *buf, size_t cap)
{
    uint32_t n = tud_cdc_available();
    if (n == 0) {
        return 0;
    }
    return tud_cdc_read(buf, (uint32_t)(cap < n ? cap : n));
}

size_t hal_transport_write(const uint8_t *buf, size_t len)
{
    uint32_t room, n;
    if (!tud_cdc_connected()) {
        return len; /* no one listening: dropped (see the top of this file) */
    }
    room = tud_cdc_write_available();
    n = (uint32_t)(len < room ? len : room);
    if (n > 0) {
        n = tud_cdc_write(buf, n);
        tud_cdc_write_flush();
    }
    return n;
}

/* ---- clock ----------------------------------------------------------------------------- */

uint64_t hal_time_us(void)
{
    uint32_t hi = timer_hw->timerawh, lo, again;
    for (;;) {
        lo = timer_hw->timerawl;
        again = timer_hw->timerawh;
        if (again == hi) {
            return ((uint64_t)hi << 32) | lo;
        }
        hi = again;
    }
}

/* ---- measurement ----------------------------------------------------------------------- */

static hal_board_info_t board = {
    "1.0.0+rp2040",     /* firmware_version */
    "",                 /* serial: rp2040_serial() at start-up */
    "spiel-c rp2040",   /* board_name */
    RP2040_USB_VID,
    RP2040_USB_PID,
    1,                  /* hw_revision */
    4,                  /* n_channels: four CH101 (the recordings' four transducers) */
    0,                  /* emitter_channel: channel 0 emits and listens */
    16,                 /* adc_bits */
    SPIEL_ASCANS_SAMPLES, /* max_samples */
    175000u,            /* emitter_freq_hz */
    400000u,            /* max_sample_rate_hz */
    SPIEL_ASCANS_SAMPLES, /* default_n_samples */
    22000u,             /* default_sample_rate_hz */
};

const hal_board_info_t *hal_board_info(void)
{
    return &board;
}

int16_t hal_temperature_cdeg(void)
{
    return 0; /* the recordings carry none */
}

#if !RP2040_SONICLIB
static uint32_t acq_frame;
static uint32_t acq_mask;
static uint64_t acq_done_us;
static int acq_busy, acq_read;
static uint32_t sample_rate_hz = 22000u;

void hal_apply_settings(const hal_settings_t *settings)
{
    if (settings != NULL && settings->sample_rate_hz > 0) {
        sample_rate_hz = settings->sample_rate_hz;
    }
}

int hal_acq_trigger(uint32_t channel_mask, uint16_t n_samples)
{
    if (channel_mask == 0 || (channel_mask >> SPIEL_ASCANS_CHANNELS) != 0 || n_samples == 0 ||
        n_samples > SPIEL_ASCANS_SAMPLES) {
        return -1;
    }
    if (acq_busy && acq_read) {
        acq_frame = (acq_frame + 1u) % SPIEL_ASCANS_N; /* in order, looped */
    }
    /* one triggered but never read is measured again: every recording reaches the host once,
     * in order, as on the posix and mps2 targets */
    acq_mask = channel_mask;
    acq_done_us = hal_time_us() + (uint64_t)n_samples * 1000000u / sample_rate_hz;
    acq_busy = 1;
    acq_read = 0;
    return 0;
}

int hal_acq_ready(void)
{
    return acq_busy && hal_time_us() >= acq_done_us;
}

int hal_acq_read(uint8_t channel, uint16_t *samples, uint16_t n_samples)
{
    if (!acq_busy || channel >= SPIEL_ASCANS_CHANNELS || !(acq_mask & (1u << channel)) ||
        n_samples > SPIEL_ASCANS_SAMPLES) {
        return -1;
    }
    memcpy(samples, spiel_ascans[acq_frame][channel], (size_t)n_samples * sizeof *samples);
    acq_read = 1;
    return 0;
}
#else
void hal_apply_settings(const hal_settings_t *settings)
{
    (void)settings; /* the CH101 samples at its own rate (its frequency / 8); n_samples comes
                     * with every trigger */
}
#endif

/* ---- flash: the config store ------------------------------------------------------------- */

uint32_t hal_flash_size(void)
{
    return RP2040_CFG_SIZE;
}

uint32_t hal_flash_sector_size(void)
{
    return RP2040_SECTOR;
}

static int in_range(uint32_t addr, uint32_t len)
{
    return addr <= RP2040_CFG_SIZE && len <= RP2040_CFG_SIZE - addr;
}

int hal_flash_erase(uint32_t addr, uint32_t len)
{
    return in_range(addr, len) ? rp2040_flash_erase(RP2040_CFG_OFF + addr, len) : -1;
}

int hal_flash_write(uint32_t addr, const uint8_t *data, uint32_t len)
{
    return in_range(addr, len) ? rp2040_flash_program(RP2040_CFG_OFF + addr, data, len) : -1;
}

int hal_flash_read(uint32_t addr, uint8_t *data, uint32_t len)
{
    if (!in_range(addr, len)) {
        return -1;
    }
    rp2040_flash_read(RP2040_CFG_OFF + addr, data, len);
    return 0;
}

/* ---- system ------------------------------------------------------------------------------ */

void hal_reset(int to_bootloader)
{
    if (to_bootloader) {
        reset_usb_boot(0, 0); /* the ROM's UF2 drive (BOOTSEL): does not return */
    }
    watchdog_reboot(0, 0, 0);
    for (;;) {
        __wfi();
    }
}

/* The watchdog's scratch 3 survives a watchdog reboot (not a power cut): the xorshift state
 * carried across reboots, so boot ids differ even where the ring oscillator's random bit is not
 * random (the emulator). On a board every draw stirs in 32 random bits of the ROSC. */
uint32_t hal_random(void)
{
    uint32_t x = watchdog_hw->scratch[3] ^ (uint32_t)hal_time_us(), i;
    for (i = 0; i < 32u; i++) {
        x ^= (rosc_hw->randombit & 1u) << i;
    }
    if (x == 0) {
        x = 0x9E3779B9u;
    }
    x ^= x << 13;
    x ^= x >> 17;
    x ^= x << 5;
    watchdog_hw->scratch[3] = x;
    return x;
}

/* ---- idle -------------------------------------------------------------------------------- */

void isr_timer0(void)
{
    timer_hw->intr = 1u; /* alarm 0: the wake-up of rp2040_wait */
}

/* Sleep until an interrupt (USB) or `us` microseconds have passed. Interrupts are masked
 * between the check and the WFI, so one that comes in between still wakes it. */
void rp2040_wait(uint32_t us)
{
    uint32_t irq;
    if (us < 20u) {
        return; /* not worth an alarm */
    }
    if (us > 100000u) {
        us = 100000u; /* tud_task() runs at least every 100 ms */
    }
    irq = save_and_disable_interrupts();
    if (tud_cdc_available() == 0 && !tud_task_event_ready()) {
        timer_hw->inte |= 1u;
        timer_hw->alarm[0] = timer_hw->timerawl + us;
        __wfi();
    }
    restore_interrupts(irq);
}

/* ---- start-up ---------------------------------------------------------------------------- */

void rp2040_hal_init(void)
{
    rp2040_clocks_start(); /* again: a debugger may start the application directly */
    unreset_block_wait(RESETS_RESET_TIMER_BITS);
    static char version[17];
    if (rp2040_image_version(version) == 0) {
        board.firmware_version = version;
    }
    board.serial = rp2040_serial();
#if RP2040_SONICLIB
    (void)rp2040_sensor_init(&board); /* on failure every trigger is refused; USB still answers */
#endif
    timer_hw->intr = 1u;
    irq_set_enabled(TIMER_IRQ_0, true); /* rp2040_wait's wake-up (usb_rp2040.c: the NVIC) */
    tusb_init();
}
