"""Grey-box calibration of the simulated pendulum (``qube-calibrate``): fit, replay validation."""

from qube_koopman.identify.calibrate.fit import HoldRefused, PlantCalibration

__all__ = ["HoldRefused", "PlantCalibration"]
