"""K-step scores: a fit's disturbance model and its test episodes predicted at horizons.

What ``qube-identify --horizon`` runs after a fit: :func:`fit_training_disturbance` estimates the
disturbance model on the training episodes (each entry point's, the best kept), and
:class:`AheadScores` predicts every test episode at each horizon with the measurements up to
each start (:func:`~qube_koopman.identify.models.disturbance.predict_ahead`), scores it as the
free-run prediction is scored (R^2 and RMS error per channel from the first scored sample), and
keeps each episode's predictions for its predictions file (``ahead_<h>``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from fractions import Fraction
from typing import Callable, Mapping, Sequence

import numpy as np

from qube_koopman.identify.data.trajectory import Trajectory
from qube_koopman.identify.models import disturbance as dm
from qube_koopman.identify.models.model import KoopmanModel
from qube_koopman.identify.models.offsets import shift_trajectory

__all__ = ["AheadOptions", "AheadScores", "MAX_EPISODES", "fit_training_disturbance", "horizon_label", "spread"]

#: Training episodes the disturbance model is estimated on, evenly spread: 8 of the paper's 28 give 80,000
#: one-step residuals for R and 1,600 K-step predictions per horizon for the choice of q and entry, at
#: under a third of the cost of all 28.
MAX_EPISODES = 8


def horizon_label(seconds: float) -> str:
    """A horizon's name in files and reports: ``0.1``, ``1`` (seconds, as given)."""
    return f"{seconds:g}"


@dataclass(frozen=True)
class AheadOptions:
    """K-step predictions of a fit (``qube-identify --horizon``).

    Parameters
    ----------
    horizons : tuple of float
        Seconds ahead.
    entry : str
        Where the disturbance enters (:data:`~qube_koopman.identify.models.disturbance.ENTRIES`), or
        ``"auto"``: each is fitted and the one whose filter predicts the training episodes best at
        the horizons is kept (``"none"`` when none beats predicting without a disturbance).
    q : float, optional
        The disturbance's variance per sample, set by hand (``R`` and the gain still estimated).
    pole : float, optional
        The disturbance's pole, set by hand (1: a random walk; below 1: a first-order process).
        Default: each entry's of :data:`~qube_koopman.identify.models.disturbance.POLES` that
        predicts the training episodes best at the horizons.
    """

    horizons: tuple[float, ...] = (0.1, 1.0)
    entry: str = "auto"
    q: float | None = None
    pole: float | None = None

    def __post_init__(self) -> None:
        if not self.horizons or any(not (np.isfinite(h) and h >= 0) for h in self.horizons):
            raise ValueError(f"horizons are seconds, 0 or more, got {self.horizons}")
        if self.entry not in ("auto", "none", *dm.ENTRIES):
            raise ValueError(f"unknown disturbance entry {self.entry!r} (auto, none, {', '.join(dm.ENTRIES)})")
        if self.pole is not None and not (0.0 <= self.pole <= 1.0):
            raise ValueError(f"the disturbance's pole is in [0, 1] (1: a random walk), got {self.pole}")

    def samples(self, dt: float) -> list[int]:
        """The horizons in samples."""
        return [int(round(h / dt)) for h in self.horizons]


def spread(items: list, n: int) -> list:
    """At most ``n`` of ``items``, evenly spread over them (their sessions, their days), in order."""
    if len(items) <= n:
        return list(items)
    return [items[int(i)] for i in np.linspace(0, len(items) - 1, n).round()]


def _sign_test_count(n: int, level: float = 0.05) -> int:
    """The fewest of ``n`` episodes that must improve for a one-sided sign test to reject chance at ``level``.

    The binomial tail ``P(X >= k)``, ``X ~ B(n, 1/2)``, summed exactly in integers (scipy.stats' ``binom.sf``
    gives the same; importing scipy.stats took 0.3 s of every ``qube-identify --horizon`` run).
    """
    for k in range(n + 1):
        if Fraction(sum(math.comb(n, j) for j in range(k, n + 1)), 2**n) <= Fraction(level):
            return k
    return n + 1


