"""Swing-up: bring the pendulum from hanging to upright before an episode, without a hand.

An episode run with a :class:`SwingUp` starts from the pendulum hanging (at rest, or still
swinging after the previous episode's end or safety stop). The phase has three modes, run by the
loop's backend one tick at a time like the episode itself (so every backend supports it):

- **pump**: the energy controller of Astrom and Furuta (:class:`EnergyController`) drives the
  pendulum's energy towards the upright's, with an arm-centering term that keeps the arm near
  its zero;
- **catch**: once ``|alpha| < catch_angle`` the episode's balance controller takes over, with
  zero references and feedforward, its state the one it reaches from zero with the catch's
  errors held for ``catch_hold`` (so that its derivative sees no step: a zero state would take
  the arm's and the pendulum's whole errors for a step and kick the arm with them); if the
  pendulum leaves the episode's pendulum limit the phase goes back to pumping;
- **settled**: once the pendulum and arm have stayed near upright and near the arm's zero for
  ``settle_time``, the phase ends and the recorded episode starts at the next tick (with a
  ``prepare`` hook, once it is ready: the balance controller runs on meanwhile), its controller
  again from zero state, as an episode started upright by hand.

The supervisor's swing-up limits (:class:`~qube_koopman.daq.safety.SwingUpLimits`: the arm angle,
the voltage and a time limit) hold throughout: a breach puts 0 V in the tick that sees it and
ends the phase with the reason, as does a stop request (Ctrl-C, SIGTERM). A phase that starts
with the arm already past its limit (left there by the previous episode's fall, on the rig) holds
0 V until the arm is back within it, under the time limit, and pumps only then: the arm limit
ends the phase once the arm has been within it. The phase's samples are
not part of the episode's: its log records only the outcome (``extra.swing_up``).

Angles: the loop's convention, ``alpha = 0`` upright, wrapped to ``[-pi, pi)``; rates are
estimated from the angles by the rig controller's derivative filter (backward Euler of
``tau s / (s + tau)``).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace
from functools import cached_property
from typing import Any, Callable

from qube_koopman.core.lti import DiscreteStateSpace
from qube_koopman.daq.backends.contract import Backend
from qube_koopman.daq.controller_step import controller_step
from qube_koopman.daq.safety import SafetyLimits, StopRequest, SwingUpLimits
from qube_koopman.daq.timing import DeadlinePacer
from qube_koopman.sim.pendulum import PendulumParameters
from qube_koopman.sim.pendulum.physics import Coefficients, static_friction

__all__ = ["EnergyController", "SwingUp", "SwingUpReport", "run_swing_up", "wrap_angle"]

_TWO_PI = 2.0 * math.pi


def wrap_angle(angle: float) -> float:
    """``angle`` wrapped to ``[-pi, pi)`` (rad)."""
    return (angle + math.pi) % _TWO_PI - math.pi


@dataclass(frozen=True)
class EnergyController:
    """Astrom and Furuta's energy control of the pendulum, plus an arm-centering term, in volts.

    The pendulum's energy about its pivot, with ``alpha = 0`` upright, is
    ``E = (Jp + mp Lp^2 / 4) alpha_dot^2 / 2 + (mp Lp g / 2) cos(alpha)``; upright at rest it is
    ``E0 = mp Lp g / 2``. Its rate under an arm acceleration ``a`` is
    ``dE/dt = -(mp Lp Lr / 2) a alpha_dot cos(alpha)`` (plus the centrifugal and damping terms the
    arm's speed and the pendulum's friction add), so the arm acceleration

        a = sat(gain (E - E0) sign(alpha_dot cos(alpha)), max_acceleration)
            - centering_kp theta - centering_kd theta_dot

    raises ``E`` while it is below ``E0`` and lowers it above (``sign(0)`` is +1 here, so a
    pendulum hanging at rest gets its first push). The acceleration is turned into a voltage
    through the pendulum model (:class:`~qube_koopman.sim.pendulum.PendulumParameters`): the
    voltage whose torque, with the back-EMF, friction, the cables' spring and the pendulum's
    reaction, gives the arm that acceleration, plus the amplifier's dead zone.

    Parameters
    ----------
    params : PendulumParameters
        The model the voltage is computed with (the calibrated twin by default).
    gain : float
        ``gain`` in (rad/s^2) / J.
    max_acceleration : float
        Saturation of the pumping term (rad/s^2).
    centering_kp, centering_kd : float
        Arm-centering gains (1/s^2, 1/s).
    energy_margin : float
        Pump towards ``(1 + energy_margin) E0``: a pendulum a little heavier, longer or more
        damped than the model still reaches the catch angle.
    """

    params: PendulumParameters = field(default_factory=PendulumParameters)
    gain: float = 20000.0
    max_acceleration: float = 20.0
    centering_kp: float = 10.0
    centering_kd: float = 6.0
    energy_margin: float = 0.1

    def __post_init__(self) -> None:
        for name in ("gain", "max_acceleration", "centering_kp", "centering_kd", "energy_margin"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"energy controller {name} must be a non-negative number, got {value!r}")

    @cached_property
    def _coefficients(self) -> Coefficients:
        """The model's coefficients, made once rather than at every tick that needs them."""
        return Coefficients.of(self.params)

    @property
    def reference_energy(self) -> float:
        """``E0``: the pendulum's energy upright at rest (J)."""
        p = self.params
        return p.mp * p.Lp * p.g / 2.0

    def energy(self, alpha: float, alpha_dot: float) -> float:
        """The pendulum's energy about its pivot (J), ``alpha = 0`` upright."""
        p = self.params
        inertia = p.Jp + p.mp * p.Lp**2 / 4.0
        return 0.5 * inertia * alpha_dot * alpha_dot + self.reference_energy * math.cos(alpha)

    def acceleration(self, theta: float, alpha: float, theta_dot: float, alpha_dot: float) -> float:
        """The arm acceleration the controller asks for (rad/s^2)."""
        pump = self.gain * (self.energy(alpha, alpha_dot) - (1.0 + self.energy_margin) * self.reference_energy)
        pump *= 1.0 if alpha_dot * math.cos(alpha) >= 0.0 else -1.0
        pump = min(max(pump, -self.max_acceleration), self.max_acceleration)
        return pump - self.centering_kp * theta - self.centering_kd * theta_dot

    def voltage(self, theta: float, alpha: float, theta_dot: float, alpha_dot: float) -> float:
        """The voltage (V, not clamped) that gives the arm :meth:`acceleration` on the model."""
        return self.voltage_for(
            self.acceleration(theta, alpha, theta_dot, alpha_dot), theta, alpha, theta_dot, alpha_dot
        )

    def voltage_for(self, acceleration: float, theta: float, alpha: float, theta_dot: float, alpha_dot: float) -> float:
        """The voltage (V) that gives the arm ``acceleration`` (rad/s^2) in the model's equations."""
        p = self.params
        s, c = math.sin(alpha), math.cos(alpha)
        quarter = p.mp * p.Lp**2 / 4.0
        m11 = p.Jr + p.Jh + p.mp * p.Lr**2 + quarter * s * s
        m12 = p.mp * p.Lp * p.Lr / 2.0 * c
        m22 = p.Jp + quarter
        r2 = -p.Dp * alpha_dot + quarter * s * c * theta_dot * theta_dot + p.mp * p.Lp * p.g / 2.0 * s
        # M [theta_ddot, alpha_ddot] = [r1, r2]: the arm's generalized force r1 giving theta_ddot.
        r1 = acceleration * (m11 - m12 * m12 / m22) + m12 * r2 / m22
        stretch = theta - p.theta_rest
        if p.cable_softening > 0:
            curvature = math.sqrt(p.cable_softening)
            stretch = math.tanh(curvature * stretch) / curvature
        passive = (
            -(p.km * p.km / p.Rm + p.Dr) * theta_dot
            - 2.0 * quarter * s * c * theta_dot * alpha_dot
            + p.mp * p.Lp * p.Lr / 2.0 * s * alpha_dot * alpha_dot
            - p.Cr * math.tanh(theta_dot / p.coulomb_speed)
            - p.Kr * stretch
        )
        if p.Cs:
            passive -= static_friction(theta_dot, self._coefficients, math.tanh)
        volts = (r1 - passive) * p.Rm / p.km
        if volts != 0.0:
            volts += math.copysign(p.dead_zone, volts)
        return volts


