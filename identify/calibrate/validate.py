"""Judging a calibrated plant on logs it did not see: closed-loop replay and open-loop prediction.

Closed-loop replay: from one second in (after the hand-raising and the
derivative kick, as the paper drops it) each logged episode is rerun with
the simulator, the log's own controller (state taken from the log), its
references and feedforward; the loop is closed on the simulated encoders
only. Each episode's pendulum encoder offset is estimated from its first
scored second in closed loop, as :mod:`qube_koopman.identify.models.offsets` estimates
a model's (:func:`estimate_offset_closed_loop`, the fitted physics held fixed): the
offset whose replay of that second best matches the log. Under a soft arm loop an offset
moves the arm's equilibrium 17.5 times as far, which a second of open-loop segments
(:func:`estimate_offset_many`) hardly sees: on the soft controller's real episodes
the segments' estimates were up to 16 mrad (5 counts) away from the closed loop's, and
the twin's replays scored R^2 0.45 against the logs instead of 0.976.

The replayed loop closes on quantized encoders, so its path depends on
where inside an encoder count the start state lies, which the log cannot
tell: moving the start (or the offset) by a tenth of a count moved an
episode's alpha standard deviation ratio between 0.948 and 0.954 (measured,
paper split). The scores are therefore means over ``n_draws`` replays whose
start angles are drawn uniformly within their encoder count (the first draw
is the measured start itself); with 8 draws the worst episode's spread of
0.0022 leaves its mean uncertain by about 0.0008.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy.signal import savgol_filter

from qube_koopman.core.qube import ALPHA_LIMIT, SKIP_SAMPLES, THETA_LIMIT
from qube_koopman.identify.calibrate import shooting as ms
from qube_koopman.identify.calibrate.fit import ENCODER_SIGMA
from qube_koopman.identify.calibrate.solver import levenberg_marquardt
from qube_koopman.sim.pendulum import CableRelaxation, PendulumParameters, RandomLoad, simulate_closed_loop
from qube_koopman.sim.pendulum.sensor import COUNTS_PER_REV

ENCODER_COUNT = 2 * math.pi / COUNTS_PER_REV  # rad: one count of the rig's encoders

__all__ = [
    "estimate_offset",
    "estimate_offset_many",
    "estimate_offset_closed_loop",
    "COARSE_OFFSETS",
    "OPEN_LOOP_HORIZON",
    "FINE_STEPS",
    "ReplayResult",
    "replay_episodes",
    "open_loop_error",
    "controller_groups",
    "controller_label",
    "per_episode_params",
]


def controller_label(episode) -> str:
    """A short name of an episode's controller: its gains, or its kind and number of states."""
    info = episode.metadata.controller
    if info.gains:
        return ", ".join(f"{k} {v:g}" for k, v in info.gains.items())
    return f"{info.kind} controller, {info.system.A.shape[0]} states"


def controller_groups(episodes: Sequence) -> list[tuple[str, list[int]]]:
    """The episodes grouped by the controller they ran under (and their length), in order of first appearance.

    Two episodes share a group when their controllers are the same system
    (:func:`~qube_koopman.core.lti.same_system`) and they have as many
    samples: :func:`replay_episodes` replays one group at a time.

    Returns
    -------
    list of (str, list of int)
        Each group's label (:func:`controller_label`) and its episodes' indices.
    """
    from qube_koopman.core.lti import same_system

    groups: list[tuple[str, list[int]]] = []
    for i, e in enumerate(episodes):
        for _, members in groups:
            first = episodes[members[0]]
            if same_system(first.controller, e.controller) and len(first) == len(e):
                members.append(i)
                break
        else:
            groups.append((controller_label(e), [i]))
    return groups


def per_episode_params(
    params: PendulumParameters | Sequence[PendulumParameters], n_episodes: int
) -> list[PendulumParameters]:
    """The twin of each of ``n_episodes`` episodes: ``params`` repeated, or checked to be one per episode."""
    if isinstance(params, PendulumParameters):
        return [params] * n_episodes
    each = list(params)
    if len(each) != n_episodes:
        raise ValueError(f"{len(each)} parameter sets for {n_episodes} episodes: give one, or one per episode")
    return each


