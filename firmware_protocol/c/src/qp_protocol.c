/* QUBE bridge protocol, version 1: the C codec (see qp_protocol.h). */
#include "qp_protocol.h"

#ifdef __AVR__
#include <util/crc16.h>
#endif

#include <string.h>

/* Written for 8-bit targets too: int may be 16 bits, so every shift that can
 * pass bit 15 is done on an explicitly 32-bit unsigned value. */

static void put_u16(uint8_t *p, uint16_t v)
{
    p[0] = (uint8_t)(v & 0xFFu);
    p[1] = (uint8_t)(v >> 8);
}

static void put_u32(uint8_t *p, uint32_t v)
{
    p[0] = (uint8_t)(v & 0xFFu);
    p[1] = (uint8_t)((v >> 8) & 0xFFu);
    p[2] = (uint8_t)((v >> 16) & 0xFFu);
    p[3] = (uint8_t)(v >> 24);
}

static uint16_t get_u16(const uint8_t *p)
{
    return (uint16_t)((uint16_t)p[0] | (uint16_t)((uint16_t)p[1] << 8));
}

static uint32_t get_u32(const uint8_t *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);
}

uint16_t qp_crc16(uint16_t crc, const uint8_t *data, size_t len)
{
    size_t i;
#ifdef __AVR__
    /* avr-libc's hand-written update for polynomial 0x1021 (MSB first, the
     * same CRC as below): about a fifth of the cycles of the C version. */
    for (i = 0; i < len; i++) {
        crc = _crc_xmodem_update(crc, data[i]);
    }
#else
    /* Table-free byte update for polynomial 0x1021: no 512-byte table to
     * keep in an AVR's RAM, and still a few instructions per byte. */
    for (i = 0; i < len; i++) {
        uint16_t x = (uint16_t)(((crc >> 8) ^ data[i]) & 0xFFu);
        x = (uint16_t)(x ^ (x >> 4));
        crc = (uint16_t)((uint16_t)(crc << 8) ^ (uint16_t)(x << 12) ^ (uint16_t)(x << 5) ^ x);
    }
#endif
    return crc;
}

size_t qp_cobs_encode(const uint8_t *in, size_t len, uint8_t *out, size_t cap)
{
    size_t read = 0, write = 1, code_pos = 0;
    uint8_t code = 1;

    if (cap < 1) {
        return 0;
    }
    while (read < len) {
        if (in[read] == 0) {
            out[code_pos] = code;
            code = 1;
            code_pos = write++;
        } else {
            if (write >= cap) {
                return 0;
            }
            out[write++] = in[read];
            code++;
            /* A full block only opens another if input remains: the
             * canonical encoding of 254 non-zero bytes has no trailing code. */
            if (code == 0xFF && read + 1 < len) {
                out[code_pos] = code;
                code = 1;
                code_pos = write++;
            }
        }
        read++;
        if (code_pos >= cap) {
            return 0;
        }
    }
    out[code_pos] = code;
    return write;
}

long qp_cobs_decode(const uint8_t *in, size_t len, uint8_t *out, size_t cap)
{
    size_t pos = 0, w = 0, i;

    /* In-place safe: the write index never passes the read index. */
    while (pos < len) {
        uint8_t code = in[pos];
        size_t n;
        if (code == 0) {
            return -1;
        }
        n = (size_t)code - 1u;
        if (n > len - pos - 1u || w + n > cap) {
            return -1;
        }
        for (i = 0; i < n; i++) {
            uint8_t b = in[pos + 1u + i];
            if (b == 0) {
                return -1;
            }
            out[w + i] = b;
        }
        w += n;
        pos += 1u + n;
        if (code != 0xFF && pos < len) {
            if (w >= cap) {
                return -1;
            }
            out[w++] = 0;
        }
    }
    return (long)w;
}

