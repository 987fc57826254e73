"""The QUBE-Servo rotary inverted pendulum: model, encoders and a per-tick simulator."""

from qube_koopman.sim.pendulum.closed_loop import ClosedLoopRun, linear_loop_radius, simulate_closed_loop
from qube_koopman.sim.pendulum.load import LoadStream, RandomLoad
from qube_koopman.sim.pendulum.physics import (
    SAMPLE_PERIOD,
    PendulumParameters,
    dynamics,
    linear_model,
    linearize_upright,
    rk4_step,
    simulate,
    total_energy,
)
from qube_koopman.sim.pendulum.relaxation import CableRelaxation
from qube_koopman.sim.pendulum.sensor import SensorModel, ZeroOffsetDistribution, measure
from qube_koopman.sim.pendulum.simulator import PendulumSimulator

__all__ = [
    "CableRelaxation",
    "ClosedLoopRun",
    "LoadStream",
    "RandomLoad",
    "SAMPLE_PERIOD",
    "PendulumParameters",
    "PendulumSimulator",
    "SensorModel",
    "ZeroOffsetDistribution",
    "dynamics",
    "linear_loop_radius",
    "linear_model",
    "linearize_upright",
    "measure",
    "rk4_step",
    "simulate",
    "simulate_closed_loop",
    "total_energy",
]
