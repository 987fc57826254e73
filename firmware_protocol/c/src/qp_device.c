/* The bridge firmware's core (see qp_device.h and PROTOCOL.md). */
#include "qp_device.h"

#include <string.h>

#define QD_AGE_NONE 0xFFFFu

static const qp_config DEFAULT_CONFIG = { QP_DEFAULT_RATE_HZ, QP_DEFAULT_WATCHDOG_TICKS,
                                          (uint16_t)QP_MAX_MILLIVOLTS };

size_t qd_device_size(void)
{
    return sizeof(qd_device);
}

/* Appends in at most two copies (the queue wraps once at most). */
static void push_bytes(qd_device *dev, const uint8_t *data, size_t len)
{
    size_t tail = (dev->tx_head + dev->tx_len) % QD_TX_CAPACITY;
    size_t first = QD_TX_CAPACITY - tail < len ? QD_TX_CAPACITY - tail : len;
    memcpy(dev->tx + tail, data, first);
    memcpy(dev->tx, data + first, len - first);
    dev->tx_len = (uint16_t)(dev->tx_len + len);
}

/* Queue one whole frame or none: a half-sent frame would cost the host the
 * next one too. Dropped frames still use a sequence number, so the host
 * sees the gap. */
static void send(qd_device *dev, uint8_t type, const uint8_t *payload, size_t len, uint32_t now_us)
{
    uint8_t frame[QP_MAX_FRAME];
    size_t tail = (dev->tx_head + dev->tx_len) % QD_TX_CAPACITY;
    /* With room for the largest frame before the queue wraps, encode it in place (one copy fewer). */
    int in_place = QD_TX_CAPACITY - dev->tx_len >= QP_MAX_FRAME && QD_TX_CAPACITY - tail >= QP_MAX_FRAME;
    uint8_t *out = in_place ? dev->tx + tail : frame;
    size_t n = qp_encode_frame(type, dev->seq_out, now_us, payload, len, out, QP_MAX_FRAME);
    dev->seq_out++;
    if (n == 0 || n > QD_TX_CAPACITY - dev->tx_len) {
        dev->tx_overflow = 1;
        return;
    }
    if (in_place) {
        dev->tx_len = (uint16_t)(dev->tx_len + n);
    } else {
        push_bytes(dev, frame, n);
    }
}

static void send_fault(qd_device *dev, uint8_t code, uint32_t value, uint32_t now_us)
{
    qp_fault fault;
    uint8_t payload[QP_FAULT_SIZE];
    fault.code = code;
    fault.tick = dev->tick;
    fault.value = value;
    send(dev, QP_FAULT, payload, qp_pack_fault(&fault, payload), now_us);
}

static void start_session(qd_device *dev)
{
    dev->connected = 1;
    dev->armed = 0;
    dev->tripped = 0;
    dev->fresh = 0;
    dev->pending_resets = 0;
    memset(&dev->command, 0, sizeof dev->command);
    dev->command_seq = 0;
    dev->command_age = QD_AGE_NONE;
    dev->config = DEFAULT_CONFIG;
    dev->period_us = 1000000UL / DEFAULT_CONFIG.rate_hz;
    dev->tick = 0;
    dev->have_last_tick = 0;
    /* Faults already present are news to the new host. */
    dev->last_qube_status = 0;
    dev->bad_id_reported = 0;
}

static uint32_t rx_errors(const qd_device *dev)
{
    const qp_counters *c = &dev->decoder.counters;
    /* Bad versions have their own fault report. */
    return c->bad_crc + c->bad_cobs + c->bad_length + c->unknown_type + c->oversize;
}

void qd_init(qd_device *dev, uint32_t extra_capabilities)
{
    memset(dev, 0, sizeof *dev);
    qp_decoder_init(&dev->decoder);
    dev->capabilities = QD_CAPABILITIES | extra_capabilities;
    dev->config = DEFAULT_CONFIG;
    dev->period_us = 1000000UL / DEFAULT_CONFIG.rate_hz;
    dev->command_age = QD_AGE_NONE;
    /* A leading delimiter ends whatever partial frame the host holds. */
    dev->tx[0] = 0;
    dev->tx_len = 1;
}

