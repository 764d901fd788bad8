/*
 * spiel_proto.h - reference implementation of the spiel-edge frame layer (PROTOCOL.md).
 *
 *   wire = COBS(body + CRC32C(body) as u32 LE) + 0x00,  body = header(12) + payload
 *
 * C99, no dynamic allocation, no I/O; endian-independent (explicit byte packing).
 * The decoder is fed one byte at a time (from a UART/USB ISR or a task) and owns one
 * frame-sized buffer, so an sp_decoder_t needs about SP_MAX_ENCODED bytes of RAM.
 */
#ifndef SPIEL_PROTO_H
#define SPIEL_PROTO_H

#include <stddef.h>
#include <stdint.h>

#include "spiel_registry.h"

#ifdef __cplusplus
extern "C" {
#endif

/* Protocol constants (SP_PROTOCOL_VERSION, SP_HEADER_SIZE, SP_MAX_PAYLOAD, SP_MAX_ENCODED,
 * SP_FLAG_*, ...), message types, error codes and the packed STREAM_DATA and config blob
 * headers are generated from the Python registry into spiel_registry.h. */
typedef struct {
    uint8_t version;
    uint8_t flags;
    uint16_t msg_type;
    uint16_t seq;
    uint16_t payload_len;
    uint32_t aux;
} sp_header_t;

typedef struct {
    sp_header_t header;
    const uint8_t *payload; /* points into the decoder's buffer; valid until the next feed */
} sp_frame_t;

/* Every dropped piece is counted under exactly one kind (same as the Python DecoderStats). */
typedef struct {
    uint32_t frames;
    uint32_t crc;
    uint32_t cobs;
    uint32_t length;
    uint32_t oversize;
    uint32_t version;
    uint32_t flags;
} sp_stats_t;

typedef struct {
    uint8_t buf[SP_MAX_ENCODED];
    size_t len;
    int discarding; /* inside an over-long piece: drop bytes until the next 0x00 */
    sp_stats_t stats;
} sp_decoder_t;

/* CRC-32C (Castagnoli, reflected, init/xorout 0xFFFFFFFF). Check: "123456789" -> 0xE3069283.
 * Chain calls by passing the previous result as crc (start with 0). */
uint32_t sp_crc32c(uint32_t crc, const uint8_t *data, size_t len);

void sp_header_pack(const sp_header_t *h, uint8_t out[SP_HEADER_SIZE]);
void sp_header_unpack(const uint8_t in[SP_HEADER_SIZE], sp_header_t *h);

/* COBS-encode src into dst (no delimiter). Returns the encoded length, 0 if dst is too small. */
size_t sp_cobs_encode(const uint8_t *src, size_t len, uint8_t *dst, size_t cap);
/* COBS-decode; dst may equal src (decodes in place). Returns 0 on success, -1 if malformed. */
int sp_cobs_decode(const uint8_t *src, size_t len, uint8_t *dst, size_t *out_len);

/* Build a whole frame (header with version 1, payload, CRC, COBS, delimiter) into out.
 * Returns the wire length, or 0 if payload_len > SP_MAX_PAYLOAD, flags are unknown or out
 * is too small (SP_MAX_WIRE always suffices). No scratch buffer is needed. */
size_t sp_frame_encode(uint16_t msg_type, uint16_t seq, uint8_t flags, uint32_t aux,
                       const uint8_t *payload, uint16_t payload_len, uint8_t *out, size_t cap);

void sp_decoder_init(sp_decoder_t *d);
/* Feed one byte. Returns 1 and fills *frame when a valid frame completes, else 0. */
int sp_decoder_feed(sp_decoder_t *d, uint8_t byte, sp_frame_t *frame);

#ifdef __cplusplus
}
#endif
#endif /* SPIEL_PROTO_H */
