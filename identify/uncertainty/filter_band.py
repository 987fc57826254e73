"""Prediction intervals from the disturbance model's Kalman filter: the error variance of a prediction made
with the measurements up to its start, calibrated on held-out training episodes.

The variance
------------
In innovations form the measured channels follow ``y_{k+1} = y_{k+1|k} + eps_{k+1}``, the innovations
``eps`` white with covariance ``S = G P G' + R`` (:func:`~qube_koopman.identify.models.disturbance.steady_state_gain`'s
``P``; ``S = R`` without a disturbance). An innovation moves the lifted state (the newest measurement
is lifted) and the filtered disturbance (by the gain ``L``), and the prediction ``j`` samples later by
``Psi_j = H_j + S_j L'``: ``H_j`` the loop's response to a change of its newest measurement, ``S_j`` its
response to a unit disturbance estimate (``H_0 = I``, ``S_0 = 0``). A prediction ``K`` samples ahead
misses the ``K`` innovations since its start, so its error's covariance is

    V_K = sum_{j=0}^{K-1} Psi_j S Psi_j',    V_1 = S,

the linear innovations form's ``R + sum_{j=1}^{K-1} (C A^j K) R (C A^j K)'``. The free run from the
first window is the prediction with no updates: its error at horizon ``h`` is ``V_h``, growing with the
horizon as the random walk's response accumulates. ``Psi_j`` is taken from the model as its
predictions run (re-lifted, in closed loop: central differences of
:meth:`~qube_koopman.identify.models.model.KoopmanModel.simulate` at the upright equilibrium,
perturbed by one innovation's standard deviation), for :data:`LINEARIZED_STEPS` samples; beyond,
``Psi`` is held at its last value (the loop has settled; a random walk's response stays). The
cumulative sums give every horizon at once: ``O(K n^2)`` once per loop, not per sample.

The band
--------
``prediction +- k_c sqrt(V(h) + q_c (1 - exp(-h / tau_c)))``: the filter's variance in place of the
bootstrap members' spread in :class:`~qube_koopman.identify.uncertainty.calibration.IntervalCalibration`,
``q_c``, ``tau_c`` and ``k_c`` fitted on the training episodes the calibration folds hold out, each
predicted by a fit on the others (:func:`fold_fits`: one refit per fold, no bootstrap members; 3
folds of 12 episodes gave the paper split's bands of 5 folds of 16 to a few thousandths). The
K-step predictions get a factor per horizon and channel, ``k_{c,K}``, the level's quantile of
``|e| / sqrt(V_K)`` over the held-out episodes' K-step predictions.
"""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Callable, Sequence

import numpy as np

from qube_koopman.identify.data.trajectory import as_episodes, select_episodes
from qube_koopman.identify.models import disturbance as dm
from qube_koopman.identify.models.model import KoopmanModel
from qube_koopman.identify.uncertainty.calibration import CalibrationOptions, IntervalCalibration, probe_set_groups
from qube_koopman.identify.uncertainty.ensemble import EnsembleFit, FoldEnsemble, IntervalOptions, episode_folds
from qube_koopman.identify.uncertainty.loops import Loop, consecutive_runs
from qube_koopman.identify.uncertainty.prediction import diverged_from, predict_group_sets, predict_groups

__all__ = [
    "AheadBand",
    "FilterCalibration",
    "FilterVariance",
    "LINEARIZED_STEPS",
    "calibrate_filter",
    "calibrate_filter_on_probes",
    "calibrate_filter_on_probe_sets",
    "filter_variance",
    "fold_fits",
    "innovation_covariance",
    "innovation_responses",
    "residual_model",
]

#: Samples over which the loop's response to an innovation is simulated (2 s at 500 Hz: the QUBE's
#: balancing loops settle within about 1 s); beyond, it is held at its last value.
LINEARIZED_STEPS = 1000
#: Calibration folds and held-out episodes at most (fewer than the bootstrap band's: each fold's refit folds
#: every other episode's statistics again, and each held-out episode is predicted; the few parameters per channel
#: are fitted on thousands of samples either way).
FILTER_FOLDS = 3
FILTER_HELD_OUT = 12
#: Starts per held-out episode of the K-step calibration (the level's quantile of a few thousand ratios).
CALIBRATION_STARTS = 20