static void on_hello(qd_device *dev, const qp_frame *frame, uint32_t now_us)
{
    qp_hello hello;
    qp_hello_reply reply;
    uint8_t payload[QP_HELLO_REPLY_SIZE];

    (void)qp_unpack_hello(frame->payload, frame->payload_len, &hello);
    start_session(dev);
    dev->rx_errors_reported = rx_errors(dev);
    reply.nonce = hello.nonce;
    reply.protocol_version = QP_VERSION;
    reply.firmware_major = QD_FIRMWARE_MAJOR;
    reply.firmware_minor = QD_FIRMWARE_MINOR;
    reply.firmware_patch = QD_FIRMWARE_PATCH;
    reply.capabilities = dev->capabilities;
    reply.rate_hz = dev->config.rate_hz;
    reply.watchdog_ticks = dev->config.watchdog_ticks;
    reply.max_millivolts = dev->config.max_millivolts;
    reply.module_id = dev->module_id;
    send(dev, QP_HELLO_REPLY, payload, qp_pack_hello_reply(&reply, payload), now_us);
}

static void on_config(qd_device *dev, const qp_frame *frame, uint32_t now_us)
{
    qp_config cfg;
    qp_config_ack ack;
    uint8_t payload[QP_CONFIG_ACK_SIZE];

    (void)qp_unpack_config(frame->payload, frame->payload_len, &cfg);
    ack.result = (uint8_t)qp_config_problem(&cfg);
    if (ack.result == QP_CONFIG_OK) {
        dev->config = cfg;
        dev->period_us = 1000000UL / cfg.rate_hz; /* divided once here, not every tick */
    }
    ack.rate_hz = dev->config.rate_hz;
    ack.watchdog_ticks = dev->config.watchdog_ticks;
    ack.max_millivolts = dev->config.max_millivolts;
    send(dev, QP_CONFIG_ACK, payload, qp_pack_config_ack(&ack, payload), now_us);
}

static void on_command(qd_device *dev, const qp_frame *frame)
{
    qp_command cmd;
    (void)qp_unpack_command(frame->payload, frame->payload_len, &cmd);
    /* Newest wins, but resets from a command overtaken before the tick
     * must not be lost. */
    dev->pending_resets |= (uint8_t)(cmd.flags & (QP_CMD_RESET_ENCODER0 | QP_CMD_RESET_ENCODER1));
    dev->command = cmd;
    dev->command_seq = frame->seq;
    dev->fresh = 1;
    dev->armed = 1;
    /* Like the QUBE's stall error, a tripped watchdog is cleared by
     * commanding the amplifier off, so a host cannot re-enable it by accident. */
    if (dev->tripped && !(cmd.flags & QP_CMD_AMP_ENABLE)) {
        dev->tripped = 0;
    }
}

static void on_frame(qd_device *dev, const qp_frame *frame, uint32_t now_us)
{
    if (frame->type == QP_HELLO) {
        on_hello(dev, frame, now_us);
    } else if (frame->type == QP_CONFIG || frame->type == QP_COMMAND) {
        if (!dev->connected) {
            send_fault(dev, QP_FAULT_NOT_CONNECTED, frame->type, now_us);
        } else if (frame->type == QP_CONFIG) {
            on_config(dev, frame, now_us);
        } else {
            on_command(dev, frame);
        }
    }
    /* Device-to-host types arriving here are ignored. */
}

void qd_receive(qd_device *dev, const uint8_t *data, size_t len, uint32_t now_us)
{
    qp_frame frame;
    size_t i = 0;
    while (i < len) {
        /* The bytes up to the next delimiter in one copy: only a delimiter ends a frame. */
        const uint8_t *zero = (const uint8_t *)memchr(data + i, 0, len - i);
        size_t run = zero ? (size_t)(zero - (data + i)) : len - i;
        uint32_t bad_versions;
        qp_decoder_append(&dev->decoder, data + i, run);
        i += run;
        if (i == len) {
            break;
        }
        i++;
        bad_versions = dev->decoder.counters.bad_version;
        if (qp_decoder_push(&dev->decoder, 0, &frame)) {
            on_frame(dev, &frame, now_us);
        } else if (dev->decoder.counters.bad_version != bad_versions) {
            /* Answer even before HELLO: this is how a host speaking another
             * version learns which one the device speaks. */
            send_fault(dev, QP_FAULT_BAD_VERSION, dev->decoder.counters.last_bad_version, now_us);
        }
    }
}

