/* device.c - the protocol engine, acquisition scheduler and streaming of the portable core.
 *
 * One request is handled per poll and only when the transmit buffer is empty, so a response
 * never interleaves with a stream frame (frames are written whole, in order). Requests are
 * stop-and-wait (PROTOCOL.md 5.3): the host sends the next one after the answer. */
#include <math.h>
#include <string.h>

#include "core.h"

#define WIRE_CAP(payload) (SP_HEADER_SIZE + (payload) + SP_CRC_SIZE + \
    (SP_HEADER_SIZE + (payload) + SP_CRC_SIZE) / 254u + 2u)
#define RX_CAP (WIRE_CAP(SPIEL_MAX_PAYLOAD) - 1u) /* the longest COBS piece we accept */
#define TX_CAP WIRE_CAP(SPIEL_MAX_PAYLOAD)
#define CACHE_CAP 64u /* responses up to this payload are cached for retries */
#define MAX_RATE_HZ 10000.0f
#define ERROR_TEXT_MAX 48u

/* ---- state ------------------------------------------------------------------------------ */

static struct {
    uint8_t buf[RX_CAP];
    uint32_t len;
    int discarding;
    uint8_t chunk[64]; /* bytes read from the transport, not yet fed */
    uint32_t chunk_len, chunk_pos;
} rx;

static struct {
    uint8_t buf[TX_CAP];
    uint32_t len, pos;
} tx;

static uint8_t payload[SPIEL_MAX_PAYLOAD];

static struct {
    int valid;
    uint16_t seq, msg_type, resp_type;
    uint8_t flags;
    uint16_t len;
    uint8_t data[CACHE_CAP];
} cache;

static struct {
    hal_settings_t settings;
    uint8_t staging[SPIEL_CONFIG_MAX];
    uint32_t staged_length;
    uint32_t acquisition;  /* index of the next acquisition, since boot */
    uint32_t counter;      /* aux of the next STREAM_DATA frame, since boot */
} dev;

static struct {
    uint16_t seq;          /* the STREAM_START's seq */
    uint32_t mask;         /* resolved channel mask */
    uint8_t format;        /* SP_SAMPLE_U16_ENVELOPE or (version 2) SP_SAMPLE_I16_IQ */
    uint8_t n_channels;
    uint16_t n_samples;
    uint64_t period_us;    /* 0: as fast as possible */
    uint64_t window_us;    /* one acquisition's listening time: at rate 0, the least gap */
    uint64_t next_us;      /* when the next acquisition is due */
    uint32_t remaining;    /* acquisitions (sent or skipped) still to schedule; 0 endless */
    int endless;
    uint32_t sent;         /* acquisitions of this stream sent whole */
    /* the acquisition in flight */
    int busy;              /* 1 measuring, 2 sending */
    uint32_t index;
    uint64_t stamp_us;
    uint8_t next_channel;  /* next physical channel to send */
    uint8_t rank;          /* frames of it sent */
    int last;              /* the stream ends after it */
} st;

/* ---- transmit ----------------------------------------------------------------------------- */

static void flush(void)
{
    while (tx.pos < tx.len) {
        size_t n = hal_transport_write(tx.buf + tx.pos, tx.len - tx.pos);
        if (n == 0) {
            return;
        }
        tx.pos += (uint32_t)n;
    }
    tx.pos = tx.len = 0;
}

static void send_frame(uint16_t msg_type, uint16_t seq, uint8_t flags, uint32_t aux,
                       const uint8_t *data, uint16_t len)
{
    size_t n = sp_frame_encode(msg_type, seq, flags, aux, data, len, tx.buf, sizeof tx.buf);
    tx.len = (uint32_t)n;
    tx.pos = 0;
    flush();
}

/* ---- responses ---------------------------------------------------------------------------- */

static uint16_t error_payload(uint16_t code, uint16_t request_type, const char *text)
{
    size_t n = strlen(text);
    if (n > ERROR_TEXT_MAX) {
        n = ERROR_TEXT_MAX;
    }
    sp_le_put_u16(payload, code);
    sp_le_put_u16(payload + 2, request_type);
    sp_le_put_u16(payload + 4, (uint16_t)n);
    memcpy(payload + 6, text, n);
    return (uint16_t)(6 + n);
}

/* A handler's result: the payload in `payload`, its length, and whether it is an error. */
typedef struct {
    int error;
    uint16_t len;
} result_t;

static result_t ok(uint16_t len)
{
    result_t r;
    r.error = 0;
    r.len = len;
    return r;
}

static result_t fail(uint16_t code, uint16_t request_type, const char *text)
{
    result_t r;
    r.error = 1;
    r.len = error_payload(code, request_type, text);
    return r;
}

