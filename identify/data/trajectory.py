"""Trajectories: one episode's time-aligned signals, as identification sees them."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from qube_koopman.identify._checks import as_signal

__all__ = [
    "Trajectory",
    "EpisodeShape",
    "check_trajectories",
    "EpisodeSequence",
    "as_episodes",
    "select_episodes",
    "episode_signals",
]

#: The signals a trajectory may have, besides its states ``x``.
SIGNALS = ("u", "r", "f", "xc")


@dataclass(frozen=True, eq=False)
class Trajectory:
    """Signals of one episode, one row per sample (the naming guide's symbols).

    Parameters
    ----------
    x : array_like of shape (n_samples, n_states)
        Measured plant states (for the QUBE-Servo: theta, alpha).
    u : array_like of shape (n_samples, n_plant_inputs), optional
        Plant input (controller output plus feedforward, as applied).
    r : array_like of shape (n_samples, n_references), optional
        Controller reference.
    f : array_like of shape (n_samples, n_plant_inputs), optional
        Feedforward added to the controller output.
    xc : array_like of shape (n_samples, n_controller_states), optional
        Controller state.
    name : str
        Where the episode came from (file name); used in messages.
    state_names, input_names : sequence of str, optional
        Names of the columns of ``x`` and ``u``.
    dt : float, optional
        Sample period in seconds.

    Raises
    ------
    ValueError
        If a signal is not 1-D/2-D, has a non-finite value or a different
        number of samples than ``x``.
    """

    x: np.ndarray
    u: np.ndarray | None = None
    r: np.ndarray | None = None
    f: np.ndarray | None = None
    xc: np.ndarray | None = None
    name: str = ""
    state_names: tuple[str, ...] | None = field(default=None)
    input_names: tuple[str, ...] | None = field(default=None)
    dt: float | None = None

    def __post_init__(self) -> None:
        label = f"trajectory {self.name!r}: " if self.name else ""
        if self.dt is not None and not (np.isfinite(self.dt) and self.dt > 0):
            raise ValueError(f"{label}dt must be a positive number of seconds, got {self.dt!r}")
        x = as_signal(self.x, f"{label}x")
        object.__setattr__(self, "x", x)
        for key in ("u", "r", "f", "xc"):
            value = getattr(self, key)
            if value is not None:
                object.__setattr__(self, key, as_signal(value, f"{label}{key}", n_samples=x.shape[0]))
        for key, n in (("state_names", x.shape[1]), ("input_names", None if self.u is None else self.u.shape[1])):
            names = getattr(self, key)
            if names is not None:
                names = tuple(str(s) for s in names)
                if n is not None and len(names) != n:
                    raise ValueError(f"{label}{key} has {len(names)} names for {n} channels")
                object.__setattr__(self, key, names)

    @property
    def n_samples(self) -> int:
        """Number of samples."""
        return self.x.shape[0]

    def skip(self, n: int) -> "Trajectory":
        """The same trajectory without its first ``n`` samples."""

        def cut(signal: np.ndarray | None) -> np.ndarray | None:
            return None if signal is None else signal[n:]

        return replace(self, x=self.x[n:], u=cut(self.u), r=cut(self.r), f=cut(self.f), xc=cut(self.xc))

    def width(self, signal: str) -> int | None:
        """Channels of ``signal`` (``"x"``, ``"u"``, ``"r"``, ``"f"`` or ``"xc"``), None when it has none."""
        value = getattr(self, signal)
        return None if value is None else value.shape[1]

    def shape(self) -> "EpisodeShape":
        """What checks of this trajectory look at, without its samples."""
        return EpisodeShape(self.name, self.dt, self.n_samples, {key: self.width(key) for key in ("x", *SIGNALS)})


@dataclass(frozen=True)
class EpisodeShape:
    """An episode's name, sample period, length and signal widths: what the data checks read.

    A lazy sequence that knows its episodes' shapes (:meth:`EpisodeSequence.shapes`) is checked
    from them, without reading every episode again at every fit.

    Parameters
    ----------
    name : str
    dt : float or None
        Sample period in seconds.
    n_samples : int
    widths : dict
        Channels per signal (``"x"``, ``"u"``, ``"r"``, ``"f"``, ``"xc"``), None for a missing one.
    """

    name: str
    dt: float | None
    n_samples: int
    widths: dict

    def width(self, signal: str) -> int | None:
        """Channels of ``signal``, None when the episode has none (as :meth:`Trajectory.width`)."""
        return self.widths.get(signal)


class EpisodeSequence(Sequence):
    """Episodes made when asked for and not kept: memory holds one at a time, whatever their number.

    Subclasses say how to make episode ``i`` (:meth:`_make`), e.g. by reading its log again
    (:class:`~qube_koopman.identify.data.logs.LogTrajectories`). Fits, sweeps and scores pass over such a
    sequence episode by episode; a list of in-memory trajectories works the same.
    """

    def _make(self, i: int):
        raise NotImplementedError

    def shapes(self) -> "list[EpisodeShape] | None":
        """Every episode's :class:`EpisodeShape` when known without reading the episodes, else None."""
        return None

    def __getitem__(self, index):
        if isinstance(index, slice):
            return [self._make(i) for i in range(*index.indices(len(self)))]
        i = int(index) + (len(self) if index < 0 else 0)
        if not 0 <= i < len(self):
            raise IndexError(f"episode {index} of {len(self)}")
        return self._make(i)


class _EpisodeView(EpisodeSequence):
    """Some episodes of a lazy sequence (``indices``), or one signal of each (``signal``)."""

    def __init__(
        self, base: EpisodeSequence, indices: Sequence[int] | np.ndarray | None = None, signal: str | None = None
    ):
        self._base, self._indices, self._signal = base, None if indices is None else [int(i) for i in indices], signal

    def __len__(self) -> int:
        return len(self._base) if self._indices is None else len(self._indices)

    def _make(self, i: int):
        episode = self._base[i if self._indices is None else self._indices[i]]
        return episode if self._signal is None else getattr(episode, self._signal)

    def shapes(self) -> "list[EpisodeShape] | None":
        shapes = None if self._signal is not None else self._base.shapes()
        return shapes if shapes is None or self._indices is None else [shapes[i] for i in self._indices]


def as_episodes(episodes) -> Sequence:
    """A sequence of episodes: lazy ones (:class:`EpisodeSequence`) as they are, anything else as a list."""
    if isinstance(episodes, Trajectory):
        return [episodes]
    return episodes if isinstance(episodes, EpisodeSequence) else list(episodes)


def select_episodes(episodes: Sequence, indices: Sequence[int] | np.ndarray) -> Sequence:
    """``[episodes[i] for i in indices]``, lazily for a lazy sequence (nothing read until asked for)."""
    if isinstance(episodes, EpisodeSequence):
        return _EpisodeView(episodes, indices=indices)
    return [episodes[int(i)] for i in indices]


def episode_signals(episodes: Sequence, signal: str) -> Sequence:
    """One signal of each episode (e.g. ``"x"``), lazily for a lazy sequence."""
    if isinstance(episodes, EpisodeSequence):
        return _EpisodeView(episodes, signal=signal)
    return [getattr(t, signal) for t in episodes]


def described_episodes(episodes: Sequence) -> "Sequence[Trajectory | EpisodeShape]":
    """The episodes' shapes when a lazy sequence knows them (nothing read), else the episodes themselves.

    Checks that look only at names, sample periods, lengths and signal widths (``.name``,
    ``.dt``, ``.n_samples``, ``.width(signal)``) pass over either.
    """
    shapes = episodes.shapes() if isinstance(episodes, EpisodeSequence) else None
    return episodes if shapes is None else shapes


def check_trajectories(
    trajectories, needs: Sequence[str], min_samples: int, what: str, each=None
) -> Sequence[Trajectory]:
    """A non-empty sequence of trajectories with the needed signals and consistent widths.

    A lazy sequence (:class:`EpisodeSequence`) is checked episode by episode and returned as it is;
    one that knows its episodes' shapes (:meth:`EpisodeSequence.shapes`) is checked from them,
    nothing read. ``each(i, episode)``, if given, checks more of every episode in the same pass
    (before its signals), from what :func:`described_episodes` gives: a stored log is read at
    most once for all the checks.
    """
    trajectories = as_episodes(trajectories)
    if not len(trajectories):
        raise ValueError(f"{what} needs at least one trajectory")
    described = described_episodes(trajectories)
    first = described[0]
    for i, traj in enumerate(described):
        if not isinstance(traj, (Trajectory, EpisodeShape)):
            raise ValueError(f"{what}: item {i} is a {type(traj).__name__}, not a Trajectory")
        if each is not None:
            each(i, traj)
        label = traj.name or f"#{i}"
        for key in needs:
            width, ref = traj.width(key), first.width(key)
            if width is None:
                raise ValueError(f"{what} needs signal {key!r}, missing in trajectory {label}")
            if width != ref:
                raise ValueError(f"trajectory {label}: {key} has {width} channels, the first trajectory has {ref}")
        if traj.dt != first.dt:
            raise ValueError(f"trajectory {label} has sample period {traj.dt}, the first has {first.dt}")
        if traj.n_samples < min_samples:
            raise ValueError(
                f"trajectory {label} has {traj.n_samples} samples; {what} needs at least "
                f"{min_samples} (delays plus two)"
            )
    return trajectories
