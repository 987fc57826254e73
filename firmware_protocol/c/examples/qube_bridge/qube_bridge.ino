/*
 * QUBE-Servo 2 bridge for the Arduino Uno (ATmega328P, 16 MHz): SPI to the
 * QUBE, UART to the host.
 *
 * Thin glue around the firmware core (src/qp_device.h): it moves bytes
 * between the UART and the core, keeps the tick clock and does the SPI
 * transfer. All protocol and safety logic (handshake, watchdog, command
 * application, telemetry) is in the core, which the host test suite compiles
 * and checks on a PC; this glue is tested on an emulated ATmega328P
 * (sim/bridge/avr.py).
 *
 * Build: firmware_protocol/avr_build.py (Debian's gcc-avr, avr-libc and
 * arduino-core-avr; no IDE), or arduino-cli compile --library
 * <repo>/firmware_protocol/c --fqbn arduino:avr:uno <this folder>.
 *
 * Timing: Timer1 counts the periods from the crystal and its interrupt only
 * counts them; the main loop runs one tick per batch of elapsed periods,
 * stamped with the period's start, so the core sees exactly how many
 * periods went by and reports every lost one (TICK_OVERRUN, and the
 * telemetry's tick counter advances by elapsed periods). Between ticks and
 * during the SPI transaction (run by its interrupt) the CPU sleeps (idle
 * mode), which also makes its busy time measurable.
 *
 * UART: 500000 baud exactly (UBRR0 = 3 with U2X, 16 MHz); 460800 would be
 * 8.5 % off. The receive interrupt fills a 128-byte ring (a burst of eight
 * commands is about 160 bytes, decoded faster than they arrive); the
 * transmit interrupt feeds the UART from its own 128-byte ring, refilled
 * from the core's output queue by the main loop (no HardwareSerial; only
 * the main loop touches the core). The ring is topped up after every tick
 * and every decoded chunk.
 *
 * Chip select (pin 10, PB2) is driven high before it becomes an output, so
 * the QUBE sees no empty transaction at power-up.
 */
#include <avr/interrupt.h>
#include <avr/io.h>
#include <avr/sleep.h>
#include <qp_device.h>

#define RX_RING 128u /* power of two */
#define CS_BIT PB2

static qd_device dev;
static volatile uint8_t rx_ring[RX_RING];
static volatile uint8_t rx_head, rx_tail;
static volatile uint8_t work; /* set by the interrupts when the main loop has something to do */
static volatile uint8_t periods_due;
static volatile uint32_t period_start_us;
static uint32_t period_us;
static uint8_t us_shift_left; /* Timer1 count to microseconds: prescaler 8 -> /2, 64 -> *4 */

ISR(USART_RX_vect)
{
    uint8_t byte = UDR0;
    uint8_t head = rx_head;
    uint8_t next = (uint8_t)((head + 1u) & (RX_RING - 1u));
    uint8_t tail = rx_tail;
    if (next != tail) { /* a full ring drops the byte: the frame's CRC then fails and is reported */
        rx_ring[head] = byte;
        rx_head = next;
        if (byte == 0 || (uint8_t)((next - tail) & (RX_RING - 1u)) >= RX_RING / 2u) {
            work = 1; /* a frame is complete, or the ring is half full */
        }
    }
}

/* The transmit interrupt's own ring with 8-bit indices: the cheapest
 * interrupt for each of the 46 bytes of a tick, and the core is touched by
 * the main loop only (no masking: simavr, like a careless port, can lose a
 * transmit interrupt that was pending while masked). What the ring cannot
 * take stays in the core's queue until the next tick or decoded chunk
 * (a tick adds 46 bytes; the ring takes up to 127). */
#define TX_RING 128u /* power of two */
static volatile uint8_t tx_ring[TX_RING];
static volatile uint8_t tx_head, tx_tail;

ISR(USART_UDRE_vect)
{
    uint8_t tail = tx_tail;
    UDR0 = tx_ring[tail];
    tail = (uint8_t)((tail + 1u) & (TX_RING - 1u));
    tx_tail = tail;
    if (tail == tx_head) {
        UCSR0B &= (uint8_t)~_BV(UDRIE0);
    }
}

ISR(TIMER1_COMPA_vect)
{
    period_start_us += period_us;
    if (periods_due < 255u) {
        periods_due++;
    }
    work = 1;
}

static uint32_t now_us(void)
{
    uint8_t sreg = SREG;
    uint32_t t;
    uint16_t count;
    cli();
    t = period_start_us;
    count = TCNT1;
    if (TIFR1 & _BV(OCF1A)) { /* a period ended but its interrupt has not run */
        t += period_us;
        count = TCNT1;
    }
    SREG = sreg;
    return t + (us_shift_left ? (uint32_t)count << 2 : (uint32_t)(count >> 1));
}

/* Timer1 in CTC mode: 0.5 us counts up to 32.7 ms periods, 4 us counts beyond. */
static void set_period(uint32_t us)
{
    uint8_t sreg = SREG;
    cli();
    period_us = us;
    us_shift_left = us > 32767u;
    TCCR1A = 0;
    TCCR1B = (uint8_t)(_BV(WGM12) | (us_shift_left ? (_BV(CS11) | _BV(CS10)) : _BV(CS11)));
    OCR1A = (uint16_t)(us_shift_left ? us / 4u - 1u : us * 2u - 1u);
    if (TCNT1 > OCR1A) {
        TCNT1 = 0;
    }
    SREG = sreg;
}

