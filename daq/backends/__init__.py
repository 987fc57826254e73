"""Acquisition backends: the simulated pendulum, and the bridge firmware over a serial port."""

from qube_koopman.daq.backends.contract import Backend, BackendFault, Pacing
from qube_koopman.daq.backends.serial import SerialBackend
from qube_koopman.daq.backends.sim import SimBackend

__all__ = ["Backend", "BackendFault", "Pacing", "SerialBackend", "SimBackend"]