def innovation_covariance(model: KoopmanModel, disturbance: dm.DisturbanceModel | None) -> np.ndarray:
    """``S``, the covariance of the filter's one-step innovations: ``G P G' + R`` (``R`` without a disturbance)."""
    if disturbance is None:
        raise ValueError("the filter's variance needs a disturbance model (its R at least)")
    R = np.asarray(disturbance.R, dtype=float)
    if disturbance.q <= 0 or not np.any(disturbance.gain):
        return R
    G = model.C @ dm.disturbance_direction(model, disturbance.entry)
    _, P = dm.steady_state_gain(G, disturbance.pole, disturbance.q, R)
    return R + P * np.outer(G, G)


def innovation_responses(
    model: KoopmanModel, disturbance: dm.DisturbanceModel | None, n_steps: int, relift: bool = True
) -> np.ndarray:
    """``Psi_j``, the prediction's response ``j`` samples later to a unit innovation, for ``j < n_steps``.

    Central differences of the model's simulation at the upright equilibrium (zero history, inputs
    and controller state), re-lifted as its predictions are: the newest measurement moved by one
    innovation's standard deviation (``H_j``), and the disturbance estimate by as much as that
    innovation moves it (``S_j L'``).

    Returns
    -------
    ndarray of shape (n_steps, n_states, n_states)
        ``[j, :, c]``: the measured channels' response to an innovation in channel ``c``.
    """
    n_steps = int(n_steps)
    if n_steps < 1:
        raise ValueError(f"the responses need at least one step, got {n_steps}")
    d, m, n_in = model.n_delays, model.n_states, model.B.shape[1]
    S = np.asarray(disturbance.R, dtype=float) if disturbance is not None else np.eye(m)
    eps = np.sqrt(np.maximum(np.diag(S), 1e-12))
    T = d + n_steps
    x_init = np.zeros((2 * m, d + 1, m))
    for c in range(m):
        x_init[2 * c, d, c], x_init[2 * c + 1, d, c] = eps[c], -eps[c]
    v = np.zeros((2 * m, T, n_in))
    p0 = np.zeros((2 * m, model.n_passthrough)) if model.n_passthrough else None
    x, _ = model.simulate(x_init, v, p0, relift=relift)
    H = np.stack([(x[2 * c, d:] - x[2 * c + 1, d:]) / (2 * eps[c]) for c in range(m)], axis=-1)
    psi = H
    if disturbance is not None and disturbance.q > 0 and np.any(disturbance.gain):
        size = float(np.abs(disturbance.gain) @ eps)  # one innovation's move of the estimate
        forecast = size * disturbance.pole ** np.arange(n_steps)
        xs = np.zeros((2, d + 1, m))
        vv = np.zeros((2, T, n_in))
        p = None if p0 is None else p0[:2]
        signs = np.array([1.0, -1.0])[:, None]
        if disturbance.entry == "input":
            vv[:, d:, -1] = signs * forecast[None, :]
            y, _ = model.simulate(xs, vv, p, relift=relift)
        else:
            y = dm.simulate_with_rate(model, disturbance, xs, vv, p, signs * forecast[None, :], relift)
        response = (y[0, d:] - y[1, d:]) / (2 * size)  # S_j, j = 0 .. n_steps - 1
        psi = H + response[:, :, None] * np.asarray(disturbance.gain, dtype=float)[None, None, :]
    return psi


@dataclasses.dataclass(frozen=True)
class FilterVariance:
    """``V_h`` per channel for every horizon: the cumulative sums of :func:`innovation_responses`.

    Parameters
    ----------
    cumulative : ndarray of shape (n_steps + 1, n_states)
        ``diag V_K`` for ``K = 0 .. n_steps``.
    slope : ndarray of shape (n_states,)
        Its growth per sample beyond ``n_steps`` (the last response's ``diag Psi S Psi'``).
    """

    cumulative: np.ndarray
    slope: np.ndarray

    def __call__(self, horizons: np.ndarray) -> np.ndarray:
        """``diag V_h`` at these horizons (samples; 0 and below: 0), shape ``horizons.shape + (n_states,)``."""
        h = np.maximum(np.asarray(horizons, dtype=int), 0)
        n = self.cumulative.shape[0] - 1
        beyond = np.maximum(h - n, 0)[..., None]
        return self.cumulative[np.minimum(h, n)] + beyond * self.slope


