"""Episode file names: one pattern for the logs ``qube-run`` writes and the rig's CSV files.

A name is ``qube_<YYYYMMDD>T<HHMMSS>[.<ms>]_<theta seed>_<alpha seed>_<ff seed>[_<n>]<suffix>``:
the start time (ISO 8601 basic; milliseconds in the logs, where free-running episodes start
several per second), the three excitation seeds, and a ``_<n>`` only when a name was taken.
Names sort in the order the episodes ran (the paper's split takes the first files by name).
"""

from __future__ import annotations

import re
from datetime import datetime, timezone
from pathlib import Path
from typing import Mapping, NamedTuple

__all__ = [
    "LOG_SUFFIX",
    "SEED_SIGNALS",
    "EpisodeName",
    "episode_stem",
    "parse_episode_name",
    "log_path",
    "find_logs",
    "expand_logs",
]

#: Suffix of an episode log.
LOG_SUFFIX = ".mcap"

#: The excitation signals, in the order their seeds appear in a name.
SEED_SIGNALS = ("target_theta", "target_alpha", "feedforward")

_PATTERN = r"qube_(\d{8}T\d{6})(?:\.(\d{3}))?_(\d+)_(\d+)_(\d+)(?:_\d+)?"


class EpisodeName(NamedTuple):
    """What a file name says: its start time text and the excitation seeds."""

    stamp: str
    milliseconds: int | None
    seeds: dict[str, int]


def episode_stem(start: datetime, seeds: Mapping[str, int]) -> str:
    """``qube_<date>T<time>.<ms>_<s1>_<s2>_<s3>``: the start time (in UTC when it has a zone) and seeds.

    Parameters
    ----------
    start : datetime
        When the episode started.
    seeds : mapping
        Seeds by signal name (:data:`SEED_SIGNALS`); missing ones are left out.

    Returns
    -------
    str
        The file name without suffix.
    """
    if start.tzinfo is not None:
        start = start.astimezone(timezone.utc)
    parts = [str(seeds[k]) for k in SEED_SIGNALS if k in seeds]
    return "_".join([f"qube_{start:%Y%m%dT%H%M%S}.{start.microsecond // 1000:03d}", *parts])


def parse_episode_name(path: str | Path, suffix: str) -> EpisodeName | None:
    """Start time and seeds from a file name (folders ignored), or None when it does not follow the pattern.

    Parameters
    ----------
    path : str or Path
        The file.
    suffix : str
        The suffix it must have (``".csv"``, :data:`LOG_SUFFIX`).

    Returns
    -------
    EpisodeName or None
    """
    match = re.fullmatch(_PATTERN + re.escape(suffix), Path(path).name)
    if match is None:
        return None
    ms = None if match[2] is None else int(match[2])
    return EpisodeName(match[1], ms, dict(zip(SEED_SIGNALS, map(int, match.groups()[2:]))))


def log_path(folder: str | Path, stem: str) -> Path:
    """The episode log named ``stem`` in ``folder``.

    Parameters
    ----------
    folder : str or Path
        Where the logs are.
    stem : str
        The episode's name (:func:`episode_stem`), without the suffix.

    Returns
    -------
    Path
    """
    return Path(folder) / f"{stem}{LOG_SUFFIX}"


def find_logs(folder: str | Path) -> list[Path]:
    """The episode logs in ``folder``, sorted by name (so in the order they ran).

    Parameters
    ----------
    folder : str or Path
        Where the logs are.

    Returns
    -------
    list of Path
    """
    return sorted(Path(folder).glob(f"*{LOG_SUFFIX}"))


def expand_logs(items) -> list[Path]:
    """Log paths from a command line: files as given, folders as the logs in them (:func:`find_logs`).

    Parameters
    ----------
    items : iterable of str or Path, or None

    Returns
    -------
    list of Path

    Raises
    ------
    CliError
        An item that does not exist, or a folder without logs (the message names it).
    """
    from qube_koopman.core.command import CliError

    paths = []
    for item in items or []:
        path = Path(item)
        if path.is_dir():
            found = find_logs(path)
            if not found:
                raise CliError(f"{path}: folder has no {LOG_SUFFIX} logs")
            paths.extend(found)
        elif path.is_file():
            paths.append(path)
        else:
            raise CliError(f"{path}: no such file or folder")
    return paths
