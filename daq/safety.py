"""The safety supervisor: voltage clamp, angle limits, start gate, stop on signals.

The rules are those of the C program that ran the rig: the command is clamped to
+-10 V; the episode stops when ``|theta| > pi/2`` or ``|alpha| > pi/4``, with 0 V
written in the same tick; control starts only once ``|alpha| < 5 deg``; Ctrl-C
writes 0 V. Here SIGTERM does the same as SIGINT.

While an episode's pendulum is swung up (:mod:`daq.swing_up`) the pendulum limit cannot apply:
the supervisor then enforces :class:`SwingUpLimits` instead (the arm angle, the voltage and a time
limit), with 0 V in the tick that sees a breach.
"""

from __future__ import annotations

import math
import signal
import threading
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from typing import Iterator

from qube_koopman.core.qube import ALPHA_LIMIT, THETA_LIMIT

__all__ = ["SafetyLimits", "StopRequest", "SwingUpLimits", "stop_on_signals"]


@dataclass(frozen=True)
class SafetyLimits:
    """Limits the supervisor enforces (rad, V, s).

    Parameters
    ----------
    max_voltage : float
        The command is clamped to ``+-max_voltage``.
    theta_limit : float
        Abort when ``|theta|`` exceeds it (motor arm too far round).
    alpha_limit : float
        Abort when ``|alpha|`` exceeds it (pendulum falling).
    start_alpha : float
        An episode starts only once ``|alpha|`` is below it.
    start_timeout : float or None
        Give up waiting for the start condition after this many seconds of
        samples (counted in ticks, so it holds for a free-running backend
        too); None waits until stopped, as the rig did while the pendulum
        was raised by hand.
    """

    max_voltage: float = 10.0
    theta_limit: float = THETA_LIMIT
    alpha_limit: float = ALPHA_LIMIT
    start_alpha: float = math.radians(5.0)
    start_timeout: float | None = 10.0

    def __post_init__(self) -> None:
        for name in ("max_voltage", "theta_limit", "alpha_limit", "start_alpha"):
            value = getattr(self, name)
            if (
                isinstance(value, bool)
                or not isinstance(value, (int, float))
                or not (math.isfinite(value) and value > 0)
            ):
                raise ValueError(f"safety limit {name} must be a positive number, got {value!r}")
        if self.start_alpha > self.alpha_limit:
            raise ValueError(f"start_alpha {self.start_alpha} must not exceed alpha_limit {self.alpha_limit}")
        timeout = self.start_timeout
        if timeout is not None and not (math.isfinite(timeout) and timeout > 0):
            raise ValueError(f"start_timeout must be positive or None, got {timeout!r}")

    def as_dict(self) -> dict:
        """Plain-data form, for episode metadata."""
        return asdict(self)

    def violation(self, theta: float, alpha: float) -> str | None:
        """Why the measured angles end the episode, or None when they are within limits.

        NaN readings count as violations: a sensor that reports nothing
        meaningful must not keep the motor running.
        """
        if not abs(theta) <= self.theta_limit:
            return f"safety stop: |theta| = {abs(theta):.3f} rad > {self.theta_limit:.3f} rad"
        if not abs(alpha) <= self.alpha_limit:
            return f"safety stop: |alpha| = {abs(alpha):.3f} rad > {self.alpha_limit:.3f} rad"
        return None


@dataclass(frozen=True)
class SwingUpLimits:
    """The supervisor's limits while a pendulum is swung up (rad, V, s).

    Parameters
    ----------
    arm_limit : float
        Give up, with 0 V, when ``|theta|`` exceeds it (the episode's arm limit, 90 deg, by
        default).
    max_voltage : float
        The swing-up's commands are clamped to ``+-max_voltage`` (the rig's 10 V by default).
    time_limit : float
        Give up, with 0 V, when the pendulum has not been caught and settled after this many
        seconds of samples (counted in ticks).
    """

    arm_limit: float = THETA_LIMIT
    max_voltage: float = 10.0
    time_limit: float = 20.0

    def __post_init__(self) -> None:
        for name in ("arm_limit", "max_voltage", "time_limit"):
            value = getattr(self, name)
            if (
                isinstance(value, bool)
                or not isinstance(value, (int, float))
                or not (math.isfinite(value) and value > 0)
            ):
                raise ValueError(f"swing-up limit {name} must be a positive number, got {value!r}")

    def as_dict(self) -> dict:
        """Plain-data form, for episode metadata."""
        return asdict(self)

    def violation(self, theta: float, alpha: float) -> str | None:
        """Why the measured angles end the swing-up, or None; NaN readings count as violations."""
        if not abs(theta) <= self.arm_limit:
            return f"swing-up stopped: |theta| = {abs(theta):.3f} rad > {self.arm_limit:.3f} rad"
        if not math.isfinite(alpha):
            return f"swing-up stopped: alpha reads {alpha}"
        return None

    def timeout_reason(self) -> str:
        """Why a swing-up that ran out of time ended."""
        return f"swing-up gave up: not caught and settled within {self.time_limit:g} s"


class StopRequest:
    """A flag the loop checks every tick; set by a signal handler or another thread.

    Attributes
    ----------
    requested : bool
        Set once a stop has been requested.
    reason : str
        Why (e.g. ``"interrupted by SIGINT"``).
    signal : int or None
        The signal number, when a signal asked for the stop.
    """

    def __init__(self) -> None:
        self.requested = False
        self.reason = ""
        self.signal: int | None = None

    def request(self, reason: str, signum: int | None = None) -> None:
        """Ask the loop to stop; the first reason given is kept."""
        if not self.requested:
            self.reason = reason
            self.signal = signum
            self.requested = True


@contextmanager
def stop_on_signals(stop: StopRequest, signals=(signal.SIGINT, signal.SIGTERM)) -> Iterator[bool]:
    """Turn SIGINT and SIGTERM into ``stop.request`` while the block runs; restore the handlers after.

    Handlers can only be installed from the main thread; elsewhere this does
    nothing and yields False (the caller then stops the loop through ``stop``).

    Yields
    ------
    bool
        Whether the handlers were installed.
    """
    if threading.current_thread() is not threading.main_thread():
        yield False
        return

    def handler(signum, frame):
        stop.request(f"interrupted by {signal.Signals(signum).name}", signum)

    saved = {}
    try:
        for signum in signals:
            saved[signum] = signal.signal(signum, handler)
        yield True
    finally:
        for signum, previous in saved.items():
            signal.signal(signum, previous)
