/*
 * QUBE bridge protocol, version 1: the C codec.
 *
 * Portable C99, no dynamic allocation, no hardware access. The normative
 * description is firmware_protocol/PROTOCOL.md; firmware_protocol/messages.py
 * is the Python twin of this file and both are checked against
 * firmware_protocol/golden_vectors.json.
 *
 * Wire frame: COBS(header + payload) + 3-byte CRC trailer + 0x00.
 * The CRC-16/CCITT-FALSE covers the COBS bytes (see PROTOCOL.md for why).
 */
#ifndef QP_PROTOCOL_H
#define QP_PROTOCOL_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define QP_VERSION 1u
#define QP_MAX_PAYLOAD 64u
#define QP_HEADER_SIZE 11u
#define QP_TRAILER_SIZE 3u
#define QP_MAX_BODY (QP_HEADER_SIZE + QP_MAX_PAYLOAD)
/* Bytes between two delimiters: COBS adds one byte per started 254. */
#define QP_MIN_WIRE (QP_HEADER_SIZE + 1u + QP_TRAILER_SIZE)
#define QP_MAX_WIRE (QP_MAX_BODY + 1u + QP_TRAILER_SIZE)
/* A whole encoded frame, delimiter included. */
#define QP_MAX_FRAME (QP_MAX_WIRE + 1u)

#define QP_MAX_MILLIVOLTS 15000
#define QP_LED_MAX 999u
#define QP_MODULE_ID_QUBE_SERVO_2 777u
#define QP_DEFAULT_RATE_HZ 500u
#define QP_DEFAULT_WATCHDOG_TICKS 5u

enum qp_type {
    QP_HELLO = 0x01,
    QP_CONFIG = 0x02,
    QP_COMMAND = 0x03,
    QP_HELLO_REPLY = 0x81,
    QP_CONFIG_ACK = 0x82,
    QP_TELEMETRY = 0x83,
    QP_FAULT = 0x84
};

/* Payload sizes (bytes). */
enum qp_size {
    QP_HELLO_SIZE = 4,
    QP_HELLO_REPLY_SIZE = 20,
    QP_CONFIG_SIZE = 6,
    QP_CONFIG_ACK_SIZE = 7,
    QP_COMMAND_SIZE = 9,
    QP_TELEMETRY_SIZE = 30,
    QP_FAULT_SIZE = 9
};

enum qp_capability {
    QP_CAP_TELEMETRY = 1u << 0,
    QP_CAP_WATCHDOG = 1u << 1,
    QP_CAP_ENCODER_RESET = 1u << 2,
    QP_CAP_LED = 1u << 3,
    QP_CAP_CURRENT_SENSE = 1u << 4,
    QP_CAP_TACHOMETER = 1u << 5,
    QP_CAP_CONFIGURABLE_RATE = 1u << 6,
    QP_CAP_EMULATED = 1u << 7
};

enum qp_command_flag {
    QP_CMD_AMP_ENABLE = 1u << 0,
    QP_CMD_RESET_ENCODER0 = 1u << 1,
    QP_CMD_RESET_ENCODER1 = 1u << 2
};

enum qp_status {
    QP_ST_AMP_FAULT = 1u << 0,
    QP_ST_STALL_DETECTED = 1u << 1,
    QP_ST_STALL_ERROR = 1u << 2,
    QP_ST_WATCHDOG_TRIPPED = 1u << 3,
    QP_ST_AMP_ENABLED = 1u << 4,
    QP_ST_SATURATED = 1u << 5,
    QP_ST_BAD_MODULE_ID = 1u << 6,
    QP_ST_TICK_OVERRUN = 1u << 7,
    QP_ST_ENCODER_RESET = 1u << 8,
    QP_ST_TX_OVERFLOW = 1u << 9
};

enum qp_fault_code {
    QP_FAULT_WATCHDOG_TRIPPED = 1,
    QP_FAULT_AMP_FAULT = 2,
    QP_FAULT_STALL_ERROR = 3,
    QP_FAULT_BAD_MODULE_ID = 4,
    QP_FAULT_TICK_OVERRUN = 5,
    QP_FAULT_BAD_VERSION = 6,
    QP_FAULT_NOT_CONNECTED = 7,
    QP_FAULT_RX_ERRORS = 8
};

enum qp_config_result {
    QP_CONFIG_OK = 0,
    QP_CONFIG_BAD_RATE = 1,
    QP_CONFIG_BAD_WATCHDOG = 2,
    QP_CONFIG_BAD_VOLTAGE = 3
};

/* Why a piece between delimiters is not a frame (the decoder's counters). */
enum qp_reject {
    QP_OK = 0,
    QP_BAD_CRC = 1,
    QP_BAD_COBS = 2,
    QP_BAD_LENGTH = 3,
    QP_BAD_VERSION = 4,
    QP_UNKNOWN_TYPE = 5,
    QP_OVERSIZE = 6
};

/* Messages: field names and order as in firmware_protocol/messages.py. */
typedef struct { uint32_t nonce; } qp_hello;

typedef struct {
    uint32_t nonce;
    uint8_t protocol_version, firmware_major, firmware_minor, firmware_patch;
    uint32_t capabilities;
    uint16_t rate_hz, watchdog_ticks, max_millivolts, module_id;
} qp_hello_reply;

