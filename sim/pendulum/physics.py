"""The Quanser QUBE-Servo rotary inverted pendulum: the rigid-body equations of the arm and
pendulum driven by the DC motor, with the Quanser QUBE-Servo 2 workbook's parameters as the
starting point (:class:`PendulumParameters`).

State ``x = (theta, alpha, theta_dot, alpha_dot)``: motor-arm angle, pendulum
angle with ``alpha = 0`` upright (the dataset's convention), and their rates;
input: motor voltage, held constant over each sample (zero-order hold).

The equations are written once, in plain arithmetic on the four state
components, so the same code integrates a batch of numpy arrays (replays,
tests) and plain Python floats (:class:`PendulumSimulator`, called once per
500 Hz tick, where numpy's per-call overhead would dominate).
"""

from __future__ import annotations

import math
from functools import partial
from dataclasses import dataclass, fields, replace
from typing import Any, Callable, NamedTuple, Sequence

import numpy as np

from qube_koopman.core.controller import QUBE_SAMPLE_PERIOD
from qube_koopman.core.lti import DiscreteStateSpace

__all__ = [
    "PendulumParameters",
    "dynamics",
    "rk4_step",
    "simulate",
    "total_energy",
    "static_friction",
    "linearize_upright",
    "linear_model",
    "SAMPLE_PERIOD",
    "MAX_PARAMETER",
    "MIN_POSITIVE_PARAMETER",
    "MAX_DELAY",
]

#: The simulator's step: the rig's sample period, defined once (core.controller.QUBE_SAMPLE_PERIOD).
SAMPLE_PERIOD = QUBE_SAMPLE_PERIOD
#: The largest size of any parameter (SI units): past it the model's own arithmetic overflows.
MAX_PARAMETER = 1e6
#: The smallest resistance, mass, length or Coulomb speed: the model divides by them.
MIN_POSITIVE_PARAMETER = 1e-15
#: The longest transport delay (s): the simulator keeps that many seconds of commands.
MAX_DELAY = 1.0
#: The largest tilt of the base (rad, about 6 degrees): far beyond any rig that balances on a desk.
MAX_TILT = 0.1
DEFAULT_SUBSTEPS = 2


