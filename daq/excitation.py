"""The rig's excitation: smoothed PRBS references and feedforward.

Reproduces, sample for sample, the generator of the C program that recorded
the paper's QUBE-Servo dataset, so an episode's target_theta, target_alpha and
feedforward follow from the three seeds in its file name.

How the rig built each signal (checked against all 48 dataset files):

1. A 16-bit Fibonacci LFSR (taps 16, 14, 13, 11) started at the seed gives
   one bit per bit period; the LFSR advances once per bit, not per sample.
   The bits start at sample 0, so the first ``window_start`` samples consume
   bits that are then blanked.
2. Each bit is held for ``bit_period * sample_rate`` samples and maps to
   ``+amplitude`` (bit 1) or ``-amplitude`` (bit 0). Only whole bits that
   fit before ``window_stop`` are generated; anything after is zero.
3. Samples before ``window_start`` are set to zero, then the first-order
   low-pass ``y[k] = g x[k] + (1 - g) y[k-1]``, ``g = (c/fs) / (1 + c/fs)``
   (backward Euler of ``c/(s + c)``) runs over samples ``0 .. window_stop-1``.
   From ``window_stop`` on the signal is exactly zero (no filter tail).
4. target_theta is the forward-Euler integral of the smoothed rate signal,
   ``out[0] = 0``, ``out[i] = out[i-1] + in[i] / fs``, so it holds its last
   value once the rate is zero.
"""

from __future__ import annotations

import sys

from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Iterator

import numpy as np

from qube_koopman.core.controller import QUBE_SAMPLE_PERIOD
from qube_koopman.daq.log.names import SEED_SIGNALS, parse_episode_name

__all__ = [
    "PrbsChannel",
    "ExcitationSettings",
    "Excitation",
    "ExcitationStream",
    "lfsr_bits",
    "held_prbs",
    "smooth",
    "integrate",
    "generate_excitation",
    "parse_seeds",
]

_SEED_MAX = 0xFFFF


def lfsr_bits(seed: int, n_bits: int) -> np.ndarray:
    """Output bits of the rig's 16-bit Fibonacci LFSR (taps 16, 14, 13, 11).

    Parameters
    ----------
    seed : int
        Initial register, 1 .. 65535 (zero would lock the register at zero).
    n_bits : int
        Number of bits to produce (non-negative).

    Returns
    -------
    ndarray of bool, shape (n_bits,)
        The feedback bit of each shift, which is also the output bit.
    """
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not 1 <= seed <= _SEED_MAX:
        raise ValueError(f"LFSR seed must be an integer in 1..{_SEED_MAX}, got {seed!r}")
    if n_bits < 0:
        raise ValueError(f"n_bits must be non-negative, got {n_bits}")
    register = int(seed)
    out = np.empty(n_bits, dtype=bool)
    for i in range(n_bits):
        bit = (register ^ (register >> 2) ^ (register >> 3) ^ (register >> 5)) & 1
        register = (register >> 1) | (bit << 15)
        out[i] = bit
    return out


