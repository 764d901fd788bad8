/*
 * iq_plan.c - see iq_plan.h. C99, no I/O: the same file builds for the RP2040 and the host.
 */
#include "iq_plan.h"

/* floor(sqrt(v)), bit by bit (no division: the Cortex-M0+ has none) */
static uint32_t isqrt32(uint32_t v)
{
    uint32_t r = 0, bit = 1u << 30;
    while (bit > v) {
        bit >>= 2;
    }
    while (bit != 0) {
        if (v >= r + bit) {
            v -= r + bit;
            r = (r >> 1) + bit;
        } else {
            r >>= 1;
        }
        bit >>= 2;
    }
    return r;
}

uint16_t iq_magnitude(int16_t q, int16_t i)
{
    int32_t qq = q, ii = i;
    uint32_t v = (uint32_t)(qq * qq) + (uint32_t)(ii * ii); /* <= 2^31 */
    uint32_t r = isqrt32(v);
    /* round to nearest: r + 0.5 <= sqrt(v)  <=>  r^2 + r + 0.25 <= v  <=>  r^2 + r < v */
    if (r * r + r < v) {
        r++;
    }
    return (uint16_t)r;
}

void iq_magnitudes(const iq_pair_t *iq, uint16_t *out, uint16_t n)
{
    uint16_t k;
    for (k = 0; k < n; k++) {
        out[k] = iq_magnitude(iq[k].q, iq[k].i);
    }
}

void iq_words(const iq_pair_t *iq, uint16_t *out, uint16_t n)
{
    uint16_t k;
    for (k = 0; k < n; k++) {
        out[2u * k] = (uint16_t)iq[k].q;
        out[2u * k + 1u] = (uint16_t)iq[k].i;
    }
}

uint32_t iq_i2c_read_ns(uint32_t n_bytes, uint32_t scl_hz)
{
    uint64_t clocks = (3u + (uint64_t)n_bytes) * 9u + 3u;
    if (scl_hz == 0) {
        return UINT32_MAX;
    }
    return (uint32_t)((clocks * 1000000000u + scl_hz - 1u) / scl_hz);
}

uint32_t iq_acq_read_us(uint32_t mask, uint16_t n_samples, const uint8_t *bus_of, uint8_t n_ch,
                        uint8_t n_buses, uint32_t scl_hz)
{
    uint64_t worst = 0;
    uint8_t b, c;
    for (b = 0; b < n_buses; b++) {
        uint64_t ns = 0;
        for (c = 0; c < n_ch && c < 32u; c++) {
            if ((mask & (1u << c)) && bus_of[c] == b) {
                ns += iq_i2c_read_ns(4u * (uint32_t)n_samples, scl_hz);
            }
        }
        if (ns > worst) {
            worst = ns;
        }
    }
    return (uint32_t)((worst + 999u) / 1000u);
}

uint32_t iq_acq_rate_centi(uint32_t mask, uint16_t n_samples, uint32_t sample_rate_hz,
                           const uint8_t *bus_of, uint8_t n_ch, uint8_t n_buses,
                           uint32_t scl_hz, uint32_t overhead_us)
{
    uint64_t period_us;
    if (sample_rate_hz == 0) {
        return 0;
    }
    period_us = ((uint64_t)n_samples * 1000000u + sample_rate_hz - 1u) / sample_rate_hz +
                iq_acq_read_us(mask, n_samples, bus_of, n_ch, n_buses, scl_hz) + overhead_us;
    return period_us == 0 ? 0 : (uint32_t)(100000000u / period_us);
}