def fit_training_disturbance(
    model: KoopmanModel, train: Sequence[Trajectory], options: AheadOptions, skip: int = 0
) -> tuple[dm.DisturbanceModel | None, dict]:
    """The disturbance model of a fit, from its training episodes, and the report's account of the choice.

    Returns
    -------
    disturbance : DisturbanceModel or None
        None when no entry is supported (better than none on more training episodes than chance
        gives, a one-sided sign test at 5 %) or the options ask for ``"none"``.
    report : dict
        Each entry's K-step cost on the training episodes (without a disturbance: ``"none"``), the
        entry kept and why.
    """
    dt = model.dt if model.dt is not None else train[0].dt
    assert dt is not None, "a model or an episode gives the sample period"
    horizons = [max(1, K) for K in options.samples(dt)]
    if options.entry == "none":
        return None, {"entry": "none", "why": "no disturbance model asked for (--disturbance none)"}
    train = spread(list(train), MAX_EPISODES)
    data = dm.KStepData.of(model, train, horizons, skip)
    none = dm.DisturbanceModel("input", 1.0, 0.0, np.eye(model.n_states), np.zeros(model.n_states))
    per_episode = {"none": dm.prediction_errors(model, data, [none], per_episode=True)[0].sum(axis=(1, 2))}
    fitted: dict[str, dm.DisturbanceModel] = {}
    refused: dict[str, str] = {}
    by_pole: dict[str, dict[str, float]] = {}
    for entry in dm.ENTRIES if options.entry == "auto" else (options.entry,):
        try:
            fitted[entry], per_episode[entry], by_pole[entry] = _best_pole(model, train, entry, options, data)
        except (dm.NotDetectable, ValueError) as exc:
            refused[entry] = str(exc)
    if options.entry != "auto" and options.entry in refused:
        raise ValueError(refused[options.entry])
    costs = {k: float(v.mean()) for k, v in per_episode.items()}
    better = {k: int(np.sum(v < per_episode["none"])) for k, v in per_episode.items() if k != "none"}
    n = len(train)
    # The data support an entry when it predicts better on more training episodes than chance would give
    # (a one-sided sign test at 5 %: 7 of 8, 15 of 20); of those, the lowest cost wins.
    needed = _sign_test_count(n)
    supported = [k for k in better if better[k] >= needed]
    if options.entry == "auto":
        best = min(supported, key=lambda k: costs[k]) if supported else "none"
        why = (
            f"{best} ({_pole_words(fitted[best].pole, dt)}) predicts the training episodes best at "
            f"{', '.join(horizon_label(h) for h in options.horizons)} s, better than none on {better[best]} of {n}"
            if best != "none"
            else f"no entry predicts better than none on {needed} or more of the {n} training episodes"
        )
    else:
        best = options.entry
        why = f"{best} asked for (--disturbance {best}), {_pole_words(fitted[best].pole, dt)}"
    report = {
        "entry": best,
        "criterion": "1 - R^2 of the training episodes' predictions at the scored horizons, summed over horizons "
        "and channels, averaged over episodes (lower is better); an entry is supported when it predicts better "
        f"than none on at least {needed} of the {n} episodes (a one-sided sign test at 5 %)",
        "training_cost": costs,
        "training_cost_by_pole": by_pole,
        "pole_choice": "each entry's pole is the one of "
        + ", ".join(f"{p:g}" for p in (dm.POLES if options.pole is None else (options.pole,)))
        + (" (--disturbance-pole)" if options.pole is not None else "")
        + " whose filter, its q chosen likewise, has the lowest training cost",
        "episodes_better": better,
        "training_episodes": n,
        "refused": refused,
        "why": why,
    }
    if best == "none":
        return None, report
    report["model"] = fitted[best].as_dict()
    return fitted[best], report


def _best_pole(
    model: KoopmanModel, train: Sequence[Trajectory], entry: str, options: AheadOptions, data: dm.KStepData
) -> tuple[dm.DisturbanceModel, np.ndarray, dict[str, float]]:
    """One entry's disturbance model at the pole (:data:`~dm.POLES`, or the one asked for) whose filter predicts the
    training episodes best; its per-episode costs; the cost at each pole."""
    best: tuple[dm.DisturbanceModel, np.ndarray] | None = None
    costs: dict[str, float] = {}
    for pole in dm.POLES if options.pole is None else (options.pole,):
        candidate = dm.fit_disturbance(model, train, entry, q=options.q, pole=pole, data=data)
        per_episode = dm.prediction_errors(model, data, [candidate], per_episode=True)[0].sum(axis=(1, 2))
        costs[f"{pole:g}"] = float(per_episode.mean())
        if best is None or per_episode.mean() < best[1].mean():
            best = (candidate, per_episode)
    assert best is not None
    return best[0], best[1], costs


def _pole_words(pole: float, dt: float) -> str:
    """A pole as the report says it: a random walk, or a first-order process and its time constant."""
    if pole >= 1.0:
        return "a random walk"
    return f"first-order, pole {pole:g}: a time constant of {dt / max(1e-12, -np.log(pole)):.2g} s"