@dataclass(frozen=True)
class SwingUp:
    """How an episode swings its pendulum up before it starts (``qube-run --swing-up``).

    Parameters
    ----------
    energy : EnergyController
        The pumping controller.
    limits : SwingUpLimits
        The supervisor's limits during the phase (arm angle, voltage, time).
    catch_angle : float
        The balance controller takes over once ``|alpha|`` is below it (rad; 20 deg).
    settle_alpha, settle_theta : float
        Settled: ``|alpha|`` below ``settle_alpha`` (the start gate's 5 deg) and ``|theta|`` below
        ``settle_theta`` (rad; 0.1) ...
    settle_time : float
        ... for this long without a break (s; 1).
    rate_filter : float
        Bandwidth of the rate estimates (rad/s; the rig controller's 50).
    catch_hold : float
        At a catch the balance controller's state is the one it reaches from zero with the
        catch's tracking errors held this long (s; 0.1, five time constants of the rig
        controller's derivative filter): its derivative then sees no step. 0 takes over from
        zero state, whose derivative takes the whole errors for a step (on the rig's PD, 82 V
        per rad of the arm's error in the first tick, from the derivative alone).
    """

    energy: EnergyController = field(default_factory=EnergyController)
    limits: SwingUpLimits = field(default_factory=SwingUpLimits)
    catch_angle: float = math.radians(20.0)
    settle_alpha: float = math.radians(5.0)
    settle_theta: float = 0.1
    settle_time: float = 1.0
    rate_filter: float = 50.0
    catch_hold: float = 0.1

    def __post_init__(self) -> None:
        for name in ("catch_angle", "settle_alpha", "settle_theta", "settle_time", "rate_filter"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"swing-up {name} must be a positive number, got {value!r}")
        if not (math.isfinite(self.catch_hold) and 0 <= self.catch_hold <= 10):
            raise ValueError(f"swing-up catch_hold must be in [0, 10] s, got {self.catch_hold!r}")

    def as_dict(self) -> dict:
        """Plain-data form, for episode metadata."""
        return asdict(self)