def per_episode_relaxations(relaxation, n_episodes: int) -> list:
    """The cables' relaxation of each of ``n_episodes`` episodes: ``relaxation`` (a
    :class:`~qube_koopman.sim.pendulum.CableRelaxation`, or None for none) repeated, or checked to be one per
    episode."""
    if relaxation is None or isinstance(relaxation, CableRelaxation):
        return [relaxation] * n_episodes
    each = list(relaxation)
    if len(each) != n_episodes:
        raise ValueError(f"{len(each)} relaxations for {n_episodes} episodes: give one, or one per episode")
    return each


def _rates(y: np.ndarray, dt: float) -> np.ndarray:
    return savgol_filter(np.asarray(y, float), 21, 2, deriv=1, delta=dt, axis=0)


def estimate_offset(
    y: np.ndarray, u: np.ndarray, params: PendulumParameters, dt: float, start: int, window: int, horizon: int = 100
) -> float:
    """One episode's alpha encoder offset (rad) from samples ``start:start + window``.

    Multiple shooting with the physics fixed: the segments' node states and
    the offset are free (:func:`estimate_offset_many` for one episode).
    """
    return float(estimate_offset_many([y], [u], params, dt, start, window, horizon)[0])


def estimate_offset_many(
    ys: Sequence[np.ndarray],
    us: Sequence[np.ndarray],
    params: PendulumParameters,
    dt: float,
    start: int,
    window: int,
    horizon: int = 100,
    max_iter: int = 40,
) -> np.ndarray:
    """Each episode's alpha encoder offset (rad) from its samples ``start:start + window``.

    One least-squares problem over all episodes, solved by the calibration's
    Levenberg-Marquardt (:func:`~qube_koopman.identify.calibrate.solver.levenberg_marquardt`):
    with the physics fixed the episodes share no variable, so the normal matrix is block
    diagonal and each episode's offset is its own problem's minimizer, while every residual
    evaluation simulates all their segments at once (one Python loop over a segment's
    samples, not one per episode).
    """
    cut = start + window + 1
    seg = ms.make_segments([y[:cut] for y in ys], [u[:cut] for u in us], horizon, start, 0, horizon)
    n = len(ys)
    rates = [_rates(y, dt) for y in ys]
    nodes = np.concatenate([seg.y[0], np.stack([rates[e][k] for e, k in zip(seg.episode, seg.start)])], axis=1)
    phys = ms.from_params(params, params)
    offset0 = np.array([np.mean(y[start : start + window, 1]) for y in ys])
    nodes[:, 1] -= offset0[seg.episode]
    z0 = np.concatenate([offset0 / ms.OFFSET_SCALE, nodes.ravel()])

    def fun(z):
        return ms.residuals(np.concatenate([phys, z]), seg, n, params, dt, ENCODER_SIGMA)

    def jac(z, r):
        # The nodes' four columns only: four grouped differences cost no more than the tangents (measured)
        full = ms.jacobian(
            np.concatenate([phys, z]), r, seg, n, params, dt, ENCODER_SIGMA, physics=False, method="differences"
        )
        return full[:, ms.N_PHYSICAL :]

    unbounded = np.full(z0.size, np.inf)
    result = levenberg_marquardt(fun, jac, z0, -unbounded, unbounded, max_iter=max_iter, ftol=1e-10)
    return result.x[:n] * ms.OFFSET_SCALE


#: The open-loop prediction :func:`open_loop_error` makes of each episode by default (s).
OPEN_LOOP_HORIZON = 0.2

#: The offsets (rad) :func:`estimate_offset_closed_loop` tries first: 2 mrad apart (two thirds of an encoder
#: count) up to 40 mrad (13 counts) either side of zero; a plausible zero is a few counts off.
COARSE_OFFSETS = np.linspace(-0.04, 0.04, 41)
#: Then these around the best of them (0.25 mrad apart), a parabola fitted to their costs.
FINE_STEPS = np.linspace(-0.002, 0.002, 17)


