/*
 * The bridge firmware's core: session, watchdog, command application and
 * telemetry, with no hardware access. Bytes and time go in, bytes come out:
 *
 *   qd_receive(dev, bytes, n, now_us)    bytes from the host
 *   qd_tick_begin(dev, now_us, spi_tx)   at each tick: the 17 bytes to send
 *       ... the glue (or an emulated QUBE) does the SPI transfer ...
 *   qd_tick_end(dev, spi_rx)             the 17 bytes that came back
 *   qd_take_output(dev, out, cap)        bytes for the host
 *
 * The Arduino sketch (examples/qube_bridge) and the emulated bridge (through
 * ctypes, firmware_protocol/ccore.py) are two kinds of glue around it.
 * Behaviour is specified in firmware_protocol/PROTOCOL.md, "Device behaviour".
 */
#ifndef QP_DEVICE_H
#define QP_DEVICE_H

#include <stddef.h>
#include <stdint.h>

#include "qp_protocol.h"
#include "qp_qube.h"

#ifdef __cplusplus
extern "C" {
#endif

#ifndef QD_TX_CAPACITY
/* Five telemetry frames: room for a host that reads a few ticks late. */
#define QD_TX_CAPACITY 256u
#endif

#define QD_FIRMWARE_MAJOR 1u
#define QD_FIRMWARE_MINOR 0u
#define QD_FIRMWARE_PATCH 0u
#define QD_CAPABILITIES (QP_CAP_TELEMETRY | QP_CAP_WATCHDOG | QP_CAP_ENCODER_RESET | QP_CAP_LED | \
                         QP_CAP_CURRENT_SENSE | QP_CAP_TACHOMETER | QP_CAP_CONFIGURABLE_RATE)

typedef struct {
    qp_decoder decoder;
    uint8_t tx[QD_TX_CAPACITY];
    uint16_t tx_head, tx_len;
    uint8_t tx_overflow;
    uint32_t capabilities;
    uint32_t seq_out;

    /* Session (reset by HELLO). */
    uint8_t connected, armed, tripped, fresh, pending_resets;
    qp_command command;
    uint32_t command_seq;
    uint16_t command_age;
    qp_config config;
    uint32_t period_us; /* 1e6 / config.rate_hz */
    uint32_t tick;
    uint32_t rx_errors_reported;

    /* Timing and edges. */
    uint32_t last_tick_us;
    uint8_t have_last_tick;
    uint8_t last_qube_status;
    uint8_t bad_id_reported;
    uint16_t module_id;

    /* Carried from qd_tick_begin to qd_tick_end. */
    uint32_t tick_time_us;
    uint16_t tick_status;
    int16_t applied_millivolts;
    uint16_t motor_word;
} qd_device;

/* sizeof(qd_device), for callers that allocate it opaquely (ctypes). */
size_t qd_device_size(void);
/* Power-on state; extra_capabilities is OR-ed in (QP_CAP_EMULATED for a simulator). */
void qd_init(qd_device *dev, uint32_t extra_capabilities);
void qd_receive(qd_device *dev, const uint8_t *data, size_t len, uint32_t now_us);
void qd_tick_begin(qd_device *dev, uint32_t now_us, uint8_t spi_tx[QP_SPI_SIZE]);
void qd_tick_end(qd_device *dev, const uint8_t spi_rx[QP_SPI_SIZE]);
/* Move up to cap pending output bytes to out; returns how many. */
size_t qd_take_output(qd_device *dev, uint8_t *out, size_t cap);
/* Output bytes waiting. */
size_t qd_pending_output(const qd_device *dev);
/* The tick period the glue must keep, in microseconds. */
uint32_t qd_period_us(const qd_device *dev);
/* Counters of the device's own frame decoder. */
const qp_counters *qd_rx_counters(const qd_device *dev);

#ifdef __cplusplus
}
#endif

#endif /* QP_DEVICE_H */
