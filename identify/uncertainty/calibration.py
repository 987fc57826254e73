"""The model error's calibration: ``q_c``, ``tau_c`` and ``k_c`` fitted on held-out training episodes, or
on the twin's probe episodes for loops the training never ran."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from qube_koopman.identify.data.trajectory import Trajectory, as_episodes, select_episodes
from qube_koopman.identify.uncertainty.ensemble import EnsembleFit, FoldEnsemble
from qube_koopman.identify.uncertainty.loops import Loop, consecutive_runs
from qube_koopman.identify.uncertainty.prediction import (
    diverged_from,
    members_variance,
    predict_group_sets,
    predict_groups,
)

__all__ = [
    "CalibrationOptions",
    "IntervalCalibration",
    "REPORTED_HORIZONS",
    "calibrate",
    "calibrate_on_probes",
    "calibrate_on_probe_sets",
    "probe_set_groups",
    "widest",
]


def _growth(horizons: np.ndarray, timescale: float) -> np.ndarray:
    """``1 - exp(-h / tau)`` for positive horizons, 0 at the initial condition."""
    h = np.asarray(horizons, dtype=float)
    return np.where(h > 0, -np.expm1(-np.maximum(h, 0.0) / timescale), 0.0)


def _fit_channel(errors: np.ndarray, variances: np.ndarray, horizons: np.ndarray, level: float):
    """``(q, tau, k)`` of one channel: Gaussian maximum likelihood (in log q, log tau), then the level's quantile."""
    # ndtri: the normal quantile (scipy.stats would add half a second of imports).
    from scipy.optimize import minimize
    from scipy.special import ndtri

    use = np.isfinite(errors) & np.isfinite(variances) & (horizons > 0)
    e2, v, h = errors[use] ** 2, variances[use], horizons[use].astype(float)
    if not np.any(e2 > 0):  # nothing to learn the model error from
        return 0.0, 1.0, float(ndtri(0.5 + level / 2))
    tiny = np.finfo(float).tiny

    @np.errstate(over="ignore", under="ignore")
    def cost(p: np.ndarray) -> tuple[float, np.ndarray]:
        q, tau = np.exp(p)
        decay = np.exp(-h / tau)
        total = np.maximum(v + q * (1.0 - decay), tiny)
        slope = (total - e2) / total**2  # d cost / d total, per sample
        gradient = [np.mean(slope * q * (1.0 - decay)), np.mean(slope * -q * decay * h / tau)]
        return float(np.mean(np.log(total) + e2 / total)), np.array(gradient)

    start = [np.log(np.mean(e2)), np.log(max(float(np.median(h)) / 10, 1.0))]
    best = minimize(cost, start, jac=True, method="L-BFGS-B", bounds=[(None, None), (np.log(1e-3), np.log(1e9))])
    q, tau = float(np.exp(best.x[0])), float(np.exp(best.x[1]))
    s = np.sqrt(v + q * _growth(h, tau))
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(e2 > 0, np.sqrt(e2) / s, 0.0)
    return q, tau, float(np.quantile(ratio, level, method="higher"))


#: Horizons (samples predicted) at which reports give a calibration's half-width (0.2, 2 and 20 s at 500 Hz).
REPORTED_HORIZONS = (100, 1000, 10000)


