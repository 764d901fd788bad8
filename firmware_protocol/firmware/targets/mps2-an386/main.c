/*
 * main.c - the mps2-an386 firmware: the portable core (spiel_device.h) over hal_mps2.c.
 * Between polls the CPU sleeps (WFI) until a byte arrives or the core's next deadline.
 */
#include "spiel_device.h"

void mps2_hal_init(void);
void mps2_wait(uint32_t us);

int main(void)
{
    mps2_hal_init();
    spiel_device_init();
    for (;;) {
        uint32_t idle;
        spiel_device_poll();
        idle = spiel_device_idle_us();
        if (idle > 0) {
            mps2_wait(idle);
        }
    }
}