def filter_variance(
    model: KoopmanModel, disturbance: dm.DisturbanceModel | None, n_steps: int = LINEARIZED_STEPS
) -> FilterVariance:
    """The filter's prediction error variance at every horizon (:class:`FilterVariance`).

    ``V_K = sum_{j<K} Psi_j S Psi_j'`` by cumulative sums over ``n_steps`` responses (only the diagonal is
    kept: the band is per channel).
    """
    S = innovation_covariance(model, disturbance)
    psi = innovation_responses(model, disturbance, n_steps)
    terms = np.einsum("jab,bc,jac->ja", psi, S, psi)  # diag(Psi_j S Psi_j')
    with np.errstate(invalid="ignore", over="ignore"):
        cumulative = np.vstack([np.zeros((1, terms.shape[1])), np.cumsum(terms, axis=0)])
    cumulative = np.where(np.isfinite(cumulative), cumulative, np.inf)
    slope = np.where(np.isfinite(terms[-1]), terms[-1], np.inf)
    return FilterVariance(cumulative, slope)


class FilterCalibration(IntervalCalibration):
    """:class:`IntervalCalibration` with the filter's variance ``V(h)`` in place of the members' spread.

    Parameters
    ----------
    level : float
        The coverage the factors give on the held-out samples.
    model_error : bool
        Also fit the model-error term ``q_c (1 - exp(-h / tau_c))`` (Gaussian maximum likelihood, as
        the bootstrap band's); without, the band is ``k_c sqrt(V(h))`` alone.

    Attributes
    ----------
    variance_ : FilterVariance
        Of the loop this calibration's bands are for (:meth:`for_loop` gives another loop's).
    ahead_factors_ : dict of int to ndarray of shape (n_states,)
        ``k_{c,K}`` of the K-step predictions, by horizon in samples.
    ahead_coverage_ : dict of int to ndarray of shape (n_states,)
        Their held-out coverage.
    """

    #: The band needs no bootstrap members: a prediction without them has a zero spread here.
    uses_spread = False
    variance_: FilterVariance
    ahead_factors_: dict[int, np.ndarray]
    ahead_coverage_: dict[int, np.ndarray]

    def __init__(self, level: float = 0.95, model_error: bool = True) -> None:
        super().__init__(level)
        self.model_error = model_error

    def fit_filter(
        self,
        errors: np.ndarray,
        variances: np.ndarray,
        horizons: np.ndarray,
        variance: FilterVariance,
        filter_variances: np.ndarray | None = None,
    ) -> FilterCalibration:
        """Fit on held-out samples: their errors, other variances (offsets'; zeros without) and horizons, with the
        filter's variance ``variance`` of the loop that predicted them (``filter_variances``: each sample's own,
        when they ran several loops; ``variance`` is then the loop the bands are for).

        Returns
        -------
        self
        """
        errors, horizons = np.asarray(errors, dtype=float), np.asarray(horizons)
        self.variance_ = variance
        own = variance(horizons) if filter_variances is None else np.asarray(filter_variances, dtype=float)
        total = np.asarray(variances, dtype=float) + own
        if self.model_error:
            plain = IntervalCalibration(self.level).fit(errors, total, horizons)
            self.scale_, self.timescale_, self.factor_ = plain.scale_, plain.timescale_, plain.factor_
        else:
            with np.errstate(divide="ignore", invalid="ignore"):
                ratio = np.abs(errors) / np.sqrt(total)
            factor = []
            for c in range(errors.shape[1]):
                r = ratio[:, c][np.isfinite(ratio[:, c])]
                factor.append(float(np.quantile(r, self.level, method="higher")) if r.size else np.inf)
            self.scale_, self.timescale_ = np.zeros(errors.shape[1]), np.ones(errors.shape[1])
            self.factor_ = np.array(factor)
        with np.errstate(invalid="ignore"):
            inside = np.abs(errors) <= IntervalCalibration.half_width(self, total, horizons)
        self.coverage_ = inside.mean(axis=0) if len(errors) else np.full(errors.shape[1], np.nan)
        self.n_samples_, self.n_diverged_ = len(errors), 0
        return self

    def for_loop(self, variance: FilterVariance) -> FilterCalibration:
        """The same calibration for a loop with this filter variance (another controller's)."""
        other = copy.copy(self)
        other.variance_ = variance
        return other

    def half_width(self, variances: np.ndarray, horizons: np.ndarray) -> np.ndarray:
        """Half-widths of samples with these other variances (offsets'; ..., n_states) at these horizons."""
        return super().half_width(np.asarray(variances, dtype=float) + self.variance_(horizons), horizons)

    def ahead_half_width(self, K: int) -> np.ndarray:
        """The K-step predictions' half-width per channel (``k_{c,K} sqrt(V_K)``)."""
        return self.ahead_factors_[int(K)] * np.sqrt(self.variance_(np.array(int(K))))

    def as_dict(self, names: Sequence[str]) -> dict:
        """:meth:`IntervalCalibration.as_dict`, with the filter's standard deviation at the reported horizons and
        the K-step factors."""
        from qube_koopman.identify.uncertainty.calibration import REPORTED_HORIZONS

        out = super().as_dict(names)
        sd = np.sqrt(self.variance_(np.array(REPORTED_HORIZONS)))
        for c, name in enumerate(names):
            out[name]["filter_sd"] = {str(n): float(s) for n, s in zip(REPORTED_HORIZONS, sd[:, c])}
            out[name]["ahead_factor"] = {str(K): float(f[c]) for K, f in getattr(self, "ahead_factors_", {}).items()}
            out[name]["ahead_held_out_coverage"] = {
                str(K): float(f[c]) for K, f in getattr(self, "ahead_coverage_", {}).items()
            }
        return out


