/*
 * chbsp_rp2040.h - the RP2040 board support of SonicLib (chbsp_rp2040.c): what the sensor
 * layer (sensor_soniclib.c) needs beyond SonicLib's own chbsp_* interface.
 *
 * Wiring (docs/build-a-board.md): four CH101, two per I2C bus at 400 kHz.
 *   I2C0 SDA GP4, SCL GP5: sensors 0, 1        I2C1 SDA GP6, SCL GP7: sensors 2, 3
 *   INT 0..3  GP10..GP13 (per sensor; SonicLib triggers through them and the sensor answers
 *             with a high pulse when its measurement is ready)
 *   PROG 0..3 GP14..GP17 (per sensor, active high)
 *   RESET_N   GP18 (all four, active low)
 */
#ifndef SPIEL_CHBSP_RP2040_H
#define SPIEL_CHBSP_RP2040_H

#include <stdint.h>

#define RP2040_SENSORS 4u
#define RP2040_SENSOR_BUSES 2u
#define RP2040_I2C_HZ 400000u
/* each sensor's bus (the wiring above), shared with the timing budget (iq_plan.h) */
extern const uint8_t rp2040_sensor_bus[RP2040_SENSORS];

struct ch_group_t;
/* The group whose interrupts and non-blocking I/O completions the BSP reports (ch_interrupt,
 * ch_io_notify). Set before ch_group_start. */
void chbsp_rp2040_set_group(struct ch_group_t *grp);
/* GPIO and I2C blocks out of reset, pins set up, RESET_N held low, PROG low: call first. */
void chbsp_rp2040_board_init(void);
/* Interrupt handlers (vector table, startup_rp2040.c) */
void isr_io_bank0(void);
void isr_i2c0(void);
void isr_i2c1(void);

#endif
