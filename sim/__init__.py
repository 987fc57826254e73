"""Physics and emulated hardware: the systems ``daq`` and ``identify`` run against.

``sim`` owns the
paper's Duffing experiment (``sim.duffing``), the QUBE-Servo rotary pendulum
model, its encoders and integrators (``sim.pendulum``), and the emulated
bridge device that speaks ``firmware_protocol`` over a pseudo-terminal
(``sim.bridge``, ``qube-emulate``). Start with
:class:`~qube_koopman.sim.pendulum.simulator.PendulumSimulator` for the pendulum
(controllers and linear plants are :class:`~qube_koopman.core.DiscreteStateSpace`
objects). Imports only ``firmware_protocol`` and ``core`` from this project.

Import what is listed here from ``qube_koopman.sim``: each name is imported from its module when
first used.
"""

from qube_koopman.core.exports import lazy_exports

# Each public name and the module (relative to this package) that defines it.
_HOMES = {
    # the QUBE-Servo pendulum: parameters, simulator, closed loop, encoders, linearization
    "PendulumParameters": "pendulum",
    "PendulumSimulator": "pendulum",
    "simulate_closed_loop": "pendulum",
    "ClosedLoopRun": "pendulum",
    "SensorModel": "pendulum",
    "ZeroOffsetDistribution": "pendulum",
    "linearize_upright": "pendulum",
    "linear_model": "pendulum",
    "linear_loop_radius": "pendulum",
    # plant files (qube-calibrate's output)
    "load_plant": "pendulum.params_file",
    "save_plant": "pendulum.params_file",
    "PlantFile": "pendulum.params_file",
    # the paper's Duffing experiment
    "DuffingParameters": "duffing",
    "DuffingExperiment": "duffing",
    "duffing_experiment": "duffing",
}

__all__ = list(_HOMES)

__getattr__, __dir__ = lazy_exports(__name__, _HOMES)