typedef struct { uint16_t rate_hz, watchdog_ticks, max_millivolts; } qp_config;

typedef struct {
    uint8_t result;
    uint16_t rate_hz, watchdog_ticks, max_millivolts;
} qp_config_ack;

typedef struct {
    int16_t millivolts;
    uint8_t flags;
    uint16_t led_red, led_green, led_blue;
} qp_command;

typedef struct {
    uint32_t tick;
    int32_t encoder0, encoder1;
    uint32_t tach_raw;
    uint16_t current_raw, status;
    uint32_t last_command_seq;
    int16_t applied_millivolts;
    uint16_t motor_word, command_age;
} qp_telemetry;

typedef struct {
    uint8_t code;
    uint32_t tick, value;
} qp_fault;

typedef struct {
    uint8_t version, type;
    uint32_t seq, timestamp_us;
    uint8_t payload_len;
    uint8_t payload[QP_MAX_PAYLOAD];
} qp_frame;

typedef struct {
    uint32_t frames, bad_crc, bad_cobs, bad_length, bad_version, unknown_type, oversize;
    uint32_t last_bad_version, bytes_in;
} qp_counters;

typedef struct {
    uint8_t buf[QP_MAX_WIRE];
    uint16_t len;
    uint8_t overflowed;
    qp_counters counters;
} qp_decoder;

/* CRC-16/CCITT-FALSE continued from crc (start with 0xFFFF). */
uint16_t qp_crc16(uint16_t crc, const uint8_t *data, size_t len);

/* COBS-encode len bytes into out (capacity cap); returns the encoded length,
 * 0 if out is too small. No delimiter is written. */
size_t qp_cobs_encode(const uint8_t *in, size_t len, uint8_t *out, size_t cap);

/* Decode a COBS encoding (no delimiter); in and out may be the same buffer.
 * Returns the decoded length, or -1 if the encoding is invalid or out is
 * too small. */
long qp_cobs_decode(const uint8_t *in, size_t len, uint8_t *out, size_t cap);

/* Payload size of a known message type, 0 for an unknown one. */
size_t qp_payload_size(uint8_t type);

/* Encode one frame, delimiter included, from raw parts. Returns the number of
 * bytes written, 0 if payload_len > QP_MAX_PAYLOAD or cap is too small. */
size_t qp_encode_frame(uint8_t type, uint32_t seq, uint32_t timestamp_us, const uint8_t *payload,
                       size_t payload_len, uint8_t *out, size_t cap);

/* Decode the bytes between two delimiters (piece is modified in place).
 * Returns QP_OK and fills *frame, or the reason for rejecting it. */
int qp_parse_piece(uint8_t *piece, size_t len, qp_frame *frame);

void qp_decoder_init(qp_decoder *dec);
/* sizeof(qp_decoder) and its counters, for callers that allocate it
 * opaquely (ctypes). */
size_t qp_decoder_size(void);
const qp_counters *qp_decoder_counters(const qp_decoder *dec);
/* Feed one received byte. Returns 1 when it completes a valid frame (copied
 * to *frame), else 0; rejected pieces are counted in dec->counters. */
int qp_decoder_push(qp_decoder *dec, uint8_t byte, qp_frame *frame);
/* The same as qp_decoder_push for each of len bytes none of which is 0x00
 * (a run inside a frame), in one copy. */
void qp_decoder_append(qp_decoder *dec, const uint8_t *data, size_t len);

/* Feed a buffer: stores up to max_frames valid frames in frames[] and
 * returns how many valid frames the buffer completed (possibly more). */
size_t qp_decoder_feed(qp_decoder *dec, const uint8_t *data, size_t len, qp_frame *frames, size_t max_frames);

/* Payload packing: pack writes exactly the type's size and returns it;
 * unpack returns 0, or -1 if len is not the type's size. */
size_t qp_pack_hello(const qp_hello *m, uint8_t *out);
int qp_unpack_hello(const uint8_t *p, size_t len, qp_hello *m);
size_t qp_pack_hello_reply(const qp_hello_reply *m, uint8_t *out);
int qp_unpack_hello_reply(const uint8_t *p, size_t len, qp_hello_reply *m);
size_t qp_pack_config(const qp_config *m, uint8_t *out);
int qp_unpack_config(const uint8_t *p, size_t len, qp_config *m);
size_t qp_pack_config_ack(const qp_config_ack *m, uint8_t *out);
int qp_unpack_config_ack(const uint8_t *p, size_t len, qp_config_ack *m);
size_t qp_pack_command(const qp_command *m, uint8_t *out);
int qp_unpack_command(const uint8_t *p, size_t len, qp_command *m);
size_t qp_pack_telemetry(const qp_telemetry *m, uint8_t *out);
int qp_unpack_telemetry(const uint8_t *p, size_t len, qp_telemetry *m);
size_t qp_pack_fault(const qp_fault *m, uint8_t *out);
int qp_unpack_fault(const uint8_t *p, size_t len, qp_fault *m);

/* Why a configuration would be refused (QP_CONFIG_OK if it would not). */
int qp_config_problem(const qp_config *cfg);

#ifdef __cplusplus
}
#endif

#endif /* QP_PROTOCOL_H */