def estimate_offset_closed_loop(
    episodes: Sequence,
    params: PendulumParameters | Sequence[PendulumParameters],
    start: int = SKIP_SAMPLES,
    window: int = 500,
) -> np.ndarray:
    """Each episode's alpha encoder offset (rad): the one whose closed-loop replay of samples
    ``start:start + window`` best matches the log.

    The cost is the replay's squared theta and alpha errors over the window, each channel weighted
    by one over its spread there (:func:`~qube_koopman.identify.models.offsets.channel_scales`, as a
    model's estimate weighs them). The replay closes on quantized encoders, so the cost is rough at the scale
    of a tenth of a count, and Gauss-Newton steps on it wandered by a count on the rig's stiff loop
    (measured): instead every episode is replayed at :data:`COARSE_OFFSETS`, then at
    :data:`FINE_STEPS` around the best, all episodes and offsets of a stage in one batch, and the
    offset is the vertex of the parabola fitted by least squares to the fine costs (clipped to the
    fine range), which averages the roughness out.

    On twin logs with known zeros it comes back within 0.4 encoder counts (root mean square 0.13
    under the soft arm gains, 0.06 under the rig's; 24 episodes each), where the open-loop segments
    of :func:`estimate_offset_many` come within 0.1: the closed loop takes some of the window's
    disturbances for offset. But only the closed loop sees the offset where the real plant departs
    from the twin: on the soft controller's real episodes the segments' estimates were up to 5
    counts away, and only the closed loop's made the replays match their logs.

    Parameters
    ----------
    episodes : sequence of daq.episode.Episode
        Of one controller and length (:func:`controller_groups`).
    params : PendulumParameters or sequence of them
        The twin, or one per episode.
    start, window : int
        The window's first sample and its length (samples; at most what the shortest episode holds
        after ``start``).

    Returns
    -------
    ndarray of shape (n_episodes,)
    """
    window = min(int(window), min(len(e) for e in episodes) - start)  # a shorter log: what it holds
    if window < 2:
        raise ValueError(f"the offset window needs 2 samples or more after sample {start} of every episode")
    from qube_koopman.identify.models.offsets import channel_scales

    dt = episodes[0].dt
    ys = [np.asarray(e.states, float) for e in episodes]
    us = [np.asarray(e.plant_input, float) for e in episodes]
    real = np.stack([y[start + 1 : start + window] for y in ys], axis=1)  # (samples, episodes, 2)
    weight = channel_scales(np.moveaxis(real, 1, 0))  # (episodes, 2): a model's estimate weighs them alike
    first = np.stack([np.concatenate([y[start], _rates(y, dt)[start]]) for y in ys])  # (episodes, 4)

    def costs(trials: np.ndarray) -> np.ndarray:  # (n_trials, episodes) offsets -> their costs
        draws = np.broadcast_to(first, (len(trials), *first.shape)).copy()
        draws[..., 1] -= trials
        run = _replay_draws(episodes, us, draws, trials, params, start, start + window)
        res = (real[:, None] - run.measurements[1:]) * weight  # (samples, trials, episodes, 2)
        cost = np.sum(res**2, axis=(0, 3))
        return np.where(np.isfinite(cost), cost, np.inf)

    n = len(ys)
    coarse = np.repeat(COARSE_OFFSETS[:, None], n, axis=1)
    centre = COARSE_OFFSETS[np.argmin(costs(coarse), axis=0)]
    fine = centre + FINE_STEPS[:, None]
    cost = costs(fine)
    offsets = np.empty(n)
    for e in range(n):  # the parabola's vertex; the best fine offset when the fit is not convex
        ok = np.isfinite(cost[:, e])
        a, b, _ = np.polyfit(FINE_STEPS[ok], cost[ok, e], 2) if ok.sum() >= 3 else (0.0, 0.0, 0.0)
        best = FINE_STEPS[np.argmin(cost[:, e])]
        vertex = -b / (2 * a) if a > 0 else best
        offsets[e] = centre[e] + np.clip(vertex, FINE_STEPS[0], FINE_STEPS[-1])
    return offsets


@dataclass(frozen=True)
class ReplayResult:
    """Per-episode closed-loop replay scores (arrays over episodes).

    Attributes
    ----------
    std_ratio : ndarray (n, 3)
        Standard deviation twin / real of theta, alpha, voltage, the mean
        over the replays from start angles within an encoder count.
    balanced : ndarray (n,) of bool
        Every replay stayed within ``|theta| < pi/2`` and ``|alpha| < pi/4``.
    nrmse : ndarray (n,)
        Mean over theta and alpha of RMSE / max|real| (percent), the mean
        over the replays.
    offsets : ndarray (n,)
        The offsets used (rad).
    twin : ndarray (n_steps, n, 3)
        The twin's theta, alpha (measured) and voltage of the replay from the
        measured start; ``real`` the log's.
    twins : ndarray (n_steps, n_draws, n, 3) or None
        Every replay's (``twin`` is the first); :func:`~qube_koopman.identify.calibrate.replay_spectra.band_std_ratios`
        averages the band powers over them.
    """

    std_ratio: np.ndarray
    balanced: np.ndarray
    nrmse: np.ndarray
    offsets: np.ndarray
    twin: np.ndarray
    real: np.ndarray
    twins: np.ndarray | None = None


