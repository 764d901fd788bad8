/*
 * hal_mps2.c - spiel_hal.h on the Arm MPS2 AN386 image (Cortex-M4) under qemu-system-arm.
 *
 * transport  CMSDK UART0: receive interrupt into a ring (the interrupt is masked while the
 *            ring is full, so the sender is held back, never overrun); transmit into a ring
 *            that the TX interrupt drains whenever the UART takes the next byte.
 * clock      CMSDK timer 0 counting down at 25 MHz from 0xFFFFFFFF; its wrap interrupt
 *            extends it to 64 bits.
 * A-scans    the vendored recordings as constant data (ascans.c, generated), in order and
 *            looped, one per measurement that was read; ready after the listening time
 *            n_samples / sample rate.
 * flash      64 KiB of NOR-like memory in the PSRAM, which qemu can back with a host file
 *            (nor_mps2.c, with the tests' power-cut hook); the image slots are image_mps2.c.
 * reset      SCB AIRCR SYSRESETREQ: the boot stage (boot_mps2.c) runs again.
 */
#include <string.h>

#include "ascans.h"
#include "mps2.h"
#include "spiel_hal.h"

void uart0_rx_handler(void);
void uart0_tx_handler(void);
void timer0_handler(void);
void timer1_handler(void);
void mps2_hal_init(void);
void mps2_wait(uint32_t us);
int mps2_image_version(char version[17]); /* image_mps2.c */

/* ---- transport ------------------------------------------------------------------------- */

#define RX_RING 1024u /* a power of two */
static volatile uint8_t rx_ring[RX_RING];
static volatile uint32_t rx_head, rx_tail; /* head: written by the ISR; tail: by the reader */

void uart0_rx_handler(void)
{
    UART_INTSTATUS(UART0_BASE) = UART_INT_RX; /* clear first: a byte arriving now re-raises */
    while (UART_STATE(UART0_BASE) & UART_STATE_RXFULL) {
        if (rx_head - rx_tail >= RX_RING) {
            /* ring full: leave the byte in the UART and stop listening until the reader
             * has made room (hal_transport_read turns the interrupt back on) */
            UART_CTRL(UART0_BASE) &= ~UART_CTRL_RXINTEN;
            return;
        }
        rx_ring[rx_head % RX_RING] = (uint8_t)UART_DATA(UART0_BASE);
        rx_head++;
    }
}

size_t hal_transport_read(uint8_t *buf, size_t cap)
{
    size_t n = 0;
    while (n < cap && rx_tail != rx_head) {
        buf[n++] = rx_ring[rx_tail % RX_RING];
        rx_tail++;
    }
    if (!(UART_CTRL(UART0_BASE) & UART_CTRL_RXINTEN)) {
        uint32_t key = irq_save(); /* the handler must not run twice at once */
        UART_CTRL(UART0_BASE) |= UART_CTRL_RXINTEN;
        uart0_rx_handler(); /* the byte that waited in the UART raised no interrupt */
        irq_restore(key);
    }
    return n;
}

#define TX_RING 1024u /* a power of two; the largest frame at max_payload 1024 fits */
static volatile uint8_t tx_ring[TX_RING];
static volatile uint32_t tx_head, tx_tail; /* head: written by the core; tail: by the pump */

/* Hand the UART what it takes now; with interrupts masked or from the TX interrupt. */
static void tx_pump(void)
{
    while (tx_tail != tx_head && !(UART_STATE(UART0_BASE) & UART_STATE_TXFULL)) {
        UART_DATA(UART0_BASE) = tx_ring[tx_tail % TX_RING];
        tx_tail++;
    }
}

void uart0_tx_handler(void)
{
    UART_INTSTATUS(UART0_BASE) = UART_INT_TX; /* the UART took a byte: give it the next */
    tx_pump();
}

size_t hal_transport_write(const uint8_t *buf, size_t len)
{
    size_t n = 0;
    uint32_t key;
    while (n < len && tx_head - tx_tail < TX_RING) {
        tx_ring[tx_head % TX_RING] = buf[n++];
        tx_head++;
    }
    key = irq_save();
    tx_pump(); /* an idle UART raises no interrupt: start it */
    irq_restore(key);
    return n;
}

