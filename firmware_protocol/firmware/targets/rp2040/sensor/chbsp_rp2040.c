/*
 * chbsp_rp2040.c - SonicLib's board support (chirp_bsp.h) for CH101/CH201 on the Raspberry Pi
 * Pico: the pins of chbsp_rp2040.h, I2C on the RP2040's two DW_apb_i2c blocks at 400 kHz
 * (register level: the vendored SDK has no I2C driver), blocking and interrupt-driven
 * (non-blocking) register reads, the INT lines as SonicLib's trigger outputs and data-ready
 * inputs (rising edge), PROG and RESET_N as outputs.
 *
 * Non-blocking reads (chbsp_i2c_mem_read_nb): SonicLib queues one read per sensor on its
 * bus (ch_get_iq_data with CH_IO_MODE_NONBLOCK) and starts each bus's first one
 * (ch_io_start_nb); each completes in the bus's interrupt, which calls ch_io_notify, which
 * starts that bus's next read or, once every bus is idle, calls the group's I/O completion
 * callback. The two buses run at the same time.
 *
 * On hardware only: nothing here runs in the emulator or the tests (docs/firmware.md).
 */
#include <stddef.h>

#include "chbsp_rp2040.h"
#include "hardware/address_mapped.h"
#include "hardware/irq.h"
#include "hardware/resets.h"
#include "hardware/structs/i2c.h"
#include "hardware/structs/io_bank0.h"
#include "hardware/structs/pads_bank0.h"
#include "hardware/structs/sio.h"
#include "invn/soniclib/soniclib.h"
#include "invn/soniclib/chirp_bsp.h"
#include "spiel_hal.h"

#define PIN_SDA0 4u
#define PIN_SCL0 5u
#define PIN_SDA1 6u
#define PIN_SCL1 7u
#define PIN_INT0 10u  /* INT k: GP10 + k */
#define PIN_PROG0 14u /* PROG k: GP14 + k */
#define PIN_RESET_N 18u
#define FUNC_I2C 3u
#define FUNC_SIO 5u
#define EDGE_HIGH 0x8u /* the per-pin interrupt bits: level low, level high, edge low, edge high */
#define FIFO_DEPTH 16u

const uint8_t rp2040_sensor_bus[RP2040_SENSORS] = {0, 0, 1, 1};
/* each sensor's address once SonicLib has programmed it (they start at 0x45, selected by PROG) */
static const uint8_t app_address[RP2040_SENSORS] = {0x29, 0x2A, 0x2B, 0x2C};
static ch_group_t *group;

/* ---- pins ------------------------------------------------------------------------------ */

/* The pad: input on, output allowed; with pull_up the pull-up instead of the reset's pull-down
 * (both on would make a bus keeper); drive strength and slew as reset leaves them. */
static void pin_function(uint32_t pin, uint32_t func, uint32_t pull_up)
{
    uint32_t pad = pads_bank0_hw->io[pin] & ~PADS_BANK0_GPIO0_OD_BITS;
    if (pull_up) {
        pad = (pad & ~PADS_BANK0_GPIO0_PDE_BITS) | PADS_BANK0_GPIO0_PUE_BITS;
    }
    pads_bank0_hw->io[pin] = pad | PADS_BANK0_GPIO0_IE_BITS;
    io_bank0_hw->io[pin].ctrl = func;
}

static uint32_t int_bit(uint32_t pin)
{
    return EDGE_HIGH << (4u * (pin % 8u));
}

static uint32_t int_pin(ch_dev_t *dev)
{
    return PIN_INT0 + ch_get_dev_num(dev);
}

static uint32_t group_int_mask(void)
{
    return 0xFu << PIN_INT0;
}

void chbsp_rp2040_set_group(struct ch_group_t *grp)
{
    group = grp;
}

/* ---- I2C ------------------------------------------------------------------------------- */

/* One transfer on one bus: the register byte (if any) and wlen bytes written, then (repeated
 * START) rlen bytes read, STOP. */
typedef struct {
    i2c_hw_t *hw;
    const uint8_t *w;
    uint8_t *r;
    uint16_t wlen, rlen, wsent, rcmd, rgot;
    volatile uint8_t busy, err, nb;
    uint8_t reg, reg_pending, wrote;
} bus_t;

static bus_t buses[RP2040_SENSOR_BUSES];