@dataclass(frozen=True)
class SwingUpReport:
    """How a swing-up went.

    Parameters
    ----------
    outcome : {"settled", "failed", "stopped"}
        Settled (the episode starts next tick); failed (a swing-up limit, or a reading the
        supervisor refuses); stopped (a stop request). The motor is at 0 V unless settled.
    reason : str
        Why it did not settle; empty when it did.
    duration : float
        Seconds of the phase (ticks times the sample period).
    catch_time : float or None
        Seconds from the start to the last catch (None: never caught).
    n_catches : int
        How many times the balance controller took over.
    max_abs_theta, max_abs_voltage : float
        Largest ``|theta|`` read and ``|V|`` written during the phase (``|theta|`` from the first
        tick the arm was within its limit).
    """

    outcome: str
    reason: str
    duration: float
    catch_time: float | None
    n_catches: int
    max_abs_theta: float
    max_abs_voltage: float

    @property
    def settled(self) -> bool:
        """True when the episode can start."""
        return self.outcome == "settled"

    def as_dict(self) -> dict[str, Any]:
        """Plain-data form, for episode metadata."""
        return asdict(self)


def run_swing_up(
    backend: Backend,
    balance: DiscreteStateSpace,
    swing: SwingUp,
    limits: SafetyLimits,
    stop: StopRequest,
    pacer: DeadlinePacer | None = None,
    prepare: Callable[[SwingUpReport], Callable[[], bool]] | None = None,
) -> SwingUpReport:
    """Swing the pendulum up, catch it with ``balance`` and wait until it has settled.

    Parameters
    ----------
    backend : Backend
        Started; left running (at 0 V when the phase did not settle). A
        :class:`~qube_koopman.daq.backends.contract.BackendFault` propagates to the caller.
    balance : DiscreteStateSpace
        The episode's controller (tracking errors, and optionally the feedforward, in; volts out).
    swing : SwingUp
    limits : SafetyLimits
        The episode's limits: the balance controller's clamp and the pendulum limit of a catch.
    stop : StopRequest
        Checked every tick.
    pacer : DeadlinePacer, optional
        For a loop-paced backend.
    prepare : callable, optional
        Called once with the settled report when the pendulum has settled (the episode's log
        opening, for a device whose clock runs on regardless); it returns a poll, and the phase
        keeps the balance controller running, under the same limits, until the poll says True:
        the recorded episode then starts at the next tick, with no tick left uncommanded. A
        pendulum lost meanwhile fails the phase. Without it the phase returns at once.

    Returns
    -------
    SwingUpReport
        With ``prepare``, a settled report is the one ``prepare`` was given (its duration and
        largest values up to the settling; the ticks waited for the poll follow it).
    """
    period = backend.sample_period
    sup = swing.limits
    energy = swing.energy
    max_ticks = max(1, round(sup.time_limit / period))
    settle_ticks = max(1, round(swing.settle_time / period))
    hold_ticks = round(swing.catch_hold / period)
    pole = 1.0 / (1.0 + swing.rate_filter * period)
    gain = swing.rate_filter * pole
    theta_prev = alpha_prev = 0.0
    theta_dot = alpha_dot = 0.0
    catching = False
    output = update = None
    n_catches = 0
    catch_k: int | None = None
    still = 0
    max_theta = max_volts = 0.0
    arm_within = False  # the arm limit applies once the arm has been within it
    settled: SwingUpReport | None = None  # given to prepare; then waiting for ready()
    ready: Callable[[], bool] | None = None
    started = False  # a tick within it has run (the rate estimates' first)
    if pacer is not None:
        pacer.start()

    def report(outcome: str, reason: str, k: int) -> SwingUpReport:
        return SwingUpReport(
            outcome,
            reason,
            k * period,
            None if catch_k is None else catch_k * period,
            n_catches,
            max_theta,
            max_volts,
        )

    for k in range(max_ticks + 1):
        if pacer is not None and k:
            pacer.wait(k)
        theta, alpha_raw = backend.read()
        alpha = wrap_angle(alpha_raw) if math.isfinite(alpha_raw) else alpha_raw
        if stop.requested:
            backend.write(0.0)
            return report("stopped", f"{stop.reason} during the swing-up", k)
        arm_within = arm_within or abs(theta) <= sup.arm_limit
        violation = sup.violation(theta if arm_within or not math.isfinite(theta) else 0.0, alpha)
        if violation is not None:
            backend.write(0.0)
            return report("failed", violation, k)
        if k == max_ticks:
            backend.write(0.0)
            return report("failed", sup.timeout_reason(), k)
        if not arm_within:
            # Past the arm's limit since before the phase: 0 V until the arm is back (its rates
            # are estimated from the first tick within).
            backend.write(0.0)
            continue
        max_theta = max(max_theta, abs(theta))
        if started:
            theta_dot = pole * theta_dot + gain * (theta - theta_prev)
            alpha_dot = pole * alpha_dot + gain * wrap_angle(alpha - alpha_prev)
        theta_prev, alpha_prev = theta, alpha
        started = True
        if catching and abs(alpha) > limits.alpha_limit:
            if settled is not None:
                backend.write(0.0)
                return report(
                    "failed",
                    f"swing-up stopped: the pendulum fell after it settled (|alpha| = "
                    f"{abs(alpha):.3f} rad > {limits.alpha_limit:.3f} rad)",
                    k,
                )
            catching = False  # missed: pump again
            still = 0
        if not catching and abs(alpha) < swing.catch_angle:
            catching = True
            output, update = controller_step(balance)
            for _ in range(hold_ticks):  # the catch's errors held: no step for a derivative
                update(-theta, -alpha, 0.0)
            n_catches += 1
            catch_k = k
            still = 0
        if catching:
            assert output is not None and update is not None
            u, _ = output(-theta, -alpha, 0.0)
            update(-theta, -alpha, 0.0)
            vmax = min(limits.max_voltage, sup.max_voltage)
            still = still + 1 if abs(alpha) < swing.settle_alpha and abs(theta) < swing.settle_theta else 0
            if settled is None and still >= settle_ticks:
                settled = report("settled", "", k + 1)
                ready = prepare(settled) if prepare is not None else None
            if settled is not None and (ready is None or ready()):
                # Settled (and the episode ready): the last command stays applied until the
                # episode's first tick writes its own (one period, as between any two ticks).
                volts = min(max(u, -vmax), vmax)
                backend.write(volts)
                max_volts = max(max_volts, abs(volts))
                if prepare is not None:
                    return settled  # what the log was opened with
                return replace(settled, max_abs_voltage=max_volts)
        else:
            u = energy.voltage(theta, alpha, theta_dot, alpha_dot)
            vmax = sup.max_voltage
        volts = min(max(u, -vmax), vmax) if math.isfinite(u) else 0.0
        backend.write(volts)
        max_volts = max(max_volts, abs(volts))
    raise AssertionError("unreachable: the last tick gives up")  # pragma: no cover
