"""The real bridge firmware on an emulated ATmega328P (simavr), in simulated time.

:class:`AvrBridge` runs the Uno image built by :mod:`firmware_protocol.avr_build`
on simavr through a small C harness (``avr_harness.c``, built here on first
use and cached by source hash, driven through ctypes). The bridge's SPI bus
is answered by the same :class:`~sim.bridge.emulated_qube.EmulatedQube` the host
emulator uses: at chip select falling the QUBE latches its answer, at chip
select rising it takes the bridge's command, and the pendulum is advanced by
the simulated time between transactions, so the firmware's timing errors
show in the physics. Time is the chip's cycle counter: tests built on this
do not depend on the host's load.

simavr is GPL-3: the harness is a development and test tool compiled on the
user's machine (Debian: ``simavr``, ``libsimavr-dev``, ``libsimavrparts1``);
it is never part of the wheel.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

from qube_koopman.firmware_protocol.avr_build import F_CPU, symbol_address
from qube_koopman.firmware_protocol.ccore import cache_root, find_c_compiler
from qube_koopman.sim.bridge.emulated_qube import EmulatedQube

__all__ = ["HARNESS_SOURCE", "AvrBridge", "AvrChip", "cached_harness", "harness_missing", "RAMEND"]

HARNESS_SOURCE = Path(__file__).resolve().parent / "avr_harness.c"
RAMEND = 0x8FF
PAINT = 0xA5
_U8P = ctypes.POINTER(ctypes.c_uint8)
_LIBS = ("-lsimavr", "-l:libsimavrparts.so.1")
_INCLUDE = Path("/usr/include/simavr/sim_avr.h")


def harness_missing() -> list[str]:
    """What is missing to build the harness (empty when it can be built)."""
    missing = [] if find_c_compiler() else ["a C compiler"]
    if not HARNESS_SOURCE.is_file():
        missing.append(f"{HARNESS_SOURCE.name} (a source checkout: the wheel does not ship it)")
    if not _INCLUDE.is_file():
        missing.append("simavr headers (libsimavr-dev)")
    return missing


def cached_harness(cache_dir: str | os.PathLike | None = None) -> Path:
    """Build ``avr_harness.c`` against the system's simavr once per source version; return the library."""
    missing = harness_missing()
    if missing:
        raise RuntimeError(
            f"cannot build the simavr harness, missing: {', '.join(missing)}; "
            "apt-get install simavr libsimavr-dev libsimavrparts1"
        )
    cc = find_c_compiler()
    assert cc is not None  # harness_missing() found it
    digest = hashlib.sha256("\0".join((cc, *_LIBS)).encode() + HARNESS_SOURCE.read_bytes())
    root = Path(cache_dir) if cache_dir is not None else cache_root()
    final = root / f"simavr-harness-{digest.hexdigest()[:16]}" / "libqubeavr.so"
    if final.is_file():
        return final
    final.parent.mkdir(parents=True, exist_ok=True)
    scratch = Path(tempfile.mkdtemp(dir=final.parent, prefix="build-"))
    try:
        lib = scratch / final.name
        cmd = [cc, "-std=gnu99", "-O2", "-Wall", "-shared", "-fPIC", "-o", str(lib), str(HARNESS_SOURCE), *_LIBS]
        proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
        if proc.returncode != 0:
            raise RuntimeError(f"harness build failed ({' '.join(cmd)}):\n{proc.stdout}{proc.stderr}")
        os.replace(lib, final)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    return final


