"""How far to trust a design's predicted figures, and a design that allows for it.

A model file of ``qube-identify`` (with its intervals, the default) holds the plant's episode-bootstrap
refits (the *members*: the fit repeated on the training episodes drawn with replacement) and the
figures of the training episodes its calibration held out, measured and as the fit on the other
episodes predicted them (MODEL_FORMAT.md, ``uncertainty``). From them, for each figure ``F`` of
the design (J, the voltage's RMS and peak, over the predicted excitation):

- **parameter uncertainty**: every member's design plant (:func:`~design.plant.linear_plant`)
  under the designed controller on the same excitations (:func:`member_figures`, one batched
  simulation), as log-ratios ``b_i = log(F_i / F_0)`` to the point plant's ``F_0`` simulated the
  same way;
- **model error**: what the model misses on an episode it was not fitted on (unmodelled
  dynamics, sensor noise, encoder zeros). The held-out episodes ran the training controller, not
  the design, and a design that feeds back harder turns more of that error into voltage; so their
  error's spectra (kept in the model file) are propagated through the designed loop
  (:mod:`~design.error_transfer`): the design's J and voltage RMS *expected* with the error are
  ``F exp(c)``, and each held-out episode's ``e_j = log(measured_j / expected_j)`` under its own
  controller is what the propagation leaves unexplained. The voltage's peak (no mean square) takes
  ``c = 0`` and ``e_j = log(measured_j / predicted_j)``, as J and the voltage's RMS do from a model
  file without the spectra. Their mean ``m`` and standard deviation ``s`` over ``n`` episodes give a
  new episode's as Student-t, ``m + s sqrt(1 + 1/n) T_{n-1}`` (relative errors: they transfer
  between loops better than absolute ones);
- the interval at level ``L``: the central ``L`` quantiles of the mixture over members of
  ``c + b_i + m + s sqrt(1 + 1/n) T_{n-1}``, applied to the predicted figure:
  ``F exp(lower) .. F exp(upper)``.

The interval is for one episode's figure; it is used for the mean over the predicted episodes as
well, since the model's error is mostly shared by the episodes (a bias, not noise that averages out).

:func:`robust_design` chooses, among LQ designs whose voltage weight is the nominal one scaled up,
the one whose worst case over the members' upper bounds of J is lowest, the nominal one when the
others do no better (see the function).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Literal, TypedDict

import numpy as np

from qube_koopman.core.qube import SKIP_SAMPLES, loop_cost
from qube_koopman.daq.excitation import Excitation
from qube_koopman.design.lq import LqDesign, Weights, design_lq
from qube_koopman.design.error_transfer import loop_spectra, propagate_error
from qube_koopman.design.plant import DesignError, LinearPlant, linear_plant
from qube_koopman.identify.models.identified import IdentifiedModel
from qube_koopman.identify.uncertainty.spectra import ErrorSpectra

__all__ = [
    "FIGURES",
    "ModelUncertainty",
    "FigureInterval",
    "model_uncertainty",
    "member_figures",
    "figure_interval",
    "interval_from_logs",
    "RobustChoice",
    "robust_design",
    "NO_MEMBERS",
]

#: The figures an interval is given for (CostPrediction.summary's keys).
FIGURES = ("J", "voltage_rms", "voltage_peak")

#: Why a model file gives no interval.
NO_MEMBERS = (
    "the model file holds no bootstrap plants (identified with --interval 0, with the disturbance filter's band "
    "(--interval-method disturbance, the default with --horizon), by an older version, or an ARX model): identify "
    "it again with qube-identify --interval-method bootstrap for one"
)

#: Held-out episodes needed for the model-error term (its spread has n - 1 degrees of freedom).
MIN_HELD_OUT = 3


@dataclass(frozen=True)
class ModelUncertainty:
    """What a model file says of its own uncertainty.

    Parameters
    ----------
    members : list of LinearPlant
        The design plants of the bootstrap refits.
    held_out : ndarray of shape (n, 2, 3) or None
        Measured and predicted ``[J, voltage RMS, voltage peak]`` of the held-out training episodes.
    spectra : ErrorSpectra or None
        Their prediction error's band spectra (None in a file written before they were kept).
    """

    members: list
    held_out: np.ndarray | None
    spectra: ErrorSpectra | None = None

    def model_error(self) -> np.ndarray | None:
        """Log-ratios measured / predicted of the held-out episodes, (n, 3); None when fewer than 3 are finite."""
        if self.held_out is None:
            return None
        with np.errstate(all="ignore"):
            ratios = np.log(self.held_out[:, 0] / self.held_out[:, 1])
        ratios = ratios[np.all(np.isfinite(ratios), axis=1)]
        return ratios if len(ratios) >= MIN_HELD_OUT else None


def model_uncertainty(model: IdentifiedModel) -> ModelUncertainty | None:
    """The uncertainty a loaded model file holds (:func:`identify.models.model_file.load_model`), or None.

    Parameters
    ----------
    model : IdentifiedModel
        The loaded model file.

    Returns
    -------
    ModelUncertainty or None
        None when the file holds no bootstrap plants.
    """
    members = model.plant_members
    if not members or model.uncertainty is None:
        return None
    held = model.uncertainty.held_out
    held_out, spectra = None, None
    if held is not None and held.n_episodes:
        held_out = np.stack([held.measured, held.predicted], axis=1)
        spectra = held.error_spectra
    return ModelUncertainty([linear_plant(member) for member in members], held_out, spectra)


def member_figures(
    plants: list[LinearPlant], design: LqDesign, excitations: list[Excitation], skip: int = SKIP_SAMPLES
) -> np.ndarray:
    """``[J, voltage RMS, voltage peak]`` of each plant under the design on each excitation, from upright.

    The design plants in closed loop with the design's controller (its state feedback on the
    history of tracking errors, the arm's integral), simulated together: on the history each
    plant needs two rows of its one-step map, so a plant costs a few hundred operations a
    sample, not the closed loop's dense matrices. For a plant of a linear lifting it is
    :func:`~design.predict.predict_cost` of that plant, sample for sample.

    Parameters
    ----------
    plants : list of LinearPlant
        Of one history length.
    design : LqDesign
        The design (its gain).
    excitations : list of Excitation
        References and feedforward (of one length).
    skip : int
        Samples left out at each episode's start.

    Returns
    -------
    ndarray of shape (n_plants, n_episodes, 3)
        Inf where a prediction diverged.
    """
    x, u, r = _member_runs(plants, design, excitations)
    return _run_figures(x, u, r, skip)


def _member_runs(
    plants: list[LinearPlant], design: LqDesign, excitations: list[Excitation]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`member_figures`' simulation: states (P, E, T, m), voltage (P, E, T), references (E, T, m)."""
    m, d = plants[0].n_measured, plants[0].n_delays
    n = m * (d + 1)
    if any(p.n_states != n for p in plants):
        raise DesignError("the plants differ in their history's length")
    dt = plants[0].dt
    integral = design.weights.integral
    gain = np.asarray(design.gain, dtype=float).reshape(-1)
    # Oldest lag first, as the history window is stored: index i is x_{k-d+i}.
    K = gain[:n].reshape(d + 1, m)[::-1].reshape(n)
    K_w = gain[n] if integral else 0.0
    # On the history window stored oldest first: (n, m) of each plant, (n,) of the gain.
    F = np.stack([p.F[:m].reshape(m, d + 1, m)[:, ::-1].reshape(m, n).T for p in plants])  # (P, n, m)
    G = np.stack([p.G[:m, 0] for p in plants])[:, None, :]  # (P, 1, m)
    c = np.stack([p.c[:m] for p in plants])[:, None, :]
    r = np.stack([np.column_stack([e.target_theta, e.target_alpha]) for e in excitations])  # (E, T, m)
    f = np.stack([np.asarray(e.feedforward, dtype=float) for e in excitations])  # (E, T)
    P, E, T = len(plants), len(excitations), r.shape[1]
    x = np.zeros((P, E, T, m))
    err = np.zeros((P, E, T, m))  # the controller's errors; zero before it runs (at rest)
    u = np.zeros((P, E, T))
    w = np.zeros((P, E))
    with np.errstate(all="ignore"):
        for k in range(d, T):
            err[:, :, k] = r[None, :, k] - x[:, :, k]
            u[:, :, k] = err[:, :, k - d : k + 1].reshape(P, E, n) @ K - K_w * w + f[None, :, k]
            if integral:
                w = w + dt * err[:, :, k, 0]
            if k + 1 < T:
                x[:, :, k + 1] = x[:, :, k - d : k + 1].reshape(P, E, n) @ F + G * u[:, :, k, None] + c
    return x, u, r


