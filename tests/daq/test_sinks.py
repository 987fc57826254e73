"""Sinks (daq.sinks): the writer thread, the in-memory sink and the MCAP episode-log sink."""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest
from _episodes import make_metadata

from qube_koopman.daq.log import read_episode, read_episode_metadata
from qube_koopman.daq.sinks import EpisodeOutcome, McapSink, MemorySink, Sample, SinkWriter, episode_file_stem
from qube_koopman.daq.timing import timing_stats


def _sample(k: int, late: float = math.nan) -> Sample:
    return Sample(
        k, k / 500, 0.001 * k, -0.002 * k, 0.1, 0.0, 0.5, 1.0 + k, 1.5 + k, 0, late, 1e-5, (float(k), -float(k))
    )


def _outcome(n: int, status="complete", reason="", paced=True) -> EpisodeOutcome:
    late = np.full(n, 2e-5) if paced else np.full(n, np.nan)
    return EpisodeOutcome(status, reason, n, timing_stats(late, np.full(n, 1e-5), 0.002))


def test_writer_thread_delivers_every_sample_in_order_then_closes():
    seen = []

    class Recorder(MemorySink):
        def write(self, sample):
            seen.append((sample.k, threading.current_thread().name))
            super().write(sample)

    sink = Recorder()
    writer = SinkWriter([sink], poll_interval=0.001)
    assert writer.open(make_metadata())
    for k in range(5000):
        writer.put(_sample(k))
    errors = writer.close(_outcome(5000))
    assert errors == [] and [k for k, _ in seen] == list(range(5000))
    assert {name for _, name in seen} == {"episode-writer"}, "sinks write off the loop's thread"
    assert sink.episodes[0].outcome.n_samples == 5000


def test_mcap_sink_names_files_like_the_dataset_and_records_timing(tmp_path):
    meta = make_metadata(start_time="2026-11-21T12:34:56.789+00:00")
    assert episode_file_stem(meta) == "qube_20261121T123456.789_1_2_3"
    sink = McapSink(tmp_path)
    for _ in range(2):  # the same name twice: the second gets a suffix, nothing is overwritten
        writer = SinkWriter([sink])
        assert writer.open(meta)
        for k in range(1200):
            writer.put(_sample(k, late=1e-5 * (k % 7)))
        assert writer.close(_outcome(1200)) == []
    assert [p.name for p in sink.paths] == [
        "qube_20261121T123456.789_1_2_3.mcap",
        "qube_20261121T123456.789_1_2_3_1.mcap",
    ]
    ep = read_episode(sink.paths[1])
    assert ep.is_complete and len(ep) == 1200
    assert np.array_equal(ep.controller_state[:, 0], np.arange(1200.0))
    assert np.array_equal(ep.lateness, 1e-5 * (np.arange(1200) % 7))
    timing = ep.metadata.timing
    assert timing["paced"] is True and timing["n_ticks"] == 1200
    assert timing["lateness_p99"] == pytest.approx(2e-5) and timing["overruns"] == 0


def test_mcap_sink_aborted_episode_keeps_every_sample(tmp_path):
    sink = McapSink(tmp_path)
    writer = SinkWriter([sink])
    writer.open(make_metadata())
    for k in range(777):
        writer.put(_sample(k))
    writer.close(_outcome(777, "aborted", "interrupted by SIGINT", paced=False))
    meta = read_episode_metadata(sink.paths[0])
    assert meta.status == "aborted" and meta.status_reason == "interrupted by SIGINT"
    assert meta.timing["lateness_p50"] is None and meta.timing["paced"] is False
    assert len(read_episode(sink.paths[0])) == 777


def test_memory_sink_episode_carries_the_outcome():
    sink = MemorySink()
    sink.open(make_metadata())
    for k in range(10):
        sink.write(_sample(k))
    sink.close(_outcome(10, "aborted", "safety stop"))
    ep = sink.episodes[0].episode()
    assert len(ep) == 10 and ep.metadata.status == "aborted" and ep.metadata.status_reason == "safety stop"
    assert np.array_equal(ep.plant_input, 1.5 + np.arange(10))
    assert ep.metadata.timing["n_ticks"] == 10


def test_writer_keeps_clear_of_the_loops_deadlines():
    import time

    stamps = []

    class Stamper(MemorySink):
        def write(self, sample):
            stamps.append(time.perf_counter())

    period, guard = 0.02, 0.01
    writer = SinkWriter([Stamper()], poll_interval=0.001)
    writer.open(make_metadata())
    t0 = time.perf_counter()
    writer.keep_clear(t0, period, guard)
    for k in range(40):  # trickled in, as the loop does
        writer.put(_sample(k))
        time.sleep(0.003)
    writer.close(_outcome(40))
    phase = (np.array(stamps[:-5]) - t0) % period  # the last few may be drained at close, unguarded
    # Unguarded, half the writes would land in the window before a deadline.
    assert np.mean(phase > period - guard) < 0.1
    with pytest.raises(ValueError, match="guard"):
        writer.keep_clear(t0, period, period)
