"""What a designed controller will do, from the model alone: cost on the rig's excitation, spectrum, margins.

- :func:`predict_loop` and :func:`predict_cost`: the identified plant model in closed loop with the controller
  (``identify.estimators.structure.close_loop``, re-lifted at every step as ``qube-identify`` predicts)
  driven by the rig's excitation of ``qube-run --seed S --episodes N`` (the same references and
  feedforward, from upright), scored after the first second as the twin's logs are:
  ``J = mean((theta - target_theta)^2) + mean(alpha^2)``, tracking and pendulum RMS, the
  voltage's RMS and peak (the model does not clamp it).
- :func:`closed_loop_eigenvalues`: the design plant (:class:`~design.plant.LinearPlant`) wrapped
  with the controller.
- :func:`loop_margins`: the loop broken at the plant input, ``L(z) = K(z) P(z)`` (``P``: voltage
  to angles; ``K``: tracking errors to voltage, so that ``u = -L u`` closes it), its frequency
  response computed by python-control and its margins by ``control.stability_margins``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from qube_koopman.core.qube import SKIP_SAMPLES, loop_cost
from qube_koopman.daq.excitation import Excitation, generate_excitation
from qube_koopman.daq.session import excitation_settings, run_seeds
from qube_koopman.design.plant import LinearPlant
from qube_koopman.identify.models.model import KoopmanModel
from qube_koopman.identify.estimators.structure import close_loop, closed_loop_matrices, plant_input
from qube_koopman.core.lti import DiscreteStateSpace
from qube_koopman.sim.pendulum.physics import SAMPLE_PERIOD

__all__ = [
    "CostPrediction",
    "LoopTrajectories",
    "Margins",
    "rig_excitations",
    "predict_loop",
    "predict_cost",
    "closed_loop_matrix",
    "closed_loop_eigenvalues",
    "loop_response",
    "loop_margins",
    "episode_cost",
]

#: The loop's voltage limit (V): a predicted voltage beyond it would saturate on the rig.
VOLTAGE_LIMIT = 10.0


@dataclass(frozen=True)
class CostPrediction:
    """Per-episode figures of a closed loop, after the first second.

    Parameters
    ----------
    cost : ndarray
        ``J = mean((theta - target_theta)^2) + mean(alpha^2)`` of each episode (rad^2).
    tracking_rms, alpha_rms, voltage_rms, voltage_peak : ndarray
        Of each episode (rad, rad, V, V).
    diverged : int
        Episodes whose prediction went non-finite (their figures are inf).
    """

    cost: np.ndarray
    tracking_rms: np.ndarray
    alpha_rms: np.ndarray
    voltage_rms: np.ndarray
    voltage_peak: np.ndarray
    diverged: int

    def summary(self) -> dict:
        """Means over the episodes (RMS figures pooled as RMS), for reports."""

        def rms(values):
            return float(np.sqrt(np.mean(np.square(values))))

        return {
            "J": float(np.mean(self.cost)),
            "tracking_rms": rms(self.tracking_rms),
            "alpha_rms": rms(self.alpha_rms),
            "voltage_rms": rms(self.voltage_rms),
            "voltage_peak": float(np.max(self.voltage_peak)),
            "diverged": self.diverged,
            "episodes": len(self.cost),
        }


def rig_excitations(seed: int, n_episodes: int, duration: float = 20.0) -> list[Excitation]:
    """The excitations ``qube-run --seed seed --episodes n_episodes --duration duration`` runs."""
    seeds, _ = run_seeds(seed, n_episodes)
    settings = excitation_settings(duration)
    return [generate_excitation((int(a), int(b), int(c)), settings) for a, b, c in seeds]


def episode_cost(theta, target_theta, alpha, voltage, skip: int = SKIP_SAMPLES) -> tuple[float, ...]:
    """``(J, tracking RMS, alpha RMS, voltage RMS, voltage peak)`` of one episode after ``skip`` samples.

    J is :func:`~qube_koopman.core.qube.loop_cost`; all five are inf when a signal is not finite.
    """
    tracking = np.asarray(theta, dtype=float)[skip:] - np.asarray(target_theta, dtype=float)[skip:]
    pendulum = np.asarray(alpha, dtype=float)[skip:]
    voltage = np.asarray(voltage, dtype=float)[skip:]
    if not (np.all(np.isfinite(tracking)) and np.all(np.isfinite(pendulum)) and np.all(np.isfinite(voltage))):
        return (np.inf,) * 5
    return (
        float(loop_cost(theta, target_theta, alpha, skip)),
        float(np.sqrt(np.mean(tracking**2))),
        float(np.sqrt(np.mean(pendulum**2))),
        float(np.sqrt(np.mean(voltage**2))),
        float(np.max(np.abs(voltage), initial=0.0)),
    )


@dataclass(frozen=True)
class LoopTrajectories:
    """The plant model's closed loop on each excitation, from upright: ``(n_episodes, n_samples)`` arrays.

    Attributes
    ----------
    theta, alpha : ndarray
        Predicted angles (rad).
    target_theta : ndarray
        The arm's reference (rad).
    voltage : ndarray
        The voltage the controller asks for, feedforward included (V; not clamped).
    dt : float
        Sample period (s).
    """

    theta: np.ndarray
    alpha: np.ndarray
    target_theta: np.ndarray
    voltage: np.ndarray
    dt: float

    def cost(self, skip: int = SKIP_SAMPLES) -> CostPrediction:
        """The figures of each episode after ``skip`` samples (:func:`episode_cost`)."""
        rows = np.array(
            [
                episode_cost(self.theta[i], self.target_theta[i], self.alpha[i], self.voltage[i], skip)
                for i in range(len(self.theta))
            ]
        )
        return CostPrediction(
            rows[:, 0], rows[:, 1], rows[:, 2], rows[:, 3], rows[:, 4], diverged=int(np.sum(~np.isfinite(rows[:, 0])))
        )


def predict_loop(
    plant: KoopmanModel, controller: DiscreteStateSpace, excitations: list[Excitation]
) -> LoopTrajectories:
    """The plant model under ``controller`` on each excitation, from upright.

    Parameters
    ----------
    plant : KoopmanModel
        The identified plant model (input: the voltage).
    controller : DiscreteStateSpace
        Tracking errors ``r - [theta, alpha]`` in, voltage out (before the feedforward).
    excitations : list of Excitation
        References and feedforward of each episode (all of one length).

    Returns
    -------
    LoopTrajectories
        Non-finite where the prediction diverged.
    """
    loop = close_loop(plant, controller)
    r = np.stack([np.column_stack([e.target_theta, e.target_alpha]) for e in excitations])
    f = np.stack([np.asarray(e.feedforward, dtype=float)[:, None] for e in excitations])
    n_ep, d = len(excitations), plant.n_delays
    with np.errstate(all="ignore"):
        x, xc = loop.simulate(
            np.zeros((n_ep, d + 1, plant.n_states)),
            np.concatenate([r, f], axis=2),
            np.zeros((n_ep, controller.n_states)),
        )
        xc = np.nan_to_num(xc, nan=0.0)  # NaN before the history is full, where the controller is at rest
        u = plant_input(controller, xc, r, x, f)
    return LoopTrajectories(
        x[:, :, 0], x[:, :, 1], r[:, :, 0], u[:, :, 0], float(plant.dt) if plant.dt is not None else SAMPLE_PERIOD
    )


def predict_cost(
    plant: KoopmanModel, controller: DiscreteStateSpace, excitations: list[Excitation], skip: int = SKIP_SAMPLES
) -> CostPrediction:
    """The figures of :func:`predict_loop`'s episodes after ``skip`` samples (:meth:`LoopTrajectories.cost`).

    Parameters
    ----------
    plant : KoopmanModel
        The plant model (input ``u``).
    controller : DiscreteStateSpace
        The controller on the tracking errors.
    excitations : list of Excitation
        The episodes' references and feedforward (:func:`rig_excitations`).
    skip : int
        Samples left out at the start of each episode.

    Returns
    -------
    CostPrediction
    """
    return predict_loop(plant, controller, excitations).cost(skip)


def closed_loop_matrix(plant: LinearPlant, controller: DiscreteStateSpace) -> np.ndarray:
    """State matrix of the design plant in feedback with the controller (state ``[x^c; s]``).

    Parameters
    ----------
    plant : LinearPlant
        The plant on its history.
    controller : DiscreteStateSpace
        The controller on the tracking errors.

    Returns
    -------
    ndarray of shape (n, n)
    """
    C_p = np.eye(plant.n_measured, plant.n_states)
    A_f, _ = closed_loop_matrices(plant.F, plant.G, controller, C_p, 0)
    return A_f


def closed_loop_eigenvalues(plant: LinearPlant, controller: DiscreteStateSpace) -> np.ndarray:
    """Eigenvalues of the design plant in feedback with the controller (state ``[x^c; s]``).

    Parameters
    ----------
    plant, controller
        As for :func:`closed_loop_matrix`.

    Returns
    -------
    ndarray of complex
    """
    return np.linalg.eigvals(closed_loop_matrix(plant, controller))


@dataclass(frozen=True)
class Margins:
    """Margins of the loop broken at the plant input.

    Parameters
    ----------
    gain_increase : float
        The factor by which the loop gain may grow before instability (inf when none).
    gain_decrease : float
        The factor (< 1) to which it may shrink (0 when none; an unstable plant has one).
    phase : float
        The smallest phase margin (degrees; inf without a gain crossing).
    phase_frequency : float
        Where (Hz).
    stability : float
        ``min |1 + L|``: the distance of the Nyquist curve from -1.
    """

    gain_increase: float
    gain_decrease: float
    phase: float
    phase_frequency: float
    stability: float

    def as_dict(self) -> dict:
        """Plain data (dB for the gain margins), for reports and provenance."""

        def db(value):
            return float(20 * np.log10(value)) if 0 < value < np.inf else (float("inf") if value else float("-inf"))

        return {
            "gain_margin_up_db": db(self.gain_increase),
            "gain_margin_down_db": db(self.gain_decrease),
            "phase_margin_deg": float(self.phase),
            "phase_crossover_hz": float(self.phase_frequency),
            "stability_margin": float(self.stability),
        }


def loop_response(plant: LinearPlant, controller: DiscreteStateSpace, omega: np.ndarray) -> np.ndarray:
    """The loop ``L = K(z) P(z)`` broken at the plant input, at ``z = exp(j omega dt)``.

    The plant's (:meth:`~design.plant.LinearPlant.frequency_response`) times the controller's
    (:meth:`~core.lti.DiscreteStateSpace.frequency_response`): the same response as python-control's
    of the two in series.

    Parameters
    ----------
    plant, controller
        As for :func:`closed_loop_matrix`.
    omega : ndarray
        Frequencies (rad/s).

    Returns
    -------
    ndarray of complex, shaped as ``omega``
    """
    omega = np.asarray(omega, dtype=float)
    frequencies = omega.ravel() / (2 * np.pi)
    P = plant.frequency_response(frequencies)
    K = controller.frequency_response(frequencies)
    return (K @ P)[:, 0, 0].reshape(omega.shape)


def loop_margins(plant: LinearPlant, controller: DiscreteStateSpace, n_points: int = 1500) -> Margins:
    """Gain, phase and stability margins at the plant input (python-control, on a dense frequency grid).

    ``control.stability_margins`` finds the crossings inside the grid; a phase crossing exactly at
    the Nyquist frequency (where a discrete loop's response is real) is added by hand, since no
    sign change marks it.

    Parameters
    ----------
    plant, controller
        As for :func:`closed_loop_matrix`: the loop is ``L = K(z) P(z)``.
    n_points : int
        Points of the logarithmic frequency grid, up to the Nyquist frequency.

    Returns
    -------
    Margins
    """
    import control  # lazily: python-control imports matplotlib

    nyquist = np.pi / plant.dt
    omega = np.geomspace(1e-2, nyquist, n_points)
    response = loop_response(plant, controller, omega)
    gm, pm, _, _, wpm, _ = control.stability_margins(control.frd(response, omega, dt=plant.dt), returnall=True)
    gm, pm, wpm = (np.atleast_1d(np.asarray(v, dtype=float)) for v in (gm, pm, wpm))
    at_nyquist = response[-1]
    if at_nyquist.real < 0 and abs(at_nyquist.imag) <= 1e-9 * max(abs(at_nyquist), 1e-300):
        gm = np.append(gm, 1 / abs(at_nyquist.real))
    up, down = gm[gm > 1], gm[(gm < 1) & (gm > 0)]
    i = int(np.argmin(np.abs(pm))) if len(pm) else None
    return Margins(
        float(up.min()) if len(up) else np.inf,
        float(down.max()) if len(down) else 0.0,
        float(pm[i]) if i is not None else np.inf,
        float(wpm[i]) / (2 * np.pi) if i is not None else float("nan"),
        float(np.min(np.abs(1 + response))),
    )
