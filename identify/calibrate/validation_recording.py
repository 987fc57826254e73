"""A rerun recording of a calibration's validation (rerun-sdk imported lazily; the ``viz`` extra).

Entities: ``validation/<episode>/<channel>/{real,twin}`` against the timeline
``time`` (seconds from the start of the replay), for the channels theta,
alpha (rad) and voltage (V); ``spectra/<channel>/{real,twin}``, the log10 of
the Welch PSD averaged over the validation episodes, against the bin index
(timeline ``frequency_bin``) and the bin frequency rounded to integer
millihertz (timeline ``frequency_millihertz``); ``spectra/frequency_hz``
gives each bin's frequency in Hz.

The recording carries a blueprint (:func:`blueprint`): one tab with a grid of
the validation episodes (theta, alpha and voltage, real vs twin, one plot
each), one with the three spectra. The viewer opens on the ``time``
timeline; the spectra need ``frequency_bin`` or ``frequency_millihertz``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from qube_koopman.core.rrd import RrdFile, import_rerun
from qube_koopman.identify.calibrate.replay_spectra import CHANNELS, replay_spectra

__all__ = ["blueprint", "episode_paths", "write_recording"]

#: Series colours: the logged data light grey, the twin orange.
_COLORS = {"real": (190, 190, 190), "twin": (255, 140, 0)}


def episode_paths(names: list[str]) -> list[str]:
    """Entity path parts of the episodes: the log names without their suffix, escaped, made unique."""
    import rerun as rr

    parts: list[str] = []
    for i, name in enumerate(names):
        part = rr.escape_entity_path_part(Path(str(name)).stem or f"episode_{i}")
        parts.append(part if part not in parts else f"{part}_{i}")
    return parts


def blueprint(parts: list[str], names: list[str] | None = None):
    """The recording's layout: a tab of validation episodes (a grid), a tab of spectra.

    Parameters
    ----------
    parts : list of str
        The episodes' entity path parts (:func:`episode_paths`).
    names : list of str, optional
        Their titles; ``parts`` when not given.
    """
    import rerun.blueprint as rrb

    cells = [
        rrb.Vertical(
            *(
                rrb.TimeSeriesView(origin=f"validation/{part}/{channel}", name=f"{title}: {channel}")
                for channel in CHANNELS
            ),
            name=title,
        )
        for part, title in zip(parts, names or parts)
    ]
    spectra = [
        rrb.TimeSeriesView(origin=f"spectra/{channel}", name=f"{channel}: log10 PSD, real vs twin")
        for channel in CHANNELS
    ]
    spectra.append(rrb.TimeSeriesView(origin="spectra/frequency_hz", name="bin frequency (Hz)"))
    tabs = rrb.Tabs(
        rrb.Grid(*cells, name="validation episodes: real vs twin (x: time)"),
        rrb.Grid(*spectra, name="power spectra (x: frequency_bin or frequency_millihertz)"),
    )
    return rrb.Blueprint(tabs, rrb.TimePanel(timeline="time", state="collapsed"), collapse_panels=True)


def _send(rec, path: str, indexes, values: np.ndarray) -> None:
    import rerun as rr

    values = np.asarray(values, dtype=float)
    rec.send_columns(
        path, indexes=indexes, columns=rr.Scalars.columns(scalars=np.where(np.isfinite(values), values, np.nan))
    )


def _style(rec, path: str, kind: str) -> None:
    import rerun as rr

    rec.log(path, rr.SeriesLines(colors=[_COLORS[kind]], names=[kind]), static=True)


def write_recording(path: str | Path, replay, names: list[str], dt: float, nperseg: int = 1024) -> Path:
    """Write the validation replay and its spectra to an .rrd file.

    Parameters
    ----------
    path : str or Path
        The .rrd file to write (replaced when it exists).
    replay : validate.ReplayResult
        Closed-loop replay; ``real`` and ``twin`` are (n_steps, n_episodes, 3).
    names : list of str
        The validation logs' names, one per episode.
    dt : float
        Sample period (s) of the replay.
    nperseg : int, optional
        Welch segment length (:func:`spectra.replay_spectra`).

    Returns
    -------
    Path
        ``path``.
    """
    if len(names) != replay.real.shape[1]:
        raise ValueError(f"{len(names)} names for {replay.real.shape[1]} replayed episodes")
    rr = import_rerun()
    parts = episode_paths(names)
    path = Path(path)
    rrd = RrdFile(path, "qube-calibrate", blueprint=blueprint(parts, [Path(str(n)).stem for n in names]))
    rec = rrd.recording
    time = [rr.TimeColumn("time", duration=np.arange(replay.real.shape[0]) * dt)]
    for i, part in enumerate(parts):
        for j, channel in enumerate(CHANNELS):
            for kind, data in (("real", replay.real), ("twin", replay.twin)):
                _style(rec, f"validation/{part}/{channel}/{kind}", kind)
                _send(rec, f"validation/{part}/{channel}/{kind}", time, data[:, i, j])
    spectra = replay_spectra(replay, dt, nperseg)
    bins = [
        rr.TimeColumn("frequency_bin", sequence=np.arange(len(spectra.frequency))),
        rr.TimeColumn("frequency_millihertz", sequence=np.round(1e3 * spectra.frequency).astype(np.int64)),
    ]
    _send(rec, "spectra/frequency_hz", bins, spectra.frequency)
    with np.errstate(divide="ignore", invalid="ignore"):
        for kind, psd in zip(("real", "twin"), spectra.mean()):
            for j, channel in enumerate(CHANNELS):
                _style(rec, f"spectra/{channel}/{kind}", kind)
                _send(rec, f"spectra/{channel}/{kind}", bins, np.log10(psd[:, j]))
    rrd.save()  # whole or not at all
    return path
