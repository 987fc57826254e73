"""Fixtures for the tests of the bridge firmware on the emulated ATmega328P."""

from __future__ import annotations

import os

import pytest

from qube_koopman.firmware_protocol import Command, Hello, StreamDecoder, encode_frame
from qube_koopman.firmware_protocol import avr_build


def _need_tools() -> None:
    from qube_koopman.sim.bridge import avr as avr_sim

    missing = avr_build.avr_tools_missing() + avr_sim.harness_missing()
    if missing:
        message = (
            f"AVR firmware tests need {', '.join(missing)}: run tools/install_system_deps.sh "
            "(gcc-avr avr-libc arduino-core-avr simavr libsimavr-dev libsimavrparts1)"
        )
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(message)  # CI installs them: missing there is a failure, not a skip
        pytest.skip(message)


@pytest.fixture(scope="session")
def avr_cache(tmp_path_factory):
    """A cache folder holding the built Uno firmware and the simavr harness."""
    _need_tools()
    from qube_koopman.sim.bridge import avr as avr_sim

    root = tmp_path_factory.mktemp("avr_cache")
    return avr_build.cached_firmware(root), avr_sim.cached_harness(root)


def new_bridge(avr_cache):
    """A freshly reset Uno with the simulated QUBE on its SPI bus."""
    from qube_koopman.sim.bridge.avr import AvrBridge

    elf, harness = avr_cache
    return AvrBridge(elf, harness=harness)


class Host:
    """Frames in, decoded frames out, over the simulated UART."""

    def __init__(self, bridge) -> None:
        self.bridge = bridge
        self.decoder = StreamDecoder()
        self.seq = 0
        self.frames = []

    def send(self, *messages) -> None:
        wire = b""
        for message in messages:
            self.seq += 1
            wire += encode_frame(message, seq=self.seq, timestamp_us=0)
        self.bridge.chip.push(wire)

    def read(self) -> list:
        new = [f.message for f in self.decoder.feed(self.bridge.chip.pull())]
        self.frames += new
        return new

    def connect(self) -> None:
        self.bridge.run_for(0.05)
        self.send(Hello(nonce=5))
        self.bridge.run_for(0.01)
        self.read()

    def command_every_tick(self, seconds: float, millivolts: int = 200) -> None:
        """One COMMAND per 2 ms of simulated time, sent 1 ms after a tick as a host loop answers telemetry."""
        bridge = self.bridge
        start = bridge.transactions[-1][0] + 16_000 if bridge.transactions else bridge.chip.cycle
        bridge.run_until(max(start, bridge.chip.cycle))
        for k in range(1, round(seconds / 0.002) + 1):
            self.send(Command(millivolts=millivolts, flags=1))
            bridge.run_until(start + k * 32_000)
            self.read()
