/*
 * harness.c - runs the RP2040 sensor layer (targets/rp2040/sensor/sensor_soniclib.c) and
 * SonicLib's own non-blocking queue (the user's checkout, SPIEL_SONICLIB_DIR) on the host,
 * with a fake board in place of chbsp_rp2040.c: four sensors, two per bus; non-blocking reads
 * are recorded and completed when the harness says. What it checks cannot be seen on the
 * emulator (no sensor there): the acquisition's flow through SonicLib across two buses.
 * Prints one line per check; exits non-zero on the first failure.
 * ch_group_start is the harness's (ch_api.c is built with it renamed): no sensor firmware is
 * loaded, the group is marked started with every sensor connected.
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "chbsp_rp2040.h"
#include "invn/soniclib/chirp_bsp.h"
#include "invn/soniclib/soniclib.h"
#include "rp2040_board.h"
#include "spiel_hal.h"

#define CHECK(cond, what)                                                                    \
    do {                                                                                     \
        if (!(cond)) {                                                                       \
            printf("FAIL %s (line %d)\n", what, __LINE__);                                   \
            exit(1);                                                                         \
        }                                                                                    \
        printf("ok %s\n", what);                                                             \
    } while (0)

const uint8_t rp2040_sensor_bus[RP2040_SENSORS] = {0, 0, 1, 1};
static const uint8_t address[RP2040_SENSORS] = {0x29, 0x2A, 0x2B, 0x2C};
static ch_group_t *grp;
static uint64_t now_us;
static int triggers;

/* the reads started, in order: bus, address, bytes; at most one running per bus */
typedef struct {
    uint8_t bus, addr;
    uint16_t n;
    uint8_t *buf;
} nb_read_t;
static nb_read_t started[16];
static int n_started;
static int running[2] = {-1, -1};

uint64_t hal_time_us(void) { return now_us; }
void chbsp_rp2040_set_group(struct ch_group_t *g) { grp = g; }
void chbsp_rp2040_board_init(void) {}
int chbsp_i2c_init(void) { return 0; }
uint8_t chbsp_i2c_get_info(ch_group_t *g, uint8_t dev_num, ch_i2c_info_t *info)
{
    (void)g;
    info->address = address[dev_num];
    info->bus_num = rp2040_sensor_bus[dev_num];
    info->drv_flags = 0;
    return 0;
}
int chbsp_i2c_write(ch_dev_t *d, const uint8_t *data, uint16_t n) { (void)d; (void)data; (void)n; return 0; }
int chbsp_i2c_mem_write(ch_dev_t *d, uint16_t a, uint8_t *data, uint16_t n) { (void)d; (void)a; (void)data; (void)n; return 0; }
int chbsp_i2c_read(ch_dev_t *d, uint8_t *data, uint16_t n) { (void)d; memset(data, 0, n); return 0; }
int chbsp_i2c_mem_read(ch_dev_t *d, uint16_t a, uint8_t *data, uint16_t n) { (void)d; (void)a; memset(data, 0, n); return 0; }
void chbsp_i2c_reset(ch_dev_t *d) { running[ch_get_bus(d)] = -1; }
void chbsp_reset_assert(void) {}
void chbsp_reset_release(void) {}
void chbsp_program_enable(ch_dev_t *d) { (void)d; }
void chbsp_program_disable(ch_dev_t *d) { (void)d; }
void chbsp_group_set_int1_dir_out(ch_group_t *g) { (void)g; }
void chbsp_group_int1_set(ch_group_t *g) { (void)g; triggers++; }
void chbsp_delay_us(uint32_t us) { now_us += us; }
void chbsp_delay_ms(uint32_t ms) { now_us += 1000u * ms; }
uint32_t chbsp_timestamp_ms(void) { return (uint32_t)(now_us / 1000u); }

int chbsp_i2c_mem_read_nb(ch_dev_t *d, uint16_t mem_addr, uint8_t *data, uint16_t n)
{
    uint8_t bus = ch_get_bus(d);
    (void)mem_addr;
    if (running[bus] >= 0 || n_started >= 16) {
        printf("FAIL a second read started on bus %u while one runs\n", bus);
        exit(1);
    }
    started[n_started] = (nb_read_t){bus, ch_get_i2c_address(d), n, data};
    running[bus] = n_started++;
    return 0;
}

/* the harness's ch_group_start: every sensor connected, the group started */
uint8_t ch_group_start(ch_group_t *g)
{
    uint8_t k;
    for (k = 0; k < RP2040_SENSORS; k++) {
        g->device[k]->sensor_connected = 1;
        g->device[k]->i2c_address = g->device[k]->app_i2c_address; /* as programming leaves it */
        g->num_connected[rp2040_sensor_bus[k]]++;
    }
    g->status = CH_GROUP_STAT_INIT_OK;
    return 0;
}