def held_prbs(seed: int, amplitude: float, bit_samples: int, n_samples: int) -> np.ndarray:
    """Binary sequence of +-amplitude, each LFSR bit held for ``bit_samples`` samples.

    Only whole bits are produced; samples after the last whole bit are zero,
    as on the rig.
    """
    if bit_samples < 1:
        raise ValueError(f"a bit must last at least one sample, got {bit_samples}")
    if n_samples < 0:
        raise ValueError(f"n_samples must be non-negative, got {n_samples}")
    bits = lfsr_bits(seed, n_samples // bit_samples)
    out = np.zeros(n_samples)
    levels = np.where(bits, float(amplitude), -float(amplitude))
    out[: bits.size * bit_samples] = np.repeat(levels, bit_samples)
    return out


def smooth(x: np.ndarray, cutoff: float, sample_rate: float) -> np.ndarray:
    """First-order low-pass ``c/(s + c)`` discretized by backward Euler, from rest.

    ``y[k] = g x[k] + p y[k-1]`` with ``g = (c/fs) / (1 + c/fs)`` and
    ``p = 1 / (1 + c/fs)``, both computed as the rig did so the output
    matches its rounding. ``cutoff <= 0`` returns a copy (the rig's "no
    smoothing").
    """
    x = np.array(x, dtype=float)
    if cutoff <= 0:
        return x
    ratio = cutoff / sample_rate
    return _low_pass(ratio / (1.0 + ratio), 1.0 / (1.0 + ratio), x, 0.0)[0]


#: Longest signal the low-pass filters in a Python loop (:func:`_low_pass`): 100,000 samples take
#: about 50 ms there, and importing scipy.signal about 1-2 s.
_LOOP_SAMPLES = 100_000


def _low_pass(gain: float, pole: float, x: np.ndarray, previous: float, long: bool = False) -> tuple[np.ndarray, float]:
    """``y[k] = gain x[k] + pole y[k-1]`` from ``y[-1] = previous``; the outputs and the last one.

    The products and sums of ``scipy.signal.lfilter([gain], [1, -pole], x)``, bit for bit
    (tests/daq/test_excitation.py), in a loop of Python floats for an ordinary episode (its
    10,000 samples take about 5 ms; importing scipy.signal took 1-2 s of every ``qube-run``'s
    start-up), by lfilter itself for a signal longer than ``_LOOP_SAMPLES`` (or ``long``:
    chunks of one) or once scipy.signal is imported anyway.
    """
    x = np.asarray(x, dtype=float)
    if long or len(x) > _LOOP_SAMPLES or "scipy.signal" in sys.modules:
        from scipy.signal import lfilter

        out = lfilter([gain], [1.0, -pole], x, zi=[pole * previous])[0]
        return out, float(out[-1]) if len(out) else previous
    return _loop_low_pass(gain, pole, x, previous)


def _long_window(settings: "ExcitationSettings") -> bool:
    """Whether the excitation's window is smoothed by lfilter rather than the loop (``_LOOP_SAMPLES``)."""
    return settings.window_stop - settings.window_start > _LOOP_SAMPLES


def _loop_low_pass(gain: float, pole: float, x: np.ndarray, previous: float) -> tuple[np.ndarray, float]:
    """:func:`_low_pass` in a loop of Python floats."""
    out = np.empty(len(x))
    y = previous
    for k, value in enumerate(x.tolist()):
        y = gain * value + pole * y
        out[k] = y
    return out, y


def integrate(rate: np.ndarray, sample_rate: float) -> np.ndarray:
    """Forward-Euler running integral as the rig did it.

    ``out[0] = 0`` (``rate[0]`` is not used), ``out[i] = out[i-1] + rate[i] / fs``.
    """
    rate = np.asarray(rate, dtype=float)
    out = np.empty_like(rate)
    if rate.size:
        out[0] = 0.0
        # cumsum adds sequentially, so it rounds exactly as the rig's loop did.
        np.cumsum((1.0 / sample_rate) * rate[1:], out=out[1:])
    return out


@dataclass(frozen=True)
class PrbsChannel:
    """One PRBS channel: levels ``+-amplitude``, each bit held ``bit_period`` seconds."""

    amplitude: float
    bit_period: float

    def __post_init__(self) -> None:
        for name in ("amplitude", "bit_period"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
                raise ValueError(f"PRBS {name} must be a finite number, got {value!r}")
        if self.amplitude < 0:
            raise ValueError(f"PRBS amplitude must be non-negative, got {self.amplitude}")
        if self.bit_period <= 0:
            raise ValueError(f"PRBS bit_period must be positive, got {self.bit_period}")

    def bit_samples(self, sample_rate: float) -> int:
        """Samples per bit; the bit period must be a whole number of samples."""
        exact = self.bit_period * sample_rate
        n = round(exact)
        if n < 1 or abs(exact - n) > 1e-9 * max(1.0, exact):
            raise ValueError(
                f"bit period {self.bit_period} s is not a whole number of samples at {sample_rate} Hz ({exact} samples)"
            )
        return n


@dataclass(frozen=True)
class ExcitationSettings:
    """Settings of the rig's excitation; the defaults are those that recorded the dataset.

    Parameters
    ----------
    sample_rate : float
        Samples per second.
    n_samples : int
        Episode length in samples.
    window_start, window_stop : int
        Active window ``[window_start, window_stop)``: the signals are zero
        before it and zero after it (target_theta holds its last value).
    theta_rate : PrbsChannel
        Rate PRBS (rad/s) integrated into target_theta.
    alpha : PrbsChannel
        Pendulum-angle reference PRBS (rad).
    feedforward : PrbsChannel
        Feedforward voltage PRBS (V).
    smoothing_cutoff : float
        Cutoff ``c`` (rad/s) of the low-pass applied to all three PRBS;
        ``c / sample_rate`` is the coefficient in
        ``y[k] = (c/fs) / (1 + c/fs) x[k] + 1 / (1 + c/fs) y[k-1]``
        (0.4 on the rig). Zero or negative disables smoothing.
    """

    sample_rate: float = 1.0 / QUBE_SAMPLE_PERIOD
    n_samples: int = 10_000
    window_start: int = 2000
    window_stop: int = 8000
    theta_rate: PrbsChannel = PrbsChannel(0.25, 0.25)
    alpha: PrbsChannel = PrbsChannel(0.01, 0.1)
    feedforward: PrbsChannel = PrbsChannel(0.5, 0.1)
    smoothing_cutoff: float = 200.0

    def __post_init__(self) -> None:
        if not (np.isfinite(self.sample_rate) and self.sample_rate > 0):
            raise ValueError(f"sample_rate must be positive, got {self.sample_rate!r}")
        if not np.isfinite(self.smoothing_cutoff):
            raise ValueError(f"smoothing_cutoff must be finite, got {self.smoothing_cutoff!r}")
        for name in ("n_samples", "window_start", "window_stop"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
                raise ValueError(f"{name} must be an integer number of samples, got {value!r}")
        if not 0 <= self.window_start <= self.window_stop <= self.n_samples:
            raise ValueError(
                "need 0 <= window_start <= window_stop <= n_samples, got "
                f"{self.window_start}, {self.window_stop}, {self.n_samples}"
            )
        for name in ("theta_rate", "alpha", "feedforward"):
            channel = getattr(self, name)
            if not isinstance(channel, PrbsChannel):
                raise ValueError(f"{name} must be a PrbsChannel, got {channel!r}")
            channel.bit_samples(self.sample_rate)

    def as_dict(self) -> dict:
        """Plain-data form, for episode metadata."""
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> "ExcitationSettings":
        """Inverse of :meth:`as_dict`."""
        unknown = sorted(set(data) - {f.name for f in fields(cls)})
        if unknown:
            raise ValueError(f"unknown excitation settings {', '.join(unknown)}")
        values = dict(data)
        for name in ("theta_rate", "alpha", "feedforward"):
            if name in values and isinstance(values[name], dict):
                values[name] = PrbsChannel(**values[name])
        return cls(**values)


@dataclass(frozen=True, eq=False)
class Excitation:
    """The three exogenous signals of an episode, one sample per row of the log."""

    target_theta: np.ndarray
    target_alpha: np.ndarray
    feedforward: np.ndarray

    def __len__(self) -> int:
        return len(self.target_theta)

    def chunks(self, size: int) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """(target_theta, target_alpha, feedforward) ``size`` samples at a time (the last may be shorter)."""
        for k in range(0, len(self), size):
            theta, alpha, feedforward = (
                np.asarray(signal[k : k + size], dtype=float)
                for signal in (self.target_theta, self.target_alpha, self.feedforward)
            )
            yield theta, alpha, feedforward


class _ChannelStream:
    """One channel's windowed, smoothed PRBS (steps 1 to 3 of the module docstring), chunk by chunk."""

    def __init__(self, seed: int, channel: PrbsChannel, settings: ExcitationSettings) -> None:
        lfsr_bits(seed, 0)  # checks the seed
        self.register = int(seed)
        self.amplitude = float(channel.amplitude)
        self.bit_samples = channel.bit_samples(settings.sample_rate)
        # Only whole bits that fit before window_stop are generated; zero after them.
        self.held_end = (settings.window_stop // self.bit_samples) * self.bit_samples
        self.window_start, self.window_stop = settings.window_start, settings.window_stop
        ratio = settings.smoothing_cutoff / settings.sample_rate
        self.smoothing = settings.smoothing_cutoff > 0
        self.gain, self.pole = ratio / (1.0 + ratio), 1.0 / (1.0 + ratio)  # as smooth() computes them
        self.previous = 0.0
        self.long = _long_window(settings)  # filtered by lfilter, chunk by chunk
        self.next_bit = 0
        self.level = 0.0

    def _levels(self, first: int, last: int) -> np.ndarray:
        """The held levels of bits ``first..last``; bit ``first`` is the last one made, or the next."""
        levels = [self.level] if first < self.next_bit else []
        register, high, low = self.register, self.amplitude, -self.amplitude
        for _ in range(self.next_bit, last + 1):
            bit = (register ^ (register >> 2) ^ (register >> 3) ^ (register >> 5)) & 1
            register = (register >> 1) | (bit << 15)
            levels.append(high if bit else low)
        self.register, self.next_bit, self.level = register, last + 1, levels[-1]
        return np.array(levels)

    def take(self, k0: int, k1: int) -> np.ndarray:
        """Samples ``k0 .. k1 - 1`` (called for consecutive ranges from 0)."""
        out = np.zeros(k1 - k0)
        held = min(k1, self.held_end)
        if held > k0:
            bit = np.arange(k0, held) // self.bit_samples
            out[: held - k0] = self._levels(int(bit[0]), int(bit[-1]))[bit - bit[0]]
        out[: max(0, min(self.window_start, k1) - k0)] = 0.0
        active = min(k1, self.window_stop) - k0
        if active > 0 and self.smoothing:
            out[:active], self.previous = _low_pass(self.gain, self.pole, out[:active], self.previous, self.long)
        return out


class ExcitationStream:
    """The rig's excitation for one episode, made a chunk at a time: memory does not grow with its length.

    Chunk for chunk the same values, bit for bit, as the whole-episode arrays of
    :func:`generate_excitation` (which is this stream taken in one chunk).

    Parameters
    ----------
    seeds : (int, int, int)
        LFSR seeds of the motor-angle rate, pendulum-angle reference and feedforward.
    settings : ExcitationSettings
        Amplitudes, bit periods, window and smoothing.
    """

    def __init__(self, seeds: tuple[int, int, int], settings: ExcitationSettings = ExcitationSettings()) -> None:
        if len(seeds) != 3:
            raise ValueError(f"need three seeds (theta, alpha, feedforward), got {seeds!r}")
        for seed in seeds:
            lfsr_bits(seed, 0)
        self.seeds = tuple(int(seed) for seed in seeds)
        self.settings = settings
        if settings.smoothing_cutoff > 0 and _long_window(settings):
            import scipy.signal  # noqa: F401  (a long stream's filter: imported as it is made, not as it streams)

    def __len__(self) -> int:
        return self.settings.n_samples

    def chunks(self, size: int) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """(target_theta, target_alpha, feedforward) ``size`` samples at a time (the last may be shorter)."""
        if size < 1:
            raise ValueError(f"chunk size must be positive, got {size}")
        settings = self.settings
        channels = [
            _ChannelStream(seed, channel, settings)
            for seed, channel in zip(self.seeds, (settings.theta_rate, settings.alpha, settings.feedforward))
        ]
        step = 1.0 / settings.sample_rate
        theta_end = 0.0
        for k0 in range(0, len(self), size):
            k1 = min(len(self), k0 + size)
            rate, alpha, ff = (channel.take(k0, k1) for channel in channels)
            # integrate(), continued across chunks: the same sequential additions.
            theta = np.empty_like(rate)
            if k0 == 0:
                theta[0] = 0.0
                np.cumsum(step * rate[1:], out=theta[1:])
            else:
                theta = np.cumsum(np.concatenate(([theta_end], step * rate)))[1:]
            theta_end = theta[-1]
            yield theta, alpha, ff

    def whole(self) -> Excitation:
        """The whole episode as read-only arrays."""
        n = len(self)
        signals = next(self.chunks(n)) if n else (np.zeros(0), np.zeros(0), np.zeros(0))
        for s in signals:
            s.setflags(write=False)
        return Excitation(*signals)

    @property
    def target_theta(self) -> np.ndarray:
        """The whole episode's target_theta (made when asked for)."""
        return self.whole().target_theta

    @property
    def target_alpha(self) -> np.ndarray:
        """The whole episode's target_alpha (made when asked for)."""
        return self.whole().target_alpha

    @property
    def feedforward(self) -> np.ndarray:
        """The whole episode's feedforward (made when asked for)."""
        return self.whole().feedforward


def generate_excitation(seeds: tuple[int, int, int], settings: ExcitationSettings = ExcitationSettings()) -> Excitation:
    """The rig's references and feedforward for one episode.

    Parameters
    ----------
    seeds : (int, int, int)
        LFSR seeds of the motor-angle rate, pendulum-angle reference and
        feedforward, as in the dataset's file names (see :func:`parse_seeds`).
    settings : ExcitationSettings
        Amplitudes, bit periods, window and smoothing.

    Returns
    -------
    Excitation
        target_theta (rad), target_alpha (rad), feedforward (V), each of
        ``settings.n_samples`` samples; read-only arrays. For long episodes,
        :class:`ExcitationStream` makes the same values a chunk at a time.
    """
    return ExcitationStream(seeds, settings).whole()


def parse_seeds(file_name: str | Path) -> tuple[int, int, int]:
    """The three seeds in a dataset file name ``qube_<date>T<time>_<theta>_<alpha>_<ff>.csv``.

    Raises
    ------
    ValueError
        If the name (directories are ignored) does not have that form.
    """
    name = Path(file_name).name
    parsed = parse_episode_name(name, ".csv")
    if parsed is None:
        raise ValueError(
            f"{name!r} is not a dataset file name of the form "
            "'qube_<YYYYMMDD>T<HHMMSS>_<theta seed>_<alpha seed>_<ff seed>.csv'"
        )
    theta, alpha, feedforward = (parsed.seeds[k] for k in SEED_SIGNALS)
    return theta, alpha, feedforward