_SIGNATURES = {
    "qh_new": (ctypes.c_void_p, [ctypes.c_char_p, ctypes.c_uint32]),
    "qh_free": (None, [ctypes.c_void_p]),
    "qh_run": (ctypes.c_int, [ctypes.c_void_p, ctypes.c_uint64]),
    "qh_cycle": (ctypes.c_uint64, [ctypes.c_void_p]),
    "qh_busy": (ctypes.c_uint64, [ctypes.c_void_p]),
    "qh_pc_cycles": (ctypes.POINTER(ctypes.c_uint64 * 16384), [ctypes.c_void_p]),
    "qh_peek": (ctypes.c_uint8, [ctypes.c_void_p, ctypes.c_uint16]),
    "qh_rx_lost": (ctypes.c_uint32, [ctypes.c_void_p]),
    "qh_rx_pending": (ctypes.c_uint32, [ctypes.c_void_p]),
    "qh_cs_driven_low": (ctypes.c_uint32, [ctypes.c_void_p]),
    "qh_spi_stall": (None, [ctypes.c_void_p, ctypes.c_uint32]),
    "qh_paint": (None, [ctypes.c_void_p, ctypes.c_uint16, ctypes.c_uint16, ctypes.c_uint8]),
    "qh_unpainted_low": (ctypes.c_uint16, [ctypes.c_void_p, ctypes.c_uint16, ctypes.c_uint16, ctypes.c_uint8]),
    "qh_push_rx": (None, [ctypes.c_void_p, _U8P, ctypes.c_uint32]),
    "qh_pull_tx": (ctypes.c_uint32, [ctypes.c_void_p, _U8P, ctypes.c_uint32]),
    "qh_spi_reply": (None, [ctypes.c_void_p, _U8P, ctypes.c_uint32]),
    "qh_spi_sent": (ctypes.c_uint32, [ctypes.c_void_p, _U8P, ctypes.c_uint32]),
}


class AvrChip:
    """An ATmega328P at 16 MHz running an ELF image, in simulated time.

    Parameters
    ----------
    elf : path
        The firmware image.
    harness : path, optional
        The harness library (default: :func:`cached_harness`).
    """

    def __init__(self, elf: str | os.PathLike, harness: str | os.PathLike | None = None) -> None:
        lib = ctypes.CDLL(str(harness or cached_harness()))
        for name, (restype, argtypes) in _SIGNATURES.items():
            fn = getattr(lib, name)
            fn.restype, fn.argtypes = restype, argtypes
        self._lib = lib
        self._h = lib.qh_new(str(elf).encode(), F_CPU)
        if not self._h:
            raise RuntimeError(f"simavr could not load {elf}")
        # Paint the RAM between the static data and the top of the stack.
        self.paint_start = symbol_address(elf, "__bss_end")
        lib.qh_paint(self._h, self.paint_start, RAMEND + 1, PAINT)
        self._buf = (ctypes.c_uint8 * 65536)()

    def close(self) -> None:
        """Free the simulated chip."""
        if self._h:
            self._lib.qh_free(self._h)
            self._h = None

    def __del__(self) -> None:
        self.close()

    @property
    def cycle(self) -> int:
        """Cycles since reset."""
        return self._lib.qh_cycle(self._h)

    @property
    def busy_cycles(self) -> int:
        """Cycles spent running (not asleep) since reset."""
        return self._lib.qh_busy(self._h)

    def pc_cycles(self) -> list[int]:
        """Running cycles since reset by program word address (a flat profile)."""
        return list(self._lib.qh_pc_cycles(self._h).contents)

    def run(self, until_cycle: int) -> int:
        """Run to ``until_cycle`` or the next chip-select edge: 0, 1 (fell), 2 (rose); -1 if the chip stopped."""
        return self._lib.qh_run(self._h, until_cycle)

    def peek(self, address: int) -> int:
        """A byte of data space (registers and RAM)."""
        return self._lib.qh_peek(self._h, address)

    def push(self, data: bytes) -> None:
        """Bytes to UART0's receive pin, one frame time apart at the baud rate the firmware set."""
        self._lib.qh_push_rx(self._h, (ctypes.c_uint8 * max(1, len(data))).from_buffer_copy(data or b"\0"), len(data))

    def pull(self) -> bytes:
        """Bytes UART0 has sent since the last call."""
        n = self._lib.qh_pull_tx(self._h, self._buf, len(self._buf))
        return bytes(self._buf[:n])

    def spi_reply(self, data: bytes) -> None:
        """The slave's bytes for the transaction that has just begun."""
        self._lib.qh_spi_reply(self._h, (ctypes.c_uint8 * len(data)).from_buffer_copy(data), len(data))

    def spi_sent(self) -> bytes:
        """The master's bytes of the transaction (at chip select rising)."""
        n = self._lib.qh_spi_sent(self._h, self._buf, 64)
        return bytes(self._buf[:n])

    def spi_stall(self, cycles: int) -> None:
        """Delay the next SPI byte by ``cycles`` (a slave holding the bus)."""
        self._lib.qh_spi_stall(self._h, cycles)

    @property
    def rx_lost(self) -> int:
        """Bytes lost by UART0 overrun (received while its two-byte buffer was full)."""
        return self._lib.qh_rx_lost(self._h)

    @property
    def rx_pending(self) -> int:
        """Bytes pushed but not yet on the wire."""
        return self._lib.qh_rx_pending(self._h)

    @property
    def cs_driven_low(self) -> int:
        """Times chip select (PB2) has been driven low since reset."""
        return self._lib.qh_cs_driven_low(self._h)

    @property
    def stack_low(self) -> int:
        """Lowest RAM address the stack has reached (from the painted RAM)."""
        return self._lib.qh_unpainted_low(self._h, self.paint_start, RAMEND + 1, PAINT)

    @property
    def ubrr0(self) -> tuple[int, bool]:
        """UART0's baud divisor and whether U2X (double speed) is set."""
        return (self.peek(0xC5) & 0x0F) << 8 | self.peek(0xC4), bool(self.peek(0xC0) & 0x02)