@dataclass(frozen=True)
class PendulumParameters:
    """Physical parameters (SI units); defaults: the twin calibrated on the rig under two controllers.

    The defaults are ``plants/qube_20230828_20230915.toml`` (``qube-calibrate``
    on the paper's 28 training episodes, under the rig's gains, and on 10
    episodes of the same rig under a softer arm loop; validated by
    closed-loop replay of the paper's 20 test episodes, see that file's
    provenance; a test keeps the two equal). The twin calibrated on the
    paper's 28 episodes alone, without the cables' spring, is the named set
    ``calibrated-20230828`` (``sim.pendulum.params_file``).
    The Quanser workbook's values are :meth:`workbook`; the simulator's
    defaults before the calibration (workbook masses, another public
    project's hardware-fitted damping) are :meth:`previous`. Masses, arm
    length, ``Rm`` and ``g`` are the workbook's in all three.

    Parameters
    ----------
    Rm : float
        Motor terminal resistance (ohm).
    km : float
        Motor torque and back-EMF constant (N m / A = V s / rad).
    mr, Lr : float
        Rotary arm mass (kg) and length (m).
    mp, Lp : float
        Pendulum mass (kg) and length (m).
    g : float
        Gravity (m/s^2).
    Dr, Dp : float
        Viscous damping of the arm and the pendulum (N m s / rad). The
        workbook's larger values (:meth:`workbook`) made 4 of 5 replayed
        dataset episodes fall.
    Cr : float
        Coulomb (dry) friction torque of the arm (N m), smoothed as
        ``Cr tanh(theta_dot / coulomb_speed)``; 0 leaves it out.
    coulomb_speed : float
        Arm speed (rad/s) over which the Coulomb torque changes sign.
    Cs : float
        Static friction of the arm beyond its Coulomb torque (N m): the arm breaks away at ``Cr + Cs``,
        the excess fading as the arm speeds up (Stribeck), ``Cs exp(-(theta_dot / stribeck_speed)^2)
        tanh(theta_dot / coulomb_speed)``; 0 leaves it out.
    stribeck_speed : float
        Arm speed (rad/s) over which the static friction's excess fades.
    dead_zone : float
        Amplifier dead zone (V): the motor sees ``V - clip(V, -dead_zone, dead_zone)``;
        0 leaves it out.
    Jh : float
        Inertia the arm carries besides its rod (kg m^2): the motor's rotor, the
        hub, the pendulum's encoder and bearing at the arm's tip. The workbook's
        ``Jr = mr Lr^2 / 12`` leaves them out; 0 keeps its model.
    Kr : float
        Stiffness (N m / rad) of the cables between the arm's hub and the base
        (the pendulum encoder's lead): they pull the arm back towards
        ``theta_rest`` with the torque ``-Kr (theta - theta_rest)``; 0 leaves
        them out. Under a soft arm loop this slow, position-dependent load is
        what moves the arm (see ``docs/calibration.md``). The cables are dressed anew
        each day the rig is set up: the default is the geometric mean of the two
        recording days' stiffnesses, which the plant file keeps (its setups).
    theta_rest : float
        Arm angle (rad, the arm encoder's frame) at which the cables pull
        nothing. The rig's operator zeroes the arm encoder with the arm at its
        rest position, so 0 by default.
    cable_softening : float
        How much the cables' pull softens as the arm swings out (1/rad^2): with
        ``c = sqrt(cable_softening)`` the torque is ``-Kr tanh(c (theta - theta_rest)) / c``,
        ``-Kr (x - cable_softening x^3 / 3 + ...)`` for a small excursion ``x``,
        levelling off at ``Kr / c`` beyond about ``1 / c`` rad (the cables run taut, or
        slide in their clamp); 0 keeps the spring linear. Run backwards on the logs,
        the equations without a spring leave a restoring load that levels off near
        half a radian on both recording days, each with its own stiffness.
    tilt_x, tilt_y : float
        The base's tilt (rad), to first order: the pendulum balances at
        ``alpha_b = tilt_x sin(theta) + tilt_y cos(theta)`` in the encoder's frame
        (``tilt_y`` the slope across the arm where it points at ``theta = 0``,
        ``tilt_x`` the slope along it), and the arm's tip rises and falls as it turns,
        so gravity pulls the arm with ``-(mr / 2 + mp) g Lr alpha_b``. Under the balancing
        loop a balance point that moves with the arm is a load on the arm (the loop
        pushes the arm to keep the pendulum upright), the slower the arm loop the more.
        A rig set up on a desk a few tenths of a degree off level is tilted by some
        mrad, differently each time it is set up: a setup's value, like the cables'.
        0 (a level base) leaves the terms out; at most 0.1 rad.
    delay : float
        Transport delay (s) from a command to the motor: over each sample the
        motor sees the command of ``delay`` seconds earlier, so a fraction of a
        sample period splits the sample between the previous and the current
        command. Used by the sampled simulations (:func:`simulate`, the closed
        loop, :class:`PendulumSimulator`), not by :func:`dynamics` nor the
        linearization; 0 applies each command at once.
    """

    # The calibrated twin, digit for digit as plants/qube_20230828_20230915.toml (tests/sim/test_plant_file.py).
    Rm: float = 8.4
    km: float = 0.043454588905303834
    mr: float = 0.095
    Lr: float = 0.085
    mp: float = 0.024
    Lp: float = 0.12237129252750036
    g: float = 9.81
    Dr: float = 4.3218138967563495e-05
    Dp: float = 0.0
    Cr: float = 0.00040048485875993534
    coulomb_speed: float = 0.05
    dead_zone: float = 0.04545963558672975
    Jh: float = 6.531913563680526e-05
    delay: float = 0.0013464229902617549
    Kr: float = 0.0017123295002048101
    theta_rest: float = 0.0
    cable_softening: float = 5.179489002800374
    tilt_x: float = 0.0
    tilt_y: float = 0.0
    Cs: float = 0.0
    stribeck_speed: float = 0.1

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ValueError(f"parameter {f.name} must be a finite number, got {value!r}")
        for name in ("Rm", "mr", "Lr", "mp", "Lp"):
            if getattr(self, name) <= 0:
                raise ValueError(f"parameter {name} must be positive, got {getattr(self, name)}")
        # km = 0 (motor disconnected) and zero damping are legitimate idealizations.
        for name in ("coulomb_speed", "stribeck_speed"):
            if getattr(self, name) <= 0:
                raise ValueError(f"parameter {name} must be positive, got {getattr(self, name)}")
        for name in ("km", "Dr", "Dp", "g", "Cr", "Cs", "dead_zone", "Jh", "delay", "Kr", "cable_softening"):
            if getattr(self, name) < 0:
                raise ValueError(f"parameter {name} must be non-negative, got {getattr(self, name)}")
        # Beyond these the arithmetic of the model itself overflows (km**2 / Rm, a delay buffer of
        # delay / dt samples): no pendulum's parameter comes near them in SI units.
        for f in fields(self):
            if abs(getattr(self, f.name)) > MAX_PARAMETER:
                raise ValueError(
                    f"parameter {f.name} must be at most {MAX_PARAMETER:g} in size, got {getattr(self, f.name)}"
                )
        for name in ("Rm", "mr", "Lr", "mp", "Lp", "coulomb_speed", "stribeck_speed"):
            if getattr(self, name) < MIN_POSITIVE_PARAMETER:
                raise ValueError(
                    f"parameter {name} must be at least {MIN_POSITIVE_PARAMETER:g}, got {getattr(self, name)}"
                )
        if self.delay > MAX_DELAY:
            raise ValueError(f"parameter delay must be at most {MAX_DELAY:g} s, got {self.delay}")
        for name in ("tilt_x", "tilt_y"):
            if abs(getattr(self, name)) > MAX_TILT:
                raise ValueError(
                    f"parameter {name} must be at most {MAX_TILT:g} rad in size, got {getattr(self, name)}"
                )

    @classmethod
    def workbook(cls) -> "PendulumParameters":
        """All values from the Quanser QUBE-Servo 2 workbook, including its damping.

        No dry friction, dead zone, hub inertia, cable stiffness or delay: the workbook's model.
        """
        return cls(
            km=0.042,
            Lp=0.129,
            Dr=0.0015,
            Dp=0.0005,
            Cr=0.0,
            dead_zone=0.0,
            Jh=0.0,
            delay=0.0,
            Kr=0.0,
            cable_softening=0.0,
        )

    @classmethod
    def previous(cls) -> "PendulumParameters":
        """The simulator's defaults before calibration: the workbook with hardware-fitted damping.

        Another public project fitted ``Dr`` and ``Dp`` to a QUBE-Servo 2;
        everything else is :meth:`workbook`. Replaying the paper's episodes
        through it: theta's standard deviation 0.88-0.96 of the real one,
        alpha's 0.71-0.84. It is the calibration's starting point.
        """
        return replace(cls.workbook(), Dr=2.7e-4, Dp=5e-5)

    @property
    def Jr(self) -> float:
        """Arm moment of inertia about its centre, ``mr Lr^2 / 12`` (kg m^2)."""
        return self.mr * self.Lr**2 / 12.0

    @property
    def Jp(self) -> float:
        """Pendulum moment of inertia about its centre, ``mp Lp^2 / 12`` (kg m^2)."""
        return self.mp * self.Lp**2 / 12.0


