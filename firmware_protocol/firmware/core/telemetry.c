/* telemetry.c - TIME_SYNC and TELEMETRY of protocol version 2 (PROTOCOL.md 14.1-14.2) and the
 * device-originated HEARTBEAT and LOG frames (the LOG queue is link.c's: every unit logs).
 * Calls only the units below it (config_store.c, link.c). No allocation. */
#include <string.h>

#include "core.h"

#define HEARTBEAT_DEFAULT_MS 1000u

static struct {
    uint16_t heartbeat_ms;
    uint8_t log_per_s;
    uint64_t next_beat;
    uint64_t tokens_at;   /* when the log tokens were last refilled */
    uint32_t tokens_milli;
} tel;

void telemetry_init(void)
{
    memset(&tel, 0, sizeof tel);
    tel.heartbeat_ms = SPIEL_PROTOCOL_MAX >= 2 ? HEARTBEAT_DEFAULT_MS : 0u;
    tel.log_per_s = 20;
    tel.tokens_milli = 20000u;
    tel.next_beat = hal_time_us() + (uint64_t)tel.heartbeat_ms * 1000u;
}

int telemetry_time_sync(const uint8_t *p, uint16_t len, uint8_t *out, uint16_t *code,
                        const char **text)
{
    uint8_t in[8] = {0};
    (void)code, (void)text;
    memcpy(in, p, len < sizeof in ? len : sizeof in);
    memcpy(out, in, 8); /* host_time_us, echoed */
    sp_le_put_u64(out + 8, hal_time_us());
    sp_le_put_u32(out + 16, spiel_link.boot_id);
    return 20;
}

int telemetry_set(const uint8_t *p, uint16_t len, uint8_t *out, uint16_t *code,
                  const char **text)
{
    uint8_t in[4] = {0};
    (void)code, (void)text;
    memcpy(in, p, len < sizeof in ? len : sizeof in);
    tel.heartbeat_ms = sp_le_get_u16(in);
    if (tel.heartbeat_ms != 0 && tel.heartbeat_ms < 50u) {
        tel.heartbeat_ms = 50u;
    }
    spiel_link.log.level = in[2] > SP_LOG_DEBUG ? (uint8_t)SP_LOG_DEBUG : in[2];
    tel.log_per_s = in[3];
    tel.next_beat = hal_time_us() + (uint64_t)tel.heartbeat_ms * 1000u;
    sp_le_put_u16(out, tel.heartbeat_ms);
    out[2] = spiel_link.log.level;
    out[3] = tel.log_per_s;
    return 4;
}

static uint32_t error_flags(void)
{
    uint32_t f = 0;
    if (spiel_stats.flash_errors) {
        f |= SP_EFLAG_FLASH;
    }
    if (cfg_active() < 0) {
        f |= SP_EFLAG_DEFAULT_CONFIG;
    }
    if (spiel_link.log.dropped) {
        f |= SP_EFLAG_LOG_DROPPED;
    }
    return f;
}

static uint16_t log_line(uint64_t now, uint8_t *out, uint16_t *out_len)
{
    link_log_t *l = &spiel_link.log;
    /* token bucket: log_per_s lines a second, at most that many at once */
    uint64_t gained = (now - tel.tokens_at) * tel.log_per_s / 1000u; /* milli-tokens */
    uint32_t cap = (uint32_t)tel.log_per_s * 1000u;
    size_t n;
    tel.tokens_at = now;
    tel.tokens_milli = gained >= cap || tel.tokens_milli + gained >= cap
                           ? cap : tel.tokens_milli + (uint32_t)gained;
    if (tel.tokens_milli < 1000u) {
        return 0;
    }
    n = strlen(l->q[l->head].text);
    if (n + 15u > spiel_link.max_payload) { /* the link's limit (at least 64) */
        n = spiel_link.max_payload - 15u;
    }
    tel.tokens_milli -= 1000u;
    out[0] = l->q[l->head].level;
    sp_le_put_u32(out + 1, l->dropped);
    sp_le_put_u64(out + 5, now);
    sp_le_put_u16(out + 13, (uint16_t)n);
    memcpy(out + 15, l->q[l->head].text, n);
    l->dropped = 0;
    l->head = (uint8_t)((l->head + 1u) % SPIEL_LOG_QUEUE);
    l->count--;
    *out_len = (uint16_t)(15u + n);
    return SP_MSG_LOG;
}

uint16_t telemetry_due(uint64_t now, uint8_t board_state, uint32_t error_flags_in, uint8_t *out,
                       uint16_t *out_len)
{
    if (spiel_link.version < 2) {
        return 0;
    }
    if (tel.heartbeat_ms && now >= tel.next_beat) {
        tel.next_beat = now + (uint64_t)tel.heartbeat_ms * 1000u;
        sp_le_put_u32(out, (uint32_t)(now / 1000u));
        out[4] = board_state;
        out[5] = 0;
        sp_le_put_u16(out + 6, tel.heartbeat_ms);
        sp_le_put_u32(out + 8, error_flags() | error_flags_in);
        sp_le_put_u32(out + 12, spiel_link.boot_id);
        sp_le_put_u64(out + 16, now);
        *out_len = SP_HEARTBEAT_SIZE;
        return SP_MSG_HEARTBEAT;
    }
    if (spiel_link.log.count && tel.log_per_s) {
        return log_line(now, out, out_len);
    }
    return 0;
}

uint64_t telemetry_next_us(uint64_t now)
{
    uint64_t wake = now + 50000u;
    if (spiel_link.version < 2) {
        return wake;
    }
    if (tel.heartbeat_ms && tel.next_beat < wake) {
        wake = tel.next_beat;
    }
    if (spiel_link.log.count && tel.log_per_s && now + 1000000u / tel.log_per_s < wake) {
        wake = now + 1000000u / tel.log_per_s;
    }
    return wake;
}