def _run_figures(x: np.ndarray, u: np.ndarray, r: np.ndarray, skip: int) -> np.ndarray:
    """``[J, voltage RMS, voltage peak]`` (P, E, 3) of :func:`_member_runs`' runs after ``skip`` samples."""
    with np.errstate(all="ignore"):
        J = loop_cost(x[..., 0], r[None, ..., 0], x[..., 1], skip)
        volt = u[:, :, skip:]
        rms = np.sqrt(np.mean(volt**2, axis=-1))
        peak = np.max(np.abs(volt), axis=-1)
    out = np.stack([J, rms, peak], axis=-1)
    return np.where(np.isfinite(out), out, np.inf)


def _pooled(per_episode: np.ndarray) -> np.ndarray:
    """``[J, voltage RMS, voltage peak]`` over the episodes (axis -2), as CostPrediction.summary pools them."""
    return np.stack(
        [
            np.mean(per_episode[..., 0], axis=-1),
            np.sqrt(np.mean(per_episode[..., 1] ** 2, axis=-1)),
            np.max(per_episode[..., 2], axis=-1),
        ],
        axis=-1,
    )


def _mixture_quantiles(shifts: np.ndarray, scale: float, dof: int | None, level: float) -> tuple[float, float]:
    """Central ``level`` quantiles of the equal mixture of ``shifts + scale T_dof``.

    Without ``dof`` the members' own quantiles, outward (the lower one rounded down, the upper up).
    """
    shifts = np.asarray(shifts, dtype=float)
    tail = (1 - level) / 2
    if dof is None or scale == 0:
        return float(np.quantile(shifts, tail, method="lower")), float(np.quantile(shifts, 1 - tail, method="higher"))
    from scipy.optimize import brentq
    from scipy.special import stdtr, stdtrit

    def cdf(v: float) -> float:
        return float(np.mean(stdtr(dof, (v - shifts) / scale)))

    width = scale * float(stdtrit(dof, 1 - tail / 10))
    lo, hi = shifts.min() - width, shifts.max() + width
    return brentq(lambda v: cdf(v) - tail, lo, hi), brentq(lambda v: cdf(v) - (1 - tail), lo, hi)