size_t qp_payload_size(uint8_t type)
{
    switch (type) {
    case QP_HELLO: return QP_HELLO_SIZE;
    case QP_HELLO_REPLY: return QP_HELLO_REPLY_SIZE;
    case QP_CONFIG: return QP_CONFIG_SIZE;
    case QP_CONFIG_ACK: return QP_CONFIG_ACK_SIZE;
    case QP_COMMAND: return QP_COMMAND_SIZE;
    case QP_TELEMETRY: return QP_TELEMETRY_SIZE;
    case QP_FAULT: return QP_FAULT_SIZE;
    default: return 0;
    }
}

size_t qp_encode_frame(uint8_t type, uint32_t seq, uint32_t timestamp_us, const uint8_t *payload,
                       size_t payload_len, uint8_t *out, size_t cap)
{
    uint8_t body[QP_MAX_BODY];
    size_t n;
    uint16_t crc;

    if (payload_len > QP_MAX_PAYLOAD) {
        return 0;
    }
    body[0] = QP_VERSION;
    body[1] = type;
    put_u32(body + 2, seq);
    put_u32(body + 6, timestamp_us);
    body[10] = (uint8_t)payload_len;
    if (payload_len > 0) {
        memcpy(body + QP_HEADER_SIZE, payload, payload_len);
    }
    n = qp_cobs_encode(body, QP_HEADER_SIZE + payload_len, out, cap);
    if (n == 0 || n + QP_TRAILER_SIZE + 1u > cap) {
        return 0;
    }
    crc = qp_crc16(0xFFFFu, out, n);
    out[n++] = (uint8_t)(0x80u | (crc & 0x7Fu));
    out[n++] = (uint8_t)(0x80u | ((crc >> 7) & 0x7Fu));
    out[n++] = (uint8_t)(0x80u | (crc >> 14));
    out[n++] = 0;
    return n;
}

int qp_parse_piece(uint8_t *piece, size_t len, qp_frame *frame)
{
    uint8_t k0, k1, k2;
    uint16_t crc;
    long n;
    size_t enc_len, size;

    frame->version = 0;
    if (len > QP_MAX_WIRE) {
        return QP_OVERSIZE;
    }
    if (len < QP_MIN_WIRE) {
        return QP_BAD_LENGTH;
    }
    k0 = piece[len - 3u];
    k1 = piece[len - 2u];
    k2 = piece[len - 1u];
    if (!(k0 & k1 & 0x80u) || (k2 & 0xFCu) != 0x80u) {
        return QP_BAD_CRC;
    }
    enc_len = len - QP_TRAILER_SIZE;
    crc = (uint16_t)((k0 & 0x7Fu) | ((uint16_t)(k1 & 0x7Fu) << 7) | ((uint16_t)(k2 & 0x03u) << 14));
    if (qp_crc16(0xFFFFu, piece, enc_len) != crc) {
        return QP_BAD_CRC;
    }
    n = qp_cobs_decode(piece, enc_len, piece, enc_len);
    if (n < 0) {
        return QP_BAD_COBS;
    }
    if (n >= 1) {
        frame->version = piece[0];
    }
    if (n < 1 || piece[0] != QP_VERSION) {
        return QP_BAD_VERSION;
    }
    if ((size_t)n < QP_HEADER_SIZE || piece[10] != (size_t)n - QP_HEADER_SIZE) {
        return QP_BAD_LENGTH;
    }
    size = qp_payload_size(piece[1]);
    if (size == 0) {
        return QP_UNKNOWN_TYPE;
    }
    if (piece[10] != size) {
        return QP_BAD_LENGTH;
    }
    frame->type = piece[1];
    frame->seq = get_u32(piece + 2);
    frame->timestamp_us = get_u32(piece + 6);
    frame->payload_len = piece[10];
    memcpy(frame->payload, piece + QP_HEADER_SIZE, size);
    return QP_OK;
}

void qp_decoder_init(qp_decoder *dec)
{
    memset(dec, 0, sizeof *dec);
}

