"""Identification's memory does not grow with the number of training episodes (issue 29).

The lifting is fitted and the regression's statistics folded one episode at a time: the peak of
the memory traced while fitting 24 episodes is that of fitting 6, where holding every episode's
lifted snapshots (as before) made it grow four times. Numpy reports its arrays to tracemalloc, so
the measure is the arrays', deterministic and independent of the machine's load.
"""

from __future__ import annotations

import tracemalloc
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from qube_koopman.identify import ClEdmd, Constant, Delay, Lifting, Polynomial, ThinPlateRbf, Trajectory
from qube_koopman.core.blas import limited_blas_threads
from qube_koopman.identify.estimators.regression import Snapshots
from qube_koopman.identify.data.trajectory import EpisodeSequence
from qube_koopman.core.lti import DiscreteStateSpace

N_SAMPLES = 2000
CONTROLLER = DiscreteStateSpace(np.eye(2) * 0.5, np.eye(2), -np.eye(2), np.zeros((2, 2)), dt=0.002)


@pytest.fixture(autouse=True)
def _one_blas_thread():
    # Factors of a few thousand rows: threads gain nothing, and on a loaded machine OpenBLAS's
    # waiting threads made each QR 50 times slower (a 2 s test took 50 s).
    with limited_blas_threads(1):
        yield


def _lifting() -> Lifting:
    return Lifting([Polynomial(2), Delay(20), ThinPlateRbf(20, seed=0), Constant()])


def _episodes(n: int) -> list[Trajectory]:
    rng = np.random.default_rng(0)
    out = []
    for _ in range(n):
        x = np.cumsum(rng.standard_normal((N_SAMPLES, 2)), axis=0) * 1e-2
        out.append(
            Trajectory(
                x=x, r=rng.standard_normal((N_SAMPLES, 2)) * 1e-2, xc=rng.standard_normal((N_SAMPLES, 2)), dt=0.002
            )
        )
    return out


def _peak(work) -> int:
    """Peak traced bytes while ``work()`` runs, above what was allocated before it."""
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        before = tracemalloc.get_traced_memory()[0]
        work()
        return tracemalloc.get_traced_memory()[1] - before
    finally:
        tracemalloc.stop()


@pytest.mark.parametrize("fit", ["lifting", "cl_edmd"])
def test_the_peak_memory_of_a_fit_does_not_grow_with_the_episodes(fit):
    small, large = _episodes(6), _episodes(24)
    lifted_episode = N_SAMPLES * _lifting().fit([small[0].x]).n_features_out_ * 8

    def run(trajectories):
        if fit == "lifting":
            return lambda: _lifting().fit([t.x for t in trajectories])
        return lambda: ClEdmd(CONTROLLER, _lifting(), alpha=1e-6).fit(trajectories)

    peak_small, peak_large = _peak(run(small)), _peak(run(large))
    # 18 more lifted episodes held at once would add 18 x 0.67 MB; folding one at a time adds nothing.
    assert peak_large - peak_small < 2 * lifted_episode, (peak_small, peak_large, lifted_episode)


def test_folding_statistics_in_batches_equals_one_factor_of_everything():
    rng = np.random.default_rng(1)
    parts = [Snapshots.from_snapshots(rng.standard_normal((50, 3)), rng.standard_normal((50, 5))) for _ in range(37)]
    everything = Snapshots.from_snapshots(
        np.vstack([p.R[:, 5:] for p in parts]), np.vstack([p.R[:, :5] for p in parts])
    )
    folded = Snapshots.total(iter(parts), batch=4)
    assert folded.q == sum(p.q for p in parts)
    np.testing.assert_allclose(folded.H, everything.H, rtol=1e-12)
    np.testing.assert_allclose(folded.G, everything.G, rtol=1e-12)
    np.testing.assert_allclose(folded.F, everything.F, rtol=1e-12)
    np.testing.assert_allclose(Snapshots.total(parts).H, folded.H, rtol=1e-12)


# --- logs on disk, streamed: the fit, the sweeps' folds and the test scores (issue 29 section 1) ---------------