@dataclass(frozen=True)
class FigureInterval:
    """The predicted figures of a design with their interval.

    Parameters
    ----------
    level : float
        The interval's level.
    predicted : dict
        ``J``, ``voltage_rms``, ``voltage_peak`` as predicted (the point plant).
    lower, upper : dict
        The interval's bounds, by figure.
    n_members : int
        Bootstrap plants.
    n_held_out : int
        Held-out episodes the model-error term came from (0: none, the members alone).
    member_range : dict
        Smallest and largest figure over the members, by figure.
    expected : dict
        The predicted figures with the model's mean error: propagated through the designed loop
        (``propagated``) or as the held-out episodes' mean ratio; the predicted figures without
        held-out episodes.
    propagated : bool
        Whether the held-out error of J and the voltage's RMS was propagated through the designed loop
        (:mod:`~design.error_transfer`) rather than taken as the training controller's ratio.
    median : dict, optional
        The interval's median, by figure (inf when a member diverged). The interval is of the loop's figure
        over the bootstrap plants with the model's error, so neither ``predicted`` (the point plant) nor
        ``expected`` need lie inside it; its median does.
    """

    level: float
    predicted: dict
    lower: dict
    upper: dict
    n_members: int
    n_held_out: int
    member_range: dict
    expected: dict
    propagated: bool = False
    median: dict | None = None

    @property
    def sources(self) -> str:
        """What the interval is made of, in words."""
        members = f"{self.n_members} bootstrap plants"
        if not self.n_held_out:
            return f"{members} alone (too few held-out episodes for the model's error)"
        how = ", propagated through the designed loop" if self.propagated else ""
        return f"{members} and the model's error on {self.n_held_out} held-out training episodes{how}"

    def contains(self, figure: str, value: float) -> bool:
        """Whether ``value`` lies within the interval of ``figure``."""
        return self.lower[figure] <= value <= self.upper[figure]

    def as_dict(self) -> dict:
        """Plain data, for report.json and the controller file's provenance."""
        return {
            "level": self.level,
            "sources": self.sources,
            "n_members": self.n_members,
            "n_held_out": self.n_held_out,
            "propagated": self.propagated,
            **{
                name: {
                    "predicted": self.predicted[name],
                    "expected": self.expected[name],
                    "lower": self.lower[name],
                    "upper": self.upper[name],
                    "median": None if self.median is None else self.median[name],
                    "members": list(self.member_range[name]),
                }
                for name in FIGURES
            },
        }