static void i2c_setup(i2c_hw_t *hw)
{
    /* clk_sys 125 MHz: an SCL period of 312 cycles, low 60 %, high 40 % (fast mode needs
     * at least 1.3 us low, 0.6 us high) */
    const uint32_t period = 125000000u / RP2040_I2C_HZ, low = period * 3u / 5u;
    hw->enable = 0;
    hw->con = I2C_IC_CON_MASTER_MODE_BITS | I2C_IC_CON_IC_SLAVE_DISABLE_BITS |
              I2C_IC_CON_IC_RESTART_EN_BITS | I2C_IC_CON_TX_EMPTY_CTRL_BITS |
              (I2C_IC_CON_SPEED_VALUE_FAST << I2C_IC_CON_SPEED_LSB);
    hw->fs_scl_lcnt = low;
    hw->fs_scl_hcnt = period - low;
    hw->fs_spklen = low < 16u ? 1u : low / 16u;
    hw->sda_hold = 125u * 3u / 10u + 1u; /* 300 ns of data hold after SCL falls */
    hw->tx_tl = 0;
    hw->rx_tl = 0;
    hw->intr_mask = 0;
}

static bus_t *dev_bus(ch_dev_t *dev)
{
    uint8_t b = ch_get_bus(dev);
    return b < RP2040_SENSOR_BUSES ? &buses[b] : NULL;
}

/* reg < 0: no register byte */
static void xfer_start(bus_t *b, uint8_t addr, int reg, const uint8_t *w, uint16_t wlen,
                       uint8_t *r, uint16_t rlen, uint8_t nb)
{
    i2c_hw_t *hw = b->hw;
    hw->intr_mask = 0;
    hw->enable = 0;
    hw->tar = addr;
    hw->enable = 1;
    (void)hw->clr_intr; /* a stale abort or STOP of the previous transfer */
    b->w = w;
    b->r = r;
    b->wlen = wlen;
    b->rlen = rlen;
    b->wsent = b->rcmd = b->rgot = 0;
    b->reg = (uint8_t)reg;
    b->reg_pending = reg >= 0;
    b->wrote = 0;
    b->err = 0;
    b->nb = nb;
    b->busy = 1;
}

/* Move what can move now; 1 once the transfer is over (b->err says how). Called from the
 * bus's interrupt (non-blocking) or in a loop (blocking). */
static int xfer_service(bus_t *b)
{
    i2c_hw_t *hw = b->hw;
    if (hw->raw_intr_stat & I2C_IC_RAW_INTR_STAT_TX_ABRT_BITS) { /* NACK, lost arbitration */
        (void)hw->clr_tx_abrt;
        b->err = 1;
        b->busy = 0;
        return 1;
    }
    while (b->rgot < b->rlen && hw->rxflr > 0) {
        b->r[b->rgot++] = (uint8_t)hw->data_cmd;
    }
    while (hw->txflr < FIFO_DEPTH && (b->reg_pending || b->wsent < b->wlen || b->rcmd < b->rlen) &&
           (uint16_t)(b->rcmd - b->rgot) < FIFO_DEPTH - 2u) {
        uint32_t cmd;
        if (b->reg_pending || b->wsent < b->wlen) {
            if (b->reg_pending) {
                cmd = b->reg;
                b->reg_pending = 0;
            } else {
                cmd = b->w[b->wsent];
                b->wsent++;
            }
            b->wrote = 1;
            if (b->wsent == b->wlen && b->rlen == 0) {
                cmd |= I2C_IC_DATA_CMD_STOP_BITS;
            }
        } else {
            cmd = I2C_IC_DATA_CMD_CMD_BITS;
            if (b->rcmd == 0 && b->wrote) {
                cmd |= I2C_IC_DATA_CMD_RESTART_BITS;
            }
            b->rcmd++;
            if (b->rcmd == b->rlen) {
                cmd |= I2C_IC_DATA_CMD_STOP_BITS;
            }
        }
        hw->data_cmd = cmd;
    }
    if (!b->reg_pending && b->wsent == b->wlen && b->rgot == b->rlen &&
        (hw->raw_intr_stat & I2C_IC_RAW_INTR_STAT_STOP_DET_BITS)) {
        (void)hw->clr_stop_det;
        b->busy = 0;
        return 1;
    }
    if (b->nb) { /* interrupt on: room for commands while some remain, the received bytes, the end */
        uint32_t waiting = (uint32_t)(b->rcmd - b->rgot);
        hw->rx_tl = waiting > 8u ? 7u : (waiting > 0 ? waiting - 1u : 0u);
        hw->intr_mask = I2C_IC_INTR_MASK_M_TX_ABRT_BITS | I2C_IC_INTR_MASK_M_STOP_DET_BITS |
                        (waiting > 0 ? I2C_IC_INTR_MASK_M_RX_FULL_BITS : 0u) |
                        (b->reg_pending || b->wsent < b->wlen || b->rcmd < b->rlen
                             ? I2C_IC_INTR_MASK_M_TX_EMPTY_BITS
                             : 0u);
    }
    return 0;
}