def fold_fits(
    estimator,
    trajectories,
    options: IntervalOptions,
    controllers=None,
    controller=None,
    measured: Sequence[int] | None = None,
    elsewhere=None,
) -> EnsembleFit:
    """The fit on all the episodes and one refit per calibration fold, in one pass over the episodes.

    :func:`~qube_koopman.identify.uncertainty.ensemble.fit_ensemble` without bootstrap members, each
    fold's point fit alone: at most :data:`FILTER_FOLDS` folds of :data:`FILTER_HELD_OUT` episodes
    (fewer if ``options`` asks), drawn with ``options``' seed.

    Returns
    -------
    EnsembleFit
        With no members; each fold's ``members`` empty.
    """
    from qube_koopman.identify.model_selection.sweep import fitted_models
    from qube_koopman.identify.uncertainty.ensemble import bootstrap_counts, ensemble_statistics

    trajectories = as_episodes(trajectories)
    n = len(trajectories)
    if n < 2:
        raise ValueError(
            f"prediction intervals are calibrated on held-out training episodes: they need at least 2, got {n}"
        )
    rng = np.random.default_rng(options.seed)
    bootstrap_counts(n, options.n_members, rng)  # the same folds as the bootstrap band's (the same draws first)
    splits = episode_folds(
        n, min(options.n_folds, FILTER_FOLDS), rng, min(options.n_calibration_episodes, FILTER_HELD_OUT)
    )
    selections = np.zeros((len(splits), n), dtype=int)
    for i, (train, _) in enumerate(splits):
        selections[i, train] = 1
    setup = estimator.setup_fit(trajectories) if controllers is None else estimator.setup_fit(trajectories, controllers)
    total, selected = ensemble_statistics(estimator, setup, selections, elsewhere)
    rows = estimator.relift_rows(setup)
    partial = setup if rows is None else dataclasses.replace(setup, target_rows=rows)
    models = []
    for snapshots in selected:
        closed, plants = fitted_models(estimator, partial, snapshots, [estimator.alpha], controller, measured)
        models.append((closed[0], plants[0]))
    estimator.finish_fit(setup, total)
    folds = [FoldEnsemble(validation, model, []) for model, (_, validation) in zip(models, splits)]
    return EnsembleFit(estimator, [], folds, np.zeros((0, n), dtype=int))