class AvrBridge:
    """The bridge firmware on simavr with a simulated QUBE-Servo 2 on its SPI bus.

    Parameters
    ----------
    elf : path
        The firmware image (:func:`firmware_protocol.avr_build.cached_firmware`).
    qube : EmulatedQube, optional
        The QUBE behind the SPI bus (default: a fresh one, pendulum hanging).
    harness : path, optional
        The harness library.
    """

    def __init__(
        self, elf: str | os.PathLike, qube: EmulatedQube | None = None, harness: str | os.PathLike | None = None
    ) -> None:
        self.chip = AvrChip(elf, harness)
        self.qube = qube if qube is not None else EmulatedQube()
        # (cycle at CS fall, cycle at CS rise, bytes, busy cycles at CS fall) of each transaction
        self.transactions: list[tuple[int, int, int, int]] = []
        self._last_fall: int | None = None

    @property
    def seconds(self) -> float:
        """Simulated time since reset."""
        return self.chip.cycle / F_CPU

    def run_until(self, cycle: int) -> None:
        """Run the chip to ``cycle``, answering every SPI transaction on the way."""
        chip = self.chip
        while True:
            event = chip.run(cycle)
            if event == 0:
                return
            if event < 0:
                raise RuntimeError(f"the firmware stopped at cycle {chip.cycle}")
            if event == 1:
                self._on_select(chip.cycle)
            else:
                sent = chip.spi_sent()
                assert self._last_fall is not None  # select rises (2) only after it fell (1): it starts high
                self.transactions.append((self._last_fall, chip.cycle, len(sent), self._busy_at_fall))
                if len(sent) == len(self._reply):
                    self.qube.apply(sent)

    def run_for(self, seconds: float) -> None:
        """Run for ``seconds`` of simulated time."""
        self.run_until(self.chip.cycle + round(seconds * F_CPU))

    def busy_per_tick(self, first: int = 0, window: int = 10) -> tuple[float, float]:
        """Running cycles per tick from transaction ``first`` on: the mean, and the worst mean of ``window`` ticks.

        Counted between chip-select falls. A single period is not a fair
        unit: a command whose last byte lands just across a tick boundary is
        decoded in the next period, which then holds two decodes and its
        neighbour none; the mean over a few ticks is what the chip must keep.
        """
        busy = [t[3] for t in self.transactions[first:]]
        if len(busy) <= window:
            raise ValueError(f"need more than {window} transactions, have {len(busy)}")
        spans = [(busy[i + window] - busy[i]) / window for i in range(len(busy) - window)]
        return (busy[-1] - busy[0]) / (len(busy) - 1), max(spans)

    def _on_select(self, now: int) -> None:
        if self._last_fall is not None:
            self.qube.set_period(round((now - self._last_fall) * 1e6 / F_CPU) * 1e-6)
            self.qube.advance()
        self._last_fall = now
        self._busy_at_fall = self.chip.busy_cycles
        self._reply = self.qube.latch()
        self.chip.spi_reply(self._reply)