@dataclass
class AheadScores:
    """Test episodes' K-step predictions and scores, added as they stream by.

    ``band``, when given, is the half-width per channel of a loop's predictions ``K`` samples ahead
    (``band(model, K)``, :meth:`~qube_koopman.identify.uncertainty.filter_band.FilterCalibration.ahead_half_width`):
    each episode's predictions then get ``ahead_<h>_lower`` and ``_upper`` and its coverage is scored.
    """

    options: AheadOptions
    disturbance: dm.DisturbanceModel | None
    start: int
    keep: bool = True
    band: Callable[[KoopmanModel, int], np.ndarray] | None = None
    per_horizon: dict[str, list[dict]] = field(default_factory=dict)
    predictions: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)

    def add_many(
        self,
        names: Sequence[str],
        model: KoopmanModel,
        trajectories: Sequence[Trajectory],
        offsets: Sequence[Mapping[int, float] | None],
    ) -> None:
        """Predict and score test episodes of one loop in one batch (``offsets``: each one's sensor offsets by
        channel, measured = true + offset, or None).

        With offsets the model runs in true coordinates, as
        :func:`~qube_koopman.identify.models.offsets.predict_with_offsets` does: the offset channels and
        their references shifted, the offsets added back to the predictions.
        """
        if not trajectories:
            return
        dt = model.dt if model.dt is not None else trajectories[0].dt
        assert dt is not None, "a model or an episode gives the sample period"
        samples = self.options.samples(dt)
        shifts, shifted = [], []
        for t, o in zip(trajectories, offsets):
            shift = np.zeros(t.x.shape[1])
            for c, value in (o or {}).items():
                shift[c] = value
            shifts.append(shift)
            shifted.append(shift_trajectory(model, t, o) if o else t)
        strides = [[dm.starts_stride(t.n_samples, model.n_delays, K, dm.N_STARTS) for K in samples] for t in shifted]
        ahead = dm.predict_ahead_many(model, self.disturbance, shifted, samples, strides)
        for name, t, shift, predicted in zip(names, trajectories, shifts, ahead):
            kept = {}
            for h, K in zip(self.options.horizons, samples):
                pred = predicted[K] + shift[None, :]
                label = horizon_label(h)
                kept[f"ahead_{label}"] = pred
                row = _score(name, t.x, pred, self.start)
                if self.band is not None and K > 0:
                    half = np.asarray(self.band(model, K), dtype=float)
                    kept[f"ahead_{label}_lower"], kept[f"ahead_{label}_upper"] = pred - half, pred + half
                    row.update(_coverage(t.x, pred, half, self.start))
                self.per_horizon.setdefault(label, []).append(row)
            if self.keep:
                self.predictions[name] = kept

    def report(self) -> dict:
        """report.json's ``ahead``: per horizon and channel, the mean and worst R^2 and the RMS error."""
        out: dict = {
            "disturbance": None if self.disturbance is None else self.disturbance.as_dict(),
            "horizons": {},
            "note": "each scored sample predicted from the measurements up to h seconds before it (about "
            f"{dm.N_STARTS} starts per episode and horizon), under the known inputs and controller, with the "
            "disturbance filtered from the measurements",
        }
        for label, rows in self.per_horizon.items():
            r2 = np.array([row["r2"] for row in rows])
            rms = np.array([row["rms"] for row in rows])
            out["horizons"][label] = {
                "seconds": float(label),
                "r2_mean": np.nanmean(r2, axis=0).tolist(),
                "r2_worst": np.nanmin(r2, axis=0).tolist(),
                "rms_mean": np.nanmean(rms, axis=0).tolist(),
                "episodes": rows,
            }
            banded = [row for row in rows if "coverage" in row and row["n_samples"]]
            if banded:
                n = np.array([row["n_samples"] for row in banded], dtype=float)[:, None]
                cov = np.array([row["coverage"] for row in banded])
                out["horizons"][label]["band"] = {
                    "coverage": (np.sum(cov * n, axis=0) / n.sum()).tolist(),
                    "worst_episode_coverage": cov.min(axis=0).tolist(),
                    "half_width": banded[0]["half_width"],
                }
        return out


def _coverage(truth: np.ndarray, pred: np.ndarray, half: np.ndarray, start: int) -> dict:
    """The share per channel of the predicted samples from ``start`` on inside ``pred +- half``."""
    truth = np.asarray(truth, dtype=float)
    ok = (np.arange(truth.shape[0]) >= start) & np.all(np.isfinite(pred), axis=1)
    inside = np.abs(truth[ok] - pred[ok]) <= half
    nan = [float("nan")] * truth.shape[1]
    return {"coverage": inside.mean(axis=0).tolist() if np.any(ok) else nan, "half_width": half.tolist()}


def _score(name: str, truth: np.ndarray, pred: np.ndarray, start: int) -> dict:
    """R^2 and RMS error per channel of the predicted samples from ``start`` on."""
    truth = np.asarray(truth, dtype=float)
    rows = np.arange(truth.shape[0]) >= start
    ok = rows & np.all(np.isfinite(pred), axis=1)
    if not np.any(ok):
        nan = [float("nan")] * truth.shape[1]
        return {"log": name, "r2": nan, "rms": nan, "n_samples": 0}
    err = truth[ok] - pred[ok]
    var = truth[rows].var(axis=0)
    r2 = 1.0 - np.mean(err**2, axis=0) / np.where(var > 0, var, np.nan)
    return {
        "log": name,
        "r2": r2.tolist(),
        "rms": np.sqrt(np.mean(err**2, axis=0)).tolist(),
        "n_samples": int(np.sum(ok)),
    }