uint32_t qd_period_us(const qd_device *dev)
{
    return dev->period_us;
}

/* Periods since the previous tick, to the nearest (the glue stamps ticks
 * with their period's start, so this is exact on the bridge): every period
 * beyond the first was lost, and the tick counter skips it, so telemetry
 * counts elapsed periods and the host sees the gap. */
static void check_timing(qd_device *dev, uint32_t now_us)
{
    uint32_t period = qd_period_us(dev);
    if (dev->have_last_tick) {
        uint32_t elapsed = now_us - dev->last_tick_us; /* wraps correctly */
        if (elapsed >= period + period / 2u) {
            uint32_t lost = (elapsed + period / 2u) / period - 1u;
            dev->tick_status |= QP_ST_TICK_OVERRUN;
            dev->tick += lost;
            if (dev->connected) {
                send_fault(dev, QP_FAULT_TICK_OVERRUN, lost, now_us);
            }
        }
    }
    dev->last_tick_us = now_us;
    dev->have_last_tick = 1;
}

static void run_watchdog(qd_device *dev, uint32_t now_us)
{
    if (!dev->connected || !dev->armed) {
        return;
    }
    if (dev->fresh) {
        dev->command_age = 0;
    } else if (dev->command_age < QD_AGE_NONE - 1u) {
        dev->command_age++;
    }
    dev->fresh = 0;
    if (!dev->tripped && dev->command_age >= dev->config.watchdog_ticks) {
        dev->tripped = 1;
        send_fault(dev, QP_FAULT_WATCHDOG_TRIPPED, dev->config.watchdog_ticks, now_us);
    }
}

static uint16_t clamp_led(uint16_t v)
{
    return v > QP_LED_MAX ? (uint16_t)QP_LED_MAX : v;
}

void qd_tick_begin(qd_device *dev, uint32_t now_us, uint8_t spi_tx[QP_SPI_SIZE])
{
    qp_spi_command spi;
    int enable;
    int32_t mv;
    int32_t limit = (int32_t)dev->config.max_millivolts;

    dev->tick_status = 0;
    dev->tick_time_us = now_us;
    check_timing(dev, now_us);
    run_watchdog(dev, now_us);

    enable = dev->connected && dev->armed && !dev->tripped && (dev->command.flags & QP_CMD_AMP_ENABLE);
    mv = dev->command.millivolts;
    if (mv > limit || mv < -limit) {
        mv = mv > 0 ? limit : -limit;
        if (enable) {
            dev->tick_status |= QP_ST_SATURATED;
        }
    }
    dev->applied_millivolts = (int16_t)(enable ? mv : 0);
    dev->motor_word = qp_motor_word(mv, enable);
    if (enable) {
        dev->tick_status |= QP_ST_AMP_ENABLED;
    }
    if (dev->tripped) {
        dev->tick_status |= QP_ST_WATCHDOG_TRIPPED;
    }

    memset(&spi, 0, sizeof spi);
    spi.write_mask = QP_MASK_NORMAL;
    if (dev->pending_resets & QP_CMD_RESET_ENCODER0) {
        spi.write_mask |= QP_MASK_ENCODER0;
    }
    if (dev->pending_resets & QP_CMD_RESET_ENCODER1) {
        spi.write_mask |= QP_MASK_ENCODER1;
    }
    if (dev->pending_resets) {
        dev->tick_status |= QP_ST_ENCODER_RESET;
        dev->pending_resets = 0;
    }
    /* LED: blue while no command has come, red once tripped, else as commanded. */
    if (dev->tripped) {
        spi.led_red = QP_LED_MAX;
    } else if (!dev->connected || !dev->armed) {
        spi.led_blue = QP_LED_MAX;
    } else {
        spi.led_red = clamp_led(dev->command.led_red);
        spi.led_green = clamp_led(dev->command.led_green);
        spi.led_blue = clamp_led(dev->command.led_blue);
    }
    spi.motor = dev->motor_word;
    qp_spi_pack_command(&spi, spi_tx);
}