def figure_interval(
    predicted: dict,
    nominal: np.ndarray,
    members: np.ndarray,
    model_error: np.ndarray | None,
    level: float = 0.95,
    shift: np.ndarray | None = None,
) -> FigureInterval:
    """The interval of each predicted figure from the members' figures and the held-out model error.

    Parameters
    ----------
    predicted : dict
        The design's predicted figures (``J``, ``voltage_rms``, ``voltage_peak``).
    nominal : ndarray of shape (n_episodes, 3)
        The point plant's figures from :func:`member_figures` (the reference of the members' ratios).
    members : ndarray of shape (n_members, n_episodes, 3)
        The members' figures.
    model_error : ndarray of shape (n, 3) or None
        Log-ratios of held-out episodes: measured / predicted (:meth:`ModelUncertainty.model_error`),
        or, for the figures ``shift`` moves, measured / expected
        (:attr:`~design.error_transfer.PropagatedError.residuals`).
    level : float
        The interval's level, in (0, 1).
    shift : ndarray of shape (3,), optional
        ``log(expected / predicted)`` of each figure: the model's error propagated through the
        designed loop (:func:`~design.error_transfer.propagate_error`); zero where none is.

    Returns
    -------
    FigureInterval
        A bound is inf when a member diverged.
    """
    if not 0 < level < 1:
        raise DesignError(f"the interval's level must be between 0 and 1, got {level}")
    base, pooled = _pooled(nominal), _pooled(members)
    with np.errstate(all="ignore"):
        shifts = np.log(pooled / base)
    moved = np.zeros(len(FIGURES)) if shift is None else np.asarray(shift, dtype=float)
    lower, upper, spread, expected, median = {}, {}, {}, {}, {}
    n = 0 if model_error is None else len(model_error)
    for i, name in enumerate(FIGURES):
        spread[name] = (float(np.min(pooled[:, i])), float(np.max(pooled[:, i])))
        centre = moved[i] + (float(np.mean(model_error[:, i])) if n and model_error is not None else 0.0)
        expected[name] = float(predicted[name] * np.exp(centre))
        if not np.all(np.isfinite(shifts[:, i])):
            lower[name], upper[name], median[name] = float(predicted[name]), float("inf"), float("inf")
            continue
        if n and model_error is not None:  # n: the held-out episodes, none without a model error
            e = model_error[:, i]
            scale = float(np.std(e, ddof=1)) * np.sqrt(1 + 1 / n)
            lo, hi = _mixture_quantiles(shifts[:, i] + centre, scale, n - 1, level)
            mid = _mixture_quantiles(shifts[:, i] + centre, scale, n - 1, 0.0)[0]
        else:
            lo, hi = _mixture_quantiles(shifts[:, i] + moved[i], 0.0, None, level)
            mid = float(np.median(shifts[:, i] + moved[i]))
        lower[name], upper[name] = float(predicted[name] * np.exp(lo)), float(predicted[name] * np.exp(hi))
        median[name] = float(predicted[name] * np.exp(mid))
    return FigureInterval(
        level,
        {k: float(predicted[k]) for k in FIGURES},
        lower,
        upper,
        len(members),
        n,
        spread,
        expected,
        propagated=shift is not None,
        median=median,
    )


