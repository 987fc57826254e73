"""The excitation made a chunk at a time is the whole-episode excitation, bit for bit, in bounded memory."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

from qube_koopman.daq.excitation import (
    ExcitationSettings,
    ExcitationStream,
    PrbsChannel,
    generate_excitation,
    held_prbs,
    integrate,
    smooth,
)
from qube_koopman.daq.session import excitation_settings


def whole_episode_reference(seeds, settings):
    """The generator as it was before the stream: whole arrays, built from the public steps."""

    def windowed(seed, channel):
        stop = settings.window_stop
        raw = held_prbs(seed, channel.amplitude, channel.bit_samples(settings.sample_rate), stop)
        raw[: settings.window_start] = 0.0
        out = np.zeros(settings.n_samples)
        out[:stop] = smooth(raw, settings.smoothing_cutoff, settings.sample_rate)
        return out

    return (
        integrate(windowed(seeds[0], settings.theta_rate), settings.sample_rate),
        windowed(seeds[1], settings.alpha),
        windowed(seeds[2], settings.feedforward),
    )


SETTINGS = [
    ExcitationSettings(),
    excitation_settings(123.4),
    # Bits of 37 samples (not dividing the chunk), window ending mid-bit, no smoothing.
    ExcitationSettings(
        n_samples=9_001,
        window_start=13,
        window_stop=8_888,
        theta_rate=PrbsChannel(0.3, 0.074),
        alpha=PrbsChannel(0.02, 0.074),
        feedforward=PrbsChannel(1.0, 0.074),
        smoothing_cutoff=0.0,
    ),
    ExcitationSettings(n_samples=5, window_start=0, window_stop=5),
]


@pytest.mark.parametrize("settings", SETTINGS)
@pytest.mark.parametrize("size", [4096, 1000, 7])
def test_the_stream_is_the_whole_episode_bit_for_bit(settings, size):
    seeds = (434, 696, 394)
    chunks = list(ExcitationStream(seeds, settings).chunks(size))
    assert all(len(c[0]) == size for c in chunks[:-1])
    streamed = [np.concatenate([c[i] for c in chunks]) for i in range(3)]
    for got, want in zip(streamed, whole_episode_reference(seeds, settings)):
        assert got.tobytes() == want.tobytes()


@pytest.mark.parametrize("seeds", [(1, 2, 3), (65535, 4242, 17)])
def test_generate_excitation_is_unchanged(seeds):
    settings = excitation_settings(60.0)
    ex = generate_excitation(seeds, settings)
    for got, want in zip((ex.target_theta, ex.target_alpha, ex.feedforward), whole_episode_reference(seeds, settings)):
        assert got.tobytes() == want.tobytes() and not got.flags.writeable
    stream = ExcitationStream(seeds, settings)
    assert len(stream) == len(ex) == settings.n_samples
    assert stream.feedforward.tobytes() == ex.feedforward.tobytes()


def test_an_hour_of_excitation_streams_in_bounded_memory():
    stream = ExcitationStream((5, 6, 7), excitation_settings(3600.0))  # 1.8 million samples a signal
    tracemalloc.start()
    try:
        n = 0
        for theta, _alpha, _ff in stream.chunks(4096):
            n += len(theta)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert n == 1_800_000
    assert peak < 2_000_000, f"peak {peak / 1e6:.1f} MB (the whole hour would be 43 MB)"


def test_the_stream_checks_its_seeds_and_chunk_size():
    with pytest.raises(ValueError, match="three seeds"):
        ExcitationStream((1, 2))
    with pytest.raises(ValueError, match="seed"):
        ExcitationStream((0, 2, 3))
    with pytest.raises(ValueError, match="chunk size"):
        next(ExcitationStream((1, 2, 3)).chunks(0))