def calibrate_filter(
    folds: Sequence[FoldEnsemble],
    trajectories,
    loops: Sequence[Loop],
    options: CalibrationOptions,
    disturbance: dm.DisturbanceModel | None,
    model: KoopmanModel,
    ahead: Sequence[int] = (),
    variance_of: Callable[[KoopmanModel], FilterVariance] | None = None,
) -> FilterCalibration:
    """Calibrate the filter's band on the folds' held-out episodes, predicted as test episodes are.

    Parameters
    ----------
    folds : sequence of FoldEnsemble
        Their held-out episodes and point fits (:func:`fold_fits`' ``folds``, or a bootstrap ensemble's).
    trajectories : sequence of Trajectory
        The training episodes.
    loops : sequence of Loop
        The loop predicting each of them.
    options : CalibrationOptions
        The level, first scored sample, offsets, fed-back states and stride (as the bootstrap band's).
    disturbance : DisturbanceModel or None
        The fit's disturbance model (None: the filter of the measured history alone, ``R`` the
        identity; the factors then carry the scale).
    model : KoopmanModel
        The loop whose bands the calibration makes (the fit on all the episodes): its ``V(h)``.
    ahead : sequence of int
        Horizons (samples) of K-step predictions to calibrate (``k_{c,K}``).
    variance_of : callable, optional
        Each group's loop's ``V`` (the twin's probes under other controllers); by default every held-out
        episode's is ``model``'s (the folds' fits differ from it by a few episodes).

    Returns
    -------
    FilterCalibration
    """
    trajectories = as_episodes(trajectories)
    groups = _held_out_groups(folds, trajectories, loops, options)
    return _fit_on_groups(
        groups, predict_groups(groups, options.offsets), options, disturbance, model, ahead, variance_of
    )


def _held_out_groups(folds: Sequence[FoldEnsemble], trajectories, loops: Sequence[Loop], options: CalibrationOptions):
    """Each fold's held-out episodes by consecutive runs of one loop, with the fold's fit wrapped in that loop."""
    groups = []
    for fold in folds:
        held_out = select_episodes(trajectories, fold.validation)
        for run in consecutive_runs([loops[j] for j in fold.validation]):
            loop = loops[fold.validation[run[0]]]
            groups.append(([loop.model(*fold.point, options.measured)], [held_out[i] for i in run]))
    return groups


def _fit_on_groups(
    groups, predictions, options: CalibrationOptions, disturbance, model: KoopmanModel, ahead, variance_of
) -> FilterCalibration:
    """:func:`calibrate_filter` from its groups' predictions (made together with other groups')."""
    variance = filter_variance(model, disturbance) if variance_of is None else variance_of(model)
    errors, others, horizons, own, diverged = [], [], [], [], 0
    for (models, trajs), predicted in zip(groups, predictions):
        d = models[0].n_delays
        for t, p in zip(trajs, predicted):
            end = diverged_from(p.prediction, t.x, options.start) or t.n_samples
            diverged += end < t.n_samples
            k = np.arange(max(options.start, d + 1), end, options.stride)
            errors.append(t.x[k] - p.prediction[k])
            others.append(np.zeros_like(errors[-1]) if p.variance is None else p.variance[k])
            horizons.append(k - d)
            own.append((variance if variance_of is None else variance_of(models[0]))(k - d))
    h = np.concatenate(horizons)
    calibration = FilterCalibration(options.level).fit_filter(
        np.concatenate(errors), np.concatenate(others), h, variance, np.concatenate(own)
    )
    calibration.n_diverged_ = diverged
    calibration.ahead_factors_, calibration.ahead_coverage_ = {}, {}
    for K in [int(K) for K in ahead if int(K) > 0]:
        _calibrate_ahead(calibration, groups, disturbance, K, options)
    return calibration


def calibrate_filter_on_probes(
    point: tuple,
    probes,
    options: CalibrationOptions,
    disturbance: dm.DisturbanceModel,
    model: KoopmanModel,
    variance_of: Callable[[KoopmanModel], FilterVariance],
) -> FilterCalibration:
    """Calibrate the filter's band of loops the training never ran on the twin's probe episodes.

    As :func:`~qube_koopman.identify.uncertainty.calibration.calibrate_on_probes`: the fit on all the
    training episodes (``point``: closed loop, plant) predicts each probe episode wrapped with its probe's
    controller, as test episodes are predicted; each probe loop's samples get that loop's ``V``
    (``variance_of``), and ``model``'s is the calibration's until :meth:`FilterCalibration.for_loop`.
    """
    return calibrate_filter_on_probe_sets(point, [probes], options, disturbance, model, variance_of)[0]


def calibrate_filter_on_probe_sets(
    point: tuple,
    probe_sets: Sequence,
    options: CalibrationOptions,
    disturbance: dm.DisturbanceModel,
    model: KoopmanModel,
    variance_of: Callable[[KoopmanModel], FilterVariance],
) -> list[FilterCalibration]:
    """:func:`calibrate_filter_on_probes` of several probe sets, one calibration each, their episodes
    predicted in one simulation: a pass's per-sample overhead (numpy's per-call cost, most of a small
    lifting's step) is paid once for all the sets, not once each."""
    groups = probe_set_groups(probe_sets, point, [], options.measured)
    return [
        _fit_on_groups(g, p, options, disturbance, model, (), variance_of)
        for g, p in zip(groups, predict_group_sets(groups, options.offsets))
    ]