class IntervalCalibration:
    """The band's half-width ``k_c sqrt(s^2 + q_c (1 - exp(-h / tau_c)))``, fitted on held-out errors.

    Parameters
    ----------
    level : float
        The coverage the factor ``k_c`` gives on the held-out samples.

    Attributes
    ----------
    scale_ : ndarray of shape (n_states,)
        ``q_c``, the model error's variance at long horizons (squared state units).
    timescale_ : ndarray of shape (n_states,)
        ``tau_c`` in samples.
    factor_ : ndarray of shape (n_states,)
        ``k_c``.
    coverage_ : ndarray of shape (n_states,)
        The held-out samples' coverage with these.
    n_samples_ : int
        Held-out samples (per channel) the fit used.
    n_diverged_ : int
        Held-out predictions that diverged (:func:`calibrate`; their samples from there are left out).
    parts_ : tuple of IntervalCalibration
        Set by :func:`widest`: the calibrations whose widest band, at each horizon, this one's is
        (``scale_``, ``timescale_`` and ``factor_`` are then those of the band widest at long horizons,
        for the reports); empty for a calibration fitted on its own.
    """

    parts_: tuple = ()
    #: Its band widens with the bootstrap members' spread: a prediction without members has none to give.
    uses_spread = True

    def __init__(self, level: float = 0.95) -> None:
        self.level = level

    def fit(self, errors: np.ndarray, variances: np.ndarray, horizons: np.ndarray) -> IntervalCalibration:
        """Fit each channel on held-out samples.

        Parameters
        ----------
        errors, variances : ndarray of shape (n, n_states)
            Measured minus predicted, and the members' (and offsets') variance, of each sample.
        horizons : ndarray of shape (n,)
            Steps predicted since the initial condition (``sample - n_delays``).

        Returns
        -------
        self
        """
        errors, variances = np.asarray(errors, dtype=float), np.asarray(variances, dtype=float)
        horizons = np.asarray(horizons)
        fits = np.array(
            [_fit_channel(errors[:, c], variances[:, c], horizons, self.level) for c in range(errors.shape[1])]
        )
        self.scale_, self.timescale_, self.factor_ = fits[:, 0], fits[:, 1], fits[:, 2]
        with np.errstate(invalid="ignore"):
            inside = np.abs(errors) <= self.half_width(variances, horizons)
        self.coverage_ = inside.mean(axis=0) if len(errors) else np.full(errors.shape[1], np.nan)
        self.n_samples_ = len(errors)
        self.n_diverged_ = 0
        return self

    def half_width(self, variances: np.ndarray, horizons: np.ndarray) -> np.ndarray:
        """Half-widths of samples with these variances (..., n_states) at these horizons (...,)."""
        if self.parts_:
            return np.maximum.reduce([part.half_width(variances, horizons) for part in self.parts_])
        h = np.asarray(horizons)
        growth = np.stack([_growth(h, tau) for tau in self.timescale_], axis=-1)
        total = np.asarray(variances, dtype=float) + self.scale_ * growth
        with np.errstate(invalid="ignore"):
            return np.where(np.isnan(total), np.inf, self.factor_ * np.sqrt(total))

    def as_dict(self, names: Sequence[str]) -> dict:
        """Plain data for reports, by channel name.

        ``model_error_half_width``: the band's half-width without refits or offsets (``s = 0``) after
        :data:`REPORTED_HORIZONS` samples predicted. It is what the band is at those horizons, whatever
        the parameters: an error that grows as a random walk over every horizon the calibration saw
        fits ``q`` and ``tau`` both at their largest (the variance ``q h / tau``), a scale of many
        radians and a timescale of weeks that mean nothing alone.
        """
        h = np.array(REPORTED_HORIZONS, dtype=float)
        widths = self.half_width(np.zeros((h.size, len(self.scale_))), h)
        return {
            name: {
                "scale": float(np.sqrt(q)),
                "timescale_samples": float(tau),
                "factor": float(k),
                "held_out_coverage": float(cov),
                "model_error_half_width": {str(n): float(w) for n, w in zip(REPORTED_HORIZONS, widths[:, c])},
            }
            for c, (name, q, tau, k, cov) in enumerate(
                zip(names, self.scale_, self.timescale_, self.factor_, self.coverage_)
            )
        }


@dataclass(frozen=True)
class CalibrationOptions:
    """How a calibration's episodes are predicted and scored, as the test episodes are.

    Parameters
    ----------
    level : float
        The coverage asked for.
    start : int
        First scored sample of each episode (the end of the offsets' window, as the test's).
    offsets : OffsetProtocol, optional
        Estimate each episode's offsets first, as the test episodes'.
    measured : sequence of int, optional
        The fed-back states (for wrapped loops).
    stride : int
        Every ``stride``-th scored sample is used.
    """

    level: float
    start: int = 1
    offsets: Any = None
    measured: Sequence[int] | None = None
    stride: int = 5