size_t qp_decoder_size(void)
{
    return sizeof(qp_decoder);
}

const qp_counters *qp_decoder_counters(const qp_decoder *dec)
{
    return &dec->counters;
}

int qp_decoder_push(qp_decoder *dec, uint8_t byte, qp_frame *frame)
{
    qp_counters *c = &dec->counters;
    int result;
    uint16_t len;

    c->bytes_in++;
    if (byte != 0) {
        if (dec->overflowed) {
            return 0;
        }
        if (dec->len >= QP_MAX_WIRE) {
            /* Drop the piece and count it once; resynchronize at the next 0x00. */
            c->oversize++;
            dec->overflowed = 1;
            dec->len = 0;
            return 0;
        }
        dec->buf[dec->len++] = byte;
        return 0;
    }
    len = dec->len;
    dec->len = 0;
    if (dec->overflowed) {
        dec->overflowed = 0;
        return 0;
    }
    if (len == 0) {
        return 0; /* extra delimiters are idle fill */
    }
    result = qp_parse_piece(dec->buf, len, frame);
    switch (result) {
    case QP_OK: c->frames++; return 1;
    case QP_BAD_CRC: c->bad_crc++; break;
    case QP_BAD_COBS: c->bad_cobs++; break;
    case QP_BAD_LENGTH: c->bad_length++; break;
    case QP_BAD_VERSION: c->bad_version++; c->last_bad_version = frame->version; break;
    case QP_UNKNOWN_TYPE: c->unknown_type++; break;
    default: c->oversize++; break;
    }
    return 0;
}

size_t qp_decoder_feed(qp_decoder *dec, const uint8_t *data, size_t len, qp_frame *frames, size_t max_frames)
{
    qp_frame scratch;
    size_t i, found = 0;
    for (i = 0; i < len; i++) {
        qp_frame *slot = found < max_frames ? &frames[found] : &scratch;
        if (qp_decoder_push(dec, data[i], slot)) {
            found++;
        }
    }
    return found;
}

/* Payload layouts as tables, so each message's byte order is written once. */
typedef struct {
    uint8_t offset; /* of the field in the C struct */
    uint8_t width;  /* bytes on the wire: 1, 2 or 4 (little-endian) */
} qp_field;

static size_t pack_fields(const void *msg, const qp_field *fields, size_t count, uint8_t *out)
{
    const uint8_t *base = (const uint8_t *)msg;
    size_t i, pos = 0;
    for (i = 0; i < count; i++) {
        const uint8_t *src = base + fields[i].offset;
        if (fields[i].width == 1) {
            out[pos] = *src;
        } else if (fields[i].width == 2) {
            uint16_t v;
            memcpy(&v, src, sizeof v);
            put_u16(out + pos, v);
        } else {
            uint32_t v;
            memcpy(&v, src, sizeof v);
            put_u32(out + pos, v);
        }
        pos += fields[i].width;
    }
    return pos;
}

static int unpack_fields(const uint8_t *p, size_t len, size_t size, void *msg, const qp_field *fields,
                         size_t count)
{
    uint8_t *base = (uint8_t *)msg;
    size_t i, pos = 0;
    if (len != size) {
        return -1;
    }
    for (i = 0; i < count; i++) {
        uint8_t *dst = base + fields[i].offset;
        if (fields[i].width == 1) {
            *dst = p[pos];
        } else if (fields[i].width == 2) {
            uint16_t v = get_u16(p + pos);
            memcpy(dst, &v, sizeof v);
        } else {
            uint32_t v = get_u32(p + pos);
            memcpy(dst, &v, sizeof v);
        }
        pos += fields[i].width;
    }
    return 0;
}

#define QP_F(type, name) { (uint8_t)offsetof(type, name), (uint8_t)sizeof(((type *)0)->name) }
#define QP_COUNT(table) (sizeof(table) / sizeof((table)[0]))

