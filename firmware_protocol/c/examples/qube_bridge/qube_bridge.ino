/*
 * QUBE-Servo 2 bridge: SPI to the QUBE, serial to the host.
 *
 * Thin glue around the firmware core (src/qp_device.h): it moves bytes
 * between the serial port and the core, keeps the tick deadlines and does
 * the SPI transfer. All protocol and safety logic (handshake, watchdog,
 * command application, telemetry) is in the core, which the host test suite
 * compiles and checks on a PC.
 *
 * Build: arduino-cli compile --library <repo>/firmware_protocol/c \
 *            --fqbn <board> <repo>/firmware_protocol/c/examples/qube_bridge
 *
 * Link: telemetry is 46 bytes per tick (23 kB/s at 500 Hz), beyond 115200
 * baud. Use a board with native USB (CDC ignores the baud rate) or a UART at
 * 460800 baud or more; on FTDI adapters enable low-latency mode on the host.
 * A 16 MHz AVR cannot make 460800 (the nearest divisor gives 500000, 8.5 %
 * off) but makes 500000 exactly, hence the default below.
 */
#include <SPI.h>
#include <qp_device.h>

static const uint8_t CS_PIN = 10;
static const uint32_t BAUD = 500000;
static const size_t CHUNK = 64;

static qd_device dev;
static uint32_t next_tick_us;

static void spi_transfer(const uint8_t *tx, uint8_t *rx)
{
    SPI.beginTransaction(SPISettings(1000000, MSBFIRST, SPI_MODE2));
    digitalWrite(CS_PIN, LOW);
    for (uint8_t i = 0; i < QP_SPI_SIZE; i++) {
        rx[i] = SPI.transfer(tx[i]);
    }
    digitalWrite(CS_PIN, HIGH);
    SPI.endTransaction();
}

void setup()
{
    pinMode(CS_PIN, OUTPUT);
    digitalWrite(CS_PIN, HIGH);
    SPI.begin();
    Serial.begin(BAUD);
    qd_init(&dev, 0);
    next_tick_us = micros() + qd_period_us(&dev);
}

void loop()
{
    uint8_t buf[CHUNK];

    /* Host -> core. */
    size_t n = 0;
    while (n < CHUNK && Serial.available() > 0) {
        buf[n++] = (uint8_t)Serial.read();
    }
    if (n > 0) {
        qd_receive(&dev, buf, n, micros());
    }

    /* Ticks on absolute deadlines, polled rather than run from a timer
     * interrupt: an SPI transfer inside an ISR would race the serial driver on
     * many cores, and polling costs at most one loop pass of jitter. */
    uint32_t now = micros();
    if ((int32_t)(now - next_tick_us) >= 0) {
        uint8_t tx[QP_SPI_SIZE], rx[QP_SPI_SIZE];
        qd_tick_begin(&dev, now, tx);
        spi_transfer(tx, rx);
        qd_tick_end(&dev, rx);
        next_tick_us += qd_period_us(&dev);
        if ((int32_t)(now - next_tick_us) >= 0) {
            /* A whole period was lost (the core has reported the overrun):
             * restart the schedule rather than burst to catch up. */
            next_tick_us = now + qd_period_us(&dev);
        }
    }

    /* Core -> host, never blocking the loop on a full serial buffer. */
    int room = Serial.availableForWrite();
    if (room > 0) {
        size_t k = qd_take_output(&dev, buf, (size_t)room < CHUNK ? (size_t)room : CHUNK);
        if (k > 0) {
            Serial.write(buf, k);
        }
    }
}
