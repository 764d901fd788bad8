/*
 * iq_plan.h - the pure logic of the RP2040's CH101 sensor layer (no SonicLib, no hardware):
 * I/Q samples to what the protocol carries, and the I2C time an acquisition costs on each bus.
 * Built into the SonicLib variant of the RP2040 target and, for the tests, on the host
 * (tests/firmware/test_rp2040_soniclib.py).
 */
#ifndef SPIEL_IQ_PLAN_H
#define SPIEL_IQ_PLAN_H

#include <stdint.h>

/* One I/Q sample as the sensor gives it: q first, then i (the order of PROTOCOL.md 14.4). */
typedef struct {
    int16_t q;
    int16_t i;
} iq_pair_t;

/* round(sqrt(q^2 + i^2)): the envelope sample (U16_ENVELOPE). At most 46341, never wraps. */
uint16_t iq_magnitude(int16_t q, int16_t i);
/* n envelope samples from n I/Q pairs */
void iq_magnitudes(const iq_pair_t *iq, uint16_t *out, uint16_t n);
/* n I/Q pairs as the 2n wire words q0 i0 q1 i1 ... (two's complement in uint16_t), I16_IQ */
void iq_words(const iq_pair_t *iq, uint16_t *out, uint16_t n);

/* Bus time of one I2C register read of n_bytes at scl_hz, in ns: START, address+W, the
 * register byte, repeated START, address+R, the data, STOP (9 clocks a byte with its ACK,
 * one clock for each START/repeated START/STOP). Clock stretching is not counted. */
uint32_t iq_i2c_read_ns(uint32_t n_bytes, uint32_t scl_hz);

/* The I2C time of one acquisition: every channel of mask reads n_samples I/Q samples (4 bytes
 * each) on its bus (bus_of[channel], 0 .. n_buses - 1); the buses run in parallel, each
 * reads its channels one after another, so the acquisition's read time is the slowest bus's
 * sum. In us, rounded up. */
uint32_t iq_acq_read_us(uint32_t mask, uint16_t n_samples, const uint8_t *bus_of, uint8_t n_ch,
                        uint8_t n_buses, uint32_t scl_hz);

/* Acquisitions per second, times 100, that one sensor group sustains: each acquisition
 * listens (n_samples / sample_rate_hz), then is read (iq_acq_read_us) before the next trigger
 * (SonicLib must not trigger while a read runs), plus overhead_us per acquisition. */
uint32_t iq_acq_rate_centi(uint32_t mask, uint16_t n_samples, uint32_t sample_rate_hz,
                           const uint8_t *bus_of, uint8_t n_ch, uint8_t n_buses,
                           uint32_t scl_hz, uint32_t overhead_us);

#endif
