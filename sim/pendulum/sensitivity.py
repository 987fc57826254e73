"""How :func:`~qube_koopman.sim.pendulum.physics.simulate`'s angles change with the initial state and the
coefficients: its RK4 differentiated step by step (forward sensitivities, the tangent-linear model).

A multiple-shooting calibration needs the Jacobian of every segment's predicted angles with respect to
the segment's initial state and the shared parameters at every iteration. Finite differences cost a
whole simulation per parameter (about 15 a Jacobian); the tangents of all of them ride along one
simulation here: each RK4 stage's accelerations are differentiated analytically once (the partial
derivatives are arrays over the segments), and every direction's tangent is then a few multiply-adds
of them. The equations differentiated are :func:`~qube_koopman.sim.pendulum.physics._accelerations`'
(a test compares the tangents with finite differences of :func:`simulate` with every optional term on).

A direction is an initial-state tangent and a derivative of the coefficients
(:data:`FIELDS`; the cables' softening ``c^2`` stands for their curvature ``c``, as in the parameters)
and of the transport delay, optionally restricted to some of the segments (a setup's own value).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from qube_koopman.sim.pendulum.physics import (
    DEFAULT_SUBSTEPS,
    SAMPLE_PERIOD,
    Coefficients,
    PendulumParameters,
    as_states,
    check_timing,
    coefficients_and_hold,
)

__all__ = ["FIELDS", "Directions", "simulate_tangents"]

#: The coefficients a direction may move, in the order of :attr:`Directions.coefficients`' columns.
#: ``cable_softening`` is the square of :class:`Coefficients`' ``cable_curvature``.
FIELDS = (
    "m11",
    "quarter",
    "m12",
    "m22",
    "gravity",
    "torque_per_volt",
    "arm_damping",
    "pendulum_damping",
    "arm_coulomb",
    "inverse_coulomb_speed",
    "dead_zone",
    "arm_stiffness",
    "arm_rest",
    "cable_softening",
    "tilt_x",
    "tilt_y",
    "arm_gravity",
    "arm_static",
    "inverse_stribeck_speed",
)
_DEAD_ZONE = FIELDS.index("dead_zone")


@dataclass(frozen=True)
class Directions:
    """The directions whose tangents :func:`simulate_tangents` propagates.

    Attributes
    ----------
    state : ndarray (n_dir, 4)
        Each direction's tangent of the initial state (the same for every segment).
    coefficients : ndarray (n_dir, len(FIELDS))
        Each direction's derivative of the coefficients (:data:`FIELDS`).
    delay : ndarray (n_dir,)
        Each direction's derivative of the transport delay (s).
    mask : ndarray (n_dir, n_seg) or None
        Which segments a direction's coefficients and delay move (1) or not (0), for a value of one
        setup's segments only; None: every direction moves every segment.
    """

    state: np.ndarray
    coefficients: np.ndarray
    delay: np.ndarray
    mask: np.ndarray | None = None

    @property
    def n(self) -> int:
        return self.state.shape[0]


def _stretch_and_slopes(x, k: Coefficients):
    """The cables' pull per unit stiffness ``S(x) = tanh(c x) / c`` (``x`` where ``c`` is 0), its slope in
    ``x`` and its derivative in the softening ``c^2``: ``(x S' - S) / (2 c^2)``, ``-x^3 / 3`` as ``c x`` goes to 0."""
    c = k.cable_curvature
    if isinstance(c, np.ndarray):  # one curvature per segment: some may keep a linear spring
        curved = c > 0
        sigma = c * c
        safe = np.where(curved, c, 1.0)
        t = np.tanh(safe * x)
        stretch, slope = np.where(curved, t / safe, x), np.where(curved, 1.0 - t * t, 1.0)
    elif c > 0:
        sigma = c * c
        t = np.tanh(c * x)
        stretch, slope = t / c, 1.0 - t * t
    else:
        return x, np.ones_like(x), -(x**3) / 3.0
    small = sigma * x * x < 1e-6
    by_softening = np.where(small, -(x**3) / 3.0, (x * slope - stretch) / (2.0 * np.where(small, 1.0, sigma)))
    return stretch, slope, by_softening


def _optional_terms(k: Coefficients) -> tuple[bool, bool]:
    """Whether the coefficients have a tilted base and a static friction (terms :func:`_partials` adds only then)."""
    return bool(np.any(k.tilt_x)) or bool(np.any(k.tilt_y)), bool(np.any(k.arm_static))


def _partials(
    theta, alpha, theta_dot, alpha_dot, motor_voltage, k: Coefficients, active: np.ndarray, tilted: bool, static: bool
):
    """The accelerations (a, b) of :func:`~qube_koopman.sim.pendulum.physics._accelerations` at one RK4 stage,
    their partial derivatives in the state and the motor voltage (``(a_x, b_x)``, each a list of five
    arrays: theta, alpha, theta_dot, alpha_dot, voltage), and in the ``active`` coefficients
    (``(len(active), n_seg)`` arrays for a and b). ``tilted``, ``static``: whether ``k`` has a tilt
    and a static friction (:func:`_optional_terms`; the same for every stage of a simulation)."""
    s, c = np.sin(alpha), np.cos(alpha)
    sc = s * c
    friction = np.tanh(theta_dot * k.inverse_coulomb_speed)
    friction_slope = 1.0 - friction * friction
    x = theta - k.arm_rest
    stretch, stretch_slope, by_softening = _stretch_and_slopes(x, k)
    q, m12k = k.quarter, k.m12
    r1 = (
        k.torque_per_volt * motor_voltage
        - k.arm_damping * theta_dot
        - 2.0 * q * sc * theta_dot * alpha_dot
        + m12k * s * alpha_dot * alpha_dot
        - k.arm_coulomb * friction
        - k.arm_stiffness * stretch
    )
    # A tilted base (physics._tilt_torques): the balance angle alpha_b = tilt_x sin(theta) + tilt_y cos(theta)
    # and its slope in theta; on a level one exactly the arithmetic without the terms.
    upright, upright_alpha = s, c  # the pendulum's gravity term per k.gravity, and its slope in alpha
    if tilted:
        sin_theta, cos_theta = np.sin(theta), np.cos(theta)
        balance = k.tilt_x * sin_theta + k.tilt_y * cos_theta
        slope = k.tilt_x * cos_theta - k.tilt_y * sin_theta
        r1 = r1 - k.arm_gravity * balance - k.gravity * slope * s
        upright, upright_alpha = s - c * balance, c + s * balance
    # The static friction's excess (physics.static_friction): Cs e tanh(v u), e = exp(-(v w)^2).
    if static:
        fading = np.exp(-((theta_dot * k.inverse_stribeck_speed) ** 2))  # e
        excess = fading * friction  # e tanh(v u), per unit Cs
        r1 = r1 - k.arm_static * excess
    r2 = -k.pendulum_damping * alpha_dot + q * sc * theta_dot * theta_dot + k.gravity * upright
    m11 = k.m11 + q * s * s
    m12 = m12k * c
    m22 = k.m22
    inv = 1.0 / (m11 * m22 - m12 * m12)
    a = (m22 * r1 - m12 * r2) * inv
    b = (m11 * r2 - m12 * r1) * inv
    # d a = A1 d r1 + A2 d r2 + A11 d m11 + A12 d m12 + A22 d m22 (b alike): the quotient rule.
    A1, A2 = m22 * inv, -m12 * inv
    A11, A12, A22 = -a * m22 * inv, (2.0 * a * m12 - r2) * inv, (r1 - a * m11) * inv
    B1, B2 = -m12 * inv, m11 * inv
    B11, B12, B22 = (r2 - b * m22) * inv, (2.0 * b * m12 - r1) * inv, -b * m11 * inv
    cos2 = c * c - s * s
    r1_theta = -k.arm_stiffness * stretch_slope
    r1_alpha = -2.0 * q * cos2 * theta_dot * alpha_dot + m12k * c * alpha_dot * alpha_dot
    r2_alpha = q * cos2 * theta_dot * theta_dot + k.gravity * upright_alpha
    r2_theta = None
    if tilted:  # the balance angle's second slope in theta is -alpha_b
        r1_theta = r1_theta - k.arm_gravity * slope + k.gravity * balance * s
        r1_alpha = r1_alpha - k.gravity * slope * c
        r2_theta = -k.gravity * slope * c
    m11_alpha, m12_alpha = 2.0 * q * sc, -m12k * s
    r1_theta_dot = -k.arm_damping - 2.0 * q * sc * alpha_dot - k.arm_coulomb * k.inverse_coulomb_speed * friction_slope
    if static:  # d(e tanh(v u)) / dv = e (u (1 - tanh^2) - 2 v w^2 tanh)
        w = k.inverse_stribeck_speed
        r1_theta_dot = r1_theta_dot - k.arm_static * fading * (
            k.inverse_coulomb_speed * friction_slope - 2.0 * theta_dot * w * w * friction
        )
    r2_theta_dot = 2.0 * q * sc * theta_dot
    r1_alpha_dot = -2.0 * q * sc * theta_dot + 2.0 * m12k * s * alpha_dot
    r2_alpha_dot = -k.pendulum_damping

    def along(c1, c2, c11, c12):  # an acceleration's partials in the state and the voltage, by its quotient rule
        return [
            c1 * r1_theta if r2_theta is None else c1 * r1_theta + c2 * r2_theta,
            c1 * r1_alpha + c2 * r2_alpha + c11 * m11_alpha + c12 * m12_alpha,
            c1 * r1_theta_dot + c2 * r2_theta_dot,
            c1 * r1_alpha_dot + c2 * r2_alpha_dot,
            c1 * k.torque_per_volt,
        ]

    a_x, b_x = along(A1, A2, A11, A12), along(B1, B2, B11, B12)
    # Per coefficient: its (d r1, d r2, d m11, d m12, d m22), None for a zero; made for the active ones only.
    by_field = {
        "m11": lambda: (None, None, 1.0, None, None),
        "quarter": lambda: (-2.0 * sc * theta_dot * alpha_dot, sc * theta_dot * theta_dot, s * s, None, None),
        "m12": lambda: (s * alpha_dot * alpha_dot, None, None, c, None),
        "m22": lambda: (None, None, None, None, 1.0),
        "gravity": lambda: (-slope * s if tilted else None, upright, None, None, None),
        "torque_per_volt": lambda: (motor_voltage, None, None, None, None),
        "arm_damping": lambda: (-theta_dot, None, None, None, None),
        "pendulum_damping": lambda: (None, -alpha_dot, None, None, None),
        "arm_coulomb": lambda: (-friction, None, None, None, None),
        "inverse_coulomb_speed": lambda: (
            -(k.arm_coulomb + (k.arm_static * fading if static else 0.0)) * friction_slope * theta_dot,
            None,
            None,
            None,
            None,
        ),
        "arm_stiffness": lambda: (-stretch, None, None, None, None),
        "arm_rest": lambda: (k.arm_stiffness * stretch_slope, None, None, None, None),
        "cable_softening": lambda: (-k.arm_stiffness * by_softening, None, None, None, None),
        "tilt_x": lambda: (
            -k.arm_gravity * np.sin(theta) - k.gravity * np.cos(theta) * s,
            -k.gravity * c * np.sin(theta),
            None,
            None,
            None,
        ),
        "tilt_y": lambda: (
            -k.arm_gravity * np.cos(theta) + k.gravity * np.sin(theta) * s,
            -k.gravity * c * np.cos(theta),
            None,
            None,
            None,
        ),
        "arm_gravity": lambda: (-balance if tilted else None, None, None, None, None),
        "arm_static": lambda: (
            -(excess if static else np.exp(-((theta_dot * k.inverse_stribeck_speed) ** 2)) * friction),
            None,
            None,
            None,
            None,
        ),
        "inverse_stribeck_speed": lambda: (
            (2.0 * k.arm_static * theta_dot * theta_dot * k.inverse_stribeck_speed * excess) if static else None,
            None,
            None,
            None,
            None,
        ),
    }
    # Each row summed term by term into its place: the same sums as term after term, without building lists of
    # rows and stacking them (in each of a Jacobian's 1000 stages: about a fifth of its tangents' time, measured).
    a_k, b_k = np.empty((active.size, *np.shape(a))), np.empty((active.size, *np.shape(a)))
    for row, field in enumerate(active):
        first = True
        for d, ca, cb in zip(by_field[FIELDS[field]](), (A1, A2, A11, A12, A22), (B1, B2, B11, B12, B22)):
            if d is None:
                continue
            if first:
                np.multiply(ca, d, out=a_k[row])
                np.multiply(cb, d, out=b_k[row])
                first = False
            else:
                a_k[row] += ca * d
                b_k[row] += cb * d
    return a, b, a_x, b_x, a_k, b_k


def simulate_tangents(
    state0,
    voltages,
    params: PendulumParameters | Sequence[PendulumParameters],
    directions: Directions,
    dt: float = SAMPLE_PERIOD,
    n_substeps: int = DEFAULT_SUBSTEPS,
    past_voltages=None,
    loads=None,
) -> tuple[np.ndarray, np.ndarray]:
    """The angles of :func:`~qube_koopman.sim.pendulum.physics.simulate` and their tangents along ``directions``.

    Parameters
    ----------
    state0 : array_like (n_seg, 4)
    voltages : array_like (n_steps, n_seg)
    params : PendulumParameters, or one per segment
    directions : Directions
    dt, n_substeps, past_voltages, loads
        As for :func:`~qube_koopman.sim.pendulum.physics.simulate` (``loads``: (n_steps, n_seg), a known
        torque on the arm in volts at the motor past the dead zone; no direction moves it).

    Returns
    -------
    angles : ndarray (n_steps + 1, n_seg, 2)
    tangents : ndarray (n_steps + 1, n_dir, n_seg, 2)
        The derivative of the angles along each direction.
    """
    check_timing(dt, n_substeps)
    x0 = as_states(state0)
    u = np.asarray(voltages, dtype=float)
    n_steps, n_seg = u.shape
    x0 = np.broadcast_to(x0, (n_seg, 4))
    if not isinstance(params, PendulumParameters):
        params = list(params)
    delays = (
        np.full(n_seg, params.delay) if isinstance(params, PendulumParameters) else np.array([p.delay for p in params])
    )
    k, whole, weights, wholes = coefficients_and_hold(params, (n_seg,), dt, int(n_substeps))
    k = k._replace(dead_zone=np.asarray(k.dead_zone, dtype=float))
    h = dt / n_substeps
    past = np.zeros((whole + 1, n_seg)) if past_voltages is None else np.asarray(past_voltages, float)
    loads = None if loads is None else np.asarray(loads, dtype=float)
    commands = np.concatenate([np.broadcast_to(past, (past.shape[0], n_seg)), u])
    own = past.shape[0] - (np.full(n_seg, whole) if wholes is None else wholes)
    # d(weight of the previous command in substep j) / d(delay): n / dt while the switch is inside it.
    fraction = delays / dt - np.floor(delays / dt + 1e-12)
    weight_slopes = [
        np.where((fraction * n_substeps - j >= 0) & (fraction * n_substeps - j < 1), n_substeps / dt, 0.0)
        for j in range(n_substeps)
    ]
    n_dir = directions.n
    mask = directions.mask
    # The directions a mask restricts (a setup's own value): only their rows are multiplied by it.
    masked = None
    if mask is not None:
        restricted = np.flatnonzero(np.any(mask != 1.0, axis=1))
        masked = (restricted, mask[restricted]) if restricted.size else None
    optional = _optional_terms(k)
    active = np.flatnonzero(np.any(directions.coefficients != 0, axis=0))
    active = active[active != _DEAD_ZONE]  # the dead zone moves the motor's voltage (below)
    gain = directions.coefficients[:, active]  # (n_dir, n_active)
    moved = np.flatnonzero((directions.delay != 0) | (directions.coefficients[:, _DEAD_ZONE] != 0))
    comps = [x0[:, i].copy() for i in range(4)]
    tang = np.repeat(directions.state.T[:, :, None], n_seg, axis=2).astype(float)  # (4, n_dir, n_seg)
    angles = np.empty((n_steps + 1, n_seg, 2))
    tangents = np.empty((n_steps + 1, n_dir, n_seg, 2))
    angles[0] = x0[:, :2]
    tangents[0, ..., 0], tangents[0, ..., 1] = tang[0], tang[1]
    rows = np.arange(n_seg)
    for step in range(n_steps):
        now = commands[np.maximum(own + step, 0), rows]
        before = commands[np.maximum(own + step - 1, 0), rows]
        for j, w in enumerate(weights):
            voltage = now + w * (before - now)
            outside = np.abs(voltage) > k.dead_zone
            motor = voltage - np.clip(voltage, -k.dead_zone, k.dead_zone)
            if loads is not None:  # past the dead zone, as physics.advance adds it
                motor = motor + loads[step]
            # The motor voltage's tangent, in the directions that move it (delay, dead zone).
            d_motor = np.zeros((moved.size, n_seg))
            if moved.size:
                d_voltage = directions.delay[moved, None] * weight_slopes[j] * (before - now)
                d_zone = -np.sign(voltage) * directions.coefficients[moved, _DEAD_ZONE, None]
                d_motor = np.where(outside, d_voltage + d_zone, 0.0)
                if mask is not None:
                    d_motor = d_motor * mask[moved]
            comps, tang = _rk4_tangent(comps, tang, motor, d_motor, moved, h, k, active, gain, masked, optional)
        angles[step + 1, :, 0], angles[step + 1, :, 1] = comps[0], comps[1]
        tangents[step + 1, ..., 0], tangents[step + 1, ..., 1] = tang[0], tang[1]
    return angles, tangents


def _rk4_tangent(comps, tang, motor, d_motor, moved, h, k, active, gain, masked, optional):
    """One RK4 substep of the state and of every direction's tangent (``tang``: (4, n_dir, n_seg), the tangents of
    theta, alpha and their rates; ``masked``: the rows of the directions a mask restricts and their masks, or None)."""
    half, sixth = 0.5 * h, h / 6.0

    def slope(y, T):
        """The state's slope (velocities, accelerations) and the tangents' (their rates, their accelerations)."""
        a, b, a_x, b_x, a_k, b_k = _partials(*y, motor, k, active, *optional)
        K = np.empty_like(T)
        K[:2] = T[2:]
        # d a = sum_i a_x[i] d x_i over the four state components, every direction at once
        np.einsum("in,idn->dn", np.stack(a_x[:4]), T, out=K[2])
        np.einsum("in,idn->dn", np.stack(b_x[:4]), T, out=K[3])
        if active.size:
            pa, pb = gain @ a_k, gain @ b_k
            if masked is not None:
                rows, masks = masked
                pa[rows] *= masks
                pb[rows] *= masks
            K[2] += pa
            K[3] += pb
        if moved.size:
            K[2, moved] += a_x[4] * d_motor
            K[3, moved] += b_x[4] * d_motor
        return [y[2], y[3], a, b], K

    # The state and the tangents are one system whose slope is (velocities, accelerations) of each: classic RK4
    # on it, its stages' arithmetic as the model's _rk4_steps.
    k1, K1 = slope(comps, tang)
    k2, K2 = slope([y + half * s for y, s in zip(comps, k1)], tang + half * K1)
    k3, K3 = slope([y + half * s for y, s in zip(comps, k2)], tang + half * K2)
    k4, K4 = slope([y + h * s for y, s in zip(comps, k3)], tang + h * K3)
    out = [y + sixth * (s1 + 2.0 * s2 + 2.0 * s3 + s4) for y, s1, s2, s3, s4 in zip(comps, k1, k2, k3, k4)]
    return out, tang + sixth * (K1 + 2.0 * K2 + 2.0 * K3 + K4)
