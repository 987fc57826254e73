"""Acquisition backends: the simulated pendulum (a serial bridge comes later)."""

from daq.backends.base import Backend, BackendFault, Pacing
from daq.backends.sim import SimBackend

__all__ = ["Backend", "BackendFault", "Pacing", "SimBackend"]
