/*
 * chirp_board_config.h - what SonicLib asks of a board (chirp_bsp.h): the sensor and bus
 * counts of the Pico wiring (chbsp_rp2040.h). SonicLib finds it on the include path.
 */
#ifndef CHIRP_BOARD_CONFIG_H_
#define CHIRP_BOARD_CONFIG_H_

#define INCLUDE_WHITNEY_SUPPORT /* CH101 and CH201 */
#define CHIRP_MAX_NUM_SENSORS 4
#define CHIRP_NUM_BUSES 2
#define CHIRP_RTC_CAL_PULSE_MS 100

#endif