class _Generated(EpisodeSequence):
    """Episodes made when asked for (as stored logs are read), the same each time: none is kept."""

    def __init__(self, n: int, n_samples: int = N_SAMPLES, controllers=None) -> None:
        self.n, self.n_samples, self.controllers = n, n_samples, controllers

    def __len__(self) -> int:
        return self.n

    def _make(self, i: int) -> Trajectory:
        rng = np.random.default_rng(1000 + i)
        n_c = 2 if self.controllers is None else self.controllers[i].n_states
        x = np.cumsum(rng.standard_normal((self.n_samples, 2)), axis=0) * 1e-2
        return Trajectory(
            x=x,
            r=rng.standard_normal((self.n_samples, 2)) * 1e-2,
            xc=rng.standard_normal((self.n_samples, n_c)),
            dt=0.002,
            name=f"e{i}",
            state_names=("theta", "alpha"),
        )


def _direct_total(estimator, setup, episodes, indices) -> Snapshots:
    """The chosen episodes' statistics as sums of their Gram matrices (no factor folded)."""
    parts = [estimator.episode_snapshots(setup, episodes[int(j)]) for j in indices]
    return SimpleNamespace(q=sum(p.q for p in parts), **{k: sum(getattr(p, k) for p in parts) for k in "HGF"})


def _assert_same_statistics(a: Snapshots, b: Snapshots, rtol: float) -> None:
    assert a.q == b.q
    for name in ("H", "G", "F"):
        np.testing.assert_allclose(
            getattr(a, name), getattr(b, name), rtol=rtol, atol=rtol * np.abs(getattr(b, name)).max()
        )


def test_a_fit_on_a_lazy_sequence_reads_one_episode_at_a_time():
    # The episodes are made inside the traced region, as logs read from disk are: holding them (or
    # their states, as Lifting.fit did) would grow the peak by 12 episodes' signals.
    lifting = [Polynomial(2), Delay(10), Constant()]
    raw_episode = sum(a.nbytes for a in (_Generated(1)[0].x, _Generated(1)[0].r, _Generated(1)[0].xc))
    peaks = [_peak(lambda n=n: ClEdmd(CONTROLLER, lifting, alpha=1e-6).fit(_Generated(n))) for n in (4, 16)]
    assert peaks[1] - peaks[0] < 3 * raw_episode, (peaks, raw_episode)
    lazy = ClEdmd(CONTROLLER, lifting, alpha=1e-6).fit(_Generated(4))
    listed = ClEdmd(CONTROLLER, lifting, alpha=1e-6).fit(list(_Generated(4)))
    np.testing.assert_array_equal(lazy.koopman_matrix_, listed.koopman_matrix_)


@pytest.mark.parametrize("mixed", [False, True])
def test_fold_totals_from_one_pass_equal_direct_totals_over_each_folds_episodes(mixed):
    from qube_koopman.identify.model_selection.split import group_shuffle_splits

    other = DiscreteStateSpace(np.eye(3) * 0.3, np.ones((3, 2)), -np.ones((2, 3)), np.eye(2), dt=0.002)
    controllers = [CONTROLLER if i % 3 else other for i in range(10)] if mixed else None
    episodes = _Generated(10, 300, controllers)
    estimator = ClEdmd(CONTROLLER, [Polynomial(2), Delay(5), Constant()])
    splits = group_shuffle_splits(10, 3, 0.2, seed=3)
    setup, (*folds, everything) = _statistics_with(estimator, episodes, splits, controllers)
    for (train, _), fold in zip(splits, folds):
        if mixed:
            assert [c.n_states for c in fold.controllers] == [3, 2]  # the other controller appears first
            for g, part in enumerate(fold.parts):
                mine = [j for j in train if (controllers[j] is other) == (g == 0)]
                _assert_same_statistics(part, _direct_total(estimator, setup, episodes, mine), 1e-10)
        else:
            _assert_same_statistics(fold, _direct_total(estimator, setup, episodes, train), 1e-10)
    if not mixed:
        _assert_same_statistics(everything, _direct_total(estimator, setup, episodes, range(10)), 1e-10)
    # ... and bit for bit what the per-episode list the sweeps kept before gave.
    per_episode = [estimator.episode_snapshots(setup, t) for t in episodes]
    for (train, _), fold in zip(splits, folds):
        before = estimator.total_statistics(setup, per_episode, train)
        for new, old in zip(getattr(fold, "parts", [fold]), getattr(before, "parts", [before])):
            np.testing.assert_array_equal(new.R, old.R)


def _statistics_with(estimator, episodes, splits, controllers):
    from qube_koopman.identify.model_selection.sweep import _statistics

    return _statistics(estimator, episodes, [t for t, _ in splits] + [None], controllers=controllers)