/* ---- clock ------------------------------------------------------------------------------ */

static volatile uint32_t timer_wraps;

void timer0_handler(void)
{
    TIMER_INTSTATUS(TIMER0_BASE) = 1u;
    timer_wraps++;
}

uint64_t hal_time_us(void)
{
    uint32_t wraps, again, value, pending;
    do {
        wraps = timer_wraps;
        value = TIMER_VALUE(TIMER0_BASE);
        pending = TIMER_INTSTATUS(TIMER0_BASE) & 1u;
        again = timer_wraps;
    } while (wraps != again);
    if (pending && value > 0x80000000u) {
        wraps++; /* it wrapped before the read and the interrupt has not run yet */
    }
    return ((((uint64_t)wraps) << 32) | (uint64_t)(0xFFFFFFFFu - value)) /
           (MPS2_SYSCLK_HZ / 1000000u);
}

/* ---- measurement ------------------------------------------------------------------------ */

static hal_board_info_t board = {
    "1.0.0+mps2-an386", /* firmware_version: the built-in image's; an image's from its header */
    "MPS2-AN386-0001",  /* serial */
    "spiel-c mps2",     /* board_name */
    0,
    0,     /* no USB on this target */
    1,     /* hw_revision */
    4,     /* n_channels: the recordings' four listening transducers */
    0,     /* emitter_channel: channel 0 emits and listens */
    16,    /* adc_bits */
    SPIEL_ASCANS_SAMPLES, /* max_samples */
    175000u,              /* emitter_freq_hz */
    400000u,              /* max_sample_rate_hz */
    SPIEL_ASCANS_SAMPLES, /* default_n_samples */
    22000u,               /* default_sample_rate_hz */
};

const hal_board_info_t *hal_board_info(void)
{
    return &board;
}

int16_t hal_temperature_cdeg(void)
{
    return 0; /* no sensor on this board */
}

static uint32_t acq_frame;     /* the embedded frame the measurement in flight returns */
static uint32_t acq_mask;
static uint64_t acq_done_us;
static int acq_busy, acq_read;
static uint32_t sample_rate_hz = 22000u;

void hal_apply_settings(const hal_settings_t *settings)
{
    /* The recordings were sampled at one rate; only the listening time follows the config. */
    if (settings != NULL && settings->sample_rate_hz > 0) {
        sample_rate_hz = settings->sample_rate_hz;
    }
}

