/*
 * sensor_soniclib.c - the measurement half of spiel_hal.h (hal_acq_*) over TDK SonicLib, for
 * four CH101 (or CH201) on the Pico (chbsp_rp2040.h): channel k is sensor k; sensor 0 emits
 * and listens (CH_MODE_TRIGGERED_TX_RX), 1-3 listen (CH_MODE_TRIGGERED_RX_ONLY), all started
 * by one group trigger (pitch-catch).
 *
 * One acquisition:
 *   hal_acq_trigger  ch_group_trigger: a pulse on every INT line; refused while a read runs
 *                    (a measurement triggered during I/O is corrupt)
 *   data ready       each sensor's INT pulse -> ch_interrupt -> on_int; on the last one of
 *                    the mask, one non-blocking I/Q read per sensor is queued
 *                    (ch_get_iq_data, CH_IO_MODE_NONBLOCK) and started (ch_io_start_nb): the
 *                    two buses read their two sensors each at the same time
 *   hal_acq_ready    1 once the I/O completion callback has run (or the acquisition failed:
 *                    a sensor silent past its deadline, an I2C error)
 *   hal_acq_read     envelope samples, sqrt(q^2 + i^2) on the MCU (iq_plan.c)
 *   hal_acq_read_iq  the I/Q samples as they came (I16_IQ streams, PROTOCOL.md 14.4)
 * Nothing blocks but the start-up (sensor firmware load and clock calibration) and a change of
 * n_samples (a register write per sensor).
 */
#include <stddef.h>

#include "chbsp_rp2040.h"
#include "hardware/sync.h"
#include "invn/soniclib/soniclib.h"
#include "invn/soniclib/chirp_bsp.h"
#include "invn/soniclib/sensor_fw/ch101/ch101_gpr.h"
#include "iq_plan.h"
#include "rp2040_board.h"
#include "spiel_hal.h"

_Static_assert(sizeof(ch_iq_sample_t) == sizeof(iq_pair_t) &&
                   offsetof(ch_iq_sample_t, q) == offsetof(iq_pair_t, q) &&
                   offsetof(ch_iq_sample_t, i) == offsetof(iq_pair_t, i),
               "SonicLib's I/Q sample is q then i, as the protocol's");

#define MAX_SAMPLES 64u     /* per channel: the protocol's frame and SPIEL_MAX_SAMPLES / 2 */
#define DEADLINE_US 50000u  /* past the listening time: a sensor that has not answered failed */

enum { IDLE, LISTEN, READING, DONE, FAILED };

static ch_group_t group;
static ch_dev_t devs[RP2040_SENSORS];
static ch_iq_sample_t iq[RP2040_SENSORS][MAX_SAMPLES];
static volatile uint8_t state = IDLE;
static volatile uint32_t int_seen;
static uint32_t acq_mask;
static uint16_t acq_n, dev_n;
static uint64_t acq_deadline_us;
static int started;

/* In the GPIO interrupt: the sensor's data is ready. The last one of the mask queues the reads. */
static void on_int(ch_group_t *grp, uint8_t dev_num, ch_interrupt_type_t type)
{
    uint32_t c;
    (void)type;
    if (state != LISTEN || dev_num >= RP2040_SENSORS) {
        return;
    }
    int_seen |= 1u << dev_num;
    if ((int_seen & acq_mask) != acq_mask) {
        return;
    }
    for (c = 0; c < RP2040_SENSORS; c++) {
        if ((acq_mask & (1u << c)) &&
            ch_get_iq_data(&devs[c], iq[c], 0, acq_n, CH_IO_MODE_NONBLOCK) != 0) {
            state = FAILED;
            return;
        }
    }
    state = READING;
    if (ch_io_start_nb(grp) != 0) {
        state = FAILED;
    }
}

/* In the I2C interrupt of the bus that finished last: every queued read is done. */
static void on_io_done(ch_group_t *grp)
{
    (void)grp;
    if (state == READING) {
        state = DONE;
    }
}