def replay_episodes(
    episodes: Sequence,
    params: PendulumParameters | Sequence[PendulumParameters],
    start: int = SKIP_SAMPLES,
    offset_window: int = 500,
    n_draws: int = 8,
    seed: int = 0,
    load: RandomLoad | Sequence[RandomLoad | None] | None = None,
    alpha_drift: RandomLoad | None = None,
    relaxation: CableRelaxation | Sequence[CableRelaxation | None] | None = None,
) -> ReplayResult:
    """Closed-loop replay of logged episodes (``daq.episode.Episode``) through ``params``.

    All episodes must share the controller and length. ``params`` is the twin, or one per
    episode (each episode's setup: :meth:`~qube_koopman.sim.pendulum.params_file.PlantFile.params_for`).
    Each episode is replayed ``n_draws`` times from start angles drawn within the encoder
    count they were measured in (seeded by ``seed``; the first draw is the
    measured start): ``std_ratio`` and ``nrmse`` are means over the draws,
    ``balanced`` requires every draw to stay up, ``twin`` is the first draw. Each episode's
    pendulum encoder offset is the closed loop's over its first ``offset_window`` samples from
    ``start`` (:func:`estimate_offset_closed_loop`, without a load).

    ``load``: a random torque on the arm (:class:`~qube_koopman.sim.pendulum.load.RandomLoad`), or
    one per episode (None for none): each replay draws its own load, seeded by ``seed``, so the
    scores are means over ``n_draws`` loads too. None: no load, exactly as before loads existed.
    ``alpha_drift``: instead (or besides), a pendulum encoder zero that drifts as such a process
    (its values in rad): the alternative entry point the calibration's evidence weighs.
    ``relaxation``: the cables' torque that the arm's motion drives
    (:class:`~qube_koopman.sim.pendulum.relaxation.CableRelaxation`), or one per episode (None for
    none), the same in every draw. None: none.
    """
    if n_draws < 1:
        raise ValueError(f"n_draws must be at least 1, got {n_draws}")
    dt = episodes[0].dt
    ys = [np.asarray(e.states, float) for e in episodes]
    us = [np.asarray(e.plant_input, float) for e in episodes]
    each = per_episode_params(params, len(episodes))
    params = each[0] if len(set(each)) == 1 else each
    offsets = estimate_offset_closed_loop(episodes, params, start, offset_window)
    state0 = np.stack([np.concatenate([y[start] - [0.0, o], _rates(y, dt)[start]]) for y, o in zip(ys, offsets)])
    draws = np.repeat(state0[None], n_draws, axis=0)
    draws[1:, :, :2] += np.random.default_rng(seed).uniform(-0.5, 0.5, (n_draws - 1, len(ys), 2)) * ENCODER_COUNT
    loads = None
    if load is not None:
        each_load = [load] * len(ys) if isinstance(load, RandomLoad) else list(load)
        if len(each_load) != len(ys):
            raise ValueError(f"{len(each_load)} loads for {len(ys)} episodes: give one, or one per episode")
        n_steps = min(len(y) for y in ys) - start
        rng = np.random.default_rng([seed, 1])  # a stream of its own: the start draws stay as without a load
        loads = np.stack(
            [np.zeros((n_steps, n_draws)) if d is None else d.sample(n_steps, dt, rng, (n_draws,)) for d in each_load],
            axis=2,
        )
    drift = None
    if alpha_drift is not None:
        n_steps = min(len(y) for y in ys) - start
        drift = alpha_drift.sample(n_steps, dt, np.random.default_rng([seed, 2]), (n_draws, len(ys)))
    if relaxation is not None and not isinstance(relaxation, CableRelaxation):
        relaxation = per_episode_relaxations(relaxation, len(ys)) * n_draws  # the batch is (draw, episode), in C order
    run = _replay_draws(
        episodes, us, draws, offsets, params, start, load=loads, alpha_drift=drift, relaxation=relaxation
    )
    twin = np.concatenate([run.measurements, run.plant_input[..., None]], axis=-1)  # (time, draw, episode, 3)
    real = np.stack([np.column_stack([y[start:], u[start:]]) for y, u in zip(ys, us)], axis=1)
    ratio = (twin.std(axis=0) / real.std(axis=0)).mean(axis=0)
    peak = np.max(np.abs(run.measurements), axis=0)
    balanced = np.all((peak[..., 0] < THETA_LIMIT) & (peak[..., 1] < ALPHA_LIMIT), axis=0)
    rmse = np.sqrt(np.mean((twin[..., :2] - real[:, None, :, :2]) ** 2, axis=0))
    nrmse = 100 * np.mean(rmse / np.max(np.abs(real[..., :2]), axis=0), axis=(0, 2))
    return ReplayResult(ratio, balanced, nrmse, offsets, twin[:, 0], real, twin)


