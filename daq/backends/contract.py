"""The backend contract: the loop's only view of the hardware, so the simulated and serial
backends are interchangeable and the loop does not know which it has.

A backend starts, gives one sample (theta, alpha) per tick, takes one
command (V) per tick, stops with the motor at 0 V, and reports faults by
raising :class:`BackendFault`. Backends differ in who keeps time, which
they declare through :attr:`Backend.pacing`, so the loop needs no other
knowledge of them:

- ``Pacing.DEVICE``: :meth:`Backend.read` blocks until the device's next
  sample (a bridge microcontroller owning the 500 Hz clock).
- ``Pacing.LOOP``: the loop must pace ticks by its own deadlines
  (the simulator in real time).
- ``Pacing.NONE``: nothing keeps time; ticks run as fast as they can
  (the simulator for batch collection and CI).
"""

from __future__ import annotations

import enum
from abc import ABC, abstractmethod

from qube_koopman.core.controller import QUBE_SAMPLE_PERIOD

__all__ = ["Backend", "BackendFault", "Pacing"]


class Pacing(str, enum.Enum):
    """Who paces the ticks of a backend."""

    DEVICE = "device"
    LOOP = "loop"
    NONE = "none"


class BackendFault(RuntimeError):
    """The backend cannot go on (lost link, amplifier fault, stall...); the message says why."""


class Backend(ABC):
    """Interface of an acquisition backend.

    Attributes
    ----------
    name : str
        Short name recorded in episode logs (``"sim"``, ``"serial"``).
    pacing : Pacing
        Who keeps time (see the module docstring).
    sample_period : float
        Seconds between samples.
    spin : bool
        Wait for each tick busy rather than asleep: a loop-paced backend's loop spins through the
        whole period to its deadline, a device-paced one polls its link without blocking. The
        core stays awake for the controller's step that follows the wait (after a sleep a cold
        core ran an MPC's step half again as slow at its 99th percentile), at the cost of a core
        kept busy. No effect on a backend that does not wait (``Pacing.NONE``).
    """

    name: str = "backend"
    pacing: Pacing = Pacing.NONE
    sample_period: float = QUBE_SAMPLE_PERIOD
    spin: bool = False

    @abstractmethod
    def start(self) -> None:
        """Prepare for an episode (called before every episode)."""

    @abstractmethod
    def read(self) -> tuple[float, float]:
        """This tick's measured (theta, alpha) in rad, alpha = 0 upright.

        Raises
        ------
        BackendFault
            When no valid sample can be had.
        """

    @abstractmethod
    def write(self, volts: float) -> None:
        """Command the motor voltage for this tick (already clamped by the loop).

        Raises
        ------
        BackendFault
            When the command cannot be delivered.
        """

    @abstractmethod
    def stop(self) -> None:
        """Put the motor at 0 V and end the episode; safe to call twice and after a fault."""

    def device_time(self) -> float | None:
        """The device's own clock (s) at the sample the last :meth:`read` returned, or None.

        For ``Pacing.DEVICE``: the loop then measures each tick's lateness
        against the device's schedule, so a sample the host passed over (it
        fell behind, or the link lost it) does not shift every later tick.
        None (the default) measures against ``k`` sample periods.
        """
        return None

    def describe(self) -> dict:
        """Plain-data description for the episode metadata (settings, initial state...)."""
        return {"name": self.name, "pacing": self.pacing.value, "spin": self.spin}

    def statistics(self) -> dict:
        """Plain-data counters of the episode just run (e.g. a link's lost frames), or {}.

        Called once when the episode ends, after :meth:`stop`; the loop records
        the result with the episode's final status.
        """
        return {}

    def close(self) -> None:
        """Release resources when no more episodes will run (default: nothing to release)."""
        return None
