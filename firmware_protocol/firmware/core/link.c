/* link.c - the state the units of the core share: the link as negotiated (version, payload
 * limit, boot id), whether a stream runs, a reboot asked for, the counters, the sample buffer
 * and the LOG queue. The lowest unit: it calls no other unit of the core; every other unit may
 * read and update it (device.c owns the link and the stream, telemetry.c drains the queue). */
#include <string.h>

#include "core.h"

spiel_link_t spiel_link;
spiel_device_stats_t spiel_stats;
uint16_t spiel_samples[SPIEL_MAX_SAMPLES];

void link_init(void)
{
    memset(&spiel_link, 0, sizeof spiel_link);
    memset(&spiel_stats, 0, sizeof spiel_stats);
    spiel_link.boot_id = hal_random();
    spiel_link.version = 1;
    spiel_link.max_payload = (uint16_t)SPIEL_MAX_PAYLOAD;
    spiel_link.log.level = SP_LOG_INFO;
}

uint16_t link_sample_capacity(void)
{
    return (uint16_t)(SPIEL_MAX_SAMPLES > 0xFFFFu ? 0xFFFFu : SPIEL_MAX_SAMPLES);
}

void link_reboot_after_ms(int mode, uint32_t ms)
{
    spiel_link.reboot_pending = 1;
    spiel_link.reboot_mode = mode;
    spiel_link.reboot_at = hal_time_us() + (uint64_t)ms * 1000u;
}

void link_log(uint8_t level, const char *text)
{
    link_log_t *l = &spiel_link.log;
    size_t n;
    uint8_t at;
    if (level > l->level) {
        return;
    }
    if (l->count == SPIEL_LOG_QUEUE) {
        l->dropped++;
        return;
    }
    at = (uint8_t)((l->head + l->count) % SPIEL_LOG_QUEUE);
    n = strlen(text);
    if (n > SPIEL_LOG_TEXT) {
        n = SPIEL_LOG_TEXT;
    }
    l->q[at].level = level;
    memcpy(l->q[at].text, text, n);
    l->q[at].text[n] = 0;
    l->count++;
}