static void put_text(uint8_t *p, const char *s, size_t size)
{
    size_t n = s ? strlen(s) : 0;
    memset(p, 0, size);
    if (n) { /* memcpy from a null pointer is undefined even for 0 bytes */
        memcpy(p, s, n < size ? n : size);
    }
}

/* ---- session ------------------------------------------------------------------------------ */

/* HELLO capability bits offered under protocol version 2 */
static uint32_t version2_capabilities(void)
{
    return SP_CAP_TIME_SYNC | SP_CAP_TELEMETRY | SP_CAP_START_AT |
           (update_offered() ? SP_CAP_FIRMWARE_UPDATE : 0u);
}

static result_t do_hello(const uint8_t *p, uint16_t len)
{
    uint8_t in[8] = {0};
    uint8_t min_v, max_v;
    uint16_t host_payload;
    const hal_board_info_t *info = hal_board_info();
    memcpy(in, p, len < sizeof in ? len : sizeof in);
    min_v = in[0];
    max_v = in[1];
    host_payload = sp_le_get_u16(in + 2);
    if (max_v < 1u) {
        return fail(SP_ERR_VERSION_TOO_OLD, SP_MSG_HELLO, "board speaks 1-" "2");
    }
    if (min_v > SPIEL_PROTOCOL_MAX) {
        return fail(SP_ERR_VERSION_TOO_NEW, SP_MSG_HELLO, "board speaks older versions");
    }
    if (host_payload != 0 && host_payload < SPIEL_MIN_PAYLOAD) {
        return fail(SP_ERR_INVALID, SP_MSG_HELLO, "max_payload below the minimum 64");
    }
    spiel_link.version = (uint8_t)(max_v < SPIEL_PROTOCOL_MAX ? max_v : SPIEL_PROTOCOL_MAX);
    spiel_link.max_payload = (uint16_t)SPIEL_MAX_PAYLOAD;
    if (host_payload != 0 && host_payload < spiel_link.max_payload) {
        spiel_link.max_payload = host_payload;
    }
    payload[0] = spiel_link.version;
    payload[1] = 1;
    payload[2] = (uint8_t)SPIEL_PROTOCOL_MAX;
    payload[3] = info->n_channels;
    sp_le_put_u16(payload + 4, (uint16_t)SPIEL_MAX_PAYLOAD);
    sp_le_put_u16(payload + 6, info->max_samples < SPIEL_MAX_SAMPLES ? info->max_samples
                                                                     : (uint16_t)SPIEL_MAX_SAMPLES);
    sp_le_put_u32(payload + 8, SP_CAP_STREAM | (cfg_capacity() ? SP_CAP_CONFIG : 0u) |
                                   (spiel_link.version >= 2u ? version2_capabilities() : 0u) |
                                   (spiel_link.version >= 2u && SPIEL_IQ_SAMPLES ? SP_CAP_IQ_SAMPLES : 0u));
    sp_le_put_u32(payload + 12, SP_SCHEMA_HASH);
    sp_le_put_u32(payload + 16, spiel_link.boot_id);
    put_text(payload + 20, info->firmware_version, 16);
    sp_le_put_u16(payload + 36, info->usb_vid);
    sp_le_put_u16(payload + 38, info->usb_pid);
    put_text(payload + 40, info->serial, 16);
    return ok(56);
}

static result_t do_device_info(void)
{
    const hal_board_info_t *info = hal_board_info();
    sp_le_put_u16(payload, info->hw_revision);
    payload[2] = info->n_channels;
    payload[3] = info->adc_bits;
    sp_le_put_u32(payload + 4, info->emitter_freq_hz);
    sp_le_put_u32(payload + 8, info->max_sample_rate_hz);
    sp_le_put_u32(payload + 12, (uint32_t)(hal_time_us() / 1000u));
    sp_le_put_u16(payload + 16, (uint16_t)hal_temperature_cdeg());
    put_text(payload + 18, info->board_name, 16);
    return ok(34);
}

static result_t do_ping(const uint8_t *p, uint16_t len)
{
    uint16_t n;
    if (len < 2) {
        n = 0;
    } else {
        n = sp_le_get_u16(p);
        if ((uint32_t)n + 2u > len) {
            return fail(SP_ERR_INVALID, SP_MSG_PING, "data shorter than its length");
        }
    }
    if ((uint32_t)n + 2u > spiel_link.max_payload) {
        return fail(SP_ERR_TOO_LARGE, SP_MSG_PING, "ping data exceeds max_payload - 2");
    }
    memmove(payload + 2, p + 2, n);
    sp_le_put_u16(payload, n);
    return ok((uint16_t)(n + 2));
}