/* finish the running read on a bus: sensor k's sample j is q = 100 k + j, i = -(j + 1) */
static void complete(uint8_t bus)
{
    nb_read_t *r = &started[running[bus]];
    int k = r->addr - 0x29, j;
    for (j = 0; j < r->n / 4; j++) {
        int16_t q = (int16_t)(100 * k + j), i = (int16_t)(-(j + 1));
        memcpy(r->buf + 4 * j, &q, 2);
        memcpy(r->buf + 4 * j + 2, &i, 2);
    }
    running[bus] = -1;
    ch_io_notify(grp, bus);
}

int main(void)
{
    static hal_board_info_t board;
    uint16_t env[64], qi[128];
    int k;
    CHECK(rp2040_sensor_init(&board) == 0, "the sensor group starts");
    CHECK(board.max_samples == 64 && board.default_n_samples == 64, "board info: 64 samples");

    /* one acquisition of all four channels */
    CHECK(hal_acq_trigger(0xF, 64) == 0 && triggers == 1, "a trigger pulses the INT lines once");
    CHECK(!hal_acq_ready(), "not ready before the sensors' interrupts");
    CHECK(hal_acq_trigger(0xF, 64) < 0, "a second trigger while listening is refused");
    for (k = 0; k < 3; k++) {
        ch_interrupt(grp, (uint8_t)k);
    }
    CHECK(n_started == 0, "no read before the last sensor of the mask is ready");
    ch_interrupt(grp, 3);
    CHECK(n_started == 2 && started[0].bus != started[1].bus, "both buses start reading at once");
    CHECK(started[0].n == 256 && started[1].n == 256, "each read is 64 I/Q samples, 256 bytes");
    CHECK(hal_acq_trigger(0xF, 64) < 0, "a trigger while reading is refused");
    complete(0);
    CHECK(n_started == 3 && started[2].bus == 0, "bus 0's second sensor follows its first");
    CHECK(!hal_acq_ready(), "not ready while bus 1 still reads");
    complete(1);
    CHECK(n_started == 4 && started[3].bus == 1, "bus 1's second sensor follows its first");
    complete(0);
    CHECK(!hal_acq_ready(), "not ready before the last read");
    complete(1);
    CHECK(hal_acq_ready(), "ready once every read is done");
    {
        int seen = 0;
        for (k = 0; k < 4; k++) {
            seen |= 1 << (started[k].addr - 0x29);
            if (rp2040_sensor_bus[started[k].addr - 0x29] != started[k].bus) {
                seen = -1;
                break;
            }
        }
        CHECK(seen == 0xF, "each sensor read once, on its own bus");
    }
    CHECK(hal_acq_read_iq(2, qi, 64) == 0 && (int16_t)qi[0] == 200 && (int16_t)qi[1] == -1 &&
              (int16_t)qi[126] == 263 && (int16_t)qi[127] == -64,
          "I/Q words are the sensor's q, i pairs");
    CHECK(hal_acq_read(1, env, 64) == 0 && env[0] == 100 && env[63] == 175,
          "envelope = round(sqrt(q^2 + i^2)) (sensor 1: |(100, -1)| = 100, |(163, -64)| = 175.1)");

    /* a subset: channels 0 and 2, one sensor on each bus; 32 samples (a register write) */
    n_started = 0;
    CHECK(hal_acq_trigger(0x5, 32) == 0, "a subset triggers");
    ch_interrupt(grp, 0);
    ch_interrupt(grp, 2);
    CHECK(n_started == 2 && started[0].n == 128 && started[1].n == 128 &&
              started[0].bus != started[1].bus,
          "a subset reads its two sensors, 32 samples, one on each bus");
    complete(0);
    complete(1);
    CHECK(hal_acq_ready() && n_started == 2, "and is ready after those two reads");
    CHECK(hal_acq_read(1, env, 32) < 0, "a channel outside the mask does not read");
    CHECK(hal_acq_read(0, env, 64) < 0, "more samples than measured do not read");

    /* a bus that never finishes: the acquisition fails at its deadline, the next one works */
    n_started = 0;
    CHECK(hal_acq_trigger(0xF, 64) == 0, "trigger again");
    for (k = 0; k < 4; k++) {
        ch_interrupt(grp, (uint8_t)k);
    }
    complete(0); /* bus 0 moves on to its second sensor; bus 1 hangs on its first */
    now_us += 49000u;
    CHECK(!hal_acq_ready(), "still waiting 49 ms after the trigger");
    now_us += 2000u;
    CHECK(hal_acq_ready(), "given up 50 ms after the trigger");
    CHECK(hal_acq_read(0, env, 64) < 0 && hal_acq_read_iq(3, qi, 64) < 0,
          "a failed acquisition reads nothing");
    n_started = 0;
    CHECK(hal_acq_trigger(0xF, 64) == 0, "the next trigger is accepted");
    for (k = 0; k < 4; k++) {
        ch_interrupt(grp, (uint8_t)k);
    }
    CHECK(n_started == 2, "SonicLib's queue was emptied: both buses start afresh");
    complete(0);
    complete(1);
    complete(0);
    complete(1);
    CHECK(hal_acq_ready() && hal_acq_read(3, env, 64) == 0 && env[0] == 300,
          "and the acquisition after the failed one completes");
    return 0;
}
