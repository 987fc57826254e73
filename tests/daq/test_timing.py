"""Pacing and timing statistics (daq.timing), safety limits (daq.safety)."""

from __future__ import annotations

import gc
import math
import os
import signal
import sys

import numpy as np
import pytest

from qube_koopman.daq.safety import SafetyLimits, StopRequest, stop_on_signals
from qube_koopman.daq.timing import (
    EXACT_TICKS,
    STALL_THRESHOLD,
    DeadlinePacer,
    TimingRecord,
    quiet_interpreter,
    realtime_scheduling,
    timing_stats,
)


class FakeClock:
    """A clock that advances by ``tick`` per reading and jumps on sleep; records the sleeps."""

    def __init__(self, tick: float = 1e-6) -> None:
        self.now = 100.0
        self.tick = tick
        self.sleeps: list[float] = []

    def __call__(self) -> float:
        self.now += self.tick
        return self.now

    def sleep(self, seconds: float) -> None:
        self.sleeps.append(seconds)
        self.now += seconds


def test_pacer_sleeps_to_just_before_the_deadline_then_spins():
    clock = FakeClock()
    pacer = DeadlinePacer(0.002, spin=300e-6, clock=clock, sleep=clock.sleep)
    t0 = pacer.start()
    late = pacer.wait(3)
    assert clock.sleeps and clock.sleeps[0] == pytest.approx(3 * 0.002 - 300e-6, abs=5e-6)
    assert clock.now >= t0 + 0.006 and 0 <= late < 5e-6


def test_pacer_keeps_absolute_deadlines_after_a_late_tick():
    clock = FakeClock()
    pacer = DeadlinePacer(0.002, clock=clock, sleep=clock.sleep)
    t0 = pacer.start()
    pacer.wait(1)
    clock.now += 0.005  # a stall: tick 2's deadline passes
    late = pacer.wait(2)
    assert late == pytest.approx(clock.now - (t0 + 0.004))
    assert late > 0.002
    n_sleeps = len(clock.sleeps)
    pacer.wait(3)  # still late (deadline t0 + 6 ms): no sleep, no drift
    assert len(clock.sleeps) == n_sleeps
    pacer.wait(10)
    assert clock.now == pytest.approx(t0 + 0.020, abs=5e-6)


def test_pacer_rejects_bad_settings():
    with pytest.raises(ValueError, match="period"):
        DeadlinePacer(0.0)
    with pytest.raises(ValueError, match="spin"):
        DeadlinePacer(0.002, spin=-1)


def test_timing_stats_counts_overruns_and_stalls():
    period = 0.002
    lateness = np.full(1000, 10e-6)
    compute = np.full(1000, 20e-6)
    lateness[10] = 0.00199  # with its compute time: past the next deadline, an overrun
    lateness[20] = 0.0050  # a stall and an overrun
    stats = timing_stats(lateness, compute, period)
    assert stats.paced and stats.n_ticks == 1000
    assert stats.overruns == 2 and stats.stalls == 1
    assert stats.lateness_max == 0.005 and stats.lateness_p50 == pytest.approx(10e-6)
    assert stats.lateness_p99 == pytest.approx(10e-6)
    assert stats.compute_p99 == pytest.approx(20e-6)
    assert STALL_THRESHOLD == 2e-3


def test_timing_stats_of_free_running_ticks_has_no_lateness():
    stats = timing_stats(np.full(5, np.nan), np.full(5, 1e-5), 0.002)
    assert not stats.paced and math.isnan(stats.lateness_p99) and stats.overruns == 0
    plain = stats.as_dict()
    assert plain["lateness_p99"] is None and plain["compute_max"] == pytest.approx(1e-5)
    empty = timing_stats(np.zeros(0), np.zeros(0), 0.002)
    assert empty.n_ticks == 0 and empty.as_dict()["compute_p50"] is None
    with pytest.raises(ValueError, match="same length"):
        timing_stats(np.zeros(3), np.zeros(4), 0.002)


@pytest.mark.parametrize(
    "sizes",
    [(300, 700, 1000), (EXACT_TICKS - 10, 40, 5), (5, EXACT_TICKS + 7, 3)],
    ids=["exact", "into-histogram", "histogram-merged-in"],
)
def test_merged_records_say_what_one_record_of_all_the_ticks_says(sizes):
    # Episodes of worker processes (daq.parallel) are merged into the run's record: the same
    # statistics, exact or histogram, as if every tick had been added to one record.
    rng = np.random.default_rng(3)
    parts = [
        (np.where(rng.random(n) < 0.01, np.nan, rng.exponential(4e-4, n)), rng.exponential(3e-5, n)) for n in sizes
    ]
    whole, merged = TimingRecord(0.002), TimingRecord(0.002)
    for lateness, compute in parts:
        whole.add(lateness, compute)
        part = TimingRecord(0.002)
        part.add(lateness, compute)
        merged.merge(part)
    assert merged.stats() == whole.stats()
    assert merged.stats().n_ticks == sum(sizes) and merged.stats().overruns > 0
    with pytest.raises(ValueError, match="period"):
        merged.merge(TimingRecord(0.001))


def test_realtime_requests_fail_gracefully_and_are_undone():
    affinity = os.sched_getaffinity(0)
    policy = os.sched_getscheduler(0)
    cpu = min(affinity)
    with realtime_scheduling(cpu=cpu, priority=99) as report:
        assert report.cpu == cpu and os.sched_getaffinity(0) == {cpu}
        # SCHED_FIFO needs a privilege the test may or may not have: granted or noted, never raised.
        assert report.priority == 99 or any("SCHED_FIFO" in n for n in report.notes)
        assert "CPU" in report.describe()
    assert os.sched_getaffinity(0) == affinity and os.sched_getscheduler(0) == policy
    with realtime_scheduling(cpu=10_000) as report:
        assert report.cpu is None and "pinning refused" in report.notes[0]


def test_quiet_interpreter_restores_the_collector_and_switch_interval():
    interval = sys.getswitchinterval()
    with quiet_interpreter(switch_interval=1e-4):
        assert not gc.isenabled() and sys.getswitchinterval() == pytest.approx(1e-4)
    assert gc.isenabled() and sys.getswitchinterval() == interval


# --- safety ----------------------------------------------------------------------------------


def test_safety_limits_defaults_are_the_rigs():
    limits = SafetyLimits()
    assert limits.max_voltage == 10.0 and limits.theta_limit == math.pi / 2
    assert limits.alpha_limit == math.pi / 4 and limits.start_alpha == pytest.approx(math.radians(5))
    assert limits.violation(1.5, 0.7) is None
    assert "theta" in limits.violation(1.58, 0.0) and "alpha" in limits.violation(0.0, -0.79)
    assert limits.violation(math.nan, 0.0) is not None


@pytest.mark.parametrize(
    "bad",
    [
        dict(max_voltage=0),
        dict(theta_limit=-1),
        dict(alpha_limit=math.inf),
        dict(start_alpha=1.0),
        dict(start_timeout=0),
    ],
)
def test_safety_limits_refuse_nonsense(bad):
    with pytest.raises(ValueError):
        SafetyLimits(**bad)


def test_stop_on_signals_keeps_the_first_reason_and_restores_handlers():
    before = signal.getsignal(signal.SIGINT)
    stop = StopRequest()
    with stop_on_signals(stop) as installed:
        assert installed
        signal.raise_signal(signal.SIGINT)
        signal.raise_signal(signal.SIGTERM)
    assert stop.requested and stop.signal == signal.SIGINT and stop.reason == "interrupted by SIGINT"
    assert signal.getsignal(signal.SIGINT) is before
