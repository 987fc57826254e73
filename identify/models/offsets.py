"""Per-episode sensor offsets: estimated from an initial window, applied in prediction.

An encoder's zero can sit a little off the true equilibrium, differently in
each episode: the QUBE's pendulum encoder counts from where it was reset, a few counts (of
3.07 mrad) off upright; in the paper's dataset +0.0025 rad on average, spread about 0.001 rad. A
model identified on other episodes then predicts around the wrong
equilibrium. With a measured channel's offset ``o`` (measured = true + o),
prediction works in true coordinates: the channel's history is shifted by
``-o``, so is the reference the controller compares it with (the tracking
error ``r - y`` is unchanged), and ``o`` is added back to the predicted
output.

Offsets are estimated per episode from its first ``window`` samples by
simulation-error least squares: the model predicts the window from its
initial condition for trial offsets, and a Levenberg-Marquardt solve
(``scipy.optimize.least_squares``) minimizes the squared difference between
the measured and predicted states, each channel's residual divided by that
channel's spread (standard deviation) over the window. One parameter per
chosen channel; each residual evaluation is one batched prediction of the
window, the Jacobian's finite differences one more (all perturbations in one
batch).

Why the weighting: the cost is then the window's share of the score the
predictions are judged by (R^2 averaged over channels normalizes each
channel's squared error by its variance), and no channel outweighs another
because it moves more. Unweighted, both angles in rad, the arm angle, which
under a soft arm controller moves ten times more than the pendulum in the
window and carries the model's own arm errors (friction), sets the pendulum's
offset. On eight whole twin episodes under ``soft-theta`` with known encoder
zeros and a 1 s window, the error was measured at rms 0.80 encoder counts
unweighted and 0.57 weighted (tests/identify/test_transfer.py, on 12 s of each: 0.75
and 0.52). Both come out low (bias -0.78
and -0.54 counts) because the twin's arm friction, which a linear lifting
lacks, stops the arm short of where the offset would put it; on the
frictionless twin both are unbiased (+0.07 counts, rms 0.19), and a 2 s
window shrinks the friction bias to -0.19 counts.

Each estimate carries its standard error (from the Gauss-Newton curvature and
the residual left), so a flat cost (an offset the window cannot see) is said
aloud, like an estimate beyond the plausibility bound.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, replace
from typing import Mapping, Sequence

import numpy as np

from qube_koopman.identify.data.trajectory import Trajectory

__all__ = [
    "OffsetEstimate",
    "OffsetWarning",
    "estimate_offsets",
    "estimate_offsets_many",
    "estimate_offsets_models",
    "predict_with_offsets_many",
    "predict_with_offsets_models",
    "shift_trajectory",
    "predict_with_offsets",
    "predict_estimating_offsets",
    "resolve_channels",
    "channel_scales",
    "DEFAULT_BOUND",
    "SPREAD_FLOOR",
]

#: Largest plausible offset (rad) by default: 16 encoder counts of the QUBE; the dataset's are ~1.
DEFAULT_BOUND = 0.05
# Finite-difference step of the Jacobian (rad): a tenth of an encoder count, far above rounding.
_STEP = 3e-4
# Residual given to a diverged prediction: large and finite, so the solver backs off.
_DIVERGED = 1e3
# The batched Gauss-Newton steps stop once no offset moves more than this (rad): a three-thousandth of
# an encoder count, under a fiftieth of the estimates' standard errors (7e-5 rad and more on the soft
# controller's episodes). The steps shrink about tenfold each (the lifting's curvature, which
# Gauss-Newton leaves out), so what is left is below 1e-7 rad; a tighter stop took twice the steps
# (8 against 4) for digits no prediction or score shows.
_CONVERGED = 1e-6


class OffsetWarning(UserWarning):
    """An estimated offset was implausible and was not used."""


@dataclass(frozen=True)
class OffsetEstimate:
    """Offsets of one episode, estimated from its first ``window`` samples.

    Parameters
    ----------
    channels : tuple of int
        Measured channels with an offset.
    values : ndarray of shape (n_channels,)
        Estimated offsets (measured = true + offset), in the channels' units.
    window : int
        Samples used (from the trajectory's start).
    bound : float
        Plausibility bound on ``|values|``.
    rms_before, rms_after : float
        RMS simulation error over the window without and with the offsets
        (unweighted, in the channels' units).
    std_error : ndarray of shape (n_channels,), optional
        Standard error of each offset: the weighted cost's curvature and the
        residual left (``sigma^2 (J^T J)^-1``). Infinite when the cost is flat.
        It takes the window's residuals as independent, so it sees the encoders'
        noise but neither the model's error over the window nor the residuals'
        correlation: a lower bound (on twin episodes with known zeros the errors
        were 4-32 times it, ``bench/bench_offset_errors.py``).
    """

    channels: tuple[int, ...]
    values: np.ndarray
    window: int
    bound: float
    rms_before: float
    rms_after: float
    std_error: np.ndarray | None = None

    @property
    def plausible(self) -> bool:
        """Whether every offset is within the bound (an implausible estimate is never used)."""
        return bool(np.all(np.abs(self.values) <= self.bound))

    @property
    def flat(self) -> bool:
        """Whether the window hardly determines an offset: a standard error above a quarter of the bound."""
        return self.std_error is not None and bool(np.any(~(self.std_error <= self.bound / 4)))

    @property
    def status(self) -> str:
        """``"ok"``, ``"beyond bound"`` (not used) or ``"flat"`` (used, but poorly determined)."""
        return "beyond bound" if not self.plausible else "flat" if self.flat else "ok"

    def as_dict(self, names: Sequence[str] | None = None) -> dict:
        """Plain data for reports: each offset and its standard error by channel name, the status."""
        names = [str(c) for c in self.channels] if names is None else list(names)
        se = (
            [None] * len(names)
            if self.std_error is None
            else [float(e) if np.isfinite(e) else None for e in self.std_error]
        )
        return {
            **{n: float(v) for n, v in zip(names, self.values)},
            **{f"{n}_std_error": e for n, e in zip(names, se)},
            "plausible": self.plausible,
            "status": self.status,
            "rms_before": self.rms_before,
            "rms_after": self.rms_after,
        }

    def as_mapping(self) -> dict[int, float]:
        """``{channel: offset}``; empty when implausible (then no offset is applied)."""
        return {c: float(v) for c, v in zip(self.channels, self.values)} if self.plausible else {}


def resolve_channels(
    channels: Sequence[int | str], state_names: Sequence[str] | None, n_states: int
) -> tuple[int, ...]:
    """Channel indices from indices or state names (``"alpha"``)."""
    out = []
    for c in channels:
        if isinstance(c, str):
            if state_names is None or c not in state_names:
                raise ValueError(f"unknown channel {c!r}; the states are {', '.join(state_names or ())}")
            c = list(state_names).index(c)
        if isinstance(c, bool) or not isinstance(c, (int, np.integer)) or not 0 <= c < n_states:
            raise ValueError(f"offset channel {c!r} is not a state index in 0..{n_states - 1}")
        out.append(int(c))
    if len(set(out)) != len(out):
        raise ValueError(f"offset channels repeat: {list(channels)}")
    return tuple(out)


def _reference_columns(model, offsets: Mapping[int, float]) -> dict[int, int]:
    """Which reference column is compared with each offset channel (closed-loop models)."""
    if "r" not in model.input_signals:
        return {}
    feedback = list(model.feedback) if model.feedback else list(range(model.n_states))
    return {feedback.index(c): c for c in offsets if c in feedback}


def shift_trajectory(model, trajectory: Trajectory, offsets: Mapping[int, float]) -> Trajectory:
    """The trajectory in true coordinates: offset channels and their references shifted by ``-offset``."""
    if not offsets:
        return trajectory
    o = np.zeros(trajectory.x.shape[1])
    for c, value in offsets.items():
        o[c] = value
    r = trajectory.r
    columns = _reference_columns(model, offsets)
    if columns:
        assert r is not None  # a model whose references follow the states predicts closed-loop data, which has r
        r = r.copy()
        for col, c in columns.items():
            r[:, col] -= o[c]
    return replace(trajectory, x=trajectory.x - o, r=r)


def predict_with_offsets(
    model, trajectory: Trajectory, offsets: Mapping[int, float], relift: bool = True
) -> np.ndarray:
    """Prediction of the measured states with known offsets (see the module docstring).

    Parameters
    ----------
    model, trajectory, relift
        As for :func:`estimate_offsets`.
    offsets : mapping of int to float
        Offset of each measured channel (measured = true + offset).

    Returns
    -------
    ndarray of shape (n_samples, n_measured)
        The predicted measured states, offsets included.
    """
    pred = model.predict(shift_trajectory(model, trajectory, offsets), relift=relift)
    for c, value in offsets.items():
        pred[:, c] += value
    return pred


def _head(trajectory: Trajectory, window: int) -> Trajectory:
    def head(signal: np.ndarray | None) -> np.ndarray | None:
        return None if signal is None else signal[:window]

    t = trajectory
    return replace(t, x=t.x[:window], u=head(t.u), r=head(t.r), f=head(t.f), xc=head(t.xc))


def _controller_state(t: Trajectory) -> np.ndarray:
    assert t.xc is not None  # a model with passthrough states predicts closed-loop data, which has xc
    return t.xc


def _window_predictions(
    model, trajectory: Trajectory, channels, trials: np.ndarray, window: int, relift: bool
) -> np.ndarray:
    """Measured-state predictions of the first ``window`` samples for each row of offsets in ``trials``."""
    return _batch_predictions(model, [_head(trajectory, window)] * len(trials), channels, trials, relift)


def _batch_predictions(model, heads: Sequence[Trajectory], channels, trials: np.ndarray, relift: bool) -> np.ndarray:
    """Predictions of equally long episode heads, ``heads[i]`` with the offsets ``trials[i]``: one batch."""
    d = model.n_delays
    shifted = [shift_trajectory(model, h, dict(zip(channels, row))) for h, row in zip(heads, trials)]
    x_init = np.stack([t.x[: d + 1] for t in shifted])
    v = np.stack([model.inputs_of(t) for t in shifted])
    p0 = np.stack([_controller_state(t)[d] for t in shifted]) if model.n_passthrough else None
    x, _ = model.simulate(x_init, v, p0, relift=relift)
    x[:, :, list(channels)] += np.asarray(trials)[:, None, :]
    return x


def _models_predictions(
    models: Sequence, heads: Sequence[Trajectory], channels, trials: np.ndarray, relift: bool
) -> np.ndarray:
    """:func:`_batch_predictions` of several models (one lifting and structure), each with its own
    offsets ``trials[i]`` (shape (n_models, n_heads, n_channels)): one paired batch, shape
    (n_models, n_heads, n_samples, n_states). One model: :func:`_batch_predictions` itself."""
    from qube_koopman.identify.models.simulate import simulate_chunks

    if len(models) == 1:
        return _batch_predictions(models[0], heads, channels, trials[0], relift)[None]
    ref = models[0]
    d, n_p, m = ref.n_delays, ref.n_passthrough, ref.n_states
    shifted = [
        [shift_trajectory(model, h, dict(zip(channels, row))) for h, row in zip(heads, rows)]
        for model, rows in zip(models, trials)
    ]
    x_init = np.stack([[t.x[: d + 1] for t in ts] for ts in shifted])
    v = np.stack([[model.inputs_of(t) for t in ts] for model, ts in zip(models, shifted)])
    p0 = np.stack([[_controller_state(t)[d] for t in ts] for ts in shifted]) if n_p else None
    T = v.shape[2]
    x = np.full((T, len(models), len(heads), m), np.nan)  # time-major, as the chunks come
    x[: d + 1] = np.moveaxis(x_init, 2, 0)

    def store(k0: int, chunk: np.ndarray, _models: np.ndarray) -> None:  # paired: every model to the end
        x[k0 : k0 + len(chunk)] = chunk[..., n_p:]

    A = np.stack([model.A for model in models])
    B = np.stack([model.B for model in models])
    simulate_chunks(A, B, ref.lifting, n_p, x_init, v, p0, relift, store, paired=True)
    x = np.moveaxis(x, 0, 2)
    x[..., list(channels)] += np.asarray(trials)[:, :, None, :]
    return x


def estimate_offsets(
    model,
    trajectory: Trajectory,
    channels: Sequence[int | str],
    window: int,
    bound: float = DEFAULT_BOUND,
    relift: bool = True,
    weighted: bool = True,
) -> OffsetEstimate:
    """Estimate constant offsets of ``channels`` from the first ``window`` samples.

    Parameters
    ----------
    model : KoopmanModel
        Closed-loop model (inputs r, f) or plant model (input u).
    trajectory : Trajectory
        The episode (measured signals).
    channels : sequence of int or str
        Measured channels with an offset (indices or state names).
    window : int
        Samples from the start used for the estimate; more than the
        model's ``n_delays + 2``.
    bound : float
        Plausibility bound; :attr:`OffsetEstimate.plausible` says whether it holds.
    relift : bool
        As in prediction.
    weighted : bool
        Divide each channel's residual by its spread over the window (see the
        module docstring); False: the unweighted cost, kept for comparison.

    Returns
    -------
    OffsetEstimate
    """
    from scipy.optimize import least_squares

    channels = resolve_channels(channels, trajectory.state_names, trajectory.x.shape[1])
    d = model.n_delays
    window = int(window)
    if not d + 3 <= window <= trajectory.n_samples:
        raise ValueError(
            f"trajectory {trajectory.name!r}: the estimation window must hold between {d + 3} "
            f"and {trajectory.n_samples} samples, got {window}"
        )
    if not (np.isfinite(bound) and bound > 0):
        raise ValueError(f"the offset bound must be positive, got {bound!r}")
    truth = trajectory.x[d + 1 : window]
    scale = channel_scales(truth) if weighted else np.ones(truth.shape[1])
    k = len(channels)
    trials_of = lambda o: np.vstack([o, o + _STEP * np.eye(k)])  # noqa: E731 (one line, used twice)

    def residuals(pred: np.ndarray) -> np.ndarray:
        res = ((truth - pred[..., d + 1 :, :]) * scale).reshape(pred.shape[0], -1)
        return np.where(np.isfinite(res), res, _DIVERGED)

    def fun(o):
        return residuals(_window_predictions(model, trajectory, channels, o[None], window, relift))[0]

    def jac(o):
        res = residuals(_window_predictions(model, trajectory, channels, trials_of(o), window, relift))
        return ((res[1:] - res[0]) / _STEP).T

    start = np.zeros(k)
    before = fun(start)
    fit = least_squares(fun, start, jac=jac, method="lm", xtol=1e-10, ftol=1e-12, max_nfev=50)
    raw_rms = lambda r: _raw_rms(r.reshape(-1, scale.size), scale)  # noqa: E731
    return OffsetEstimate(
        channels,
        np.asarray(fit.x, dtype=float),
        window,
        float(bound),
        raw_rms(before),
        raw_rms(fit.fun),
        _std_error(fit.jac.T, fit.fun),
    )


#: Smallest spread a channel's weight uses (rad): a channel at rest over the window (a tenth
#: of a millirad, 0.03 encoder counts) must not take all the weight.
SPREAD_FLOOR = 1e-4


def channel_scales(truth: np.ndarray) -> np.ndarray:
    """Weights of the offset cost: one over each channel's spread over the window.

    Parameters
    ----------
    truth : ndarray of shape (..., n_samples, n_channels)
        Measured states over the window.

    Returns
    -------
    ndarray of shape (..., n_channels)
        ``1 / max(std, SPREAD_FLOOR)`` per channel.
    """
    return 1.0 / np.maximum(np.std(truth, axis=-2), SPREAD_FLOOR)


def _raw_rms(weighted: np.ndarray, scale: np.ndarray) -> float:
    """RMS in the channels' units of residuals weighted by ``scale`` (rows: samples)."""
    return float(np.sqrt(np.mean((weighted / scale) ** 2)))


def _std_error(J: np.ndarray, res: np.ndarray) -> np.ndarray:
    """Standard errors of least-squares parameters: J (n_params, n_residuals), res at the optimum."""
    k = J.shape[0]
    sigma2 = float(res @ res) / max(res.size - k, 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        try:
            cov = sigma2 * np.linalg.inv(J @ J.T)
        except np.linalg.LinAlgError:
            return np.full(k, np.inf)
    se = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    return np.where(np.isfinite(se), se, np.inf)


def predict_with_offsets_many(
    model, trajectories: Sequence[Trajectory], estimates: Sequence[OffsetEstimate], relift: bool = True
) -> list[np.ndarray]:
    """:func:`predict_with_offsets` for many episodes, batched by length (implausible estimates unused).

    Parameters
    ----------
    model : KoopmanModel
        Closed-loop model (inputs r, f) or plant model (input u).
    trajectories : sequence of Trajectory
        The episodes.
    estimates : sequence of OffsetEstimate
        Each episode's offsets (:func:`estimate_offsets_many`).
    relift : bool
        As in prediction.

    Returns
    -------
    list of ndarray
        Each episode's predicted measured states.
    """
    return predict_with_offsets_models([model], trajectories, [estimates], relift)[0]


def predict_with_offsets_models(
    models: Sequence,
    trajectories: Sequence[Trajectory],
    estimates: Sequence[Sequence[OffsetEstimate]],
    relift: bool = True,
) -> list[list[np.ndarray]]:
    """:func:`predict_with_offsets_many` of several models (one lifting and structure) on the same episodes,
    each with its own estimates (``estimates[i]``: model ``i``'s, per episode): one paired batch per length.

    Returns
    -------
    list of list of ndarray
        Per model, each episode's predicted measured states.
    """
    models = list(models)
    out: list[dict[int, np.ndarray]] = [{} for _ in models]
    by_length: dict[int, list[int]] = {}
    for i, t in enumerate(trajectories):
        by_length.setdefault(t.n_samples, []).append(i)
    for group in by_length.values():
        e0 = estimates[0][group[0]]
        trials = np.array(
            [[e[i].values if e[i].plausible else np.zeros(len(e0.channels)) for i in group] for e in estimates]
        )
        pred = _models_predictions(models, [trajectories[i] for i in group], e0.channels, trials, relift)
        for g in range(len(models)):
            for row, i in enumerate(group):
                out[g][i] = pred[g, row]
    return [[found[i] for i in range(len(trajectories))] for found in out]


def estimate_offsets_many(
    model,
    trajectories: Sequence[Trajectory],
    channels: Sequence[int | str],
    window: int,
    bound: float = DEFAULT_BOUND,
    relift: bool = True,
    iterations: int = 8,
    weighted: bool = True,
) -> list[OffsetEstimate]:
    """:func:`estimate_offsets` for many episodes at once, by Gauss-Newton steps batched over them.

    The problem per episode is the same (the window's simulation error in a
    few offsets); each Gauss-Newton step predicts every episode's window at
    its current offsets and at the finite-difference perturbations in one
    batched simulation, which is what makes cross-validation with offsets
    affordable. The residual is nearly affine in the offsets, so a few steps
    reach the Levenberg-Marquardt solution (tests compare the two).

    Parameters
    ----------
    model, channels, window, bound, relift, weighted
        As for :func:`estimate_offsets`.
    trajectories : sequence of Trajectory
        The episodes.
    iterations : int
        Gauss-Newton steps.

    Returns
    -------
    list of OffsetEstimate
        One per episode, in order.
    """
    return estimate_offsets_models([model], trajectories, channels, window, bound, relift, iterations, weighted)[0]


def estimate_offsets_models(
    models: Sequence,
    trajectories: Sequence[Trajectory],
    channels: Sequence[int | str],
    window: int,
    bound: float = DEFAULT_BOUND,
    relift: bool = True,
    iterations: int = 8,
    weighted: bool = True,
) -> list[list[OffsetEstimate]]:
    """:func:`estimate_offsets_many` of several models on the same episodes, their steps batched over the models too.

    A search scores a few alphas' models on each fold's episodes: each Gauss-Newton step
    predicts every (model, episode) pair's window in one paired simulation, where one model at
    a time would pay the simulator's per-sample cost once per model. Each pair's estimate is
    that of :func:`estimate_offsets_many` with its model alone, up to rounding.

    Parameters
    ----------
    models : sequence of KoopmanModel
        Of one lifting and structure (the alphas of one candidate, or their closed loops with one controller).
    trajectories, channels, window, bound, relift, iterations, weighted
        As for :func:`estimate_offsets_many`.

    Returns
    -------
    list of list of OffsetEstimate
        Per model, one per episode in order.
    """
    trajectories = list(trajectories)
    models = list(models)
    if not trajectories:
        return [[] for _ in models]
    channels = resolve_channels(channels, trajectories[0].state_names, trajectories[0].x.shape[1])
    d, k, window = models[0].n_delays, len(channels), int(window)
    if not all(d + 3 <= window <= t.n_samples for t in trajectories):
        raise ValueError(
            f"the estimation window must hold between {d + 3} samples and every episode's length, got {window}"
        )
    heads = [_head(t, window) for t in trajectories]
    truth = np.stack([t.x[d + 1 : window] for t in heads])  # (episodes, samples, states)
    scale = channel_scales(truth) if weighted else np.ones(truth.shape[::2])  # (episodes, states)
    n_models, n_eps = len(models), len(heads)
    values = np.zeros((n_models, n_eps, k))

    def residuals(offsets: np.ndarray) -> np.ndarray:  # (models, episodes, trials, residuals), weighted
        n_trials = offsets.shape[2]
        trials = offsets.reshape(n_models, -1, k)
        pred = _models_predictions(models, [h for h in heads for _ in range(n_trials)], channels, trials, relift)
        res = (truth.repeat(n_trials, axis=0) - pred[:, :, d + 1 :, :]) * scale.repeat(n_trials, axis=0)[:, None]
        return np.where(np.isfinite(res), res, _DIVERGED).reshape(n_models, n_eps, n_trials, -1)

    perturbations = np.concatenate([np.zeros((1, k)), _STEP * np.eye(k)])[None, None]
    before = residuals(values[:, :, None, :])[:, :, 0]
    # Each (model, episode) pair stops at its own first step below _CONVERGED, so that its estimate is
    # the one it gets alone whatever else shares the batch; the batch stops when every pair has.
    moving = np.ones((n_models, n_eps), dtype=bool)
    for _ in range(iterations):
        res = residuals(values[:, :, None, :] + perturbations)
        J = (res[:, :, 1:] - res[:, :, :1]) / _STEP  # (models, episodes, k, residuals)
        step = np.linalg.solve(J @ np.swapaxes(J, -1, -2) + 1e-12 * np.eye(k), -(J @ res[:, :, 0, :, None]))[..., 0]
        values += np.where(moving[..., None], step, 0.0)
        moving &= np.max(np.abs(step), axis=-1) >= _CONVERGED
        if not moving.any():
            break
    res = residuals(values[:, :, None, :] + perturbations)
    after, J = res[:, :, 0], (res[:, :, 1:] - res[:, :, :1]) / _STEP
    n_states = truth.shape[-1]
    return [
        [
            OffsetEstimate(
                channels,
                values[g, i].copy(),
                window,
                float(bound),
                _raw_rms(before[g, i].reshape(-1, n_states), scale[i]),
                _raw_rms(after[g, i].reshape(-1, n_states), scale[i]),
                _std_error(J[g, i], after[g, i]),
            )
            for i in range(n_eps)
        ]
        for g in range(n_models)
    ]


def predict_estimating_offsets(
    model,
    trajectory: Trajectory,
    channels: Sequence[int | str],
    window: int,
    bound: float = DEFAULT_BOUND,
    relift: bool = True,
) -> tuple[np.ndarray, OffsetEstimate]:
    """Estimate the offsets from the window, then predict the whole episode with them.

    An implausible estimate (beyond ``bound``) is not used: the prediction
    is then the plain one, with an :class:`OffsetWarning`.
    """
    estimate = estimate_offsets(model, trajectory, channels, window, bound, relift)
    if not estimate.plausible:
        warnings.warn(
            f"trajectory {trajectory.name!r}: estimated offsets {estimate.values.tolist()} exceed "
            f"the plausibility bound {bound:g}; not used",
            OffsetWarning,
            stacklevel=2,
        )
    return predict_with_offsets(model, trajectory, estimate.as_mapping(), relift), estimate