def _calibrate_ahead(calibration: FilterCalibration, groups, disturbance, K: int, options: CalibrationOptions) -> None:
    """``k_{c,K}``: the level's quantile of ``|e| / sqrt(V_K)`` over the groups' held-out K-step predictions."""
    ratios = []
    sd = np.sqrt(calibration.variance_(np.array(K)))
    for models, trajs in groups:
        strides = [[dm.starts_stride(t.n_samples, models[0].n_delays, K, CALIBRATION_STARTS)] for t in trajs]
        ahead = dm.predict_ahead_many(_relifted_rows(models[0]), disturbance, trajs, [K], strides)
        for t, pred in zip(trajs, ahead):
            rows = np.arange(t.n_samples) >= max(options.start, models[0].n_delays + K)
            ok = rows & np.all(np.isfinite(pred[K]), axis=1)
            ratios.append(np.abs(t.x[ok] - pred[K][ok]) / sd)
    r = np.concatenate(ratios) if ratios else np.zeros((0, sd.size))
    factor = np.array([np.quantile(r[:, c], options.level, method="higher") for c in range(r.shape[1])])
    calibration.ahead_factors_[K] = factor
    calibration.ahead_coverage_[K] = (r <= factor).mean(axis=0)


def _relifted_rows(model: KoopmanModel) -> KoopmanModel:
    """A fold's fit with the rows a re-lifted prediction does not use (left NaN: not fitted) set to zero, so that
    the filter's ``C E`` (a selection of rows) is finite."""
    if np.all(np.isfinite(model.A)) and np.all(np.isfinite(model.B)):
        return model
    return KoopmanModel(
        np.nan_to_num(model.A),
        np.nan_to_num(model.B),
        model.lifting,
        model.input_signals,
        model.n_passthrough,
        model.input_lifting,
        model.dt,
        model.passthrough_names,
        model.feedback,
    )


def residual_model(model: KoopmanModel, trajectories) -> dm.DisturbanceModel:
    """A filter without a disturbance: ``R`` the training episodes' one-step residual covariance, ``q = 0``
    (the band of a fit whose training episodes support no disturbance model)."""
    stacked = []
    for t in as_episodes(trajectories):
        r = dm.one_step_residuals(model, t)[0]
        stacked.append(r[np.all(np.isfinite(r), axis=1)])
    residuals = np.concatenate(stacked)
    if len(residuals) < 10:
        raise ValueError("too few one-step residuals to estimate the filter's innovations")
    return dm.DisturbanceModel("input", 1.0, 0.0, np.atleast_2d(np.cov(residuals.T)), np.zeros(model.n_states))


class AheadBand:
    """The K-step predictions' half-width of any loop: ``k_{c,K} sqrt(V_K)``, ``V`` that loop's (made once each).

    Parameters
    ----------
    calibration : FilterCalibration
        Fitted, with its ``ahead_factors_``.
    disturbance : DisturbanceModel
        The filter the predictions run.
    model : KoopmanModel, optional
        The loop the calibration was made for (its ``variance_`` then reused).
    """

    def __init__(
        self, calibration: FilterCalibration, disturbance: dm.DisturbanceModel, model: KoopmanModel | None = None
    ) -> None:
        self.calibration, self.disturbance = calibration, disturbance
        self._variances: dict[bytes, FilterVariance] = {}
        if model is not None:
            self._variances[self._key(model)] = calibration.variance_

    @staticmethod
    def _key(model: KoopmanModel) -> bytes:
        return np.ascontiguousarray(model.A).tobytes() + np.ascontiguousarray(model.B).tobytes()

    def variance(self, model: KoopmanModel) -> FilterVariance:
        """``V`` of this loop (the calibration's own for its loop)."""
        key = self._key(model)
        if key not in self._variances:
            self._variances[key] = filter_variance(model, self.disturbance)
        return self._variances[key]

    def __call__(self, model: KoopmanModel, K: int) -> np.ndarray:
        return self.calibration.for_loop(self.variance(model)).ahead_half_width(K)
