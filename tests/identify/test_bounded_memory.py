"""Memory that does not grow with an episode's length: timing statistics and the streamed excitation in the loop."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest
from _episodes import QUBE_PD

from qube_koopman.daq.backends import BackendFault, SimBackend
from qube_koopman.core.controller_file import ControllerInfo
from qube_koopman.daq.excitation import ExcitationSettings, ExcitationStream
from qube_koopman.daq.loop import EpisodePlan, run_episode
from qube_koopman.daq.session import plan_episodes, run_episodes
from qube_koopman.daq.sinks import MemorySink
from qube_koopman.daq.timing import EXACT_TICKS, TimingRecord, timing_stats

CONTROLLER = ControllerInfo(QUBE_PD, "backward-euler", {"kp_theta": 6.0})
SETTINGS = ExcitationSettings(n_samples=10_000, window_start=2000, window_stop=8000)


def _ticks(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    late = rng.lognormal(np.log(50e-6), 0.8, n)
    late[::997] = -2e-6  # a few early ticks (device clock re-anchoring)
    late[::5003] = 3e-3  # stalls and overruns
    return late, rng.lognormal(np.log(20e-6), 0.3, n)


def test_a_record_is_exact_while_short_and_within_a_bin_when_long():
    late, comp = _ticks(3 * EXACT_TICKS)
    for n in (EXACT_TICKS, 3 * EXACT_TICKS):
        record = TimingRecord(0.002)
        for k in range(0, n, 4096):
            record.add(late[k : min(n, k + 4096)], comp[k : min(n, k + 4096)])
        got = record.stats()
        assert got == timing_stats(late[:n], comp[:n], 0.002), "chunks or whole: the same statistics"
        want_p = np.percentile(late[:n], [50, 99])
        assert got.n_ticks == n and got.lateness_max == late[:n].max() and got.compute_max == comp[:n].max()
        assert got.overruns == int(np.count_nonzero(late[:n] + comp[:n] > 0.002))
        assert got.stalls == int(np.count_nonzero(late[:n] > 2e-3))
        if n <= EXACT_TICKS:
            assert (got.lateness_p50, got.lateness_p99) == tuple(want_p)
        else:
            np.testing.assert_allclose((got.lateness_p50, got.lateness_p99), want_p, rtol=0.012)
            np.testing.assert_allclose(got.compute_p99, np.percentile(comp[:n], 99), rtol=0.012)


def test_a_long_record_does_not_grow():
    late, comp = _ticks(4096, seed=1)
    record = TimingRecord(0.002)
    for _ in range(EXACT_TICKS // 4096 + 1):  # past the exact part: a histogram from here on
        record.add(late, comp)
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        for _ in range(500):  # another 2 million ticks
            record.add(late, comp)
        grown = tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()
    assert record.stats().n_ticks == (EXACT_TICKS // 4096 + 501) * 4096
    assert grown < 10_000, f"the record grew by {grown} bytes over 2 million ticks"


class FaultingSim(SimBackend):
    """The simulator, whose link dies at a chosen read (mid-chunk of the loop's buffers)."""

    def __init__(self, fail_at: int, **kw) -> None:
        super().__init__(**kw)
        self.fail_at, self.reads = fail_at, 0

    def read(self):
        self.reads += 1
        if self.reads == self.fail_at:
            raise BackendFault("link lost")
        return super().read()


@pytest.mark.parametrize("fail_at", [None, 6_001])
def test_the_loop_timing_covers_every_recorded_tick_across_its_chunks(fail_at):
    backend = SimBackend(seed=3) if fail_at is None else FaultingSim(fail_at, seed=3)
    sink = MemorySink()
    result = run_episode(backend, EpisodePlan(CONTROLLER, ExcitationStream((1, 2, 3), SETTINGS)), [sink])
    ep = sink.episodes[0].episode()
    assert result.n_samples == len(ep) == (10_000 if fail_at is None else len(ep)) > 4096
    assert result.timing.n_ticks == len(ep) and result.complete == (fail_at is None)
    assert result.timing.compute_max == ep.compute_time.max()
    assert result.timing.compute_p50 == np.percentile(ep.compute_time, 50)


def test_a_run_gathers_its_episodes_timing_in_one_record():
    plans = plan_episodes(CONTROLLER, [(1, 2, 3), (4, 5, 6)], SETTINGS)
    sink = MemorySink()
    record = TimingRecord(0.002)
    run = run_episodes(SimBackend(seed=4), plans, [sink], timing=record)
    assert [r.complete for r in run.results] == [True, True]
    compute = np.concatenate([e.episode().compute_time for e in sink.episodes])
    assert record.stats().n_ticks == 20_000 and record.stats().compute_max == compute.max()
    # The streamed excitation is what was logged.
    np.testing.assert_array_equal(sink.episodes[1].episode().feedforward, plans[1].excitation.feedforward)
