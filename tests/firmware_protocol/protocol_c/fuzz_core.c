/*
 * Sanitizer fuzz run of the C codec and firmware core (built by
 * tests/test_protocol_c.py with -fsanitize=address,undefined).
 *
 * Feeds mutated frame streams and random SPI responses through qd_device for
 * many rounds and checks invariants that must hold on any input:
 *   - every byte the device emits decodes as valid frames (no rejects),
 *     also when its output queue overflows and frames are dropped;
 *   - the motor word is 0 unless the amplifier-enable bit is set, and the
 *     PWM never exceeds 625 (15 V);
 *   - ASan/UBSan find no out-of-bounds access or undefined behaviour.
 * Prints "OK <counts>" and exits 0, or prints the failure and exits 1.
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "qp_device.h"

static uint32_t rng_state = 12345u;

static uint32_t rnd(void)
{
    /* xorshift32: deterministic across platforms. */
    rng_state ^= rng_state << 13;
    rng_state ^= rng_state >> 17;
    rng_state ^= rng_state << 5;
    return rng_state;
}

static int fail(const char *what, unsigned long round)
{
    printf("FAIL %s in round %lu\n", what, round);
    return 1;
}

static const uint8_t TYPES[] = { QP_HELLO, QP_CONFIG, QP_COMMAND, QP_HELLO_REPLY, QP_CONFIG_ACK,
                                 QP_TELEMETRY, QP_FAULT, 0x7F };

static size_t random_frame(uint8_t *out, size_t cap)
{
    uint8_t payload[QP_MAX_PAYLOAD];
    uint8_t type = TYPES[rnd() % sizeof TYPES];
    size_t len = qp_payload_size(type), i;
    if (len == 0 || rnd() % 16 == 0) {
        len = rnd() % (QP_MAX_PAYLOAD + 1u);
    }
    for (i = 0; i < len; i++) {
        payload[i] = (uint8_t)(rnd() % 4u == 0 ? 0 : rnd());
    }
    if (type == QP_COMMAND && len == QP_COMMAND_SIZE && rnd() % 2u) {
        payload[2] = (uint8_t)(payload[2] | QP_CMD_AMP_ENABLE);
    }
    return qp_encode_frame(type, rnd() % 8u, rnd(), payload, len, out, cap);
}

static size_t mutate(uint8_t *buf, size_t len, size_t cap)
{
    unsigned k, n = rnd() % 4u;
    for (k = 0; k < n && len > 0; k++) {
        size_t pos = rnd() % len;
        switch (rnd() % 3u) {
        case 0: buf[pos] ^= (uint8_t)(1u << (rnd() % 8u)); break;
        case 1: memmove(buf + pos, buf + pos + 1, len - pos - 1); len--; break;
        default:
            if (len < cap) {
                memmove(buf + pos + 1, buf + pos, len - pos);
                buf[pos] = (uint8_t)rnd();
                len++;
            }
        }
    }
    return len;
}

int main(int argc, char **argv)
{
    static qd_device dev;
    qp_decoder check;
    qp_frame frames[64];
    uint8_t stream[2048], out[4096], tx[QP_SPI_SIZE], rx[QP_SPI_SIZE];
    unsigned long rounds = argc > 1 ? strtoul(argv[1], NULL, 10) : 20000ul, r;
    unsigned long emitted = 0, ticks = 0;
    uint32_t now = 0;

    qd_init(&dev, 0);
    qp_decoder_init(&check);
    for (r = 0; r < rounds; r++) {
        size_t len = 0, n, i;
        uint32_t rejected;
        /* A few frames, some mutated, sometimes plain garbage; always a
         * HELLO now and then so the session is usually open. */
        if (r % 50u == 0) {
            uint8_t nonce[4] = { 1, 2, 3, 4 };
            len += qp_encode_frame(QP_HELLO, 0, 0, nonce, 4, stream, sizeof stream);
        }
        while (len < sizeof stream - QP_MAX_FRAME - 8u && rnd() % 4u != 0) {
            size_t f = random_frame(stream + len, sizeof stream - len);
            len += rnd() % 3u == 0 ? mutate(stream + len, f, sizeof stream - len) : f;
        }
        if (rnd() % 8u == 0) {
            for (i = 0; i < 8u; i++) {
                stream[len++] = (uint8_t)rnd();
            }
        }
        qd_receive(&dev, stream, len, now);
        /* A tick with a random QUBE response; sometimes late. */
        now += qd_period_us(&dev) * (rnd() % 16u == 0 ? 3u : 1u);
        qd_tick_begin(&dev, now, tx);
        {
            uint16_t word = (uint16_t)(((uint16_t)tx[15] << 8) | tx[16]);
            int16_t pwm = (int16_t)(uint16_t)((word & 0x7FFFu) | ((word & 0x4000u) ? 0x8000u : 0u));
            if (!(word & QP_MOTOR_ENABLE) && word != 0) {
                return fail("motor word without enable bit", r);
            }
            if (pwm > 625 || pwm < -625) {
                return fail("PWM beyond 15 V", r);
            }
            if (tx[0] != QP_SPI_MODE_BYTE || tx[1] != 0) {
                return fail("SPI header bytes", r);
            }
        }
        for (i = 0; i < QP_SPI_SIZE; i++) {
            rx[i] = (uint8_t)rnd();
        }
        if (rnd() % 2u) {
            rx[0] = 0x03;
            rx[1] = 0x09;
        }
        qd_tick_end(&dev, rx);
        ticks++;
        /* Drain the output, but not always: overflow must drop whole frames. */
        if (rnd() % 8u != 0) {
            n = qd_take_output(&dev, out, sizeof out);
            rejected = check.counters.bad_crc + check.counters.bad_cobs + check.counters.bad_length +
                       check.counters.bad_version + check.counters.unknown_type + check.counters.oversize;
            emitted += qp_decoder_feed(&check, out, n, frames, 64);
            if (check.counters.bad_crc + check.counters.bad_cobs + check.counters.bad_length +
                    check.counters.bad_version + check.counters.unknown_type + check.counters.oversize !=
                rejected) {
                return fail("device emitted an invalid frame", r);
            }
        }
    }
    printf("OK rounds=%lu ticks=%lu frames_out=%lu rx_frames=%lu rx_rejected=%lu\n", rounds, ticks, emitted,
           (unsigned long)dev.decoder.counters.frames,
           (unsigned long)(dev.decoder.counters.bad_crc + dev.decoder.counters.bad_cobs +
                           dev.decoder.counters.bad_length + dev.decoder.counters.unknown_type +
                           dev.decoder.counters.bad_version + dev.decoder.counters.oversize));
    return 0;
}