static result_t do_reboot(const uint8_t *p, uint16_t len)
{
    uint8_t in[3] = {0};
    memcpy(in, p, len < sizeof in ? len : sizeof in);
    if (in[0] > SP_REBOOT_BOOTLOADER) {
        return fail(SP_ERR_INVALID, SP_MSG_REBOOT, "mode must be 0 or 1");
    }
    link_reboot_after_ms(in[0], sp_le_get_u16(in + 1));
    return ok(0);
}

/* ---- streaming ---------------------------------------------------------------------------- */

static uint8_t popcount(uint32_t m)
{
    uint8_t n = 0;
    for (; m; m &= m - 1u) {
        n++;
    }
    return n;
}

static uint32_t all_channels(void)
{
    uint8_t n = hal_board_info()->n_channels;
    return n >= 32 ? 0xFFFFFFFFu : ((1u << n) - 1u);
}

/* When acquisition 0 of a stream is due: at once, or (protocol version 2, START_AT) at start_at on the
 * device clock; a start_at already past keeps its grid (start_at + k periods, the slot the
 * host chose), the first point not yet past. 1 and *due set, or 0: more than
 * START_AT_AHEAD_US ahead. */
#define START_AT_AHEAD_US 60000000u
static int first_due(uint64_t start_at, uint64_t period_us, uint64_t now, uint64_t *due)
{
    *due = now;
    if (start_at == 0u) {
        return 1;
    }
    if (start_at > now) {
        *due = start_at;
        return start_at - now <= START_AT_AHEAD_US;
    }
    if (period_us != 0u) {
        *due = start_at + ((now - start_at + period_us - 1u) / period_us) * period_us;
    }
    return 1;
}

static result_t do_stream_start(const uint8_t *p, uint16_t len, uint16_t seq)
{
    uint8_t in[20] = {0};
    uint64_t due, period_us, start_at;
    uint32_t n_acq, mask;
    float rate;
    uint16_t n_samples, max_samples;
    uint8_t fmt;
    const hal_board_info_t *info = hal_board_info();
    memcpy(in, p, len < sizeof in ? len : sizeof in);
    n_acq = sp_le_get_u32(in);
    rate = sp_le_get_f32(in + 4);
    n_samples = sp_le_get_u16(in + 8);
    fmt = in[10];
    mask = in[11];
    if (n_samples == 0) {
        n_samples = dev.settings.n_samples;
    }
    max_samples = info->max_samples < SPIEL_MAX_SAMPLES ? info->max_samples
                                                        : (uint16_t)SPIEL_MAX_SAMPLES;
    if (spiel_link.streaming) {
        return fail(SP_ERR_BAD_STATE, SP_MSG_STREAM_START, "a stream is already running");
    }
    if (fmt != SP_SAMPLE_U16_ENVELOPE &&
        !(SPIEL_IQ_SAMPLES && fmt == SP_SAMPLE_I16_IQ && spiel_link.version >= 2u)) {
        return fail(SP_ERR_UNSUPPORTED, SP_MSG_STREAM_START,
                    SPIEL_IQ_SAMPLES ? "U16_ENVELOPE, or I16_IQ under version 2" : "U16_ENVELOPE samples only");
    }
    if (mask == 0) {
        mask = all_channels();
    }
    if ((mask & ~all_channels()) != 0) {
        return fail(SP_ERR_INVALID, SP_MSG_STREAM_START, "channel_mask names absent channels");
    }
    if (spiel_link.version < 2 && mask != all_channels()) {
        /* version 1 numbers a subset's channels 0..n-1, losing which they are */
        return fail(SP_ERR_UNSUPPORTED, SP_MSG_STREAM_START, "channel subsets need version 2");
    }
    if (n_samples > max_samples ||
        SP_STREAM_HEADER_SIZE + (fmt == SP_SAMPLE_I16_IQ ? 4u : 2u) * (uint32_t)n_samples >
            spiel_link.max_payload ||
        (fmt == SP_SAMPLE_I16_IQ && 2u * (uint32_t)n_samples > SPIEL_MAX_SAMPLES)) {
        return fail(SP_ERR_TOO_LARGE, SP_MSG_STREAM_START, "n_samples too large");
    }
    if (!(rate >= 0.0f && rate <= MAX_RATE_HZ)) { /* NaN fails both */
        return fail(SP_ERR_INVALID, SP_MSG_STREAM_START, "rate_hz must be in [0, 10000]");
    }
    if (rate > 0.0f && rate < 1.0e-3f) { /* its period would overflow the microsecond clock */
        return fail(SP_ERR_INVALID, SP_MSG_STREAM_START, "rate_hz below 0.001");
    }
    period_us = rate > 0.0f ? (uint64_t)(1.0e6 / (double)rate + 0.5) : 0u;
    start_at = spiel_link.version >= 2u ? sp_le_get_u64(in + 12) : 0u; /* version 1: at once */
    if (!first_due(start_at, period_us, hal_time_us(), &due)) {
        return fail(SP_ERR_INVALID, SP_MSG_STREAM_START, "start_at_us more than 60 s ahead");
    }
    memset(&st, 0, sizeof st);
    spiel_link.streaming = 1;
    st.seq = seq;
    st.mask = mask;
    st.n_channels = popcount(mask);
    st.n_samples = n_samples;
    st.period_us = period_us;
    st.window_us = dev.settings.sample_rate_hz != 0u
                       ? (uint64_t)n_samples * 1000000u / dev.settings.sample_rate_hz
                       : 0u;
    st.next_us = due;
    st.remaining = n_acq;
    st.endless = n_acq == 0;
    sp_le_put_u32(payload, dev.acquisition);
    sp_le_put_u32(payload + 4, dev.counter);
    sp_le_put_u32(payload + 8, dev.settings.sample_rate_hz);
    sp_le_put_u16(payload + 12, n_samples);
    payload[14] = st.n_channels;
    payload[15] = fmt;
    st.format = fmt;
    if (spiel_link.version >= 2) {
        sp_le_put_u32(payload + 16, mask);
        return ok(20);
    }
    return ok(16);
}


