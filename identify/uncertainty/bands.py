"""Prediction intervals: how far to trust each predicted sample of an episode.

A test episode is predicted from its start for about 19 s; its interval at level ``L`` is, per
sample ``k`` and channel ``c`` (theta, alpha),

    prediction_c(k) +- k_c * sqrt(s_c(k)^2 + q_c * (1 - exp(-h / tau_c))),    h = k - n_delays,

built from three pieces, each measured on data the fit did not use where it can be:

- **Parameter uncertainty, by an episode bootstrap.** ``n_members`` refits on the training
  episodes drawn with replacement (episodes, not samples: a sample's neighbours are not
  independent, an episode of another session is). The statistics are per-episode triangular
  factors, so a resampled fit is one pass that folds each episode's factor, scaled by the
  square root of the times it was drawn (:meth:`~qube_koopman.identify.estimators.regression.Snapshots.repeated`),
  into each member's running total: exactly the fit on the duplicated episodes, with no
  episode lifted or factored twice. Members fit only the rows a re-lifted prediction uses.
  All members predict an episode in one batched simulation; ``s_c(k)`` is their spread
  (standard deviation). The lifting (RBF centres) is the point fit's, not resampled.
- **Offset uncertainty.** With per-episode offsets, each estimate's standard error ``se``
  (:class:`~qube_koopman.identify.models.offsets.OffsetEstimate`) is propagated through the prediction
  linearly: the prediction's sensitivity ``S(k)`` to the offset (one more simulation at the
  offset plus a tenth of an encoder count) adds ``(S(k) se)^2`` to ``s(k)^2``. The prediction is
  nearly affine in the offset (the estimation relies on it too), so this is what drawing the
  offset for every member would give, without the sampling noise of 20 draws. A standard
  error is capped at the plausibility bound, and an estimate beyond the bound (not used)
  counts as one bound of uncertainty: a flat cost widens the band, within what is plausible.
- **Model error, calibrated on held-out training episodes.** The bootstrap sees only how the
  fit varies with the data, not what the lifting cannot represent; on the paper's data that
  is most of the error (the members' spread is about a tenth of the held-out error). The
  training episodes are split into ``n_folds`` groups; each is held out once, predicted by an
  ensemble (point fit and members) fitted on the others exactly as the test episodes are
  (same protocol, offsets, scored samples). From the held-out errors ``e`` and spreads ``s``,
  per channel, ``q_c`` and ``tau_c`` are the Gaussian maximum-likelihood fit of
  ``e ~ N(0, s^2 + q_c (1 - exp(-h / tau_c)))``, and ``k_c`` the ``L`` quantile of
  ``|e| / s_eff`` over every held-out sample, so the pooled held-out coverage is ``L`` whatever
  the shape of the errors' distribution. ``1 - exp(-h / tau)`` is the growth of an AR(1)'s
  prediction variance with the horizon (exact for a first-order loop with white noise); on
  the rig it also absorbs the excitation's schedule (small errors in the first seconds).
  The test set is never looked at.
- **Model error under loops the training never ran, calibrated on the twin's probes.** Held-out
  training episodes ran the training controllers; another controller excites the plant
  differently (a softer arm wanders slowly where the model is least sure), and the error there
  is what matters for transfer. A test episode under such a loop gets ``q_c``, ``tau_c`` and
  ``k_c`` calibrated the same way on the twin's probe episodes (training excitations replayed
  on the twin as the rig's sessions differed: the command delay and the cables' stiffness of
  :func:`~qube_koopman.identify.model_selection.transfer.session_twins`, an episode each in turn,
  :func:`~qube_koopman.identify.model_selection.transfer.twin_probes`),
  predicted by the fit and its members wrapped with each probe's controller
  (:func:`calibrate_on_probes`): per channel, the wider (:func:`widest`) of the calibration on
  probes under the episode's own controller (when its PD gains are known) and that on the
  default probe controllers. The first measures this loop's error on the twin; the second keeps
  a floor for what the twin itself gets wrong under loops the rig never ran, which no data
  measures (with the rig's gains, the twin and the rig give the fit the same held-out error;
  under a soft arm loop the rig's error is twice the calibrated twin's). The session variants
  put the error that depends on the session in the band: on the soft controller's later, slower
  session the band of the search's lifting covered alpha 0.63-0.80 of the time on the one
  calibrated twin, 0.81-0.95 on the variants. It is an estimate from data the fit did not use,
  where the training loop's held-out error is no estimate at all.

A prediction that diverges (non-finite, or beyond :data:`~qube_koopman.identify.metrics.DIVERGED_FACTOR`
times the measured range), or whose bootstrap member diverges, gets an infinite interval from
that sample on, with a :class:`~qube_koopman.identify.metrics.DivergedPrediction` warning: an
unstable refit is a reason not to trust the prediction, not a narrow band.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from qube_koopman.core.files import atomic_path
from qube_koopman.identify.data.trajectory import Trajectory
from qube_koopman.identify.metrics import DivergedPrediction
from qube_koopman.identify.uncertainty.calibration import IntervalCalibration
from qube_koopman.identify.uncertainty.prediction import EpisodePrediction, diverged_from, members_variance

__all__ = ["BandSummary", "PredictionBand", "prediction_band", "summarize_bands"]


@dataclass
class PredictionBand:
    """One episode's prediction and interval over its scored samples.

    Parameters
    ----------
    name : str
        The episode (its log's file name).
    t : ndarray of shape (n,)
        Time of each scored sample from the episode's start (s).
    measured, predicted, lower, upper : ndarray of shape (n, n_states)
        The band is ``lower <= measured <= upper`` at the ``level``; infinite where the
        prediction or a bootstrap member diverged. ``measured`` is NaN for an episode recorded
        under another controller than the one predicted (not scored).
    level : float
    scored : bool
        Whether the measured states belong to the predicted loop.
    diverged_at : int or None
        First sample (of the episode) from which the band is infinite.
    calibrated_loop : bool
        Whether the predicted loop is one the calibration's held-out episodes ran.
    calibration : {"held-out", "twin probes"}
        What the band's model error was calibrated on: held-out training episodes, or (a loop
        the training never ran) the twin's probe episodes under other controllers.
    """

    name: str
    t: np.ndarray
    measured: np.ndarray
    predicted: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    level: float
    scored: bool = True
    diverged_at: int | None = None
    calibrated_loop: bool = True
    calibration: str = "held-out"

    def inside(self) -> np.ndarray:
        """Whether each measured sample is within the band, per channel."""
        with np.errstate(invalid="ignore"):
            return (self.lower <= self.measured) & (self.measured <= self.upper)

    def coverage(self) -> np.ndarray:
        """Share of the samples within the band, per channel."""
        return self.inside().mean(axis=0)

    def mean_half_width(self) -> np.ndarray:
        """Mean half-width per channel (inf when the band is infinite anywhere)."""
        with np.errstate(invalid="ignore"):
            return np.mean((self.upper - self.lower) / 2, axis=0)

    def rms_error(self) -> np.ndarray:
        """RMS of measured minus predicted per channel (inf when the prediction diverged)."""
        with np.errstate(invalid="ignore", over="ignore"):
            rms = np.sqrt(np.mean((self.measured - self.predicted) ** 2, axis=0))
        return np.where(np.isnan(rms) & self.scored, np.inf, rms)

    def save(self, path: str | Path) -> None:
        """Write the arrays to ``path`` (``.npz``: t, measured, predicted, lower, upper, level), whole or not at all."""
        with atomic_path(path) as tmp, open(tmp, "wb") as f:
            np.savez(
                f,
                t=self.t,
                measured=self.measured,
                predicted=self.predicted,
                lower=self.lower,
                upper=self.upper,
                level=np.float64(self.level),
            )


def prediction_band(
    name: str,
    trajectory: Trajectory,
    prediction: EpisodePrediction,
    calibration: IntervalCalibration,
    start: int,
    n_delays: int,
    scored: bool = True,
) -> PredictionBand:
    """The band of one predicted episode over its samples from ``start`` on.

    A diverged prediction, or a diverged member (infinite variance), makes the band infinite
    from there, with a :class:`~qube_koopman.identify.metrics.DivergedPrediction` warning.

    Parameters
    ----------
    name : str
        The episode's name.
    trajectory : Trajectory
        Its measured signals.
    prediction : EpisodePrediction
        From :func:`predict_episodes` (with members).
    calibration : IntervalCalibration
        Fitted.
    start : int
        First scored sample.
    n_delays : int
        The model's delays (horizon = sample - n_delays).
    scored : bool
        Whether the measured states belong to the predicted loop (else stored as NaN).

    Returns
    -------
    PredictionBand
    """
    x, pred = trajectory.x, prediction.prediction
    k = np.arange(start, trajectory.n_samples)
    # A calibration that does not use the members' spread (the filter's band) takes a prediction without them.
    spread = np.zeros_like(pred) if prediction.variance is None and not calibration.uses_spread else None
    half = calibration.half_width((members_variance(prediction) if spread is None else spread)[k], k - n_delays)
    diverged = diverged_from(pred, x, start)
    infinite = ~np.isfinite(half).all(axis=1)
    first_infinite = int(k[np.argmax(infinite)]) if infinite.any() else None
    candidates = [s for s in (diverged, first_infinite) if s is not None]
    at = min(candidates) if candidates else None
    with np.errstate(invalid="ignore"):
        lower, upper = pred[k] - half, pred[k] + half
    if at is not None:
        lower[k >= at], upper[k >= at] = -np.inf, np.inf
        why = "the prediction diverged" if diverged is not None and diverged <= at else "a bootstrap refit diverged"
        dt = trajectory.dt or 0.0
        warnings.warn(
            f"{name}: the prediction interval is infinite from sample {at} ({at * dt:.2f} s): {why}",
            DivergedPrediction,
            stacklevel=2,
        )
    measured = x[k] if scored else np.full_like(pred[k], np.nan)
    t = k * (trajectory.dt or 1.0)
    return PredictionBand(name, t, measured, pred[k].copy(), lower, upper, calibration.level, scored, at)


def _channel_dict(names: Sequence[str], values: np.ndarray) -> dict:
    return {n: float(v) for n, v in zip(names, values)}


class BandSummary:
    """Coverage, mean half-width and RMS error per channel, gathered band by band (no band kept).

    Parameters
    ----------
    names : sequence of str
        The channels' names.
    """

    def __init__(self, names: Sequence[str]) -> None:
        self.names = list(names)
        self.episodes: list[dict] = []
        m = len(self.names)
        self._inside, self._half, self._squared = np.zeros(m), np.zeros(m), np.zeros(m)
        self._worst, self._n, self._infinite, self._elsewhere, self._probed = np.ones(m), 0, 0, 0, 0

    def add(self, band: PredictionBand) -> None:
        """Count one band (an unscored one is left out)."""
        if not band.scored:
            return
        coverage = band.coverage()
        self.episodes.append(
            {
                "log": band.name,
                "coverage": _channel_dict(self.names, coverage),
                "mean_half_width": _channel_dict(self.names, band.mean_half_width()),
                "rms_error": _channel_dict(self.names, band.rms_error()),
                "infinite_from_sample": band.diverged_at,
                "calibrated_loop": band.calibrated_loop,
                "calibration": band.calibration,
            }
        )
        n = len(band.t)
        with np.errstate(invalid="ignore", over="ignore"):
            self._inside += coverage * n
            self._half += np.sum((band.upper - band.lower) / 2, axis=0)
            self._squared += np.sum((band.measured - band.predicted) ** 2, axis=0)
        self._worst = np.minimum(self._worst, coverage)
        self._n += n
        self._infinite += band.diverged_at is not None
        self._elsewhere += not band.calibrated_loop and band.calibration == "held-out"
        self._probed += band.calibration == "twin probes"

    def report(self) -> dict:
        """``pooled`` (``coverage``, ``mean_half_width``, ``rms_error``, ``worst_episode_coverage``,
        ``n_samples``, ``n_infinite``: bands infinite somewhere, ``n_uncalibrated_loop``: bands of a loop
        nothing calibrated, ``n_probe_calibrated``: bands of a loop calibrated on the twin's probes; None
        when no band was scored) and ``episodes`` (one entry per scored band)."""
        if not self._n:
            return {"pooled": None, "episodes": self.episodes}
        with np.errstate(invalid="ignore"):
            rms = np.sqrt(self._squared / self._n)
        return {
            "pooled": {
                "coverage": _channel_dict(self.names, self._inside / self._n),
                "mean_half_width": _channel_dict(self.names, self._half / self._n),
                "rms_error": _channel_dict(self.names, np.where(np.isnan(rms), np.inf, rms)),
                "worst_episode_coverage": _channel_dict(self.names, self._worst),
                "n_samples": self._n,
                "n_infinite": self._infinite,
                "n_uncalibrated_loop": self._elsewhere,
                "n_probe_calibrated": self._probed,
            },
            "episodes": self.episodes,
        }


def summarize_bands(bands: Sequence[PredictionBand], names: Sequence[str]) -> dict:
    """:class:`BandSummary` of ``bands``: coverage, mean half-width and RMS error per channel and episode.

    Parameters
    ----------
    bands : sequence of PredictionBand
    names : sequence of str
        The channels' names.

    Returns
    -------
    dict
        See :meth:`BandSummary.report`.
    """
    summary = BandSummary(names)
    for band in bands:
        summary.add(band)
    return summary.report()