def test_the_folds_statistics_memory_does_not_grow_with_the_episodes():
    from qube_koopman.identify.model_selection.split import group_shuffle_splits

    n_samples = 300
    estimator = ClEdmd(CONTROLLER, [Polynomial(2), Delay(20), Constant()])
    setup, _ = _statistics_with(estimator, _Generated(2, n_samples), [([0], [1])], None)
    factor = estimator.episode_snapshots(setup, _Generated(1, n_samples)[0]).R.nbytes

    def run(n):
        return lambda: _statistics_with(estimator, _Generated(n, n_samples), group_shuffle_splits(n, 3), None)

    # From 12 episodes on, each fold's running total and its few pending factors are all there is.
    small, large = _peak(run(12)), _peak(run(48))
    # A factor kept per episode (as the sweeps did) would add 36 factors; the folds' totals add none.
    assert large - small < 4 * factor, (small, large, factor)


def test_validation_episodes_scored_a_batch_at_a_time_score_as_one_by_one(monkeypatch):
    from qube_koopman.identify.model_selection import sweep

    episodes = list(_Generated(7, 300))
    models = [
        ClEdmd(CONTROLLER, [Polynomial(2), Delay(3)], alpha=a).fit(episodes[:4]).closed_loop_model_
        for a in (1e-6, 1e-2)
    ]
    whole = sweep._score(models, episodes, "cl", True, 5, True)
    monkeypatch.setattr(sweep, "EPISODES_PER_BATCH", 2)
    batched = sweep._score(models, episodes, "cl", True, 5, True)
    one_by_one = np.mean([sweep._score(models, [t], "cl", True, 5, True) for t in episodes], axis=0)
    np.testing.assert_allclose(batched, one_by_one, rtol=1e-12)
    np.testing.assert_allclose(whole, one_by_one, rtol=1e-12)


def _retained(work) -> tuple[int, object]:
    """Traced bytes still held after ``work()`` (its result kept), and the result."""
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        out = work()
        return tracemalloc.get_traced_memory()[0] - before, out
    finally:
        tracemalloc.stop()


def test_stored_logs_keep_their_metadata_only(qube_logs, monkeypatch):
    from qube_koopman.daq.log.names import find_logs
    from qube_koopman.identify.data.logs import LogTrajectories, clear_log_cache, load_logs

    # The stored logs themselves, without the process's cache of decoded logs (bounded: next test)
    monkeypatch.setenv("QUBE_KOOPMAN_LOG_CACHE_MB", "0")
    clear_log_cache()
    files = find_logs(qube_logs)[:8]
    # One log read first: the reader imports mcap, zstandard and lz4 at its first read (about 150 kB of
    # modules), which counted here when no earlier test of this worker had read a log.
    load_logs(files[:1], skip=10, stored=True)
    held, stored = _retained(lambda: load_logs(files, skip=10, stored=True))
    in_memory = load_logs(files, skip=10)
    episode = sum(getattr(in_memory[0].trajectory, k).nbytes for k in ("x", "u", "r", "f", "xc"))
    assert held < episode / 4, (held, episode)  # eight logs' metadata: less than a quarter of one episode
    for a, b in zip(stored, in_memory):
        assert (a.dt, a.n_samples, a.path, a.gains) == (b.dt, b.n_samples, b.path, b.gains)
        for key in ("x", "u", "r", "f", "xc"):
            np.testing.assert_array_equal(getattr(a.trajectory, key), getattr(b.trajectory, key))
    assert [t.name for t in LogTrajectories(stored)] == [f.name for f in files]