static result_t do_stream_stop(void)
{
    uint32_t sent = spiel_link.streaming ? st.sent : 0;
    spiel_link.streaming = 0; /* an acquisition in flight is abandoned; its index stays used */
    st.busy = 0;
    sp_le_put_u32(payload, sent);
    sp_le_put_u32(payload + 4, dev.counter);
    return ok(8);
}

static result_t do_stream_status(void)
{
    const sp_stats_t *r = &spiel_stats.rx;
    payload[0] = (uint8_t)(spiel_link.streaming != 0);
    sp_le_put_u32(payload + 1, spiel_stats.acquisitions_sent);
    sp_le_put_u32(payload + 5, spiel_stats.frames_sent);
    sp_le_put_u32(payload + 9, spiel_stats.overruns);
    sp_le_put_u32(payload + 13, r->oversize + r->cobs + r->length + r->crc + r->version + r->flags);
    sp_le_put_u32(payload + 17, 0);
    return ok(21);
}

/* Count one scheduled acquisition (sent or skipped) against n_acquisitions. */
static void scheduled(uint64_t now)
{
    /* as fast as possible is one listening window apart: a front end that answers at once
     * (a file of scans, a test driver's frozen clock) must not stamp a burst with one time */
    st.next_us = st.period_us ? st.next_us + st.period_us : now + st.window_us;
    if (!st.endless && --st.remaining == 0) {
        st.last = 1;
        if (!st.busy) {
            spiel_link.streaming = 0;
        }
    }
}

/* Start the acquisition that is due, or skip those whose time has wholly passed: one due
 * while the previous is still being measured or sent waits for it, and is skipped (an
 * overrun: its index is used, no frame carries it) once the next one is due too. */
static void schedule(uint64_t now)
{
    while (spiel_link.streaming && !st.last && now >= st.next_us) {
        if (st.busy) {
            if (st.period_us == 0 || now < st.next_us + st.period_us) {
                return; /* wait for the acquisition in flight */
            }
            spiel_stats.overruns++;
            dev.acquisition++;
            scheduled(now);
            continue;
        }
        if (update_selftest_busy()) {
            return; /* a trial's self-test holds the front end: this one waits */
        }
        if (hal_acq_trigger(st.mask, st.n_samples) == 0) {
            st.busy = 1;
            st.index = dev.acquisition++;
            st.stamp_us = now;
            st.next_channel = 0;
            st.rank = 0;
        } else {
            spiel_stats.overruns++; /* the front end refused: the acquisition is skipped */
            dev.acquisition++;
        }
        scheduled(now);
        return;
    }
}