int hal_acq_trigger(uint32_t channel_mask, uint16_t n_samples)
{
    uint32_t c;
    if (!started || state == LISTEN || state == READING || channel_mask == 0 ||
        (channel_mask >> RP2040_SENSORS) != 0 || n_samples == 0 || n_samples > MAX_SAMPLES) {
        return -1;
    }
    if (n_samples != dev_n) {
        for (c = 0; c < RP2040_SENSORS; c++) {
            if (ch_set_num_samples(&devs[c], n_samples) != 0) {
                return -1;
            }
        }
        dev_n = n_samples;
    }
    acq_mask = channel_mask;
    acq_n = n_samples;
    int_seen = 0;
    /* the listening time (n samples at about 22 kHz: < 10 ms) and the reads, with margin */
    acq_deadline_us = hal_time_us() + DEADLINE_US;
    state = LISTEN;
    ch_group_trigger(&group);
    return 0;
}

int hal_acq_ready(void)
{
    uint8_t s = state;
    if ((s == LISTEN || s == READING) && hal_time_us() > acq_deadline_us) {
        uint8_t c;
        uint32_t irq = save_and_disable_interrupts(); /* no callback between check and give-up */
        if (state == DONE) {
            restore_interrupts(irq);
            return 1;
        }
        state = FAILED;
        /* a read still under way is abandoned with its bus, and SonicLib's non-blocking queue
         * emptied (chdrv_queue_t, ch_driver.h), or the next ch_io_start_nb would find it busy */
        for (c = 0; c < RP2040_SENSORS; c++) {
            chbsp_i2c_reset(&devs[c]);
        }
        for (c = 0; c < RP2040_SENSOR_BUSES; c++) {
            group.queue[c].len = 0;
            group.queue[c].idx = 0;
            group.queue[c].running = 0;
        }
        restore_interrupts(irq);
        return 1;
    }
    return s == DONE || s == FAILED;
}

static const iq_pair_t *channel_iq(uint8_t channel, uint16_t n_samples)
{
    if (state != DONE || channel >= RP2040_SENSORS || !(acq_mask & (1u << channel)) ||
        n_samples > acq_n) {
        return NULL;
    }
    return (const iq_pair_t *)(const void *)iq[channel];
}

int hal_acq_read(uint8_t channel, uint16_t *samples, uint16_t n_samples)
{
    const iq_pair_t *p = channel_iq(channel, n_samples);
    if (p == NULL) {
        return -1;
    }
    iq_magnitudes(p, samples, n_samples);
    return 0;
}

int hal_acq_read_iq(uint8_t channel, uint16_t *qi, uint16_t n_samples)
{
    const iq_pair_t *p = channel_iq(channel, n_samples);
    if (p == NULL) {
        return -1;
    }
    iq_words(p, qi, n_samples);
    return 0;
}

/* Start the sensors (at boot, blocking: the sensor firmware is loaded and each sensor's clock
 * calibrated against a 100 ms pulse) and describe them in the board info. 0 ok, -1: no sensor
 * group (then every trigger is refused; the board still answers on USB). */
int rp2040_sensor_init(hal_board_info_t *board)
{
    uint8_t c;
    ch_config_t cfg;
    uint32_t freq;
    chbsp_rp2040_board_init();
    chbsp_rp2040_set_group(&group);
    if (ch_group_init(&group, RP2040_SENSORS, RP2040_SENSOR_BUSES, CHIRP_RTC_CAL_PULSE_MS) != 0) {
        return -1;
    }
    for (c = 0; c < RP2040_SENSORS; c++) {
        if (ch_init(&devs[c], &group, c, ch101_gpr_init) != 0) {
            return -1;
        }
    }
    if (ch_group_start(&group) != 0) {
        return -1;
    }
    for (c = 0; c < RP2040_SENSORS; c++) {
        cfg.mode = c == 0 ? CH_MODE_TRIGGERED_TX_RX : CH_MODE_TRIGGERED_RX_ONLY;
        cfg.max_range = 0;
        cfg.sample_interval = 0;
        cfg.tgt_int_filter = CH_TGT_INT_FILTER_OFF;
        if (!ch_sensor_is_connected(&devs[c]) || ch_set_config(&devs[c], &cfg) != 0 ||
            ch_set_num_samples(&devs[c], MAX_SAMPLES) != 0) {
            return -1;
        }
    }
    dev_n = MAX_SAMPLES;
    ch_io_int_callback_set(&group, on_int);
    ch_io_complete_callback_set(&group, on_io_done);
    freq = ch_get_frequency(&devs[0]);
    if (freq > 0) {
        board->emitter_freq_hz = freq;
        board->default_sample_rate_hz = (freq + 4u) / 8u; /* the sensor's output rate */
    }
    board->max_samples = MAX_SAMPLES;
    board->default_n_samples = MAX_SAMPLES;
    started = 1;
    return 0;
}