def _propagated(uncertainty: ModelUncertainty, plant: LinearPlant, design: LqDesign, x, u, r):
    """The held-out error propagated through the design (:func:`~design.error_transfer.propagate_error`) on the
    point plant's runs ``x[0], u[0]`` of :func:`_member_runs`, as ``(model_error, shift)`` for
    :func:`figure_interval`; None when the model file keeps no spectra or too few held-out episodes."""
    model_error = uncertainty.model_error()
    spectra, held_out = uncertainty.spectra, uncertainty.held_out
    if spectra is None or held_out is None or model_error is None or spectra.n_episodes != len(held_out):
        return None
    uu, eu = loop_spectra(x[0, :, :, 0], r[:, :, 0], x[0, :, :, 1], u[0], spectra.edges, spectra.dt, SKIP_SAMPLES)
    figures = _pooled(_run_figures(x[:1], u[:1], r, SKIP_SAMPLES))[0]
    found = propagate_error(spectra, held_out, plant, design.controller, uu, eu, (figures[0], figures[1]))
    residuals = np.column_stack([found.residuals, np.log(held_out[:, 0, 2] / held_out[:, 1, 2])])
    residuals = residuals[np.all(np.isfinite(residuals), axis=1)]
    if len(residuals) < MIN_HELD_OUT or not np.all(np.isfinite(found.shift)):
        return None
    return residuals, np.array([found.shift[0], found.shift[1], 0.0])


def interval_from_logs(
    uncertainty: ModelUncertainty,
    plant: LinearPlant,
    design: LqDesign,
    predicted: dict,
    excitations: list[Excitation],
    level: float = 0.95,
) -> FigureInterval:
    """The design's figure interval: its members simulated on ``excitations`` (:func:`figure_interval`).

    Parameters
    ----------
    uncertainty : ModelUncertainty
        The model file's.
    plant : LinearPlant
        The point plant designed on.
    design : LqDesign
        The design.
    predicted : dict
        Its predicted figures (``CostPrediction.summary()``).
    excitations : list of Excitation
        Those ``predicted`` came from.
    level : float
        The interval's level.

    Returns
    -------
    FigureInterval
    """
    x, u, r = _member_runs([plant] + list(uncertainty.members), design, excitations)
    figures = _run_figures(x, u, r, SKIP_SAMPLES)
    propagated = _propagated(uncertainty, plant, design, x, u, r)
    if propagated is None:
        return figure_interval(predicted, figures[0], figures[1:], uncertainty.model_error(), level)
    model_error, shift = propagated
    return figure_interval(predicted, figures[0], figures[1:], model_error, level, shift)


class RobustCandidate(TypedDict):
    """One voltage-weight scale a robust design tried (:attr:`RobustChoice.candidates`)."""

    scale: float
    worst_upper_J: float
    nominal_J: float
    stable_members: int | None


@dataclass(frozen=True)
class RobustChoice:
    """What :func:`robust_design` weighed.

    Parameters
    ----------
    design : LqDesign
        The chosen design.
    scale : float
        Its voltage weight over the nominal one.
    candidates : list of RobustCandidate
        Per scale tried (a dict): ``scale``, ``worst_upper_J`` (the members' worst J times the model error's
        upper factor; inf when a member is unstable under it), ``nominal_J`` (the point plant's),
        ``stable_members`` (bootstrap plants stable under it; None when not checked: ranked after the
        chosen one).
    """

    design: LqDesign
    scale: float
    candidates: list[RobustCandidate]

    def as_dict(self) -> dict:
        """Plain data, for reports: the chosen scale and, per key, each candidate's value by ``x<scale>``."""
        keys: tuple[Literal["worst_upper_J", "nominal_J", "stable_members"], ...] = (
            "worst_upper_J",
            "nominal_J",
            "stable_members",
        )
        return {
            "r_voltage_scale": self.scale,
            **{key: {f"x{c['scale']:g}": c[key] for c in self.candidates if c[key] is not None} for key in keys},
        }


