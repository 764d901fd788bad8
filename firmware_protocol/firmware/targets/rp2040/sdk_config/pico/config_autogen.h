/* pico/config_autogen.h - what the Pico SDK's CMake would generate: the board header. Written
 * by hand here because this target builds with make alone (targets/rp2040/target.mk). */
#ifndef SPIEL_RP2040_CONFIG_AUTOGEN_H
#define SPIEL_RP2040_CONFIG_AUTOGEN_H
#include "boards/pico.h"
#endif