def test_the_cache_of_decoded_logs_keeps_to_its_budget_and_reads_a_changed_file_again(qube_logs, tmp_path, monkeypatch):
    import shutil

    from qube_koopman.daq.log.names import find_logs
    from qube_koopman.identify.data import logs as logs_module
    from qube_koopman.identify.data.logs import clear_log_cache, load_logs

    files = find_logs(qube_logs)[:8]
    monkeypatch.setenv("QUBE_KOOPMAN_LOG_CACHE_MB", "0")
    clear_log_cache()
    fresh = load_logs(files, skip=10)  # decoded from the files, nothing kept
    episode = sum(getattr(fresh[0].trajectory, k).nbytes for k in ("x", "u", "r", "f", "xc"))
    monkeypatch.setenv("QUBE_KOOPMAN_LOG_CACHE_MB", str(2.5 * episode / 2**20))  # room for two episodes
    decoded = []
    monkeypatch.setattr(logs_module, "_decode", lambda *a, _d=logs_module._decode: decoded.append(a[0]) or _d(*a))
    clock = [1000.0]
    monkeypatch.setattr(logs_module, "_clock", lambda: clock[0])
    held, stored = _retained(lambda: load_logs(files, skip=10, stored=True))
    assert len(decoded) == 8 and 1.5 * episode < held < 2.5 * episode, (held, episode)  # two kept
    for a, b in zip(stored, fresh):
        read = a.trajectory
        for key in ("x", "u", "r", "f", "xc"):
            np.testing.assert_array_equal(getattr(read, key), getattr(b.trajectory, key))
    # Read again in the same order: the first two from memory, the others decoded and not kept, as
    # the two were read too recently to make room (least recently used, each would have pushed out
    # the next one due and this pass decoded all eight)
    assert decoded[8:] == list(files[2:]), decoded[8:]
    clock[0] += logs_module.LOG_CACHE_IDLE_S + 1  # later on, a log read now takes an idle one's place
    for _ in range(2):
        again = stored[-1].trajectory
    assert decoded[14:] == [files[-1]]
    _ = stored[1].trajectory  # read for its effect on the cache
    _ = stored[0].trajectory
    assert decoded[15:] == [files[0]], decoded[15:]  # the first one went, the second is still there
    assert not again.x.flags.writeable  # every reader gets the same arrays: none may write to them

    # A file changed since it was cached (another episode copied over it) is decoded again
    copy = tmp_path / files[-1].name
    shutil.copy(files[-1], copy)
    (log,) = load_logs([copy], skip=10, stored=True)
    np.testing.assert_array_equal(log.trajectory.x, fresh[-1].trajectory.x)
    shutil.copy(files[0], copy)
    np.testing.assert_array_equal(log.trajectory.x, fresh[0].trajectory.x)
    assert decoded[-1] == copy
    clear_log_cache()


def test_the_whole_set_checks_give_the_same_errors_on_stored_logs(tmp_path):
    from pathlib import Path

    from qube_koopman.identify.data.logs import LoggedTrajectory, StoredLog, check_same_controller, check_same_rate

    other = DiscreteStateSpace(np.eye(2) * 0.25, np.eye(2), -np.eye(2), np.zeros((2, 2)), dt=0.002)
    specs = [("a.mcap", CONTROLLER, 0.002), ("b.mcap", other, 0.002), ("c.mcap", CONTROLLER, 0.004)]
    in_memory = [LoggedTrajectory(Path(n), Trajectory(x=np.zeros((5, 2)), dt=dt), c) for n, c, dt in specs]
    stored = [StoredLog(Path(n), c, None, dt, 5) for n, c, dt in specs]
    for check, logs in ((check_same_rate, [0, 2]), (check_same_controller, [0, 1])):
        messages = []
        for kind in (in_memory, stored):
            with pytest.raises(ValueError) as caught:
                check([kind[i] for i in logs], "training")
            messages.append(str(caught.value))
        assert messages[0] == messages[1] and messages[0].startswith(specs[logs[1]][0]), messages


@pytest.mark.slow  # about 4 s: two identifications with a sweep on 4 real episodes
def test_stored_logs_identify_and_score_as_logs_in_memory(qube_logs):
    import json

    from qube_koopman.daq.log.names import find_logs
    from qube_koopman.identify.data.logs import load_logs
    from qube_koopman.identify.workflow import (
        FitOptions,
        IdentifyOptions,
        OffsetProtocol,
        OutputOptions,
        ScoreOptions,
        identify_and_score,
    )

    files = find_logs(qube_logs)
    runs = {}
    for stored in (False, True):
        train, test = (load_logs(chosen, skip=500, stored=stored) for chosen in (files[:4], files[28:30]))
        options = IdentifyOptions(
            FitOptions("cl-edmd", [Polynomial(2), Delay(5), Constant()], alphas=[1e-4, 1e-2]),
            ScoreOptions(offsets=OffsetProtocol(("alpha",))),
            output=OutputOptions(keep_predictions=not stored),
        )
        runs[stored] = identify_and_score(train, test, train[0].controller, options)
    assert json.dumps(runs[True].report) == json.dumps(runs[False].report)
    np.testing.assert_array_equal(runs[True].plant.A, runs[False].plant.A)
    # Streamed test scores keep no prediction unless asked; the ones kept are those scored.
    assert runs[True].test_predictions == [] and len(runs[False].test_predictions) == 2
    assert runs[True].test_names == runs[False].test_names == [f.name for f in files[28:30]]
    assert runs[True].report["test"]["n_episodes"] == 2 and "test_without_offsets" in runs[True].report