static const qp_field HELLO_FIELDS[] = { QP_F(qp_hello, nonce) };
static const qp_field HELLO_REPLY_FIELDS[] = {
    QP_F(qp_hello_reply, nonce), QP_F(qp_hello_reply, protocol_version),
    QP_F(qp_hello_reply, firmware_major), QP_F(qp_hello_reply, firmware_minor),
    QP_F(qp_hello_reply, firmware_patch), QP_F(qp_hello_reply, capabilities),
    QP_F(qp_hello_reply, rate_hz), QP_F(qp_hello_reply, watchdog_ticks),
    QP_F(qp_hello_reply, max_millivolts), QP_F(qp_hello_reply, module_id)
};
static const qp_field CONFIG_FIELDS[] = {
    QP_F(qp_config, rate_hz), QP_F(qp_config, watchdog_ticks), QP_F(qp_config, max_millivolts)
};
static const qp_field CONFIG_ACK_FIELDS[] = {
    QP_F(qp_config_ack, result), QP_F(qp_config_ack, rate_hz), QP_F(qp_config_ack, watchdog_ticks),
    QP_F(qp_config_ack, max_millivolts)
};
static const qp_field COMMAND_FIELDS[] = {
    QP_F(qp_command, millivolts), QP_F(qp_command, flags), QP_F(qp_command, led_red),
    QP_F(qp_command, led_green), QP_F(qp_command, led_blue)
};
static const qp_field TELEMETRY_FIELDS[] = {
    QP_F(qp_telemetry, tick), QP_F(qp_telemetry, encoder0), QP_F(qp_telemetry, encoder1),
    QP_F(qp_telemetry, tach_raw), QP_F(qp_telemetry, current_raw), QP_F(qp_telemetry, status),
    QP_F(qp_telemetry, last_command_seq), QP_F(qp_telemetry, applied_millivolts),
    QP_F(qp_telemetry, motor_word), QP_F(qp_telemetry, command_age)
};
static const qp_field FAULT_FIELDS[] = {
    QP_F(qp_fault, code), QP_F(qp_fault, tick), QP_F(qp_fault, value)
};

#define QP_CODEC(name, TABLE, SIZE)                                                     \
    size_t qp_pack_##name(const qp_##name *m, uint8_t *out)                             \
    {                                                                                   \
        return pack_fields(m, TABLE, QP_COUNT(TABLE), out);                             \
    }                                                                                   \
    int qp_unpack_##name(const uint8_t *p, size_t len, qp_##name *m)                    \
    {                                                                                   \
        return unpack_fields(p, len, SIZE, m, TABLE, QP_COUNT(TABLE));                  \
    }

QP_CODEC(hello, HELLO_FIELDS, QP_HELLO_SIZE)
QP_CODEC(hello_reply, HELLO_REPLY_FIELDS, QP_HELLO_REPLY_SIZE)
QP_CODEC(config, CONFIG_FIELDS, QP_CONFIG_SIZE)
QP_CODEC(config_ack, CONFIG_ACK_FIELDS, QP_CONFIG_ACK_SIZE)
QP_CODEC(command, COMMAND_FIELDS, QP_COMMAND_SIZE)
QP_CODEC(telemetry, TELEMETRY_FIELDS, QP_TELEMETRY_SIZE)
QP_CODEC(fault, FAULT_FIELDS, QP_FAULT_SIZE)

int qp_config_problem(const qp_config *cfg)
{
    if (cfg->rate_hz < 10u || cfg->rate_hz > 1000u || (1000000UL % cfg->rate_hz) != 0u) {
        return QP_CONFIG_BAD_RATE;
    }
    if (cfg->watchdog_ticks < 1u || cfg->watchdog_ticks > 1000u) {
        return QP_CONFIG_BAD_WATCHDOG;
    }
    if (cfg->max_millivolts > (uint16_t)QP_MAX_MILLIVOLTS) {
        return QP_CONFIG_BAD_VOLTAGE;
    }
    return QP_CONFIG_OK;
}