def calibrate(
    fit: EnsembleFit,
    trajectories,
    loops: Sequence[Loop],
    options: CalibrationOptions,
    points: dict[int, tuple[Trajectory, np.ndarray]] | None = None,
) -> IntervalCalibration:
    """Calibrate the band on the folds' held-out episodes, predicted as test episodes are.

    Parameters
    ----------
    fit : EnsembleFit
        Its folds' ensembles.
    trajectories : sequence of Trajectory
        The training episodes the fit was made on (a lazy sequence is read a batch at a time).
    loops : sequence of Loop
        The loop predicting each of them.
    options : CalibrationOptions
        The level, the first scored sample, the offsets, the fed-back states and the stride.
    points : dict, optional
        Filled with ``{index: (trajectory, prediction)}`` of the held-out episodes predicted in
        closed loop (not under a ``"plant"`` loop): the prediction by the fold's point fit,
        without offsets. :func:`held_out_figures` takes them instead of predicting again.

    Returns
    -------
    IntervalCalibration
    """
    trajectories = as_episodes(trajectories)
    groups, indices = _held_out_groups(fit.folds, trajectories, loops, options.measured)
    predictions = predict_groups(groups, options.offsets)  # the folds' ensembles together
    if points is not None:
        for idx, (_, trajs), predicted in zip(indices, groups, predictions):
            points.update(
                (j, (t, p.prediction if p.plain is None else p.plain))
                for j, t, p in zip(idx, trajs, predicted)
                if loops[j].kind != "plant"
            )
    return _fit_on_groups(groups, predictions, options)


def _held_out_groups(folds, trajectories, loops: Sequence[Loop], measured) -> tuple[list, list]:
    """(models, held-out episodes) of every fold's runs of one loop, and the episodes' indices."""
    groups, indices = [], []
    for fold in folds:
        held_out = select_episodes(trajectories, fold.validation)
        for run in consecutive_runs([loops[j] for j in fold.validation]):
            loop = loops[fold.validation[run[0]]]
            models = [loop.model(*fold.point, measured)] + [loop.model(*m, measured) for m in fold.members]
            groups.append((models, [held_out[i] for i in run]))
            indices.append([int(fold.validation[i]) for i in run])
    return groups, indices


def _fit_on_groups(groups, predictions, options: CalibrationOptions) -> IntervalCalibration:
    """:func:`calibrate` from its groups' predictions (made together with other groups')."""
    errors, variances, horizons, diverged = [], [], [], 0
    for (models, trajs), predicted in zip(groups, predictions):
        d = models[0].n_delays
        for t, p in zip(trajs, predicted):
            # A diverged held-out prediction says nothing about the size of the errors: left out from there.
            end = diverged_from(p.prediction, t.x, options.start) or t.n_samples
            diverged += end < t.n_samples
            k = np.arange(max(options.start, d + 1), end, options.stride)
            errors.append(t.x[k] - p.prediction[k])
            variances.append(members_variance(p)[k])
            horizons.append(k - d)
    calibration = IntervalCalibration(options.level).fit(
        np.concatenate(errors), np.concatenate(variances), np.concatenate(horizons)
    )
    calibration.n_diverged_ = diverged
    return calibration


