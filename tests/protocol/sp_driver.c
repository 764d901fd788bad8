/* Test driver for firmware_protocol/c: reads commands on stdin, prints results on stdout.
 *   crc <hex>                              -> crc %08x
 *   cobs <hex>                             -> cobs <hex>
 *   hdr <hex12>                            -> hdr version flags msg_type seq len aux <hex12>
 *   enc <flags> <type> <seq> <aux> <hex>   -> enc <wirehex> | enc error
 *   dec <hex>   (fed byte by byte)         -> frame flags type seq aux <hex> ... then stats ...
 *   sth <hex24>                            -> sth <the 9 sub-header fields> <repacked hex24>
 *   sthp <the 9 sub-header fields>         -> sthp <hex24>
 *   cfh <hex36>                            -> cfh <magic hex> <the 11 other fields> <repacked hex36>
 *   cfhp <magic hex> <the 11 other fields> -> cfhp <hex36>   (floats as %.9g)
 *   err <code>                             -> err <sp_error_text(code)>
 * An empty hex string is written as "-".
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "spiel_proto.h"

#define MAX_BYTES (1u << 19)

static char line[2 * MAX_BYTES + 256];
static uint8_t data[MAX_BYTES];
static uint8_t out[2 * MAX_BYTES];
static sp_decoder_t decoder;

static size_t parse_hex(const char *s)
{
    size_t n = 0;
    if (strcmp(s, "-") == 0) {
        return 0;
    }
    while (s[0] && s[1] && n < MAX_BYTES) {
        unsigned v;
        sscanf(s, "%2x", &v);
        data[n++] = (uint8_t)v;
        s += 2;
    }
    return n;
}

static void print_hex(const uint8_t *p, size_t n)
{
    size_t i;
    if (n == 0) {
        fputs("-", stdout);
    }
    for (i = 0; i < n; i++) {
        printf("%02x", p[i]);
    }
}

static void cmd_dec(const char *hex)
{
    size_t i, n = parse_hex(hex);
    sp_frame_t f;
    sp_stats_t *s = &decoder.stats;
    sp_decoder_init(&decoder);
    for (i = 0; i < n; i++) {
        if (sp_decoder_feed(&decoder, data[i], &f)) {
            printf("frame %u %u %u %lu ", f.header.flags, f.header.msg_type, f.header.seq,
                   (unsigned long)f.header.aux);
            print_hex(f.payload, f.header.payload_len);
            putchar('\n');
        }
    }
    printf("stats %lu %lu %lu %lu %lu %lu %lu\n", (unsigned long)s->frames,
           (unsigned long)s->crc, (unsigned long)s->cobs, (unsigned long)s->length,
           (unsigned long)s->oversize, (unsigned long)s->version, (unsigned long)s->flags);
}

static void cmd_enc(char *args)
{
    unsigned flags, type, seq;
    unsigned long aux;
    static char hex[2 * MAX_BYTES + 2];
    size_t n, w = 0;
    if (sscanf(args, "%u %u %u %lu %s", &flags, &type, &seq, &aux, hex) != 5) {
        puts("enc error");
        return;
    }
    n = parse_hex(hex);
    if (n <= 0xFFFFu) {
        w = sp_frame_encode((uint16_t)type, (uint16_t)seq, (uint8_t)flags, (uint32_t)aux, data,
                            (uint16_t)n, out, SP_MAX_WIRE);
    }
    if (w == 0) {
        puts("enc error");
        return;
    }
    fputs("enc ", stdout);
    print_hex(out, w);
    putchar('\n');
}

static void cmd_hdr(const char *hex)
{
    sp_header_t h;
    uint8_t packed[SP_HEADER_SIZE];
    parse_hex(hex);
    sp_header_unpack(data, &h);
    sp_header_pack(&h, packed);
    printf("hdr %u %u %u %u %u %lu ", h.version, h.flags, h.msg_type, h.seq, h.payload_len,
           (unsigned long)h.aux);
    print_hex(packed, SP_HEADER_SIZE);
    putchar('\n');
}

static void print_stream_header(const sp_stream_header_t *h)
{
    printf("%lu %u %u %u %u %lu %llu %u %u", (unsigned long)h->acquisition, h->channel,
           h->n_channels, h->sample_format, h->header_size, (unsigned long)h->sample_rate_hz,
           (unsigned long long)h->timestamp_us, h->n_samples, h->reserved);
}

static void cmd_sth(const char *hex)
{
    sp_stream_header_t h;
    uint8_t packed[SP_STREAM_HEADER_SIZE];
    parse_hex(hex);
    sp_stream_header_unpack(data, &h);
    sp_stream_header_pack(&h, packed);
    fputs("sth ", stdout);
    print_stream_header(&h);
    putchar(' ');
    print_hex(packed, sizeof packed);
    putchar('\n');
}

static void cmd_sthp(const char *args)
{
    unsigned long acq, rate;
    unsigned long long ts;
    unsigned ch, n_ch, fmt, hsize, n, res;
    sp_stream_header_t h;
    uint8_t packed[SP_STREAM_HEADER_SIZE];
    if (sscanf(args, "%lu %u %u %u %u %lu %llu %u %u", &acq, &ch, &n_ch, &fmt, &hsize, &rate, &ts,
               &n, &res) != 9) {
        puts("sthp error");
        return;
    }
    h.acquisition = (uint32_t)acq;
    h.channel = (uint8_t)ch;
    h.n_channels = (uint8_t)n_ch;
    h.sample_format = (uint8_t)fmt;
    h.header_size = (uint8_t)hsize;
    h.sample_rate_hz = (uint32_t)rate;
    h.timestamp_us = (uint64_t)ts;
    h.n_samples = (uint16_t)n;
    h.reserved = (uint16_t)res;
    sp_stream_header_pack(&h, packed);
    fputs("sthp ", stdout);
    print_hex(packed, sizeof packed);
    putchar('\n');
}

static void print_config_header(const sp_config_header_t *h)
{
    print_hex(h->magic, sizeof h->magic);
    printf(" %u %u %u %u %u %u %.9g %.9g %.9g %.9g %lu", h->version, h->header_size, h->n_samples,
           h->decimation, h->pulse_cycles, h->blind_zone_samples, (double)h->sample_rate_hz,
           (double)h->carrier_hz, (double)h->gain_db, (double)h->acquisition_rate_hz,
           (unsigned long)h->toml_length);
}

static void cmd_cfh(const char *hex)
{
    sp_config_header_t h;
    uint8_t packed[SP_CONFIG_HEADER_SIZE];
    parse_hex(hex);
    sp_config_header_unpack(data, &h);
    sp_config_header_pack(&h, packed);
    fputs("cfh ", stdout);
    print_config_header(&h);
    putchar(' ');
    print_hex(packed, sizeof packed);
    putchar('\n');
}

static void cmd_cfhp(const char *args)
{
    char magic[16];
    unsigned version, hsize, n, dec, pulse, blind;
    double rate, carrier, gain, acq_rate;
    unsigned long length;
    sp_config_header_t h;
    uint8_t packed[SP_CONFIG_HEADER_SIZE];
    if (sscanf(args, "%15s %u %u %u %u %u %u %lf %lf %lf %lf %lu", magic, &version, &hsize, &n,
               &dec, &pulse, &blind, &rate, &carrier, &gain, &acq_rate, &length) != 12 ||
        parse_hex(magic) != SP_CONFIG_MAGIC_SIZE) {
        puts("cfhp error");
        return;
    }
    memcpy(h.magic, data, sizeof h.magic);
    h.version = (uint16_t)version;
    h.header_size = (uint16_t)hsize;
    h.n_samples = (uint16_t)n;
    h.decimation = (uint16_t)dec;
    h.pulse_cycles = (uint16_t)pulse;
    h.blind_zone_samples = (uint16_t)blind;
    h.sample_rate_hz = (float)rate;
    h.carrier_hz = (float)carrier;
    h.gain_db = (float)gain;
    h.acquisition_rate_hz = (float)acq_rate;
    h.toml_length = (uint32_t)length;
    sp_config_header_pack(&h, packed);
    fputs("cfhp ", stdout);
    print_hex(packed, sizeof packed);
    putchar('\n');
}

int main(void)
{
    while (fgets(line, sizeof line, stdin)) {
        char *arg = strchr(line, ' ');
        line[strcspn(line, "\r\n")] = 0;
        if (!arg) {
            continue;
        }
        *arg++ = 0;
        if (strcmp(line, "crc") == 0) {
            size_t n = parse_hex(arg);
            printf("crc %08lx\n", (unsigned long)sp_crc32c(0, data, n));
        } else if (strcmp(line, "cobs") == 0) {
            size_t n = parse_hex(arg);
            fputs("cobs ", stdout);
            print_hex(out, sp_cobs_encode(data, n, out, sizeof out));
            putchar('\n');
        } else if (strcmp(line, "hdr") == 0) {
            cmd_hdr(arg);
        } else if (strcmp(line, "enc") == 0) {
            cmd_enc(arg);
        } else if (strcmp(line, "dec") == 0) {
            cmd_dec(arg);
        } else if (strcmp(line, "sth") == 0) {
            cmd_sth(arg);
        } else if (strcmp(line, "sthp") == 0) {
            cmd_sthp(arg);
        } else if (strcmp(line, "cfh") == 0) {
            cmd_cfh(arg);
        } else if (strcmp(line, "cfhp") == 0) {
            cmd_cfhp(arg);
        } else if (strcmp(line, "err") == 0) {
            printf("err %s\n", sp_error_text((uint16_t)strtoul(arg, NULL, 10)));
        }
    }
    return 0;
}