class Coefficients(NamedTuple):
    """The parameter combinations the equations use, computed once (:meth:`of`).

    What the integrators of this module, :class:`~qube_koopman.sim.pendulum.PendulumSimulator`
    and :func:`~qube_koopman.sim.pendulum.simulate_closed_loop` share.
    """

    m11: float  # M11 at alpha = 0: Jr + Jh + mp Lr^2
    quarter: float  # mp Lp^2 / 4: the s^2 part of M11, centrifugal coefficient
    m12: float  # mp Lp Lr / 2: M12 / cos(alpha)
    m22: float  # Jp + mp Lp^2 / 4
    gravity: float  # mp Lp g / 2
    torque_per_volt: float  # km / Rm
    arm_damping: float  # km^2 / Rm (back-EMF) + Dr
    pendulum_damping: float  # Dp
    arm_coulomb: float = 0.0  # Cr
    inverse_coulomb_speed: float = 20.0  # 1 / coulomb_speed
    dead_zone: float = 0.0
    arm_stiffness: float = 0.0  # Kr
    arm_rest: float = 0.0  # theta_rest
    cable_curvature: float = 0.0  # sqrt(cable_softening)
    tilt_x: float = 0.0  # the base's tilt: the pendulum balances at tilt_x sin(theta) + tilt_y cos(theta)
    tilt_y: float = 0.0
    arm_gravity: float = 0.0  # (mr / 2 + mp) g Lr: gravity's torque on the arm per radian of the balance angle
    arm_static: float = 0.0  # Cs
    inverse_stribeck_speed: float = 10.0  # 1 / stribeck_speed

    @classmethod
    def of(cls, p: PendulumParameters) -> Coefficients:
        """The coefficients of a pendulum's parameters."""
        return cls(
            m11=p.Jr + p.Jh + p.mp * p.Lr**2,
            quarter=p.mp * p.Lp**2 / 4.0,
            m12=p.mp * p.Lp * p.Lr / 2.0,
            m22=p.Jp + p.mp * p.Lp**2 / 4.0,
            gravity=p.mp * p.Lp * p.g / 2.0,
            torque_per_volt=p.km / p.Rm,
            arm_damping=p.km**2 / p.Rm + p.Dr,
            pendulum_damping=p.Dp,
            arm_coulomb=p.Cr,
            inverse_coulomb_speed=1.0 / p.coulomb_speed,
            dead_zone=p.dead_zone,
            arm_stiffness=p.Kr,
            arm_rest=p.theta_rest,
            cable_curvature=math.sqrt(p.cable_softening),
            tilt_x=p.tilt_x,
            tilt_y=p.tilt_y,
            arm_gravity=(p.mr / 2.0 + p.mp) * p.g * p.Lr,
            arm_static=p.Cs,
            inverse_stribeck_speed=1.0 / p.stribeck_speed,
        )

    @classmethod
    def per_episode(cls, params: Sequence[PendulumParameters], batch: tuple[int, ...]) -> Coefficients:
        """The coefficients of one pendulum per episode of a batch: each field an array of shape ``batch``
        (``params`` in the batch's C order), or a float where every pendulum has the same value."""
        unique = {p: cls.of(p) for p in dict.fromkeys(params)}  # a batch of segments shares a few pendulums
        each = [unique[p] for p in params]
        if len(each) != math.prod(batch):
            raise ValueError(f"{len(each)} parameter sets for a batch of {batch}: give one per episode")
        values: dict[str, Any] = {}  # floats, or arrays over the batch (the arithmetic takes either)
        for name in cls._fields:
            column = np.array([getattr(c, name) for c in each], dtype=float)
            values[name] = float(column[0]) if np.all(column == column[0]) else column.reshape(batch)
        return cls(**values)


def _on(value) -> bool:
    """Whether a coefficient is non-zero anywhere (a float, or an array of one per episode)."""
    return bool(value.any()) if isinstance(value, np.ndarray) else bool(value)


def _motor_voltage(voltage, k: Coefficients):
    """The voltage past the amplifier's dead zone; floats or arrays alike."""
    if not _on(k.dead_zone):
        return voltage
    if isinstance(voltage, float):  # the per-tick simulator: numpy's clip costs microseconds a call
        return voltage - min(max(voltage, -k.dead_zone), k.dead_zone)
    return voltage - np.clip(voltage, -k.dead_zone, k.dead_zone)


def _cable_stretch(k: Coefficients, tanh: Callable = np.tanh) -> Callable | None:
    """The cables' pull per unit stiffness as a function of the arm's excursion ``x``: ``tanh(c x) / c``,
    ``x`` where ``c`` is 0; None without cables. Its branches are chosen, and an array of one
    curvature per episode is made safe to divide by, once for every step of a simulation."""
    if not _on(k.arm_stiffness):
        return None
    curvature = k.cable_curvature
    if not _on(curvature):
        return lambda x: x
    if isinstance(curvature, np.ndarray):  # one pendulum per episode: some may keep a linear spring
        curved = curvature > 0
        safe = np.where(curved, curvature, 1.0)
        return lambda x: np.where(curved, np.tanh(safe * x) / safe, x)
    return lambda x: tanh(curvature * x) / curvature