def calibrate_on_probes(
    fit: EnsembleFit, probes, options: CalibrationOptions, n_members: int | None = None
) -> IntervalCalibration:
    """Calibrate the band of loops the training never ran on the twin's probe episodes.

    The probes are not training data, so the fit on all the training episodes and its members
    predict them (each wrapped with its probe's controller) as test episodes are predicted, and
    :func:`calibrate` fits the model error of those predictions.

    Parameters
    ----------
    fit : EnsembleFit
        The fit and its bootstrap members.
    probes : ProbeSet
        Twin episodes under probe controllers
        (:func:`~qube_koopman.identify.model_selection.transfer.twin_probes`).
    options : CalibrationOptions
        The level, the first scored sample, the offsets (each probe episode's estimated first, as
        the test episodes'), the fed-back states and the stride.
    n_members : int, optional
        Members predicting the probes (all when None): the spread's size is what the
        calibration needs, as the folds' fewer members give it.

    Returns
    -------
    IntervalCalibration
    """
    return calibrate_on_probe_sets(fit, [probes], options, n_members)[0]


def calibrate_on_probe_sets(
    fit: EnsembleFit, probe_sets: Sequence, options: CalibrationOptions, n_members: int | None = None
) -> list[IntervalCalibration]:
    """:func:`calibrate_on_probes` of several probe sets, one calibration each, their episodes predicted
    in one simulation: a pass's per-sample overhead (numpy's per-call cost, most of a small lifting's
    step) is paid once for all the sets, not once each."""
    estimator = fit.estimator  # a closed-loop fit's plant, or EDMD's model of the plant
    point = (getattr(estimator, "closed_loop_model_", None), getattr(estimator, "plant_model_", estimator.model_))
    members = fit.members if n_members is None else fit.members[:n_members]
    groups = probe_set_groups(probe_sets, point, members, options.measured)
    return [_fit_on_groups(g, p, options) for g, p in zip(groups, predict_group_sets(groups, options.offsets))]


def probe_set_groups(probe_sets: Sequence, point: tuple, members: Sequence, measured=None) -> list[list]:
    """Per probe set, its ``(models, episodes)`` groups: each probe controller's episodes, predicted by the
    fit on all the training episodes (``point``: closed loop, plant) and ``members``, each wrapped in it
    (:func:`~qube_koopman.identify.uncertainty.prediction.predict_group_sets` predicts them)."""
    out = []
    for probes in probe_sets:
        episodes = [episode for group in probes.episodes for episode in group]
        loops = [
            Loop("wrapped", controller) for controller, group in zip(probes.controllers, probes.episodes) for _ in group
        ]
        fold = FoldEnsemble(np.arange(len(episodes)), point, list(members))
        out.append(_held_out_groups([fold], as_episodes(episodes), loops, measured)[0])
    return out


def widest(calibrations: Sequence[IntervalCalibration]) -> IntervalCalibration:
    """Per channel and horizon, the widest of the calibrations' bands.

    A band that grows slowly to a wide limit can be the narrower one over the horizons an episode
    lasts (a timescale of 19 s against 5 s on a 20 s episode), so the band is the widest at each
    horizon, not the one widest at long horizons alone. The reports' numbers (``scale_``,
    ``timescale_``, ``factor_``) are, per channel, those of the band widest at long horizons
    (largest ``k_c sqrt(q_c)``).

    Parameters
    ----------
    calibrations : sequence of IntervalCalibration
        Fitted, of the same level and channels.

    Returns
    -------
    IntervalCalibration
        A new calibration: its half-width the calibrations' largest at each horizon (``parts_``), each
        channel's scale, timescale and factor from the one widest at long horizons (the counts of
        samples and diverged predictions are summed).
    """
    calibrations = list(calibrations)
    width = np.array([c.factor_ * np.sqrt(c.scale_) for c in calibrations])
    pick = np.argmax(width, axis=0)
    out = IntervalCalibration(calibrations[0].level)
    for name in ("scale_", "timescale_", "factor_", "coverage_"):
        values = np.array([getattr(c, name) for c in calibrations])
        setattr(out, name, values[pick, np.arange(values.shape[1])])
    out.n_samples_ = sum(c.n_samples_ for c in calibrations)
    out.n_diverged_ = sum(c.n_diverged_ for c in calibrations)
    out.parts_ = tuple(part for c in calibrations for part in (c.parts_ or (c,)))
    return out