/* The SPI transaction runs from its interrupt, one byte per 8 SCK periods
 * (128 cycles at 1 MHz): the CPU sleeps meanwhile instead of spinning. */
static uint8_t spi_tx[QP_SPI_SIZE], spi_rx[QP_SPI_SIZE];
static volatile uint8_t spi_index = QP_SPI_SIZE; /* QP_SPI_SIZE: no transaction running */
static uint8_t spi_busy;

ISR(SPI_STC_vect)
{
    uint8_t i = spi_index;
    spi_rx[i] = SPDR;
    i++;
    spi_index = i;
    if (i < QP_SPI_SIZE) {
        SPDR = spi_tx[i];
    } else {
        PORTB |= _BV(CS_BIT);
        work = 1;
    }
}

static void spi_start(void)
{
    spi_busy = 1;
    spi_index = 0;
    PORTB &= (uint8_t)~_BV(CS_BIT);
    SPDR = spi_tx[0];
}

/* Refill the transmit ring from the core's queue (straight into the ring,
 * at most two copies) and start the interrupt. The interrupt reads only
 * between tx_tail and tx_head, so the free part may be written meanwhile. */
static void start_tx(void)
{
    uint8_t head;
    if (qd_pending_output(&dev) == 0) {
        return; /* the common case after a decoded command: nothing to send */
    }
    head = tx_head;
    uint8_t room = (uint8_t)((tx_tail - head - 1u) & (TX_RING - 1u));
    while (room) {
        uint8_t run = (uint8_t)(TX_RING - head) < room ? (uint8_t)(TX_RING - head) : room;
        uint8_t n = (uint8_t)qd_take_output(&dev, (uint8_t *)&tx_ring[head], run);
        if (n == 0) {
            break;
        }
        head = (uint8_t)((head + n) & (TX_RING - 1u));
        room = (uint8_t)(room - n);
    }
    if (head != tx_head) {
        tx_head = head;
        UCSR0B |= _BV(UDRIE0);
    }
}

void setup()
{
    /* Chip select high first, then an output: no empty pulse for the QUBE. */
    PORTB |= _BV(CS_BIT);
    DDRB |= (uint8_t)(_BV(CS_BIT) | _BV(PB3) | _BV(PB5)); /* CS, MOSI, SCK */
    SPCR = (uint8_t)(_BV(SPIE) | _BV(SPE) | _BV(MSTR) | _BV(CPOL) | _BV(SPR0)); /* mode 2, 1 MHz */
    SPSR = 0;

    UCSR0A = _BV(U2X0);
    UBRR0 = 3; /* 16 MHz / (8 * (3 + 1)) = 500000 baud */
    UCSR0C = (uint8_t)(_BV(UCSZ01) | _BV(UCSZ00));
    UCSR0B = (uint8_t)(_BV(RXEN0) | _BV(TXEN0) | _BV(RXCIE0));

    TIMSK0 = 0; /* the Arduino millis() interrupt: unused, one wake-up less */
    qd_init(&dev, 0);
    set_period(qd_period_us(&dev));
    TCNT1 = 0;
    TIMSK1 = _BV(OCIE1A);
    set_sleep_mode(SLEEP_MODE_IDLE);
    start_tx();
}

/* Bytes are decoded a whole frame at a time (or when the ring is half
 * full): waking up the main loop for every byte would cost more than
 * decoding it. A tick that falls due stops the decoding. */
static void receive_pending(void)
{
    uint8_t buf[32];
    for (;;) {
        /* The indices are single bytes (read atomically); only this loop moves the tail, and
         * bytes arriving after the head was read wait for the next round. */
        uint8_t n = 0, tail = rx_tail, head = rx_head;
        if (tail == head) {
            return;
        }
        while (n < sizeof buf && tail != head) {
            buf[n++] = rx_ring[tail];
            tail = (uint8_t)((tail + 1u) & (RX_RING - 1u));
        }
        rx_tail = tail;
        qd_receive(&dev, buf, n, now_us());
        start_tx();
        if (periods_due) {
            work = 1; /* come back for the rest after the tick */
            return;
        }
    }
}

/* A tick in two halves around the SPI transaction. */
static void tick_start(void)
{
    uint32_t start;
    cli();
    periods_due = 0;
    start = period_start_us;
    sei();
    qd_tick_begin(&dev, start, spi_tx);
    spi_start();
}

static void tick_finish(void)
{
    uint32_t period;
    spi_busy = 0;
    qd_tick_end(&dev, spi_rx);
    start_tx();
    period = qd_period_us(&dev);
    if (period != period_us) {
        set_period(period);
    }
}

/* Whatever woke the CPU (every UART byte does) goes back to sleep at once
 * unless an interrupt flagged work: a tick due or a frame complete. */
void loop()
{
    sleep_enable();
    for (;;) {
        cli();
        if (!work) {
            sei(); /* the instruction after sei runs before any interrupt: no lost wake-up */
            sleep_cpu();
            continue;
        }
        work = 0;
        sei();
        if (spi_busy) {
            if (spi_index < QP_SPI_SIZE) {
                continue; /* the core is mid-tick: nothing else touches it */
            }
            tick_finish();
        }
        if (periods_due) {
            tick_start();
            continue;
        }
        receive_pending();
    }
}
