/*
 * A deterministic ATmega328P for tests: simavr driven from Python (ctypes).
 *
 * Development and test tool only, built locally from this source against the
 * system's simavr (GPL-3) at run time; it is never shipped in the wheel.
 *
 * Time is simulated: qh_run executes instructions until a cycle is reached or
 * the bridge's chip select (PB2) changes, so the caller can answer the SPI
 * side between the edges. Differences from stock simavr 1.6:
 *   - SPDR is taken over: a byte takes 8 SCK periods at the divider set in
 *     SPCR/SPSR (simavr models a fixed 100 us), the slave's answer comes from
 *     qh_spi_reply, and extra delay can be injected (qh_spi_stall);
 *   - UART0 input is paced at the frame time of the baud rate the firmware
 *     set (10 bits per byte), and a byte completing while the receive buffer
 *     (UDR0 plus one) is full is lost and counted, as on the chip;
 *   - no host sleeping and no console echo: the run is as fast as the host
 *     allows and depends on nothing but its inputs;
 *   - cycles are split into running and sleeping, for busy-time accounting:
 *     the step that executes SLEEP and the one that wakes count as busy only
 *     the instruction and the wake-up (WAKE_CYCLES); simavr's clock jumps to
 *     its next event within them.
 */
#include <stdarg.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include <simavr/avr_ioport.h>
#include <simavr/avr_spi.h>
#include <simavr/avr_uart.h>
#include <simavr/sim_avr.h>
#include <simavr/sim_elf.h>
#include <simavr/sim_irq.h>

#define SLEEP_OPCODE 0x9588u
/* Waking from idle sleep into an interrupt: the 4-cycle interrupt response plus
 * 4 cycles from sleep (ATmega328P datasheet, "Interrupt Response Time"). */
#define WAKE_CYCLES 8u
#include <simavr/sim_interrupts.h>

DEFINE_FIFO(uint16_t, uart_fifo);

#define SPCR 0x4C
#define SPSR 0x4D
#define SPDR 0x4E
#define UCSR0A 0xC0
#define UBRR0L 0xC4
#define UBRR0H 0xC5
#define UDR0 0xC6
#define IO(a) ((a) - 0x20)
#define CS_BIT 2
#define RING 65536u
#define SPI_MAX 64

typedef struct {
    avr_t *avr;
    avr_irq_t *uart_in;
    avr_uart_t *uart;
    avr_spi_t *spi;
    /* UART host -> chip */
    uint8_t rx[RING];
    uint32_t rx_head, rx_len;
    int rx_timer_on;
    uint32_t rx_lost, udr_reads;
    avr_io_read_t udr_read_orig;
    void *udr_read_param;
    /* UART chip -> host */
    uint8_t tx[RING];
    uint32_t tx_head, tx_len;
    /* SPI */
    uint8_t spi_reply[SPI_MAX], spi_sent[SPI_MAX];
    uint32_t spi_index, spi_stall;
    uint8_t spi_in_flight;
    /* pins and events */
    uint8_t port_b, ddr_b;
    int cs_level, event;
    uint32_t cs_driven_low, cs_falls;
    uint64_t busy, sleeping;
    uint64_t pc_cycles[16384]; /* running cycles by program word address */
} qh_t;

static void on_uart_out(struct avr_irq_t *irq, uint32_t value, void *param)
{
    qh_t *h = param;
    (void)irq;
    if (h->tx_len < RING) {
        h->tx[(h->tx_head + h->tx_len) % RING] = (uint8_t)value;
        h->tx_len++;
    }
}

static uint32_t byte_cycles(qh_t *h)
{
    uint8_t *d = h->avr->data;
    uint32_t ubrr = ((uint32_t)(d[UBRR0H] & 0x0F) << 8) | d[UBRR0L];
    uint32_t per_bit = (ubrr + 1u) * ((d[UCSR0A] & 0x02) ? 8u : 16u);
    return 10u * per_bit;
}

static avr_cycle_count_t rx_next(struct avr_t *avr, avr_cycle_count_t when, void *param)
{
    qh_t *h = param;
    (void)avr;
    if (h->rx_len == 0) {
        h->rx_timer_on = 0;
        return 0;
    }
    if (uart_fifo_get_read_size(&h->uart->input) >= 2) {
        h->rx_lost++; /* data overrun: UDR0 and its buffer are full */
    } else {
        avr_raise_irq(h->uart_in, h->rx[h->rx_head]);
    }
    h->rx_head = (h->rx_head + 1u) % RING;
    h->rx_len--;
    return when + byte_cycles(h);
}

static uint8_t on_udr_read(struct avr_t *avr, avr_io_addr_t addr, void *param)
{
    qh_t *h = param;
    uint8_t v = h->udr_read_orig(avr, addr, h->udr_read_param);
    h->udr_reads++;
    /* On the chip RXC stays set while the buffer holds a byte; simavr would
     * wait a frame time, so a backlog would never drain. */
    if (!uart_fifo_isempty(&h->uart->input)) {
        avr_raise_interrupt(avr, &h->uart->rxc);
    }
    return v;
}

