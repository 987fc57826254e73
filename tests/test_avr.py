"""The bridge sketch built for the Uno and run on an emulated ATmega328P (simavr), in simulated time."""

from __future__ import annotations

import pytest

from daq.backends.serial import DEFAULT_BAUD
from firmware_protocol import HelloReply, Telemetry
from firmware_protocol.avr import F_CPU, firmware_sizes
from firmware_protocol.qube_spi import SPI_SIZE
from tests.avr_helpers import Host, avr_cache, new_bridge  # noqa: F401 (fixture)


def test_fits_the_uno(avr_cache):
    sizes = firmware_sizes(avr_cache[0])
    assert sizes.flash <= 16 * 1024
    assert sizes.static_ram <= 1024
    assert avr_cache[0].with_suffix(".hex").read_text().startswith(":")


def test_uart_runs_at_the_hosts_default_baud(avr_cache):
    bridge = new_bridge(avr_cache)
    bridge.run_for(0.01)
    ubrr, u2x = bridge.chip.ubrr0
    assert (ubrr, u2x) == (3, True)
    assert F_CPU / ((8 if u2x else 16) * (ubrr + 1)) == DEFAULT_BAUD == 500_000


def test_session_over_the_emulated_uart(avr_cache):
    bridge = new_bridge(avr_cache)
    host = Host(bridge)
    host.connect()
    assert isinstance(host.frames[0], HelloReply) and host.frames[0].module_id == 777
    host.command_every_tick(0.1, millivolts=500)
    last = [f for f in host.frames if isinstance(f, Telemetry)][-1]
    assert last.applied_millivolts == 500
    assert bridge.qube.volts == pytest.approx(0.48, abs=0.03)  # 20 PWM counts of 24 mV
    assert bridge.qube.state[0] != 0.0  # the arm moved under the firmware's commands


def test_spi_bytes_take_eight_sck_periods(avr_cache):
    bridge = new_bridge(avr_cache)
    bridge.run_for(0.02)
    full = [(fall, rise) for fall, rise, n, _ in bridge.transactions if n == SPI_SIZE]
    assert full
    # 1 MHz SCK from 16 MHz: 16 cycles per bit, 128 per byte, 17 bytes per transaction.
    assert all(rise - fall >= SPI_SIZE * 128 for fall, rise in full)


def test_stack_leaves_half_a_kilobyte(avr_cache):
    bridge = new_bridge(avr_cache)
    host = Host(bridge)
    host.connect()
    host.command_every_tick(0.1)
    free = bridge.chip.stack_low - bridge.chip.paint_start
    assert free >= 512, f"only {free} B of RAM never reached by the stack"