static void report_edges(qd_device *dev, const qp_spi_response *resp, uint8_t qube_status)
{
    uint8_t rising = (uint8_t)(qube_status & ~dev->last_qube_status);
    uint32_t errors;

    dev->last_qube_status = qube_status;
    if (resp->module_id != QP_MODULE_ID_QUBE_SERVO_2) {
        if (!dev->bad_id_reported) {
            send_fault(dev, QP_FAULT_BAD_MODULE_ID, resp->module_id, dev->tick_time_us);
            dev->bad_id_reported = 1;
        }
    } else {
        dev->bad_id_reported = 0;
    }
    if (rising & QP_ST_AMP_FAULT) {
        send_fault(dev, QP_FAULT_AMP_FAULT, qube_status, dev->tick_time_us);
    }
    if (rising & QP_ST_STALL_ERROR) {
        send_fault(dev, QP_FAULT_STALL_ERROR, qube_status, dev->tick_time_us);
    }
    /* At most one report per tick, however noisy the line. */
    errors = rx_errors(dev);
    if (errors != dev->rx_errors_reported) {
        send_fault(dev, QP_FAULT_RX_ERRORS, errors, dev->tick_time_us);
        dev->rx_errors_reported = errors;
    }
}

void qd_tick_end(qd_device *dev, const uint8_t spi_rx[QP_SPI_SIZE])
{
    qp_spi_response resp;
    qp_telemetry tm;
    uint8_t payload[QP_TELEMETRY_SIZE];
    uint8_t qube_status;

    qp_spi_unpack_response(spi_rx, &resp);
    dev->module_id = resp.module_id;
    qube_status = (uint8_t)(resp.status & (QP_ST_AMP_FAULT | QP_ST_STALL_DETECTED | QP_ST_STALL_ERROR));
    dev->tick_status |= qube_status;
    if (resp.module_id != QP_MODULE_ID_QUBE_SERVO_2) {
        dev->tick_status |= QP_ST_BAD_MODULE_ID;
    }
    if (!dev->connected) {
        dev->last_qube_status = qube_status;
        return;
    }
    report_edges(dev, &resp, qube_status);
    if (dev->tx_overflow) {
        dev->tick_status |= QP_ST_TX_OVERFLOW;
    }
    tm.tick = dev->tick;
    tm.encoder0 = resp.encoder0;
    tm.encoder1 = resp.encoder1;
    tm.tach_raw = resp.tach_raw;
    tm.current_raw = resp.current_raw;
    tm.status = dev->tick_status;
    tm.last_command_seq = dev->command_seq;
    tm.applied_millivolts = dev->applied_millivolts;
    tm.motor_word = dev->motor_word;
    tm.command_age = dev->command_age;
    dev->tx_overflow = 0;
    send(dev, QP_TELEMETRY, payload, qp_pack_telemetry(&tm, payload), dev->tick_time_us);
    dev->tick++;
}

size_t qd_take_output(qd_device *dev, uint8_t *out, size_t cap)
{
    size_t n = cap < dev->tx_len ? cap : dev->tx_len;
    size_t first = QD_TX_CAPACITY - dev->tx_head < n ? QD_TX_CAPACITY - dev->tx_head : n;
    memcpy(out, dev->tx + dev->tx_head, first);
    memcpy(out + first, dev->tx, n - first);
    dev->tx_head = (uint16_t)((dev->tx_head + n) % QD_TX_CAPACITY);
    dev->tx_len = (uint16_t)(dev->tx_len - n);
    return n;
}

size_t qd_pending_output(const qd_device *dev)
{
    return dev->tx_len;
}

const qp_counters *qd_rx_counters(const qd_device *dev)
{
    return &dev->decoder.counters;
}