static avr_cycle_count_t spi_done(struct avr_t *avr, avr_cycle_count_t when, void *param)
{
    qh_t *h = param;
    (void)when;
    avr->data[SPDR] = h->spi_index < SPI_MAX ? h->spi_reply[h->spi_index] : 0;
    h->spi_index++;
    h->spi_in_flight = 0;
    avr_raise_interrupt(avr, &h->spi->spi); /* sets SPIF; runs the interrupt if SPIE */
    return 0;
}

static void on_spdr_write(struct avr_t *avr, avr_io_addr_t addr, uint8_t v, void *param)
{
    static const uint32_t DIV[4] = { 4, 16, 64, 128 };
    qh_t *h = param;
    uint32_t div = DIV[avr->data[SPCR] & 3u];
    (void)addr;
    if (avr->data[SPSR] & 1u) {
        div /= 2u;
    }
    if (h->spi_in_flight) {
        avr->data[SPSR] |= 0x40; /* WCOL: written during a transfer */
        return;
    }
    if (h->spi_index < SPI_MAX) {
        h->spi_sent[h->spi_index] = v;
    }
    avr->data[SPSR] &= (uint8_t)~0x80u;
    h->spi_in_flight = 1;
    avr_cycle_timer_register(avr, 8u * div + h->spi_stall, spi_done, h);
    h->spi_stall = 0;
}

static uint8_t on_spdr_read(struct avr_t *avr, avr_io_addr_t addr, void *param)
{
    (void)param;
    avr->data[SPSR] &= (uint8_t)~0x80u; /* reading SPSR then SPDR clears SPIF */
    return avr->data[addr];
}

static void track_cs(qh_t *h)
{
    int out = (h->ddr_b >> CS_BIT) & 1;
    int level = out ? ((h->port_b >> CS_BIT) & 1) : 1; /* input: the QUBE's pull-up */
    if (level != h->cs_level) {
        h->cs_level = level;
        if (!level) {
            h->cs_driven_low++;
            h->spi_index = 0;
        }
        h->event = level ? 2 : 1;
    }
}

static void on_port(struct avr_irq_t *irq, uint32_t value, void *param)
{
    qh_t *h = param;
    (void)irq;
    h->port_b = (uint8_t)value;
    track_cs(h);
}

static void on_ddr(struct avr_irq_t *irq, uint32_t value, void *param)
{
    qh_t *h = param;
    (void)irq;
    h->ddr_b = (uint8_t)value;
    track_cs(h);
}

static void no_log(struct avr_t *avr, const int level, const char *format, va_list ap)
{
    (void)avr;
    (void)level;
    (void)format;
    (void)ap;
}

static void no_sleep(avr_t *avr, avr_cycle_count_t how_long)
{
    (void)avr;
    (void)how_long;
}

void *qh_new(const char *elf_path, uint32_t frequency)
{
    elf_firmware_t fw;
    qh_t *h;
    uint32_t flags = 0;
    avr_t *avr;
    avr_io_t *io;

    /* Quiet: stdout may be a protocol channel (qube-emulate prints the device path on it). */
    avr_global_logger_set(no_log);
    memset(&fw, 0, sizeof fw);
    if (elf_read_firmware(elf_path, &fw) != 0) {
        return NULL;
    }
    avr = avr_make_mcu_by_name("atmega328p");
    if (!avr || avr_init(avr) != 0) {
        return NULL;
    }
    h = calloc(1, sizeof *h);
    h->avr = avr;
    avr_load_firmware(avr, &fw);
    avr->frequency = frequency;
    avr->sleep = no_sleep;
    avr_ioctl(avr, AVR_IOCTL_UART_SET_FLAGS('0'), &flags);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUTPUT), on_uart_out, h);
    for (io = avr->io_port; io; io = io->next) {
        if (strcmp(io->kind, "uart") == 0 && ((avr_uart_t *)io)->name == '0') {
            h->uart = (avr_uart_t *)io;
        } else if (strcmp(io->kind, "spi") == 0) {
            h->spi = (avr_spi_t *)io;
        }
    }
    if (!h->uart || !h->spi || !avr->io[IO(UDR0)].r.c) {
        free(h);
        return NULL;
    }
    h->uart_in = avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_INPUT);
    h->udr_read_orig = avr->io[IO(UDR0)].r.c;
    h->udr_read_param = avr->io[IO(UDR0)].r.param;
    avr->io[IO(UDR0)].r.c = on_udr_read;
    avr->io[IO(UDR0)].r.param = h;
    avr->io[IO(SPDR)].w.c = on_spdr_write;
    avr->io[IO(SPDR)].w.param = h;
    avr->io[IO(SPDR)].r.c = on_spdr_read;
    avr->io[IO(SPDR)].r.param = h;
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('B'), IOPORT_IRQ_REG_PORT), on_port, h);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('B'), IOPORT_IRQ_DIRECTION_ALL), on_ddr, h);
    h->cs_level = 1;
    return h;
}