def _replay_draws(
    episodes: Sequence,
    us: Sequence[np.ndarray],
    draws: np.ndarray,
    offsets: np.ndarray,
    params: PendulumParameters | Sequence[PendulumParameters],
    start: int,
    stop: int | None = None,
    load: np.ndarray | None = None,
    alpha_drift: np.ndarray | None = None,
    relaxation=None,
):
    """The closed loop from start states ``draws`` (n_draws, n_episodes, 4), one batch, over samples
    ``start:stop``; ``offsets`` broadcast to (n_draws, n_episodes); ``load`` (n_steps, n_draws,
    n_episodes) a torque on the arm (V at the motor) or None."""
    shape = draws.shape[:2]

    def per_draw(a: np.ndarray) -> np.ndarray:  # (time, episode, ...) -> (time, draw, episode, ...)
        return np.broadcast_to(a[:, None], (a.shape[0], *shape, *a.shape[2:]))

    refs = np.stack([np.asarray(e.references, float)[start:stop] for e in episodes], axis=1)
    ff = np.stack([np.asarray(e.feedforward, float)[start:stop] for e in episodes], axis=1)
    xc0 = np.stack([np.asarray(e.controller_state, float)[start] for e in episodes])
    max_v = float(np.max(np.abs(np.concatenate(us)))) if episodes else 10.0
    past = np.stack([u[max(0, start - ms.N_PAST) : start] for u in us], axis=1)
    if not isinstance(params, PendulumParameters):  # one per episode: the batch is (draw, episode)
        params = [p for _ in range(shape[0]) for p in params]
    return simulate_closed_loop(
        draws,
        episodes[0].controller,
        per_draw(refs),
        per_draw(ff),
        params,
        controller_state0=np.broadcast_to(xc0, (*shape, xc0.shape[-1])),
        max_voltage=max(max_v, 1e-3),
        alpha_offsets=np.broadcast_to(offsets, shape),
        past_voltages=per_draw(past) if len(past) else None,
        load=load,
        alpha_drift=alpha_drift,
        relaxation=relaxation,
    )


def open_loop_error(
    episodes: Sequence,
    params: PendulumParameters | Sequence[PendulumParameters],
    offsets: np.ndarray,
    horizon: float = OPEN_LOOP_HORIZON,
    start: int = SKIP_SAMPLES,
    relaxation=None,
) -> np.ndarray:
    """RMS error (rad) of theta and alpha over open-loop predictions of ``horizon`` seconds.

    Each prediction starts from the data (measured angles less the offset,
    Savitzky-Golay rates) every ``horizon`` seconds and is driven by the
    logged voltage; ``params`` the twin or one per episode; ``relaxation`` (a
    :class:`~qube_koopman.sim.pendulum.CableRelaxation` or one per episode, None for none) adds the
    cables' relaxation torque along the logged arm angle, as the twin's fit simulated it. Returns
    (n_episodes, 2).
    """
    dt = episodes[0].dt
    h = int(round(horizon / dt))
    relaxations = per_episode_relaxations(relaxation, len(episodes))
    out = []
    for e, o, twin, r in zip(episodes, offsets, per_episode_params(params, len(episodes)), relaxations):
        y, u = np.asarray(e.states, float), np.asarray(e.plant_input, float)
        seg = ms.make_segments([y], [u], h, start, loads=None if r is None else [r.torque_of(y[:, 0], dt)])
        nodes = np.concatenate([seg.y[0] - [0.0, o], _rates(y, dt)[seg.start]], axis=1)
        pred = ms.simulate_segments(nodes, seg.u, twin, dt, past=seg.past, load=seg.load)
        pred[..., 1] += o
        out.append(np.sqrt(np.mean((pred - seg.y) ** 2, axis=(0, 1))))
    return np.array(out)
