"""Physics and emulated hardware: the systems ``daq`` and ``identify`` run against.

``sim`` owns the discrete LTI container used everywhere and the controller replay
over logged samples (``sim.lti``), the
paper's Duffing experiment (``sim.duffing``), the QUBE-Servo rotary pendulum
model, its encoders and integrators (``sim.pendulum``), and the emulated
bridge device that speaks ``firmware_protocol`` over a pseudo-terminal
(``sim.bridge``, ``qube-emulate``). Start with
``sim.pendulum`` (``PendulumSimulator``) for the pendulum and ``sim.lti.DiscreteStateSpace``
for controllers. Imports only ``firmware_protocol`` from this project.
"""