def _accelerations(theta, s, c, theta_dot, alpha_dot, voltage, k: Coefficients, tanh: Callable = np.tanh, terms=None):
    """(theta_ddot, alpha_ddot) from the arm angle, sin and cos of alpha and the motor's voltage
    (past the dead zone, :func:`_motor_voltage`); floats or arrays alike. ``terms``: :func:`_terms`
    of ``k`` and ``tanh``, when bound once for many calls."""
    coulomb, stretch, tilted, static = _terms(k, tanh) if terms is None else terms
    # tau - Dr theta_dot with tau = km (V - km theta_dot) / Rm: the back-EMF
    # opposes the motion, which bounds the no-load speed at 1/km rad/s per volt.
    r1 = (
        k.torque_per_volt * voltage
        - k.arm_damping * theta_dot
        - 2.0 * k.quarter * s * c * theta_dot * alpha_dot
        + k.m12 * s * alpha_dot * alpha_dot
    )
    if coulomb:  # a Python branch: without friction the arithmetic is exactly as before
        r1 = r1 - k.arm_coulomb * tanh(theta_dot * k.inverse_coulomb_speed)
    if static:  # the static friction's excess (Stribeck); as above, exactly the old arithmetic without it
        r1 = r1 - static_friction(theta_dot, k, tanh)
    if stretch is not None:  # the cables' spring; as above, exactly the old arithmetic without it
        r1 = r1 - k.arm_stiffness * stretch(theta - k.arm_rest)
    upright = s
    if tilted:  # a tilted base's gravity on both bodies; as above, exactly the old arithmetic on a level one
        arm, upright = _tilt_torques(theta, s, c, k, *_TRIG[tanh is math.tanh])
        r1 = r1 + arm
    r2 = -k.pendulum_damping * alpha_dot + k.quarter * s * c * theta_dot * theta_dot + k.gravity * upright
    m11 = k.m11 + k.quarter * s * s
    m12 = k.m12 * c
    det = m11 * k.m22 - m12 * m12
    return (k.m22 * r1 - m12 * r2) / det, (m11 * r2 - m12 * r1) / det


#: sin and cos of numpy (arrays) or of math (the float integrators: scalar_rk4's floats), by ``tanh is math.tanh``.
_TRIG: dict[bool, tuple[Callable, Callable]] = {False: (np.sin, np.cos), True: (math.sin, math.cos)}


def _tilt_torques(theta, s, c, k: Coefficients, sin: Callable, cos: Callable):
    """A tilted base's gravity, to first order in the tilt: the arm's torque, and the pendulum's gravity
    term per ``k.gravity`` (``sin(alpha)`` on a level base).

    The potential ``gravity (cos(alpha) + alpha_b sin(alpha)) - arm_gravity (tilt_x cos(theta) - tilt_y
    sin(theta))`` with the balance angle ``alpha_b = tilt_x sin(theta) + tilt_y cos(theta)``: the
    pendulum's centre and the arm's tip rise and fall with the base's slope under them. Its forces:
    ``-arm_gravity alpha_b - gravity alpha_b' sin(alpha)`` on the arm, ``gravity (sin(alpha) - alpha_b
    cos(alpha))`` on the pendulum (:func:`total_energy` adds the same potential).
    """
    sin_theta, cos_theta = sin(theta), cos(theta)
    balance = k.tilt_x * sin_theta + k.tilt_y * cos_theta
    slope = k.tilt_x * cos_theta - k.tilt_y * sin_theta
    return -k.arm_gravity * balance - k.gravity * slope * s, s - c * balance


def static_friction(theta_dot, k: Coefficients, tanh: Callable = np.tanh):
    """The arm's static friction beyond its Coulomb torque (N m), ``Cs exp(-(theta_dot / v_s)^2) tanh(theta_dot /
    v_c)`` (:class:`PendulumParameters`' ``Cs``, ``stribeck_speed`` and ``coulomb_speed``): floats with ``math.tanh``,
    arrays with numpy's."""
    exp = math.exp if tanh is math.tanh else np.exp
    fade = theta_dot * k.inverse_stribeck_speed
    return k.arm_static * exp(-fade * fade) * tanh(theta_dot * k.inverse_coulomb_speed)


def _terms(k: Coefficients, tanh: Callable) -> tuple[bool, Callable | None, bool, bool]:
    """Which optional terms :func:`_accelerations` adds: Coulomb friction, the cables' pull, a tilted base and
    static friction."""
    return _on(k.arm_coulomb), _cable_stretch(k, tanh), _on(k.tilt_x) or _on(k.tilt_y), _on(k.arm_static)


def _rk4(theta, alpha, theta_dot, alpha_dot, voltage, h: float, n: int, k: Coefficients, sin: Callable, cos: Callable):
    """``n`` classic RK4 steps of size ``h`` at constant voltage, on the four components."""
    tanh = math.tanh if sin is math.sin else np.tanh
    voltage = _motor_voltage(voltage, k)  # constant over the steps: the dead zone once
    return _rk4_steps(
        theta, alpha, theta_dot, alpha_dot, voltage, h, n, partial(_accelerations, k=k, tanh=tanh), sin, cos
    )