int hal_acq_trigger(uint32_t channel_mask, uint16_t n_samples)
{
    if (channel_mask == 0 || (channel_mask >> SPIEL_ASCANS_CHANNELS) != 0 ||
        n_samples == 0 || n_samples > SPIEL_ASCANS_SAMPLES) {
        return -1;
    }
    if (acq_busy && acq_read) {
        acq_frame = (acq_frame + 1u) % SPIEL_ASCANS_N; /* the recordings in order, looped */
    }
    /* a measurement triggered but never read (a STREAM_STOP came first) is measured again,
     * so every recording reaches the host once, in order (as the posix target does) */
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

/* ---- flash ------------------------------------------------------------------------------ */

/* The config store's 64 KiB at the start of the persistent PSRAM (nor_mps2.c, mps2.h). */

uint32_t hal_flash_size(void)
{
    return CFG_FLASH_SIZE;
}

uint32_t hal_flash_sector_size(void)
{
    return NOR_SECTOR;
}

static int in_range(uint32_t addr, uint32_t len)
{
    return addr <= CFG_FLASH_SIZE && len <= CFG_FLASH_SIZE - addr;
}

int hal_flash_erase(uint32_t addr, uint32_t len)
{
    return in_range(addr, len) ? nor_erase(CFG_FLASH_OFF + addr, len) : -1;
}

int hal_flash_write(uint32_t addr, const uint8_t *data, uint32_t len)
{
    return in_range(addr, len) ? nor_write(CFG_FLASH_OFF + addr, data, len) : -1;
}

int hal_flash_read(uint32_t addr, uint8_t *data, uint32_t len)
{
    if (!in_range(addr, len)) {
        return -1;
    }
    nor_read(CFG_FLASH_OFF + addr, data, len);
    return 0;
}

/* ---- system ----------------------------------------------------------------------------- */

void hal_reset(int to_bootloader)
{
    (void)to_bootloader; /* both modes restart through the boot stage (boot_mps2.c) */
    dsb();
    SCB_AIRCR = AIRCR_VECTKEY | AIRCR_SYSRESETREQ;
    dsb();
    for (;;) {
    }
}

#define RANDOM_SEED REG32(PSRAM_BASE + SEED_OFF)

uint32_t hal_random(void)
{
    /* No entropy source on the MPS2, and the timer read at boot takes few values under qemu
     * (41 boots drew 40 distinct boot_ids; a repeat on consecutive boots hides the reboot
     * from the host). So the xorshift32 state lives in the persistent PSRAM and every
     * draw stirs in the free-running timer: boot_ids follow one chain across resets and power
     * cuts. A port uses its TRNG. */
    uint32_t x = RANDOM_SEED ^ TIMER_VALUE(TIMER0_BASE) ^ (uint32_t)(hal_time_us() >> 3);
    if (x == 0) {
        x = 0x9E3779B9u;
    }
    x ^= x << 13;
    x ^= x >> 17;
    x ^= x << 5;
    RANDOM_SEED = x;
    return x;
}

/* ---- idle ------------------------------------------------------------------------------ */

void timer1_handler(void)
{
    TIMER_CTRL(TIMER1_BASE) = 0; /* one shot */
    TIMER_INTSTATUS(TIMER1_BASE) = 1u;
}

/* Sleep (WFI) until a byte arrives or `us` microseconds have passed. Interrupts are masked
 * between the check and the WFI, so a byte that arrives in between still wakes it. */
void mps2_wait(uint32_t us)
{
    uint32_t ticks = us > 100000000u ? 0xFFFFFFFFu : us * (MPS2_SYSCLK_HZ / 1000000u);
    irq_disable();
    if (rx_head == rx_tail && ticks > 0) {
        TIMER_CTRL(TIMER1_BASE) = 0;
        TIMER_INTSTATUS(TIMER1_BASE) = 1u;
        TIMER_RELOAD(TIMER1_BASE) = ticks;
        TIMER_VALUE(TIMER1_BASE) = ticks;
        TIMER_CTRL(TIMER1_BASE) = TIMER_CTRL_EN | TIMER_CTRL_IRQEN;
        __asm volatile("wfi" ::: "memory");
    }
    irq_enable();
}

/* ---- start-up ---------------------------------------------------------------------------- */

void mps2_hal_init(void)
{
#if SPIEL_FW_UPDATE
    static char version[17];
    if (mps2_image_version(version) == 0) {
        board.firmware_version = version;
    }
#endif
    TIMER_CTRL(TIMER0_BASE) = 0;
    TIMER_RELOAD(TIMER0_BASE) = 0xFFFFFFFFu;
    TIMER_VALUE(TIMER0_BASE) = 0xFFFFFFFFu;
    TIMER_INTSTATUS(TIMER0_BASE) = 1u;
    TIMER_CTRL(TIMER0_BASE) = TIMER_CTRL_EN | TIMER_CTRL_IRQEN;

    UART_BAUDDIV(UART0_BASE) = MPS2_SYSCLK_HZ / 115200u; /* ignored by qemu's pty */
    UART_INTSTATUS(UART0_BASE) = 0xFu;
    UART_CTRL(UART0_BASE) = UART_CTRL_TXEN | UART_CTRL_RXEN | UART_CTRL_RXINTEN | UART_CTRL_TXINTEN;

    NVIC_ISER0 = (1u << UART0_RX_IRQ) | (1u << UART0_TX_IRQ) | (1u << TIMER0_IRQ) | (1u << TIMER1_IRQ);
    irq_enable();
}
