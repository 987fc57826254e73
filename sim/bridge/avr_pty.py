"""The emulated ATmega328P bridge behind a pseudo-terminal, paced to the wall clock.

``qube-emulate --target avr`` runs this: the Uno image on simavr
(:class:`~sim.bridge.avr.AvrBridge`), its UART0 joined to a pseudo-terminal
that ``qube-run --backend serial`` opens like the real bridge's port. The
chip runs in slices of simulated time, each slice started no earlier than
its wall-clock time, so the host sees 500 telemetry frames a second; when
the host machine falls behind, the chip catches up as fast as it can (its own
timing stays exact: it lives in simulated time). As the host emulator does,
each HELLO from the host puts the pendulum upright with a small seeded tilt
(a person raising the real one by hand).
"""

from __future__ import annotations

import math
import os
import select
import threading
import time

import numpy as np

from qube_koopman.firmware_protocol import Hello, StreamDecoder
from qube_koopman.firmware_protocol.avr_build import F_CPU, cached_firmware
from qube_koopman.sim.bridge.avr import AvrBridge
from qube_koopman.sim.bridge.emulator import close_fds, open_raw_pty

__all__ = ["AvrPtyBridge"]


class AvrPtyBridge:
    """The firmware on an emulated Uno, on a pseudo-terminal, in real time.

    Parameters
    ----------
    seed : int, optional
        Seeds the start tilts (default: a fresh one).
    perturbation : float
        Each session starts with ``|alpha|`` up to this (rad).
    start_upright : bool
        Raise the pendulum at each HELLO (else it hangs).
    slice_s : float
        Simulated time run between two looks at the pseudo-terminal (s).
    """

    def __init__(
        self,
        *,
        seed: int | None = None,
        perturbation: float = math.radians(2.0),
        start_upright: bool = True,
        slice_s: float = 0.0002,
    ) -> None:
        if seed is None:
            entropy = np.random.SeedSequence().entropy
            assert isinstance(entropy, int)  # drawn from the OS: one int
            seed = entropy % 2**31
        self.seed = int(seed)
        self._rng = np.random.default_rng(self.seed)
        self.perturbation = perturbation
        self.start_upright = start_upright
        self.slice_cycles = round(slice_s * F_CPU)
        self._stop = threading.Event()
        self._master = self._slave = -1
        self._host = StreamDecoder()
        self.bridge: AvrBridge | None = None
        self.path = ""
        self.sessions = 0
        self.max_behind = 0.0
        self.wall = 0.0
        self._final: dict | None = None

    def open(self) -> str:
        """Build the firmware and harness if needed, reset the chip, create the pty; returns its path."""
        self.bridge = bridge = AvrBridge(cached_firmware())
        bridge.qube.place((0.0, math.pi, 0.0, 0.0))
        self._master, self._slave, self.path = open_raw_pty()
        return self.path

    def request_stop(self) -> None:
        """Ask :meth:`run` to return (safe from a signal handler)."""
        self._stop.set()

    def run(self) -> None:
        """Run until :meth:`request_stop`."""
        bridge = self.bridge
        assert bridge is not None, "open() first"
        chip = bridge.chip
        start_wall, start_cycle = time.perf_counter(), chip.cycle
        while not self._stop.is_set():
            self._from_host()
            bridge.run_until(chip.cycle + self.slice_cycles)
            out = chip.pull()
            if out:
                self._write(out)
            lead = (chip.cycle - start_cycle) / F_CPU - (time.perf_counter() - start_wall)
            self.max_behind = max(self.max_behind, -lead)
            if lead > 0:
                select.select([self._master], [], [], lead)
        self.wall = time.perf_counter() - start_wall

    def _from_host(self) -> None:
        try:
            data = os.read(self._master, 4096)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            return
        if not data:
            return
        assert self.bridge is not None  # run() after open()
        for frame in self._host.feed(data):
            if isinstance(frame.message, Hello):
                self.sessions += 1
                if self.start_upright:
                    alpha0 = float(self._rng.uniform(-self.perturbation, self.perturbation))
                    self.bridge.qube.place((0.0, alpha0, 0.0, 0.0))
        self.bridge.chip.push(data)

    def _write(self, data: bytes) -> None:
        try:
            os.write(self._master, data)
        except (BlockingIOError, OSError):
            pass  # no reader: a UART's bytes are lost too

    def close(self) -> None:
        """Close the pseudo-terminal and free the chip."""
        fds = (self._slave, self._master)
        self._master = self._slave = -1
        close_fds(fds)  # our slave end first: the host sees the device go only once we are done
        if self.bridge is not None and self._final is None:
            self._final = self.stats()
            self.bridge.chip.close()

    def stats(self) -> dict:
        """Ticks, simulated and wall time, sessions, worst lag behind the wall clock, busy fraction."""
        if self._final is not None:
            return dict(self._final)
        assert self.bridge is not None, "open() first"
        chip = self.bridge.chip
        return dict(
            ticks=len(self.bridge.transactions),
            device_time=chip.cycle / F_CPU,
            wall_time=self.wall,
            sessions=self.sessions,
            max_behind=self.max_behind,
            busy=chip.busy_cycles / max(1, chip.cycle),
        )
