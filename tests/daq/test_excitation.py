"""The rig's excitation generator (daq.excitation) against the C program that recorded the dataset
(the settings its module docstring states) and the dataset itself."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from _qube_csv import load_episode

from qube_koopman.daq.excitation import (
    ExcitationSettings,
    PrbsChannel,
    generate_excitation,
    held_prbs,
    integrate,
    lfsr_bits,
    parse_seeds,
    smooth,
)

FS = 500.0


@pytest.fixture(scope="session")
def episodes(qube_csv_files):
    return {path.name: load_episode(path) for path in qube_csv_files}


# --- the dataset -----------------------------------------------------------------------------


@pytest.mark.dataset
def test_reproduces_all_48_dataset_files(episodes):
    assert len(episodes) == 48
    worst = 0.0
    for name, columns in episodes.items():
        generated = generate_excitation(parse_seeds(name))
        for column in ("target_theta", "target_alpha", "feedforward"):
            error = np.max(np.abs(getattr(generated, column) - columns[column]))
            assert error <= 1e-12, f"{name}: {column} off by {error:.3g}"
            worst = max(worst, error)
    print(f"excitation: worst error over 48 files {worst:.3g}")


def _bits_from_window_start(seed):
    raw = np.zeros(10_000)
    raw[2000:8000] = held_prbs(seed, 0.01, 50, 6000)
    out = smooth(raw, 200.0, FS)
    out[8000:] = 0.0
    return out


def _lfsr_per_sample(seed):
    raw = np.where(lfsr_bits(seed, 8000), 0.01, -0.01)
    raw[:2000] = 0.0
    return np.concatenate([smooth(raw, 200.0, FS), np.zeros(2000)])


def _filter_tail_after_window(seed):
    raw = np.zeros(10_000)
    raw[2000:8000] = held_prbs(seed, 0.01, 50, 8000)[2000:]
    return smooth(raw, 200.0, FS)


@pytest.mark.dataset
@pytest.mark.parametrize("variant", [_bits_from_window_start, _lfsr_per_sample, _filter_tail_after_window])
def test_other_readings_of_the_generator_do_not_reproduce_the_data(episodes, variant):
    # The order of operations the generator uses is the one the data pins down.
    # (Smoothing before or after integrating the rate cannot be told apart:
    # both are linear and time-invariant, they differ by rounding only.)
    name, columns = next(iter(episodes.items()))
    _, seed_alpha, _ = parse_seeds(name)
    assert np.max(np.abs(variant(seed_alpha) - columns["target_alpha"])) > 1e-3


# --- the pieces, against values derived by hand ----------------------------------------------


def test_lfsr_first_bits_from_seed_1():
    # Register 1: the first feedback bit is bit 0 = 1, shifted in at bit 15; it
    # then moves down one place per shift and next reaches a tap (bit 5) on shift 12.
    expected = [1] + [0] * 10 + [1]
    assert lfsr_bits(1, 12).astype(int).tolist() == expected


@pytest.mark.parametrize("seed", [1, 434, 0xFFFF])
def test_lfsr_is_maximal_length(seed):
    # Taps 16, 14, 13, 11 give a maximal-length sequence: period 2^16 - 1 with
    # 2^15 ones per period, and no shorter period (prime factors 3, 5, 17, 257).
    period = 2**16 - 1
    bits = lfsr_bits(seed, 2 * period)
    assert np.array_equal(bits[:period], bits[period:])
    assert bits[:period].sum() == 2**15
    for p in (3, 5, 17, 257):
        assert not np.array_equal(bits[: period - period // p], bits[period // p : period])


@pytest.mark.parametrize("seed", [0, -1, 0x10000, 1.5, True])
def test_lfsr_rejects_bad_seeds(seed):
    with pytest.raises(ValueError, match="seed"):
        lfsr_bits(seed, 4)


def test_held_prbs_holds_each_bit_and_maps_levels():
    bits = lfsr_bits(77, 5)
    out = held_prbs(77, 0.3, 4, 22)
    expected = np.repeat(np.where(bits, 0.3, -0.3), 4)
    np.testing.assert_array_equal(out[:20], expected)
    # Only whole bits are generated, as on the rig: the remainder stays zero.
    np.testing.assert_array_equal(out[20:], 0.0)


def test_smoothing_step_response_is_the_backward_euler_low_pass():
    # y[k] = g + p y[k-1], g = 0.4/1.4, p = 1/1.4: y[k] = 1 - p^(k+1).
    y = smooth(np.ones(50), 200.0, FS)
    k = np.arange(50)
    np.testing.assert_allclose(y, 1.0 - (1.0 / 1.4) ** (k + 1), rtol=0, atol=1e-15)
    np.testing.assert_array_equal(smooth(np.arange(3.0), 0.0, FS), np.arange(3.0))


@pytest.mark.parametrize("cutoff", [1.0, 20.0, 200.0])
def test_smoothing_is_scipys_lfilter_bit_for_bit(cutoff):
    """An episode's smoothing runs in a Python loop (no scipy.signal import at start-up), a long
    signal's in lfilter: the same roundings either way, from rest or from a chunk's last output."""
    from scipy.signal import lfilter

    from qube_koopman.daq.excitation import _loop_low_pass, _low_pass

    rng = np.random.default_rng(int(cutoff))
    x = rng.normal(size=5000) * np.repeat(rng.normal(size=50), 100)
    ratio = cutoff / FS
    gain, pole = ratio / (1.0 + ratio), 1.0 / (1.0 + ratio)
    reference = lfilter([gain], [1.0, -pole], x)
    for low_pass in (_loop_low_pass, lambda *a: _low_pass(*a, long=True)):
        first, last = low_pass(gain, pole, x[:1234], 0.0)
        second, _ = low_pass(gain, pole, x[1234:], last)
        np.testing.assert_array_equal(np.concatenate([first, second]), reference)
    np.testing.assert_array_equal(smooth(x, cutoff, FS), reference)


def test_integrate_is_forward_euler_from_zero():
    rate = np.full(6, 2.0)
    # out[0] = 0 regardless of in[0]; then out[i] = out[i-1] + in[i] T.
    np.testing.assert_allclose(integrate(rate, FS), 2.0 * np.arange(6) / FS, rtol=0, atol=1e-16)


def test_default_settings_are_the_rigs():
    s = ExcitationSettings()
    assert (s.sample_rate, s.n_samples, s.window_start, s.window_stop) == (500.0, 10_000, 2000, 8000)
    assert s.theta_rate == PrbsChannel(0.25, 0.25)
    assert s.alpha == PrbsChannel(0.01, 0.1)
    assert s.feedforward == PrbsChannel(0.5, 0.1)
    assert s.smoothing_cutoff / s.sample_rate == pytest.approx(0.4)


def test_signals_respect_the_window_and_amplitudes():
    settings = ExcitationSettings(
        window_start=100,
        window_stop=1100,
        n_samples=1500,
        alpha=PrbsChannel(0.2, 0.02),
        feedforward=PrbsChannel(1.0, 0.04),
    )
    e = generate_excitation((5, 6, 7), settings)
    for signal in (e.target_theta, e.target_alpha, e.feedforward):
        np.testing.assert_array_equal(signal[:100], 0.0)
        assert np.any(signal[100:1100] != 0.0)
    np.testing.assert_array_equal(e.target_alpha[1100:], 0.0)
    np.testing.assert_array_equal(e.feedforward[1100:], 0.0)
    np.testing.assert_array_equal(e.target_theta[1100:], e.target_theta[1099])
    assert np.max(np.abs(e.target_alpha)) <= 0.2 and np.max(np.abs(e.feedforward)) <= 1.0
    # The theta reference moves no faster than the rate amplitude.
    assert np.max(np.abs(np.diff(e.target_theta))) * FS <= 0.25 + 1e-12
    assert not e.feedforward.flags.writeable


def test_unsmoothed_signals_are_the_raw_levels():
    settings = ExcitationSettings(smoothing_cutoff=0.0)
    e = generate_excitation((11, 12, 13), settings)
    assert set(np.unique(e.feedforward[2000:8000])) == {-0.5, 0.5}


@pytest.mark.parametrize(
    "changes, match",
    [
        (dict(window_start=9000, window_stop=8000), "window_start"),
        (dict(window_stop=10_001), "window_stop"),
        (dict(n_samples=10.5), "n_samples"),
        (dict(sample_rate=0.0), "sample_rate"),
        (dict(alpha=PrbsChannel(0.01, 0.0011)), "whole number of samples"),
        (dict(feedforward=(0.5, 0.1)), "PrbsChannel"),
    ],
)
def test_settings_reject_bad_values(changes, match):
    with pytest.raises(ValueError, match=match):
        dataclasses.replace(ExcitationSettings(), **changes)


def test_prbs_channel_rejects_bad_values():
    with pytest.raises(ValueError, match="amplitude"):
        PrbsChannel(-1.0, 0.1)
    with pytest.raises(ValueError, match="bit_period"):
        PrbsChannel(1.0, 0.0)


def test_settings_round_trip_through_plain_data():
    settings = ExcitationSettings(alpha=PrbsChannel(0.02, 0.2), smoothing_cutoff=100.0)
    assert ExcitationSettings.from_dict(settings.as_dict()) == settings
    with pytest.raises(ValueError, match="unknown"):
        ExcitationSettings.from_dict({"amplitude": 1.0})


def test_generate_rejects_wrong_seed_count():
    with pytest.raises(ValueError, match="three seeds"):
        generate_excitation((1, 2))


# --- file names --------------------------------------------------------------------------------


def test_parse_seeds_from_a_dataset_name_and_path():
    assert parse_seeds("qube_20230828T150615_434_696_394.csv") == (434, 696, 394)
    assert parse_seeds("/data/x/qube_20230828T161155_017_133_007.csv") == (17, 133, 7)


@pytest.mark.parametrize(
    "name",
    [
        "qube_20230828T150615_434_696.csv",
        "qube_20230828T150615_434_696_394.txt",
        "qube_2023-08-28T150615_434_696_394.csv",
        "run_20230828T150615_434_696_394.csv",
        "qube_20230828T150615_434_696_39a.csv",
    ],
)
def test_parse_seeds_rejects_other_names(name):
    with pytest.raises(ValueError, match="not a dataset file name"):
        parse_seeds(name)
