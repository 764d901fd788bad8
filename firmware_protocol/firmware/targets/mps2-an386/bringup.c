/*
 * bringup.c - a stand-alone bring-up image for the mps2-an386 target (make TARGET=mps2-bringup):
 * no device core, only the frame layer (../../c/spiel_proto.c) over the HAL's UART. Every
 * valid frame is answered with a RESPONSE frame of the same type, seq and payload, so a host
 * can check the UART, the clock and the framing before the core runs.
 */
#include "spiel_hal.h"
#include "spiel_proto.h"

void mps2_hal_init(void);

static sp_decoder_t decoder;
static uint8_t tx[SP_MAX_WIRE];

static void send_all(const uint8_t *p, size_t n)
{
    while (n > 0) {
        size_t k = hal_transport_write(p, n);
        p += k;
        n -= k;
    }
}

int main(void)
{
    uint8_t rx[64];
    mps2_hal_init();
    sp_decoder_init(&decoder);
    for (;;) {
        size_t i, n = hal_transport_read(rx, sizeof rx);
        for (i = 0; i < n; i++) {
            sp_frame_t f;
            if (sp_decoder_feed(&decoder, rx[i], &f)) {
                size_t w = sp_frame_encode(f.header.msg_type, f.header.seq, SP_FLAG_RESPONSE,
                                           (uint32_t)hal_time_us(), f.payload,
                                           f.header.payload_len, tx, sizeof tx);
                send_all(tx, w);
            }
        }
    }
}