def array_rk4(k: Coefficients) -> Callable:
    """:func:`_rk4` with numpy's functions for one pendulum or one per episode (arrays), the terms bound once.

    ``rk4(theta, alpha, theta_dot, alpha_dot, voltage, h, n)`` returns what ``_rk4(..., k, np.sin,
    np.cos)`` does, bit for bit: the same arithmetic, without testing at every stage which terms
    are on (at a few episodes a batch's step costs numpy's per-call overhead, not arithmetic).
    ``rk4(..., load=d)`` adds a torque on the arm, ``d`` volts at the motor past the dead zone.
    """
    accelerations = partial(_accelerations, k=k, tanh=np.tanh, terms=_terms(k, np.tanh))

    def rk4(theta, alpha, theta_dot, alpha_dot, voltage, h, n, load=None):
        voltage = _motor_voltage(voltage, k)
        if load is not None:  # a random torque on the arm (volts at the motor): past the dead zone
            voltage = voltage + load
        return _rk4_steps(theta, alpha, theta_dot, alpha_dot, voltage, h, n, accelerations, np.sin, np.cos)

    return rk4


def _rk4_steps(theta, alpha, theta_dot, alpha_dot, voltage, h: float, n: int, accelerations: Callable, sin, cos):
    """:func:`_rk4`'s steps with the voltage past the dead zone and ``accelerations(theta, sin alpha, cos alpha,
    theta_dot, alpha_dot, voltage)``."""
    half = 0.5 * h
    sixth = h / 6.0
    for _ in range(n):
        a1, b1 = accelerations(theta, sin(alpha), cos(alpha), theta_dot, alpha_dot, voltage)
        th2 = theta + half * theta_dot
        al2 = alpha + half * alpha_dot
        td2 = theta_dot + half * a1
        ad2 = alpha_dot + half * b1
        a2, b2 = accelerations(th2, sin(al2), cos(al2), td2, ad2, voltage)
        th3 = theta + half * td2
        al3 = alpha + half * ad2
        td3 = theta_dot + half * a2
        ad3 = alpha_dot + half * b2
        a3, b3 = accelerations(th3, sin(al3), cos(al3), td3, ad3, voltage)
        th4 = theta + h * td3
        al4 = alpha + h * ad3
        td4 = theta_dot + h * a3
        ad4 = alpha_dot + h * b3
        a4, b4 = accelerations(th4, sin(al4), cos(al4), td4, ad4, voltage)
        theta = theta + sixth * (theta_dot + 2.0 * td2 + 2.0 * td3 + td4)
        alpha = alpha + sixth * (alpha_dot + 2.0 * ad2 + 2.0 * ad3 + ad4)
        theta_dot = theta_dot + sixth * (a1 + 2.0 * a2 + 2.0 * a3 + a4)
        alpha_dot = alpha_dot + sixth * (b1 + 2.0 * b2 + 2.0 * b3 + b4)
    return theta, alpha, theta_dot, alpha_dot


def scalar_rk4(k: Coefficients) -> Callable:
    """:func:`_rk4` for one pendulum in Python floats, its coefficients and branches bound once.

    ``rk4(theta, alpha, theta_dot, alpha_dot, voltage, h, n)`` does the same operations in the
    same order as ``_rk4(..., k, math.sin, math.cos)`` (the same :func:`_rk4_steps`), so it returns
    the same floats, bit for bit (tests/sim/test_pendulum.py); ``rk4(..., load=d)`` adds a torque on
    the arm, ``d`` volts at the motor past the dead zone. The per-tick simulator steps 500
    times a simulated second and spent most of each step looking up coefficients and testing which
    terms are on.
    """
    m11_0, quarter, m12_0, m22, gravity = k.m11, k.quarter, k.m12, k.m22, k.gravity
    torque, damping, pendulum_damping = k.torque_per_volt, k.arm_damping, k.pendulum_damping
    two_quarter = 2.0 * quarter  # the first product of the arithmetic's left-to-right 2.0 * quarter * s ...
    coulomb, inverse_speed = k.arm_coulomb, k.inverse_coulomb_speed
    stiffness, rest, curvature = k.arm_stiffness, k.arm_rest, k.cable_curvature
    dead_zone = k.dead_zone
    has_coulomb, has_spring, has_curve, has_dead_zone = (
        bool(coulomb),
        bool(stiffness),
        bool(curvature),
        bool(dead_zone),
    )
    has_tilt = bool(k.tilt_x) or bool(k.tilt_y)
    has_static = bool(k.arm_static)
    sin, cos, tanh = math.sin, math.cos, math.tanh

    def accelerations(theta, s, c, theta_dot, alpha_dot, voltage):
        r1 = (
            torque * voltage
            - damping * theta_dot
            - two_quarter * s * c * theta_dot * alpha_dot
            + m12_0 * s * alpha_dot * alpha_dot
        )
        if has_coulomb:
            r1 = r1 - coulomb * tanh(theta_dot * inverse_speed)
        if has_static:
            r1 = r1 - static_friction(theta_dot, k, tanh)
        if has_spring:
            x = theta - rest
            r1 = r1 - stiffness * (tanh(curvature * x) / curvature if has_curve else x)
        upright = s
        if has_tilt:
            arm, upright = _tilt_torques(theta, s, c, k, sin, cos)
            r1 = r1 + arm
        r2 = -pendulum_damping * alpha_dot + quarter * s * c * theta_dot * theta_dot + gravity * upright
        m11 = m11_0 + quarter * s * s
        m12 = m12_0 * c
        det = m11 * m22 - m12 * m12
        return (m22 * r1 - m12 * r2) / det, (m11 * r2 - m12 * r1) / det

    def rk4(theta, alpha, theta_dot, alpha_dot, voltage, h, n, load=None):
        if has_dead_zone:
            voltage = voltage - min(max(voltage, -dead_zone), dead_zone)
        if load is not None:
            voltage = voltage + load
        return _rk4_steps(theta, alpha, theta_dot, alpha_dot, voltage, h, n, accelerations, sin, cos)

    return rk4