static int xfer_blocking(ch_dev_t *dev, int reg, const uint8_t *w, uint16_t wlen, uint8_t *r,
                         uint16_t rlen)
{
    bus_t *b = dev_bus(dev);
    uint64_t deadline;
    if (b == NULL || b->busy) {
        return 1;
    }
    /* 2 ms and twice the bytes' time at 400 kHz (22.5 us a byte) */
    deadline = hal_time_us() + 2000u + 45u * ((uint64_t)wlen + rlen + 3u);
    xfer_start(b, ch_get_i2c_address(dev), reg, w, wlen, r, rlen, 0);
    while (!xfer_service(b)) {
        if (hal_time_us() > deadline) {
            b->hw->enable = 0; /* abandons the transfer, frees the bus */
            b->busy = 0;
            return 1;
        }
    }
    return b->err;
}

static void bus_irq(uint8_t n)
{
    bus_t *b = &buses[n];
    if (!b->busy || !b->nb) {
        b->hw->intr_mask = 0;
        return;
    }
    if (xfer_service(b)) {
        b->hw->intr_mask = 0;
        if (group != NULL) {
            ch_io_notify(group, n); /* the bus's next queued read, or the completion callback */
        }
    }
}

void isr_i2c0(void)
{
    bus_irq(0);
}

void isr_i2c1(void)
{
    bus_irq(1);
}

int chbsp_i2c_init(void)
{
    buses[0].hw = i2c0_hw;
    buses[1].hw = i2c1_hw;
    i2c_setup(i2c0_hw);
    i2c_setup(i2c1_hw);
    irq_set_enabled(I2C0_IRQ, true);
    irq_set_enabled(I2C1_IRQ, true);
    return 0;
}

uint8_t chbsp_i2c_get_info(ch_group_t *grp_ptr, uint8_t dev_num, ch_i2c_info_t *info_ptr)
{
    (void)grp_ptr;
    if (dev_num >= RP2040_SENSORS) {
        return 1;
    }
    info_ptr->address = app_address[dev_num];
    info_ptr->bus_num = rp2040_sensor_bus[dev_num];
    info_ptr->drv_flags = 0;
    return 0;
}

int chbsp_i2c_write(ch_dev_t *dev_ptr, const uint8_t *data, uint16_t num_bytes)
{
    return xfer_blocking(dev_ptr, -1, data, num_bytes, NULL, 0);
}

int chbsp_i2c_mem_write(ch_dev_t *dev_ptr, uint16_t mem_addr, uint8_t *data, uint16_t num_bytes)
{
    return xfer_blocking(dev_ptr, (uint8_t)mem_addr, data, num_bytes, NULL, 0);
}

int chbsp_i2c_read(ch_dev_t *dev_ptr, uint8_t *data, uint16_t num_bytes)
{
    return xfer_blocking(dev_ptr, -1, NULL, 0, data, num_bytes);
}

int chbsp_i2c_mem_read(ch_dev_t *dev_ptr, uint16_t mem_addr, uint8_t *data, uint16_t num_bytes)
{
    return xfer_blocking(dev_ptr, (uint8_t)mem_addr, NULL, 0, data, num_bytes);
}

int chbsp_i2c_mem_read_nb(ch_dev_t *dev_ptr, uint16_t mem_addr, uint8_t *data, uint16_t num_bytes)
{
    bus_t *b = dev_bus(dev_ptr);
    if (b == NULL || b->busy) {
        return 1;
    }
    xfer_start(b, ch_get_i2c_address(dev_ptr), (uint8_t)mem_addr, NULL, 0, data, num_bytes, 1);
    (void)xfer_service(b); /* fills the FIFO and arms the interrupt */
    return 0;
}

void chbsp_i2c_reset(ch_dev_t *dev_ptr)
{
    bus_t *b = dev_bus(dev_ptr);
    if (b != NULL) {
        b->busy = 0;
        i2c_setup(b->hw);
    }
}

/* ---- INT, PROG, RESET_N ------------------------------------------------------------------- */

void chbsp_reset_assert(void)
{
    sio_hw->gpio_clr = 1u << PIN_RESET_N;
}

void chbsp_reset_release(void)
{
    sio_hw->gpio_set = 1u << PIN_RESET_N;
}

void chbsp_program_enable(ch_dev_t *dev_ptr)
{
    sio_hw->gpio_set = 1u << (PIN_PROG0 + ch_get_dev_num(dev_ptr));
}

void chbsp_program_disable(ch_dev_t *dev_ptr)
{
    sio_hw->gpio_clr = 1u << (PIN_PROG0 + ch_get_dev_num(dev_ptr));
}

void chbsp_group_set_int1_dir_out(ch_group_t *grp_ptr)
{
    (void)grp_ptr;
    sio_hw->gpio_oe_set = group_int_mask();
}

void chbsp_set_int1_dir_out(ch_dev_t *dev_ptr)
{
    sio_hw->gpio_oe_set = 1u << int_pin(dev_ptr);
}

