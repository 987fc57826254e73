"""Power spectra of the closed-loop replay, real vs twin (Welch), and their band-power table.

:func:`replay_spectra` estimates the power spectral density of theta, alpha
and voltage of every validation episode, logged and replayed through the
calibrated twin (:class:`validate.ReplayResult`); :func:`band_power_ratios`
compares the twin's power to the real data's in frequency bands, averaged
over the episodes; :func:`spectra_text` is that comparison as markdown for
``report.md``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy.signal import welch

__all__ = [
    "CHANNELS",
    "BANDS",
    "STD_BANDS",
    "ReplaySpectra",
    "replay_spectra",
    "band_powers",
    "band_power_ratios",
    "band_std_ratios",
    "slow_std_ratio",
    "spectra_text",
]

#: The replay's channels, in the order of the last axis of ``ReplayResult.twin`` and ``.real``.
CHANNELS = ("theta", "alpha", "voltage")
_UNITS = ("rad^2", "rad^2", "V^2")
#: Frequency bands (Hz) of the report's table, each ``[low, high)``.
BANDS = ((0.0, 1.0), (1.0, 3.0), (3.0, 10.0), (10.0, 30.0), (30.0, 100.0))
#: Bands (Hz) of the per-controller standard deviation ratios: the arm's slow wander (below 0.3 Hz and
#: 0.3-1 Hz) apart from the tracking of the reference (1-3 Hz) and the balancing loop (above 3 Hz).
STD_BANDS = ((0.0, 0.3), (0.3, 1.0), (1.0, 3.0), (3.0, np.inf))
#: Welch segment (samples) of :func:`band_std_ratios`: 4096 at 500 Hz resolves 0.12 Hz, so the band
#: below 0.3 Hz holds two bins besides the mean's.
STD_NPERSEG = 4096


@dataclass(frozen=True)
class ReplaySpectra:
    """Welch power spectral densities of the replay, one-sided.

    Attributes
    ----------
    frequency : ndarray (n_f,)
        Bin frequencies (Hz), from 0 to the Nyquist frequency.
    real, twin : ndarray (n_f, n_episodes, 3)
        PSD of theta, alpha (rad^2/Hz) and voltage (V^2/Hz), logged and replayed.
    nperseg : int
        Welch segment length (samples) used.
    """

    frequency: np.ndarray
    real: np.ndarray
    twin: np.ndarray
    nperseg: int

    def mean(self) -> tuple[np.ndarray, np.ndarray]:
        """Real and twin PSD averaged over the episodes, each (n_f, 3)."""
        return self.real.mean(axis=1), self.twin.mean(axis=1)


def replay_spectra(replay, dt: float, nperseg: int = 1024) -> ReplaySpectra:
    """Welch spectra of theta, alpha and voltage per episode, real and twin.

    Parameters
    ----------
    replay : validate.ReplayResult
        Closed-loop replay; ``real`` and ``twin`` are (n_steps, n_episodes, 3).
    dt : float
        Sample period (s); the sampling frequency is ``1 / dt``.
    nperseg : int, optional
        Welch segment length, shortened to the episode length when longer.
        Segments overlap by half and have their mean removed (Hann window).

    Returns
    -------
    ReplaySpectra
    """
    if dt <= 0:
        raise ValueError(f"dt must be positive, got {dt}")
    real, twin = np.asarray(replay.real, float), np.asarray(replay.twin, float)
    if real.shape != twin.shape or real.ndim != 3 or real.shape[2] != len(CHANNELS):
        raise ValueError(f"real and twin must both be (n_steps, n_episodes, 3), got {real.shape} and {twin.shape}")
    n = min(int(nperseg), real.shape[0])
    freq, p_real = welch(real, fs=1.0 / dt, nperseg=n, axis=0)
    _, p_twin = welch(twin, fs=1.0 / dt, nperseg=n, axis=0)
    return ReplaySpectra(freq, p_real, p_twin, n)


def band_powers(frequency: np.ndarray, psd: np.ndarray, bands: Sequence[tuple[float, float]] = BANDS) -> np.ndarray:
    """Power in each band: the PSD summed over the bins in ``[low, high)`` times the bin width.

    Parameters
    ----------
    frequency : ndarray (n_f,)
        Evenly spaced bin frequencies (Hz).
    psd : ndarray (n_f, ...)
        Power spectral density along the first axis.
    bands : sequence of (float, float)
        Band edges (Hz). A band without bins (e.g. above the Nyquist frequency) has power NaN.

    Returns
    -------
    ndarray (n_bands, ...)
    """
    df = frequency[1] - frequency[0] if len(frequency) > 1 else 1.0
    out = []
    for low, high in bands:
        inside = (frequency >= low) & (frequency < high)
        out.append(psd[inside].sum(axis=0) * df if inside.any() else np.full(psd.shape[1:], np.nan))
    return np.array(out)


def band_power_ratios(spectra: ReplaySpectra, bands: Sequence[tuple[float, float]] = BANDS) -> np.ndarray:
    """Twin / real band power, each averaged over the episodes first: (n_bands, 3).

    A twin that reproduces the data's power gives 1; a band where the real
    power is zero gives inf or NaN.
    """
    real, twin = spectra.mean()
    with np.errstate(divide="ignore", invalid="ignore"):
        return band_powers(spectra.frequency, twin, bands) / band_powers(spectra.frequency, real, bands)


def band_std_ratios(
    replay,
    dt: float,
    bands: Sequence[tuple[float, float]] = STD_BANDS,
    nperseg: int = STD_NPERSEG,
    all_draws: bool = False,
) -> np.ndarray:
    """Standard deviation ratio twin / real of each channel within each band: the median over episodes.

    Each episode's ratio is the square root of its twin band power over its
    real band power (Welch, :func:`replay_spectra`); the median over the
    episodes is returned, as for the replay's overall ratios.

    Parameters
    ----------
    replay : validate.ReplayResult
    dt : float
        Sample period (s).
    bands : sequence of (float, float), optional
        Band edges (Hz), default :data:`STD_BANDS`.
    nperseg : int, optional
        Welch segment length (shortened to the episode's length).
    all_draws : bool, optional
        Average each episode's twin band power over all its replays (``replay.twins``: the draws of
        start angle and of a random load) before the ratio; by default the first replay's.

    Returns
    -------
    ndarray (n_bands, 3)
        Columns theta, alpha, voltage.
    """
    spectra = replay_spectra(replay, dt, nperseg)
    real = band_powers(spectra.frequency, spectra.real, bands)
    twin = band_powers(spectra.frequency, spectra.twin, bands)
    if all_draws and getattr(replay, "twins", None) is not None:  # every replay's band power, averaged
        n = min(int(nperseg), replay.real.shape[0])
        frequency, psd = welch(np.asarray(replay.twins, float), fs=1.0 / dt, nperseg=n, axis=0)
        twin = band_powers(frequency, psd, bands).mean(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.median(np.sqrt(twin / real), axis=1)


def slow_std_ratio(replay, dt: float, cutoff: float = 0.5) -> np.ndarray:
    """Median over episodes of the std ratio twin / real of each channel low-passed at ``cutoff`` Hz.

    A second-order Butterworth filter run forwards and backwards (no phase
    shift): the slow motion the arm's wander shows in. Returns (3,).
    """
    from scipy.signal import butter, sosfiltfilt

    sos = butter(2, cutoff, fs=1.0 / dt, output="sos")
    real = sosfiltfilt(sos, np.asarray(replay.real, float), axis=0)
    twin = sosfiltfilt(sos, np.asarray(replay.twin, float), axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.median(twin.std(axis=0) / real.std(axis=0), axis=0)


def _number(value: float, spec: str) -> str:
    return "-" if np.isnan(value) else format(value, spec)


def spectra_text(replay, dt: float, bands: Sequence[tuple[float, float]] = BANDS, nperseg: int = 1024) -> str:
    """Markdown: per channel, the real and twin band power averaged over the episodes and their ratio.

    Parameters
    ----------
    replay : validate.ReplayResult
        Closed-loop replay of the validation episodes.
    dt : float
        Sample period (s).
    bands : sequence of (float, float), optional
        Band edges (Hz), default :data:`BANDS`.
    nperseg : int, optional
        Welch segment length (:func:`replay_spectra`).

    Returns
    -------
    str
        A section with one table per channel (theta, alpha, voltage).
    """
    spectra = replay_spectra(replay, dt, nperseg)
    real, twin = (band_powers(spectra.frequency, p, bands) for p in spectra.mean())
    ratio = band_power_ratios(spectra, bands)
    n_episodes = spectra.real.shape[1]
    lines = [
        f"## Power spectra of the replay, twin vs real ({n_episodes} episodes)",
        "",
        f"Welch, {spectra.nperseg}-sample Hann segments at {1 / dt:g} Hz "
        f"(resolution {1 / (dt * spectra.nperseg):.3g} Hz); band power is the PSD "
        "integrated over the band, averaged over the episodes; twin/real is the ratio of those averages.",
    ]
    for j, (channel, unit) in enumerate(zip(CHANNELS, _UNITS)):
        lines += [
            "",
            f"### {channel}",
            "",
            f"| band (Hz) | real ({unit}) | twin ({unit}) | twin/real |",
            "|---|---|---|---|",
        ]
        for b, (low, high) in enumerate(bands):
            lines.append(
                f"| {low:g}-{high:g} | {_number(real[b, j], '.3g')} | {_number(twin[b, j], '.3g')} "
                f"| {_number(ratio[b, j], '.3f')} |"
            )
    return "\n".join(lines) + "\n"
