"""The emulated bridge: the firmware core and a simulated QUBE-Servo 2 behind a pseudo-terminal.

``BridgeEmulator`` is a device a host can open with pyserial, as it would
open the real bridge, so the serial path runs end to end without hardware
(``qube-emulate`` starts one from the command line). ``EmulatedQube`` is the
QUBE-Servo 2 behind its SPI interface; ``Faults`` says what to break.
"""

from qube_koopman.sim.bridge.emulator import DEFAULT_PERTURBATION, RECORD_FIELDS, BridgeEmulator
from qube_koopman.sim.bridge.faults import DelayLine, Faults, FaultyLink
from qube_koopman.sim.bridge.emulated_qube import EmulatedQube

__all__ = [
    "BridgeEmulator",
    "DEFAULT_PERTURBATION",
    "RECORD_FIELDS",
    "DelayLine",
    "EmulatedQube",
    "Faults",
    "FaultyLink",
]