def test_a_search_candidate_on_a_lazy_sequence_scores_as_on_a_list(monkeypatch):
    from qube_koopman.identify.model_selection import sweep
    from qube_koopman.identify.model_selection.split import group_shuffle_splits
    from qube_koopman.identify.model_selection.search import LiftingSpec, SearchData, evaluate_candidate

    def data(episodes):
        return SearchData(episodes, group_shuffle_splits(8, 2), CONTROLLER, np.array([1e-6, 1e-3, 1.0]), window=40)

    spec = LiftingSpec(delays=3, poly=1, offsets=True)
    listed = evaluate_candidate(spec, data(list(_Generated(8, 400))))
    lazy = evaluate_candidate(spec, data(_Generated(8, 400)))
    np.testing.assert_array_equal(lazy.cv_r2, listed.cv_r2)
    assert np.isfinite(listed.cv_r2).sum() >= 2  # offsets estimated at the best alphas of both folds
    # Validation episodes one at a time (as 16 of many are): the same scores (offsets converge per episode).
    monkeypatch.setattr(sweep, "EPISODES_PER_BATCH", 1)
    np.testing.assert_allclose(evaluate_candidate(spec, data(_Generated(8, 400))).cv_r2, listed.cv_r2, rtol=1e-9)


class _Described(_Generated):
    """Generated episodes that know their shapes, as stored logs do; ``made`` counts the episodes made."""

    def __init__(self, episodes: list[Trajectory]) -> None:
        super().__init__(len(episodes))
        self.episodes, self.made = episodes, 0

    def _make(self, i: int) -> Trajectory:
        self.made += 1
        return self.episodes[i]

    def shapes(self):
        return [t.shape() for t in self.episodes]


def _bad_sets() -> dict[str, list[Trajectory]]:
    """Episode sets the fit's checks refuse, each for one reason."""
    good = list(_Generated(3))
    return {
        "no controller state": [good[0], replace(good[1], xc=None), good[2]],
        "a wider controller state": [good[0], good[1], replace(good[2], xc=np.zeros((N_SAMPLES, 3)))],
        "another sample period": [good[0], replace(good[1], dt=0.004), good[2]],
        "too short": [good[0], good[1], good[2].skip(N_SAMPLES - 5)],
        "feedforward in some only": [good[0], replace(good[1], f=np.zeros((N_SAMPLES, 1))), good[2]],
    }


@pytest.mark.parametrize("case", list(_bad_sets()))
def test_a_sequence_that_knows_its_shapes_is_refused_as_its_episodes_are(case):
    episodes = _bad_sets()[case]
    messages = []
    for data in (episodes, _Described(episodes)):
        with pytest.raises(ValueError) as caught:
            ClEdmd(CONTROLLER, [Polynomial(1), Delay(10)], alpha=1e-6).fit(data)
        messages.append(str(caught.value))
    assert messages[0] == messages[1], messages


def test_a_fit_on_a_sequence_that_knows_its_shapes_reads_each_episode_once_for_its_statistics():
    episodes = list(_Generated(6))
    described = _Described(episodes)
    fitted = ClEdmd(CONTROLLER, [Polynomial(2), Delay(10), Constant()], alpha=1e-6).fit(described)
    # The first episode twice to set up (the fit's widths and names, the lifting's), then each once for
    # the statistics: the checks read the shapes, where they read every episode again before.
    assert described.made == len(episodes) + 2, described.made
    listed = ClEdmd(CONTROLLER, [Polynomial(2), Delay(10), Constant()], alpha=1e-6).fit(episodes)
    np.testing.assert_array_equal(fitted.koopman_matrix_, listed.koopman_matrix_)


def test_stored_logs_know_their_shapes_as_read(qube_logs):
    from qube_koopman.daq.log.names import find_logs
    from qube_koopman.identify.data.logs import LogTrajectories, StoredLog, load_logs

    files = find_logs(qube_logs)[:3]
    stored = LogTrajectories(load_logs(files, skip=10, stored=True))
    assert stored.shapes() == [t.shape() for t in stored]
    assert stored.shapes()[0].width("xc") == stored[0].xc.shape[1] and stored.shapes()[0].width("u") == 1
    # A stored log made without its shape (an older caller's) leaves the sequence to be read.
    bare = LogTrajectories([replace(log, shape=None) for log in stored.logs] + [])
    assert isinstance(bare.logs[0], StoredLog) and bare.shapes() is None