/* Send the next channel of the acquisition in flight (tx is empty). */
static void send_channel(void)
{
    sp_stream_header_t h;
    uint32_t c = st.next_channel;
    uint16_t i, len, values;
    while (c < 32 && !(st.mask & (1u << c))) {
        c++;
    }
    /* I/Q: 2 values per sample (q, i) in the same buffer (n_samples <= SPIEL_MAX_SAMPLES / 2) */
    values = st.format == SP_SAMPLE_I16_IQ ? (uint16_t)(2u * st.n_samples) : st.n_samples;
#if SPIEL_IQ_SAMPLES
    if (st.format == SP_SAMPLE_I16_IQ ? hal_acq_read_iq((uint8_t)c, spiel_samples, st.n_samples) != 0
                                      : hal_acq_read((uint8_t)c, spiel_samples, st.n_samples) != 0) {
#else
    if (hal_acq_read((uint8_t)c, spiel_samples, st.n_samples) != 0) {
#endif
        /* the front end lost this measurement: abandon it (an overrun; its index stays used,
         * and a host drops the channels already sent as an incomplete acquisition) */
        spiel_stats.overruns++;
        st.busy = 0;
        if (st.last) {
            spiel_link.streaming = 0;
        }
        return;
    }
    h.acquisition = st.index;
    h.channel = (uint8_t)c; /* physical id; equal to the rank in version 1 (all channels) */
    h.n_channels = st.n_channels;
    h.sample_format = st.format;
    h.header_size = SP_STREAM_HEADER_SIZE;
    h.sample_rate_hz = dev.settings.sample_rate_hz;
    h.timestamp_us = st.stamp_us;
    h.n_samples = st.n_samples;
    h.reserved = 0;
    sp_stream_header_pack(&h, payload);
    for (i = 0; i < values; i++) {
        sp_le_put_u16(payload + SP_STREAM_HEADER_SIZE + 2u * i, spiel_samples[i]);
    }
    len = (uint16_t)(SP_STREAM_HEADER_SIZE + 2u * values);
    st.rank++;
    st.next_channel = (uint8_t)(c + 1);
    send_frame(SP_MSG_STREAM_DATA, st.seq,
               (uint8_t)(SP_FLAG_STREAM | (st.rank < st.n_channels ? SP_FLAG_MORE : 0u)),
               dev.counter++, payload, len);
    spiel_stats.frames_sent++;
    if (st.rank == st.n_channels) {
        st.busy = 0;
        st.sent++;
        spiel_stats.acquisitions_sent++;
        if (st.last) {
            spiel_link.streaming = 0;
        }
    }
}

/* ---- config ------------------------------------------------------------------------------- */

static uint16_t read_limit(void)
{
    return (uint16_t)(spiel_link.max_payload - 6u);
}

static result_t do_config_read(const uint8_t *p, uint16_t len)
{
    uint8_t in[7] = {0};
    uint32_t offset, total, n;
    uint16_t want;
    memcpy(in, p, len < sizeof in ? len : sizeof in);
    offset = sp_le_get_u32(in);
    want = sp_le_get_u16(in + 4);
    if (in[6] > SP_CONFIG_SOURCE_STAGING) {
        return fail(SP_ERR_INVALID, SP_MSG_CONFIG_READ, "source must be 0 or 1");
    }
    if (in[6] == SP_CONFIG_SOURCE_ACTIVE && cfg_active() < 0) {
        return fail(SP_ERR_NOT_FOUND, SP_MSG_CONFIG_READ, "no valid config slot");
    }
    if (want > read_limit()) {
        return fail(SP_ERR_TOO_LARGE, SP_MSG_CONFIG_READ, "length exceeds max_payload - 6");
    }
    total = in[6] == SP_CONFIG_SOURCE_STAGING ? dev.staged_length : cfg_active_length();
    n = offset >= total ? 0 : total - offset;
    if (n > want) {
        n = want;
    }
    if (in[6] == SP_CONFIG_SOURCE_STAGING) {
        if (n) { /* an offset past the staging must not even form a pointer */
            memcpy(payload + 6, dev.staging + offset, n);
        }
    } else if (n && cfg_read_active(offset, payload + 6, n) != 0) {
        return fail(SP_ERR_UNKNOWN, SP_MSG_CONFIG_READ, "flash read failed");
    }
    sp_le_put_u32(payload, offset);
    sp_le_put_u16(payload + 4, (uint16_t)n);
    return ok((uint16_t)(6 + n));
}

static result_t do_config_write(const uint8_t *p, uint16_t len)
{
    uint32_t offset;
    uint16_t n;
    if (len < 6) {
        return fail(SP_ERR_INVALID, SP_MSG_CONFIG_WRITE, "CONFIG_WRITE shorter than 6 bytes");
    }
    offset = sp_le_get_u32(p);
    n = sp_le_get_u16(p + 4);
    if ((uint32_t)n + 6u > len) {
        return fail(SP_ERR_INVALID, SP_MSG_CONFIG_WRITE, "data shorter than data_len");
    }
    if ((uint64_t)offset + n > cfg_capacity()) {
        return fail(SP_ERR_TOO_LARGE, SP_MSG_CONFIG_WRITE, "config exceeds max_length");
    }
    if (offset == 0) {
        dev.staged_length = 0; /* a new staging */
    }
    if (offset > dev.staged_length) {
        memset(dev.staging + dev.staged_length, 0, offset - dev.staged_length); /* a hole */
    }
    memcpy(dev.staging + offset, p + 6, n);
    if (offset + n > dev.staged_length) {
        dev.staged_length = offset + n;
    }
    sp_le_put_u32(payload, dev.staged_length);
    return ok(4);
}

static result_t do_config_commit(const uint8_t *p, uint16_t len)
{
    uint8_t in[8] = {0};
    uint32_t total, crc;
    cfg_slot_t done;
    int slot = 0;
    uint16_t code;
    memcpy(in, p, len < sizeof in ? len : sizeof in);
    total = sp_le_get_u32(in);
    crc = sp_le_get_u32(in + 4);
    if (spiel_link.streaming) {
        return fail(SP_ERR_BAD_STATE, SP_MSG_CONFIG_COMMIT, "stop the stream before a commit");
    }
    if (total == 0 || total > dev.staged_length) {
        return fail(SP_ERR_INVALID, SP_MSG_CONFIG_COMMIT, "total_length exceeds the staged data");
    }
    if (sp_crc32c(0, dev.staging, total) != crc) {
        return fail(SP_ERR_CORRUPT, SP_MSG_CONFIG_COMMIT, "staged data CRC mismatch");
    }
    code = cfg_commit(dev.staging, total, &done, &slot);
    if (code != SP_ERR_OK) {
        return fail(code, SP_MSG_CONFIG_COMMIT, sp_error_text(code));
    }
    dev.staged_length = 0;
    cfg_settings(&dev.settings);
    hal_apply_settings(&dev.settings);
    payload[0] = (uint8_t)slot;
    sp_le_put_u32(payload + 1, done.generation);
    sp_le_put_u32(payload + 5, done.length);
    sp_le_put_u32(payload + 9, done.crc);
    return ok(13);
}

static result_t do_config_status(void)
{
    int i, a = cfg_active();
    payload[0] = (uint8_t)(a < 0 ? 0xFF : a);
    sp_le_put_u32(payload + 1, dev.staged_length);
    sp_le_put_u32(payload + 5, cfg_capacity());
    for (i = 0; i < 2; i++) {
        cfg_slot_t s;
        uint8_t *q = payload + 9 + 13 * i;
        cfg_slot(i, &s);
        sp_le_put_u32(q, s.generation);
        sp_le_put_u32(q + 4, s.length);
        sp_le_put_u32(q + 8, s.crc);
        q[12] = s.valid;
    }
    return ok(35);
}

/* ---- requests ----------------------------------------------------------------------------- */

enum { NEEDS_NOTHING, NEEDS_CONFIG, NEEDS_UPDATE };

/* The request table: every request this core answers, the lowest protocol version it is
 * answered under, what it needs, and its handler in a unit below (NULL: device.c's own, in
 * own_request). A message type not here is "unknown". tests/firmware/test_core_scope.py holds
 * this list to PROTOCOL.md's. */
static const struct {
    uint16_t msg_type;
    uint8_t min_version, needs;
    core_handler_t handler;
} requests[] = {
    {SP_MSG_HELLO, 1, NEEDS_NOTHING, NULL},
    {SP_MSG_DEVICE_INFO, 1, NEEDS_NOTHING, NULL},
    {SP_MSG_PING, 1, NEEDS_NOTHING, NULL},
    {SP_MSG_REBOOT, 1, NEEDS_NOTHING, NULL},
    {SP_MSG_STREAM_START, 1, NEEDS_NOTHING, NULL},
    {SP_MSG_STREAM_STOP, 1, NEEDS_NOTHING, NULL},
    {SP_MSG_STREAM_STATUS, 1, NEEDS_NOTHING, NULL},
    {SP_MSG_CONFIG_READ, 1, NEEDS_CONFIG, NULL},
    {SP_MSG_CONFIG_WRITE, 1, NEEDS_CONFIG, NULL},
    {SP_MSG_CONFIG_COMMIT, 1, NEEDS_CONFIG, NULL},
    {SP_MSG_CONFIG_STATUS, 1, NEEDS_CONFIG, NULL},
    {SP_MSG_TIME_SYNC, 2, NEEDS_NOTHING, telemetry_time_sync},
    {SP_MSG_TELEMETRY, 2, NEEDS_NOTHING, telemetry_set},
#if SPIEL_FW_UPDATE
    {SP_MSG_FW_INFO, 2, NEEDS_UPDATE, update_info},
    {SP_MSG_FW_BEGIN, 2, NEEDS_UPDATE, update_begin},
    {SP_MSG_FW_WRITE, 2, NEEDS_UPDATE, update_write},
    {SP_MSG_FW_VERIFY, 2, NEEDS_UPDATE, update_verify},
    {SP_MSG_FW_TEST, 2, NEEDS_UPDATE, update_test},
    {SP_MSG_FW_CONFIRM, 2, NEEDS_UPDATE, update_confirm},
#endif
};

static result_t own_request(const sp_frame_t *f)
{
    const uint8_t *p = f->payload;
    uint16_t len = f->header.payload_len;
    switch (f->header.msg_type) {
    case SP_MSG_HELLO:
        return do_hello(p, len);
    case SP_MSG_DEVICE_INFO:
        return do_device_info();
    case SP_MSG_PING:
        return do_ping(p, len);
    case SP_MSG_REBOOT:
        return do_reboot(p, len);
    case SP_MSG_STREAM_START:
        return do_stream_start(p, len, f->header.seq);
    case SP_MSG_STREAM_STOP:
        return do_stream_stop();
    case SP_MSG_STREAM_STATUS:
        return do_stream_status();
    case SP_MSG_CONFIG_READ:
        return do_config_read(p, len);
    case SP_MSG_CONFIG_WRITE:
        return do_config_write(p, len);
    case SP_MSG_CONFIG_COMMIT:
        return do_config_commit(p, len);
    case SP_MSG_CONFIG_STATUS:
        return do_config_status();
    default: /* a row of the table without its handler: refused, never another's answer */
        return fail(SP_ERR_UNSUPPORTED, f->header.msg_type, "unknown message type");
    }
}

static result_t execute(const sp_frame_t *f)
{
    uint16_t type = f->header.msg_type;
    size_t i;
    for (i = 0; i < sizeof requests / sizeof requests[0]; i++) {
        if (requests[i].msg_type == type) {
            break;
        }
    }
    if (i == sizeof requests / sizeof requests[0] || spiel_link.version < requests[i].min_version ||
        (requests[i].needs == NEEDS_UPDATE && !update_offered())) {
        return fail(SP_ERR_UNSUPPORTED, type, "unknown message type");
    }
    if (requests[i].needs == NEEDS_CONFIG && cfg_capacity() == 0) {
        return fail(SP_ERR_UNSUPPORTED, type, "no config flash");
    }
    if (requests[i].handler) {
        uint16_t code = 0;
        const char *text = "";
        int n = requests[i].handler(f->payload, f->header.payload_len, payload, &code, &text);
        return code ? fail(code, type, text) : ok((uint16_t)n);
    }
    return own_request(f);
}

static void answer(const sp_frame_t *f)
{
    const sp_header_t *h = &f->header;
    result_t r;
    uint16_t resp_type;
    uint8_t flags;
    if (h->flags & (SP_FLAG_RESPONSE | SP_FLAG_STREAM)) {
        return; /* not a request */
    }
    spiel_stats.requests++;
    if (cache.valid && cache.seq == h->seq && cache.msg_type == h->msg_type &&
        h->msg_type != SP_MSG_HELLO) {
        spiel_stats.repeated++;
        send_frame(cache.resp_type, cache.seq, cache.flags, 0, cache.data, cache.len);
        return;
    }
    r = execute(f);
    resp_type = r.error ? (uint16_t)SP_MSG_ERROR : h->msg_type;
    flags = (uint8_t)(SP_FLAG_RESPONSE | (r.error ? SP_FLAG_NACK : 0u));
    cache.valid = 0; /* HELLO also clears it: a new host session */
    if (r.len <= CACHE_CAP && h->msg_type != SP_MSG_HELLO) {
        cache.valid = 1;
        cache.seq = h->seq;
        cache.msg_type = h->msg_type;
        cache.resp_type = resp_type;
        cache.flags = flags;
        cache.len = r.len;
        memcpy(cache.data, payload, r.len);
    }
    send_frame(resp_type, h->seq, flags, 0, payload, r.len);
}

/* Validate a complete COBS piece as spiel_proto.c's decoder does (same counters, same
 * order), over a receive buffer sized by SPIEL_MAX_PAYLOAD instead of SP_MAX_PAYLOAD. */
static int decode_piece(sp_frame_t *f)
{
    size_t n;
    sp_stats_t *s = &spiel_stats.rx;
    if (sp_cobs_decode(rx.buf, rx.len, rx.buf, &n) != 0) {
        s->cobs++;
        return 0;
    }
    if (n < SP_HEADER_SIZE + SP_CRC_SIZE) {
        s->length++;
        return 0;
    }
    if (sp_crc32c(0, rx.buf, n - SP_CRC_SIZE) != sp_le_get_u32(rx.buf + n - SP_CRC_SIZE)) {
        s->crc++;
        return 0;
    }
    sp_header_unpack(rx.buf, &f->header);
    if (f->header.version != SP_PROTOCOL_VERSION) {
        s->version++;
        return 0;
    }
    if ((f->header.flags & ~SP_KNOWN_FLAGS) != 0) {
        s->flags++;
        return 0;
    }
    if (f->header.payload_len != n - SP_HEADER_SIZE - SP_CRC_SIZE) {
        s->length++;
        return 0;
    }
    f->payload = rx.buf + SP_HEADER_SIZE;
    s->frames++;
    return 1;
}

/* Feed received bytes until one frame completes; 1 and *f then. */
static int receive(sp_frame_t *f)
{
    for (;;) {
        uint8_t b;
        if (rx.chunk_pos == rx.chunk_len) {
            rx.chunk_len = (uint32_t)hal_transport_read(rx.chunk, sizeof rx.chunk);
            rx.chunk_pos = 0;
            if (rx.chunk_len == 0) {
                return 0;
            }
        }
        b = rx.chunk[rx.chunk_pos++];
        if (b != 0) {
            if (rx.discarding) {
                continue;
            }
            if (rx.len == RX_CAP) {
                spiel_stats.rx.oversize++;
                rx.discarding = 1;
                rx.len = 0;
                continue;
            }
            rx.buf[rx.len++] = b;
            continue;
        }
        if (!rx.discarding && rx.len > 0 && decode_piece(f)) {
            rx.len = 0;
            return 1;
        }
        rx.discarding = 0;
        rx.len = 0;
    }
}

/* ---- API ---------------------------------------------------------------------------------- */

void spiel_device_init(void)
{
    memset(&rx, 0, sizeof rx);
    memset(&tx, 0, sizeof tx);
    memset(&cache, 0, sizeof cache);
    memset(&dev, 0, sizeof dev);
    memset(&st, 0, sizeof st);
    link_init();
    cfg_init();
    cfg_settings(&dev.settings);
    hal_apply_settings(&dev.settings);
    telemetry_init();
    update_init();
    link_log(SP_LOG_NOTICE, "booted");
}

void spiel_device_poll(void)
{
    sp_frame_t f;
    uint64_t now;
    update_tick(hal_time_us()); /* a trial's self-test; the watchdog kick */
    flush();
    if (tx.len) {
        schedule(hal_time_us()); /* the link is blocked: count the slots that pass */
        if (st.busy == 1 && hal_acq_ready()) {
            st.busy = 2;
        }
        return;
    }
    if (spiel_link.reboot_pending && hal_time_us() >= spiel_link.reboot_at) {
        hal_reset(spiel_link.reboot_mode == SP_REBOOT_BOOTLOADER);
    }
    if (receive(&f)) {
        answer(&f);
        return;
    }
    now = hal_time_us();
    if (st.busy != 2) { /* heartbeat and log lines between acquisitions, never inside one */
        uint16_t n = 0;
        uint8_t state = update_uploading()     ? (uint8_t)SP_BOARD_UPDATING
                        : spiel_link.streaming ? (uint8_t)SP_BOARD_STREAMING
                                               : (uint8_t)SP_BOARD_IDLE;
        uint16_t type = telemetry_due(now, state, update_error_flags(), payload, &n);
        if (type) {
            send_frame(type, 0, 0, 0, payload, n);
            return;
        }
    }
    schedule(now);
    if (st.busy == 1 && hal_acq_ready()) {
        st.busy = 2;
    }
    if (st.busy == 2) {
        send_channel();
    }
}

uint32_t spiel_device_idle_us(void)
{
    uint64_t now, wake;
    if (tx.len || rx.chunk_pos < rx.chunk_len || st.busy) {
        return 0;
    }
    now = hal_time_us();
    wake = now + 50000u;
    if (spiel_link.streaming && st.next_us < wake) {
        wake = st.next_us;
    }
    if (spiel_link.reboot_pending && spiel_link.reboot_at < wake) {
        wake = spiel_link.reboot_at;
    }
    if (telemetry_next_us(now) < wake) {
        wake = telemetry_next_us(now);
    }
    if (update_next_us(now) < wake) {
        wake = update_next_us(now);
    }
    return wake <= now ? 0u : (uint32_t)(wake - now);
}

const spiel_device_stats_t *spiel_device_stats(void)
{
    return &spiel_stats;
}
