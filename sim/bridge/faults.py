"""Fault injection for the emulated bridge: a bad link, a failing QUBE, a vanishing device.

:class:`Faults` says what to break; :class:`FaultyLink` breaks the byte
streams accordingly and :class:`DelayLine` delays them. Rates are
probabilities drawn from the emulator's seeded generator, so a run with the
same seed breaks the same bytes. Times are seconds of *device* time after
the first HELLO (the host's first session), so they do not depend on when
the host was started.
"""

from __future__ import annotations

import math
import random
from collections import deque
from dataclasses import asdict, dataclass

__all__ = ["Faults", "FaultyLink", "DelayLine"]


def _check_rate(name: str, value: float) -> None:
    if not (isinstance(value, (int, float)) and 0.0 <= value <= 1.0):
        raise ValueError(f"{name} must be a probability in [0, 1], got {value!r}")


@dataclass(frozen=True)
class Faults:
    """What the emulated bridge should get wrong.

    Parameters
    ----------
    drop_rate : float
        Fraction of device-to-host frames dropped whole (their sequence
        numbers are used, so the host sees the gap).
    corrupt_rate : float
        Probability per byte, in both directions, of one flipped bit.
    garbage_rate : float
        Probability per tick of a burst of 1-40 random bytes (zeros
        included) sent to the host between frames.
    latency : float
        Seconds added to every byte's trip, in each direction.
    stall_at, amp_fault_at : float, optional
        Device time (s after the first HELLO) at which the QUBE reports a
        stall error / an amplifier fault (and stops driving the motor until
        the amplifier is commanded off).
    silence_at : float, optional
        Device time from which the bridge sends nothing more (a hung link;
        the port stays open).
    vanish_at : float, optional
        Device time at which the device disappears: the pseudo-terminal is
        closed, as a USB device unplugged.
    hold_at : float, optional
        Device time at which the firmware is held for ``hold_periods``
        sample periods (as by a QUBE holding the SPI bus): its clock and the
        pendulum go on, no tick runs, and the next tick finds the periods
        lost (the firmware then reports TICK_OVERRUN and its tick counter
        skips them).
    hold_periods : int
        How many periods the hold lasts (default 10).
    """

    drop_rate: float = 0.0
    corrupt_rate: float = 0.0
    garbage_rate: float = 0.0
    latency: float = 0.0
    stall_at: float | None = None
    amp_fault_at: float | None = None
    silence_at: float | None = None
    vanish_at: float | None = None
    hold_at: float | None = None
    hold_periods: int = 10

    def __post_init__(self) -> None:
        for name in ("drop_rate", "corrupt_rate", "garbage_rate"):
            _check_rate(name, getattr(self, name))
        if not (isinstance(self.latency, (int, float)) and 0.0 <= self.latency < 10.0):
            raise ValueError(f"latency must be in [0, 10) s, got {self.latency!r}")
        if not (isinstance(self.hold_periods, int) and 1 <= self.hold_periods <= 100_000):
            raise ValueError(f"hold_periods must be an integer in [1, 100000], got {self.hold_periods!r}")
        for name in ("stall_at", "amp_fault_at", "silence_at", "vanish_at", "hold_at"):
            value = getattr(self, name)
            if value is not None and not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a non-negative time in s, got {value!r}")

    def as_dict(self) -> dict:
        """Plain-data form."""
        return asdict(self)


class FaultyLink:
    """Applies the link faults of :class:`Faults` to byte streams.

    Parameters
    ----------
    faults : Faults
    rng : random.Random
        Seeded source of every fault decision.

    Attributes
    ----------
    frames_dropped, bytes_corrupted, garbage_bursts : int
        What was done so far.
    """

    def __init__(self, faults: Faults, rng: random.Random) -> None:
        self.faults = faults
        self._rng = rng
        self.frames_dropped = 0
        self.bytes_corrupted = 0
        self.garbage_bursts = 0

    def _corrupt(self, data: bytes) -> bytes:
        p = self.faults.corrupt_rate
        if p <= 0.0 or not data:
            return data
        out = bytearray(data)
        rng = self._rng
        # Geometric gaps between corrupted bytes: one draw per corruption, not per byte.
        log_q = math.log1p(-p) if p < 1.0 else -math.inf
        pos = -1
        while True:
            pos += 1 if p >= 1.0 else 1 + int(math.log(1.0 - rng.random()) / log_q)
            if pos >= len(out):
                return bytes(out)
            out[pos] ^= 1 << rng.randrange(8)
            self.bytes_corrupted += 1

    def incoming(self, data: bytes) -> bytes:
        """Host-to-device bytes as they arrive (corrupted)."""
        return self._corrupt(data)

    def outgoing(self, data: bytes) -> bytes:
        """Device-to-host bytes as they leave (garbage added, frames dropped, bytes corrupted).

        ``data`` is whole frames, each ending with its 0x00 delimiter, as the
        firmware core queues them.
        """
        f, rng = self.faults, self._rng
        parts = []
        if f.garbage_rate > 0.0 and rng.random() < f.garbage_rate:
            self.garbage_bursts += 1
            parts.append(bytes(rng.getrandbits(8) for _ in range(rng.randint(1, 40))))
        if f.drop_rate > 0.0:
            for piece in data.split(b"\0")[:-1]:
                if piece and rng.random() < f.drop_rate:
                    self.frames_dropped += 1
                else:
                    parts.append(piece + b"\0")
            tail = data[data.rfind(b"\0") + 1 :]
            parts.append(tail)
        else:
            parts.append(data)
        return self._corrupt(b"".join(parts))

    def counters(self) -> dict[str, int]:
        """What was done so far, as plain data."""
        return {
            "frames_dropped": self.frames_dropped,
            "bytes_corrupted": self.bytes_corrupted,
            "garbage_bursts": self.garbage_bursts,
        }


class DelayLine:
    """Holds bytes for a fixed delay (a slow link), releasing them in order.

    Parameters
    ----------
    delay : float
        Seconds each chunk is held.
    """

    def __init__(self, delay: float) -> None:
        self.delay = float(delay)
        self._queue: deque[tuple[float, bytes]] = deque()

    def put(self, now: float, data: bytes) -> None:
        """Bytes entering the line at time ``now``."""
        if data:
            self._queue.append((now + self.delay, data))

    def take(self, now: float) -> bytes:
        """Bytes whose delay has passed at time ``now``."""
        out = []
        queue = self._queue
        while queue and queue[0][0] <= now:
            out.append(queue.popleft()[1])
        return b"".join(out)

    @property
    def next_release(self) -> float:
        """When the oldest held chunk is due (inf when empty)."""
        return self._queue[0][0] if self._queue else math.inf
