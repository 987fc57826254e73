"""The QUBE-Servo rotary inverted pendulum: model, encoders and a per-tick simulator."""

from sim.pendulum.closed_loop import ClosedLoopRun, simulate_closed_loop
from sim.pendulum.model import (SAMPLE_PERIOD, PendulumParameters, dynamics, linear_model,
                                linearize_upright, rk4_step, simulate, total_energy)
from sim.pendulum.sensor import SensorModel, ZeroOffsetDistribution, measure
from sim.pendulum.simulator import PendulumSimulator

__all__ = [
    "ClosedLoopRun",
    "SAMPLE_PERIOD",
    "PendulumParameters",
    "PendulumSimulator",
    "SensorModel",
    "ZeroOffsetDistribution",
    "dynamics",
    "linear_model",
    "linearize_upright",
    "measure",
    "rk4_step",
    "simulate",
    "simulate_closed_loop",
    "total_energy",
]