#: The voltage weight's scalings a robust design tries (a larger weight: gentler gains, more margin).
ROBUST_SCALES = (1.0, 2.0, 4.0)


def robust_design(
    plant: LinearPlant,
    weights: Weights,
    uncertainty: ModelUncertainty,
    excitations: list[Excitation],
    level: float = 0.95,
    scales: tuple[float, ...] = ROBUST_SCALES,
) -> RobustChoice:
    """The LQ design, among the nominal weights with the voltage weight scaled up, best in the worst case.

    Each candidate is designed on the point plant, then scored by the worst, over the bootstrap
    plants, of their J times the upper factor of the model's held-out error at ``level``
    (:func:`figure_interval`'s model-error term, propagated through the candidate's loop when the
    model file keeps the error's spectra); a candidate under which a bootstrap plant's
    closed loop is unstable (spectral radius) or diverges is out. The nominal weights win ties
    (within 1 %).

    Parameters
    ----------
    plant : LinearPlant
        The point plant.
    weights : Weights
        The nominal weights.
    uncertainty : ModelUncertainty
        The model file's.
    excitations : list of Excitation
        The excitations the figures are predicted on.
    level : float
        The level of the model error's upper factor.
    scales : tuple of float
        The voltage weight's factors tried (1: the nominal design).

    Returns
    -------
    RobustChoice
    """
    from qube_koopman.core.lti import spectral_radius
    from qube_koopman.design.predict import closed_loop_matrix

    def upper_factor(model_error: np.ndarray | None, shift: float = 0.0) -> float:
        """``exp`` of the upper quantile of J's model error at ``level`` (1 without one)."""
        if model_error is None:
            return 1.0
        n, e = len(model_error), model_error[:, 0]
        centre = np.array([shift + np.mean(e)])
        _, hi = _mixture_quantiles(centre, float(np.std(e, ddof=1)) * np.sqrt(1 + 1 / n), n - 1, level)
        return float(np.exp(hi))

    candidates: list[RobustCandidate] = []
    designs = []
    for scale in scales:
        design = design_lq(plant, replace(weights, r_voltage=weights.r_voltage * scale))
        x, u, r = _member_runs([plant] + list(uncertainty.members), design, excitations)
        J = np.mean(_run_figures(x, u, r, SKIP_SAMPLES)[..., 0], axis=-1)
        # The model's error under this candidate: propagated through its loop when the file keeps the spectra.
        propagated = _propagated(uncertainty, plant, design, x, u, r)
        factor = (
            upper_factor(uncertainty.model_error())
            if propagated is None
            else upper_factor(propagated[0], float(propagated[1][0]))
        )
        candidates.append(
            {
                "scale": float(scale),
                "worst_upper_J": float(np.max(J[1:]) * factor),
                "nominal_J": float(J[0]),
                "stable_members": None,
            }
        )
        designs.append(design)
    # Best first (the nominal first when within 1 % of the best); a candidate is out when a bootstrap plant's
    # closed loop under it is unstable, checked until one passes (the spectra cost more than the simulations).
    order = sorted(range(len(scales)), key=lambda i: candidates[i]["worst_upper_J"])
    if 0 in order and candidates[0]["worst_upper_J"] <= 1.01 * candidates[order[0]]["worst_upper_J"]:
        order.remove(0)
        order.insert(0, 0)
    for i in order:
        if not np.isfinite(candidates[i]["worst_upper_J"]):
            break
        stable = sum(spectral_radius(closed_loop_matrix(p, designs[i].controller)) < 1 for p in uncertainty.members)
        candidates[i]["stable_members"] = int(stable)
        if stable == len(uncertainty.members):
            return RobustChoice(designs[i], candidates[i]["scale"], candidates)
        candidates[i]["worst_upper_J"] = float("inf")
    raise DesignError(
        "under every candidate design a bootstrap plant's closed loop is unstable or diverges; change the weights"
    )