void chbsp_group_set_int1_dir_in(ch_group_t *grp_ptr)
{
    (void)grp_ptr;
    sio_hw->gpio_oe_clr = group_int_mask();
}

void chbsp_set_int1_dir_in(ch_dev_t *dev_ptr)
{
    sio_hw->gpio_oe_clr = 1u << int_pin(dev_ptr);
}

void chbsp_group_int1_clear(ch_group_t *grp_ptr)
{
    (void)grp_ptr;
    sio_hw->gpio_clr = group_int_mask();
}

void chbsp_int1_clear(ch_dev_t *dev_ptr)
{
    sio_hw->gpio_clr = 1u << int_pin(dev_ptr);
}

void chbsp_group_int1_set(ch_group_t *grp_ptr)
{
    (void)grp_ptr;
    sio_hw->gpio_set = group_int_mask();
}

void chbsp_int1_set(ch_dev_t *dev_ptr)
{
    sio_hw->gpio_set = 1u << int_pin(dev_ptr);
}

static void int_enable(uint32_t pin, int on)
{
    io_bank0_hw->intr[pin / 8u] = int_bit(pin); /* a stale edge (the trigger pulse) */
    if (on) {
        hw_set_bits(&io_bank0_hw->proc0_irq_ctrl.inte[pin / 8u], int_bit(pin));
    } else {
        hw_clear_bits(&io_bank0_hw->proc0_irq_ctrl.inte[pin / 8u], int_bit(pin));
    }
}

void chbsp_int1_interrupt_enable(ch_dev_t *dev_ptr)
{
    int_enable(int_pin(dev_ptr), 1);
}

void chbsp_int1_interrupt_disable(ch_dev_t *dev_ptr)
{
    int_enable(int_pin(dev_ptr), 0);
}

void chbsp_group_int1_interrupt_enable(ch_group_t *grp_ptr)
{
    uint32_t k;
    (void)grp_ptr;
    for (k = 0; k < RP2040_SENSORS; k++) {
        int_enable(PIN_INT0 + k, 1);
    }
}

void chbsp_group_int1_interrupt_disable(ch_group_t *grp_ptr)
{
    uint32_t k;
    (void)grp_ptr;
    for (k = 0; k < RP2040_SENSORS; k++) {
        int_enable(PIN_INT0 + k, 0);
    }
}

/* A sensor's data-ready pulse: disarm its line (SonicLib re-arms it at the next trigger) and
 * tell SonicLib, which calls the group's interrupt callback (sensor_soniclib.c). */
void isr_io_bank0(void)
{
    uint32_t k;
    for (k = 0; k < RP2040_SENSORS; k++) {
        uint32_t pin = PIN_INT0 + k;
        if (io_bank0_hw->proc0_irq_ctrl.ints[pin / 8u] & int_bit(pin)) {
            int_enable(pin, 0);
            if (group != NULL) {
                ch_interrupt(group, (uint8_t)k);
            }
        }
    }
}

/* ---- time -------------------------------------------------------------------------------- */

void chbsp_delay_us(uint32_t us)
{
    uint64_t end = hal_time_us() + us;
    while (hal_time_us() < end) {
    }
}

void chbsp_delay_ms(uint32_t ms)
{
    chbsp_delay_us(ms * 1000u);
}

uint32_t chbsp_timestamp_ms(void)
{
    return (uint32_t)(hal_time_us() / 1000u);
}

/* ---- start-up ------------------------------------------------------------------------------ */

void chbsp_rp2040_board_init(void)
{
    uint32_t k, outs = (1u << PIN_RESET_N) | (0xFu << PIN_PROG0);
    unreset_block_wait(RESETS_RESET_IO_BANK0_BITS | RESETS_RESET_PADS_BANK0_BITS |
                       RESETS_RESET_I2C0_BITS | RESETS_RESET_I2C1_BITS);
    pin_function(PIN_SDA0, FUNC_I2C, 1); /* the modules' pull-ups do the work; these help */
    pin_function(PIN_SCL0, FUNC_I2C, 1);
    pin_function(PIN_SDA1, FUNC_I2C, 1);
    pin_function(PIN_SCL1, FUNC_I2C, 1);
    for (k = 0; k < RP2040_SENSORS; k++) {
        pin_function(PIN_INT0 + k, FUNC_SIO, 0);
        pin_function(PIN_PROG0 + k, FUNC_SIO, 0);
    }
    pin_function(PIN_RESET_N, FUNC_SIO, 0);
    sio_hw->gpio_clr = outs | group_int_mask(); /* RESET_N asserted, PROG and INT low */
    sio_hw->gpio_oe_set = outs;
    sio_hw->gpio_oe_clr = group_int_mask();
    io_bank0_hw->intr[PIN_INT0 / 8u] = 0xFFFFFFFFu;
    irq_set_enabled(IO_IRQ_BANK0, true);
}
