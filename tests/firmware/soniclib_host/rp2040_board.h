/* host stand-in for targets/rp2040/rp2040_board.h: what sensor_soniclib.c takes from it */
#ifndef SPIEL_RP2040_BOARD_H
#define SPIEL_RP2040_BOARD_H
#include "spiel_hal.h"
#define RP2040_SONICLIB 1
int rp2040_sensor_init(hal_board_info_t *board);
#endif
