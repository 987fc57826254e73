"""The bridge sketch built for the Uno and run on an emulated ATmega328P (simavr), in simulated time."""

from __future__ import annotations

import pytest

from qube_koopman.daq.backends.serial import DEFAULT_BAUD
from qube_koopman.firmware_protocol import Command, Fault, FaultCode, HelloReply, Status, Telemetry
from qube_koopman.firmware_protocol.avr_build import F_CPU, firmware_sizes
from qube_koopman.firmware_protocol.qube_spi import SPI_SIZE
from avr_helpers import Host, new_bridge
from bridge_helpers import run_in_real_time


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


def _telemetry(host):
    return [f for f in host.frames if isinstance(f, Telemetry)]


def test_keeps_500_hz_with_a_command_every_tick(avr_cache):
    bridge = new_bridge(avr_cache)
    host = Host(bridge)
    host.connect()
    first = len(bridge.transactions)
    start = bridge.chip.cycle
    host.command_every_tick(0.5)
    ticks = len(bridge.transactions) - first
    assert ticks / ((bridge.chip.cycle - start) / F_CPU) == pytest.approx(500, abs=2)
    tm = _telemetry(host)
    assert all(b.tick - a.tick == 1 for a, b in zip(tm, tm[1:]))
    assert not [f for f in host.frames if isinstance(f, Fault)]
    assert sum(t.command_age == 0 for t in tm[5:]) >= len(tm[5:]) - 1  # each tick applies a fresh command
    mean, worst = bridge.busy_per_tick(first)
    busy = [t[3] for t in bridge.transactions[first:]]
    per_tick = [b - a for a, b in zip(busy, busy[1:])]
    # The budget: at most 60 % of the 32,000-cycle tick (19,200), every tick. Measured here
    # (command 1 ms after each tick, as a host answers telemetry): 15,470 mean (48.4 %), 15,840 in
    # the worst tick (49.5 %, the session's first included); over 16 arrival phases the worst is
    # 17,080 (53.4 %, bench/bench_avr.py). The reference HardwareSerial sketch needed ~35,700
    # (448 ticks/s). Deterministic (simulated time): a change that adds cycles fails here.
    assert mean <= 0.50 * F_CPU / 500, f"{mean:.0f} cycles per tick on average"
    assert worst <= 0.51 * F_CPU / 500, f"{worst:.0f} cycles per tick over 10 ticks"
    assert max(per_tick) <= 0.55 * F_CPU / 500, f"{max(per_tick):.0f} cycles in one tick"


def test_sleep_counts_as_sleep_not_as_busy(avr_cache):
    # simavr executes SLEEP and moves its clock to the next event in one step: the harness counts
    # only the instruction and the wake-up (8 cycles) as busy, so each SLEEP executed costs at most
    # 9 busy cycles, and each one ends in an interrupt (one 3-cycle JMP in the vector table).
    import subprocess

    bridge = new_bridge(avr_cache)
    host = Host(bridge)
    host.connect()
    before = bridge.chip.pc_cycles()
    host.command_every_tick(0.1)
    spent = [a - b for a, b in zip(bridge.chip.pc_cycles(), before)]
    listing = subprocess.run(
        ["avr-objdump", "-d", str(avr_cache[0])], capture_output=True, text=True, check=True
    ).stdout
    sleeps = [int(ln.split(":")[0], 16) // 2 for ln in listing.splitlines() if ln.rstrip().endswith("\tsleep")]
    assert sleeps, "the sketch sleeps between ticks"
    interrupts = sum(spent[: 26 * 2]) / 3  # 26 vectors of one 2-word JMP each
    assert interrupts > 50 * 20  # ~90 interrupts a tick: telemetry, commands, SPI, the timer
    assert sum(spent[w] for w in sleeps) <= 9 * interrupts


def test_every_lost_period_is_reported(avr_cache):
    bridge = new_bridge(avr_cache)
    host = Host(bridge)
    host.connect()
    host.command_every_tick(0.02)
    # The QUBE holds the bus: one SPI byte takes four and a half periods, so the
    # tick ends 4.5 to 5 periods after its start and the next one is 4 or 5 periods on.
    bridge.chip.spi_stall(int(4.5 * F_CPU / 500))
    host.command_every_tick(0.05)
    tm = _telemetry(host)
    steps = [b.tick - a.tick for a, b in zip(tm, tm[1:])]
    overruns = [f for f in host.frames if isinstance(f, Fault) and f.code == FaultCode.TICK_OVERRUN]
    lost = sum(s - 1 for s in steps)
    assert lost in (3, 4) and sorted(set(steps)) == [1, 1 + lost]  # one gap, every period in it counted
    assert [f.value for f in overruns] == [lost]
    flagged = [t for t in tm if t.status & Status.TICK_OVERRUN]
    assert len(flagged) == 1 and flagged[0].tick == overruns[0].tick
    # The counter follows the crystal: elapsed periods = ticks in telemetry + lost.
    span_s = (tm[-1].tick - tm[0].tick) * 0.002
    assert span_s == pytest.approx(
        (bridge.transactions[-1][0] - bridge.transactions[-len(tm)][0]) / F_CPU, abs=5e-4
    )  # CS falls within a quarter period of its period's start


def test_a_burst_of_eight_commands_loses_no_byte(avr_cache):
    bridge = new_bridge(avr_cache)
    host = Host(bridge)
    host.connect()
    host.send(*[Command(millivolts=100 * k, flags=1) for k in range(1, 9)])  # 160 bytes back to back
    # 3.2 ms on the wire; decoding keeps pace with the wire between ticks (the
    # CPU is ~90 % busy meanwhile), so the last command is applied ~3 ticks later.
    bridge.run_for(0.012)
    host.read()
    assert bridge.chip.rx_lost == 0
    assert not [f for f in host.frames if isinstance(f, Fault)]
    last = _telemetry(host)[-1]
    assert last.last_command_seq == host.seq and last.applied_millivolts == 800


def test_chip_select_is_high_from_reset(avr_cache):
    bridge = new_bridge(avr_cache)
    bridge.run_for(0.011)
    sizes = [n for _, _, n, _ in bridge.transactions]
    assert len(sizes) == 5 and set(sizes) == {SPI_SIZE}  # no empty pulse before the first tick
    assert bridge.chip.cs_driven_low == len(sizes)


@pytest.mark.slow
def test_qube_run_against_the_emulated_uno_in_real_time(avr_cache, env, tmp_path, capsys):
    from qube_koopman.daq.log import read_episode

    status, out, emulator_err, tmp_path, _ = run_in_real_time(
        env, ["--target", "avr", "--seed", "5"], ["--episodes", "1", "--duration", "5", "--seed", "7"], tmp_path, capsys
    )
    assert status == 0, out + emulator_err
    assert "1 complete, 0 aborted" in out
    (log,) = tmp_path.glob("*.mcap")
    episode = read_episode(log)
    assert episode.metadata.status == "complete" and len(episode) == 2500
    link = episode.metadata.backend_stats
    assert link["ticks_missed"] == 0 and link["frames_lost"] == 0, link
    assert "CPU busy" in emulator_err and "ticks" in emulator_err
