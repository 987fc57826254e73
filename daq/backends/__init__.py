"""Acquisition backends: the simulated pendulum, and the bridge firmware over a serial port."""

from daq.backends.base import Backend, BackendFault, Pacing
from daq.backends.serial import SerialBackend
from daq.backends.sim import SimBackend

__all__ = ["Backend", "BackendFault", "Pacing", "SerialBackend", "SimBackend"]