def hold_pattern(delay: float, dt: float, n_substeps: int) -> tuple[int, tuple[float, ...]]:
    """Whole samples of ``delay`` and, per substep, the weight of the previous command in it.

    A substep the switch falls inside sees the two commands averaged by the
    time each is held (exact impulse, continuous in the delay).
    """
    samples = delay / dt
    whole = int(math.floor(samples + 1e-12))
    fraction = max(0.0, samples - whole)
    return whole, tuple(min(1.0, max(0.0, fraction * n_substeps - j)) for j in range(n_substeps))


def coefficients_and_hold(params, batch: tuple[int, ...], dt: float, n_substeps: int):
    """The coefficients and hold pattern of one pendulum, or of one per episode of a batch (:func:`simulate`,
    :func:`~qube_koopman.sim.pendulum.simulate_closed_loop`).

    Returns ``(k, whole, weights, wholes)``: ``whole`` the most whole samples of delay, ``weights``
    per substep (floats, or arrays over the batch), ``wholes`` each episode's whole samples (None when
    they are all ``whole``).
    """
    if isinstance(params, PendulumParameters):
        whole, weights = hold_pattern(params.delay, dt, n_substeps)
        return Coefficients.of(params), whole, weights, None
    params = list(params)
    k = Coefficients.per_episode(params, batch)
    by_delay = {d: hold_pattern(d, dt, n_substeps) for d in {p.delay for p in params}}
    patterns = [by_delay[p.delay] for p in params]
    wholes = np.array([w for w, _ in patterns]).reshape(batch)
    table = np.array([w for _, w in patterns])  # (episodes, substeps)
    same = bool(np.all(table == table[:1]))  # floats then, as for one pendulum; else arrays in every substep
    weights = tuple(float(c[0]) if same else c.reshape(batch) for c in table.T)
    whole = int(wholes.max(initial=0))
    return k, whole, weights, None if np.all(wholes == whole) else wholes


def advance(
    comps,
    previous,
    current,
    weights: tuple[float, ...],
    h: float,
    k: Coefficients,
    sin: Callable,
    cos: Callable,
    rk4: Callable | None = None,
    load=None,
):
    """One sample of ``len(weights)`` RK4 substeps: ``previous`` command held first, then ``current``.

    ``rk4``: ``k``'s :func:`scalar_rk4` or :func:`array_rk4` (the same floats, faster). ``load``: a
    torque on the arm over the sample, in volts at the motor past the dead zone
    (:class:`~qube_koopman.sim.pendulum.load.RandomLoad`; needs ``rk4``); None: exactly the
    arithmetic without it.
    """
    if rk4 is None:
        if load is not None:
            raise ValueError("a load needs the integrator of scalar_rk4 or array_rk4")
        rk4 = partial(_rk4, k=k, sin=sin, cos=cos)
    if load is not None:  # the same integrator with the load bound: each substep sees it
        rk4 = partial(rk4, load=load)
    theta, alpha, theta_dot, alpha_dot = comps
    # (Weights are floats, or arrays of one per episode when the episodes' delays differ.)
    fractional = any(w.any() for w in weights) if isinstance(weights[0], np.ndarray) else any(weights)
    if not fractional:  # no fractional delay: exactly the plain zero-order hold
        return rk4(theta, alpha, theta_dot, alpha_dot, current, h, len(weights))
    for w in weights:
        theta, alpha, theta_dot, alpha_dot = rk4(
            theta, alpha, theta_dot, alpha_dot, current + w * (previous - current), h, 1
        )
    return theta, alpha, theta_dot, alpha_dot


def as_states(state) -> np.ndarray:
    """``state`` as a float array of shape (..., 4), or a ValueError naming the shape it has."""
    state = np.asarray(state, dtype=float)
    if state.ndim == 0 or state.shape[-1] != 4:
        raise ValueError(f"state must have shape (..., 4): theta, alpha, theta_dot, alpha_dot; got {state.shape}")
    return state