void qh_free(void *p)
{
    qh_t *h = p;
    if (h) {
        avr_terminate(h->avr);
        free(h);
    }
}

/* Run until `until` cycles; returns 0 there, 1 at CS falling, 2 at CS rising, -1 if the chip stopped. */
int qh_run(void *p, uint64_t until)
{
    qh_t *h = p;
    avr_t *avr = h->avr;
    h->event = 0;
    while (avr->cycle < until) {
        avr_cycle_count_t c0 = avr->cycle;
        int running = avr->state == cpu_Running;
        uint32_t pc = avr->pc;
        int sleeps = running && ((uint16_t)avr->flash[pc] | ((uint16_t)avr->flash[pc + 1] << 8)) == SLEEP_OPCODE;
        int state = avr_run(avr);
        uint64_t delta = avr->cycle - c0, busy = delta;
        if (sleeps || !running) {
            /* simavr executes SLEEP and advances the clock to its next event in one step, and
             * wakes in the step that services the interrupt: those steps are asleep but for
             * the instruction itself and, when an interrupt was serviced, its wake-up. */
            busy = (sleeps ? 1u : 0u) + (avr->state == cpu_Running ? WAKE_CYCLES : 0u);
            busy = busy < delta ? busy : delta;
        }
        h->busy += busy;
        h->sleeping += delta - busy;
        h->pc_cycles[(pc >> 1) & 16383u] += busy;
        if (state == cpu_Done || state == cpu_Crashed) {
            return -1;
        }
        if (h->event) {
            return h->event;
        }
    }
    return 0;
}

uint64_t qh_cycle(void *p) { return ((qh_t *)p)->avr->cycle; }
uint64_t qh_busy(void *p) { return ((qh_t *)p)->busy; }
const uint64_t *qh_pc_cycles(void *p) { return ((qh_t *)p)->pc_cycles; }
uint8_t qh_peek(void *p, uint16_t addr) { return ((qh_t *)p)->avr->data[addr]; }
uint32_t qh_rx_lost(void *p) { return ((qh_t *)p)->rx_lost; }
uint32_t qh_rx_pending(void *p) { return ((qh_t *)p)->rx_len; }
uint32_t qh_cs_driven_low(void *p) { return ((qh_t *)p)->cs_driven_low; }
void qh_spi_stall(void *p, uint32_t cycles) { ((qh_t *)p)->spi_stall = cycles; }

void qh_paint(void *p, uint16_t start, uint16_t end, uint8_t value)
{
    qh_t *h = p;
    memset(h->avr->data + start, value, (size_t)(end - start));
}

/* Lowest address in [start, end) no longer holding `value` (end if none). */
uint16_t qh_unpainted_low(void *p, uint16_t start, uint16_t end, uint8_t value)
{
    qh_t *h = p;
    uint16_t a;
    for (a = start; a < end && h->avr->data[a] == value; a++) {
    }
    return a;
}

void qh_push_rx(void *p, const uint8_t *data, uint32_t n)
{
    qh_t *h = p;
    uint32_t i;
    for (i = 0; i < n && h->rx_len < RING; i++) {
        h->rx[(h->rx_head + h->rx_len) % RING] = data[i];
        h->rx_len++;
    }
    if (!h->rx_timer_on && h->rx_len) {
        h->rx_timer_on = 1;
        avr_cycle_timer_register(h->avr, byte_cycles(h), rx_next, h);
    }
}

uint32_t qh_pull_tx(void *p, uint8_t *out, uint32_t cap)
{
    qh_t *h = p;
    uint32_t n = 0;
    while (n < cap && h->tx_len) {
        out[n++] = h->tx[h->tx_head];
        h->tx_head = (h->tx_head + 1u) % RING;
        h->tx_len--;
    }
    return n;
}

/* The slave's bytes for the transaction that has just begun (CS fell). */
void qh_spi_reply(void *p, const uint8_t *data, uint32_t n)
{
    qh_t *h = p;
    memset(h->spi_reply, 0, SPI_MAX);
    memcpy(h->spi_reply, data, n < SPI_MAX ? n : SPI_MAX);
}

/* The master's bytes of the transaction (call at CS rising); returns how many. */
uint32_t qh_spi_sent(void *p, uint8_t *out, uint32_t cap)
{
    qh_t *h = p;
    uint32_t n = h->spi_index < SPI_MAX ? h->spi_index : SPI_MAX;
    n = n < cap ? n : cap;
    memcpy(out, h->spi_sent, n);
    return n;
}
