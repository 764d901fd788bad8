/*
 * main.c - the RP2040 firmware: the portable core (spiel_device.h) over hal_rp2040.c, with
 * TinyUSB's device task in the same loop. Between polls the CPU sleeps (WFI) until USB wakes
 * it or the core's next deadline.
 */
#include "rp2040_board.h"
#include "spiel_device.h"
#include "tusb.h"

int main(void)
{
    rp2040_hal_init();
    spiel_device_init();
    for (;;) {
        uint32_t idle;
        tud_task();
        spiel_device_poll();
        idle = spiel_device_idle_us();
        if (idle > 0) {
            rp2040_wait(idle);
        }
    }
}