def check_timing(dt: float, n_substeps: int) -> None:
    """A positive finite sample period and a positive integer number of RK4 substeps (else a ValueError)."""
    if not (math.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be a positive number of seconds, got {dt!r}")
    if isinstance(n_substeps, bool) or not isinstance(n_substeps, (int, np.integer)) or n_substeps < 1:
        raise ValueError(f"n_substeps must be a positive integer, got {n_substeps!r}")


def dynamics(state, voltage, params: PendulumParameters = PendulumParameters()) -> np.ndarray:
    """Time derivative of the state.

    Parameters
    ----------
    state : array_like of shape (..., 4)
        theta, alpha, theta_dot, alpha_dot (rad, rad/s); any leading batch shape.
    voltage : float or array_like broadcastable to ``state.shape[:-1]``
        Motor voltage (V).
    params : PendulumParameters

    Returns
    -------
    ndarray of shape (..., 4)
        theta_dot, alpha_dot, theta_ddot, alpha_ddot.
    """
    x = as_states(state)
    k = Coefficients.of(params)
    theta_ddot, alpha_ddot = _accelerations(
        x[..., 0],
        np.sin(x[..., 1]),
        np.cos(x[..., 1]),
        x[..., 2],
        x[..., 3],
        _motor_voltage(np.asarray(voltage, dtype=float), k),
        k,
    )
    return np.stack(np.broadcast_arrays(x[..., 2], x[..., 3], theta_ddot, alpha_ddot), axis=-1)


def rk4_step(
    state,
    voltage,
    params: PendulumParameters = PendulumParameters(),
    dt: float = SAMPLE_PERIOD,
    n_substeps: int = DEFAULT_SUBSTEPS,
) -> np.ndarray:
    """Advance by ``dt`` under a constant (zero-order-held) voltage with ``n_substeps`` RK4 steps.

    Shapes as in :func:`dynamics`; the result has the broadcast batch shape.
    """
    check_timing(dt, n_substeps)
    x = as_states(state)
    out = _rk4(
        x[..., 0],
        x[..., 1],
        x[..., 2],
        x[..., 3],
        np.asarray(voltage, dtype=float),
        dt / n_substeps,
        int(n_substeps),
        Coefficients.of(params),
        np.sin,
        np.cos,
    )
    return np.stack(np.broadcast_arrays(*out), axis=-1)


def simulate(
    state0,
    voltages,
    params: PendulumParameters | Sequence[PendulumParameters] = PendulumParameters(),
    dt: float = SAMPLE_PERIOD,
    n_substeps: int = DEFAULT_SUBSTEPS,
    past_voltages=None,
    loads=None,
) -> np.ndarray:
    """Open-loop trajectory under a sequence of zero-order-held voltages.

    Parameters
    ----------
    state0 : array_like of shape (..., 4)
        Initial state(s).
    voltages : array_like of shape (n_steps, ...)
        Voltage over each sample period; trailing shape broadcastable to the batch.
    params : PendulumParameters, or a sequence of them
        The pendulum, or one per element of the batch (in its C order): a multiple-shooting fit
        simulates each setup's segments with its own cables and delay, all in one batch.
    past_voltages : array_like of shape (n_past, ...), optional
        Commands before the first sample, oldest first: with a transport delay
        (``params.delay``) the motor still sees them; zero volts by default.
    loads : array_like of shape (n_steps, ...), optional
        A known torque on the arm over each sample, in volts at the motor past the dead zone and
        not delayed (as :func:`advance`'s ``load``; for example the cables' relaxation computed from
        a log's arm angle); None: exactly the arithmetic without it.

    Returns
    -------
    ndarray of shape (n_steps + 1, ..., 4)
        The state at each sample, starting with ``state0``.
    """
    check_timing(dt, n_substeps)
    x = as_states(state0)
    voltages = np.asarray(voltages, dtype=float)
    if voltages.ndim == 0:
        raise ValueError("voltages must have a leading time axis")
    batch = np.broadcast_shapes(x.shape[:-1], voltages.shape[1:])
    out = np.empty((voltages.shape[0] + 1, *batch, 4))
    out[0] = x
    comps = tuple(np.broadcast_to(x[..., i], batch) for i in range(4))
    h = dt / n_substeps
    k, whole, weights, wholes = coefficients_and_hold(params, batch, dt, int(n_substeps))
    rk4 = array_rk4(k)
    past = np.zeros((whole + 1, *voltages.shape[1:])) if past_voltages is None else np.asarray(past_voltages, float)
    if past.ndim != voltages.ndim:
        raise ValueError("past_voltages must have a leading time axis and the voltages' trailing shape")
    commands = np.concatenate([np.broadcast_to(past, (past.shape[0], *voltages.shape[1:])), voltages])
    if loads is not None:
        loads = np.asarray(loads, dtype=float)
        if loads.shape[0] != voltages.shape[0]:
            raise ValueError(
                f"loads must have one row per sample of the voltages: {loads.shape[0]} for {voltages.shape[0]}"
            )
    first = past.shape[0] - whole
    if wholes is not None:  # each episode's own whole samples of delay back: commands over the whole batch
        commands = np.broadcast_to(commands, (commands.shape[0], *batch))
        own = past.shape[0] - wholes
    for step in range(voltages.shape[0]):
        if wholes is None:
            now = commands[max(0, first + step)]
            before = commands[max(0, first + step - 1)]
        else:
            now = np.take_along_axis(commands, np.maximum(own + step, 0)[None], 0)[0]
            before = np.take_along_axis(commands, np.maximum(own + step - 1, 0)[None], 0)[0]
        load = None if loads is None else loads[step]
        comps = advance(comps, before, now, weights, h, k, np.sin, np.cos, rk4, load)
        out[step + 1] = np.stack(np.broadcast_arrays(*comps), axis=-1)
    return out


def total_energy(state, params: PendulumParameters = PendulumParameters()) -> np.ndarray:
    """Kinetic (full inertia matrix) plus potential energy (J), zero potential level at the pivot.

    With alpha = 0 upright the pendulum's potential is ``mp g Lp / 2 cos(alpha)``; a tilted base adds
    its slope under the pendulum and the arm (:func:`_tilt_torques`); the cables'
    spring adds ``Kr (theta - theta_rest)^2 / 2``, or with a ``cable_softening`` ``c^2``,
    ``Kr log(cosh(c (theta - theta_rest))) / c^2`` (the work of its levelling pull).
    """
    x = as_states(state)
    k = Coefficients.of(params)
    s, c = np.sin(x[..., 1]), np.cos(x[..., 1])
    td, ad = x[..., 2], x[..., 3]
    kinetic = 0.5 * ((k.m11 + k.quarter * s * s) * td * td + 2.0 * k.m12 * c * td * ad + k.m22 * ad * ad)
    stretch, curvature = x[..., 0] - k.arm_rest, k.cable_curvature
    # log cosh(y) = |y| + log1p(exp(-2|y|)) - log 2: no overflow at large stretches
    spring = (
        0.5 * stretch**2
        if not curvature
        else (np.abs(curvature * stretch) + np.log1p(np.exp(-2 * np.abs(curvature * stretch))) - np.log(2.0))
        / curvature**2
    )
    sin_theta, cos_theta = np.sin(x[..., 0]), np.cos(x[..., 0])
    balance = k.tilt_x * sin_theta + k.tilt_y * cos_theta
    tilt = k.gravity * balance * s - k.arm_gravity * (k.tilt_x * cos_theta - k.tilt_y * sin_theta)
    return kinetic + k.gravity * c + k.arm_stiffness * spring + tilt


def linearize_upright(params: PendulumParameters = PendulumParameters()) -> tuple[np.ndarray, np.ndarray]:
    """Continuous linearization ``x_dot = A x + B V`` at the upright equilibrium.

    Parameters
    ----------
    params : PendulumParameters
        The pendulum (the calibrated twin by default).

    Returns
    -------
    A : ndarray of shape (4, 4)
    B : ndarray of shape (4, 1)
        State order theta, alpha, theta_dot, alpha_dot. With the workbook's
        parameters (:meth:`PendulumParameters.previous`) A[2, 1] ~ -149,
        A[3, 1] ~ 262, B ~ (50, -49): magnitudes as in the Quanser workbook;
        the signs are this frame's (alpha positive pushes the arm backwards),
        the one in which the dataset's controller (u = +30 alpha + ...)
        stabilizes. The calibrated defaults' larger arm inertia (``Jh``) gives
        about -81, 204 and (31, -32).

    Notes
    -----
    The amplifier's dead zone and the transport delay are left out: the
    slope at 0 V of a dead zone is zero, which describes no motion the loop
    makes; the linearization is that of the motor outside it. The smoothed
    Coulomb torque enters through its slope at rest, ``Cr / coulomb_speed``,
    as viscous damping of the arm (with static friction, ``(Cr + Cs) / coulomb_speed``). The
    cables' spring (``Kr``) enters as a stiffness of the arm (its slope at rest, whatever its ``cable_softening``); the
    equilibrium is at ``theta = theta_rest``, so the state's theta is measured from there.
    A tilted base enters to first order in the tilt, at ``theta_rest``: the slope there of the
    pendulum's balance angle ``alpha_b`` couples the pendulum's gravity to the arm (both ways) and
    stiffens or softens the arm; ``alpha_b`` there is where the state's alpha is measured from (as
    from an encoder's zero), and the constant torque the tilt puts on the arm there is left out (a
    load, which the loop holds), so this is the Jacobian there rather than at an equilibrium.
    """
    k = Coefficients.of(params)
    mass = np.array([[k.m11, k.m12], [k.m12, k.m22]])
    # Generalized forces to first order at alpha = 0: columns (theta, alpha, theta_dot, alpha_dot).
    # The smoothed Coulomb torque's slope at rest acts as viscous damping there, and so does the static friction's.
    arm_damping = k.arm_damping + (k.arm_coulomb + k.arm_static) * k.inverse_coulomb_speed
    slope = k.tilt_x * math.cos(k.arm_rest) - k.tilt_y * math.sin(k.arm_rest)  # of the balance angle
    forces = np.array(
        [
            [-k.arm_stiffness - k.arm_gravity * slope, -k.gravity * slope, -arm_damping, 0.0],
            [-k.gravity * slope, k.gravity, 0.0, -k.pendulum_damping],
        ]
    )
    A = np.zeros((4, 4))
    A[0, 2] = A[1, 3] = 1.0
    A[2:] = np.linalg.solve(mass, forces)
    B = np.zeros((4, 1))
    B[2:, 0] = np.linalg.solve(mass, [k.torque_per_volt, 0.0])
    return A, B


def linear_model(params: PendulumParameters = PendulumParameters(), dt: float = SAMPLE_PERIOD) -> DiscreteStateSpace:
    """The upright linearization discretized exactly under zero-order hold, measuring (theta, alpha).

    Parameters
    ----------
    params : PendulumParameters
        The pendulum (the calibrated twin by default).
    dt : float
        Sample period (s).

    Returns
    -------
    DiscreteStateSpace
        State theta, alpha, theta_dot, alpha_dot (from :func:`linearize_upright`), input the
        voltage, outputs theta and alpha.
    """
    from scipy.linalg import expm  # here: the simulator itself does without scipy

    check_timing(dt, 1)
    A, B = linearize_upright(params)
    block = np.zeros((5, 5))
    block[:4, :4] = A
    block[:4, 4:] = B
    phi = expm(block * dt)
    C = np.hstack([np.eye(2), np.zeros((2, 2))])
    return DiscreteStateSpace(phi[:4, :4], phi[:4, 4:], C, np.zeros((2, 1)), dt)
