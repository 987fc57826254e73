"""Input validation shared by the estimators: errors that name the problem."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from qube_koopman.core.lti import DiscreteStateSpace

if TYPE_CHECKING:
    from qube_koopman.identify.data.trajectory import EpisodeShape, Trajectory


def as_signal(
    value, name: str, n_samples: int | None = None, n_columns: int | None = None, allow_nonfinite: bool = False
) -> np.ndarray:
    """A finite 2-D float array (samples x channels); 1-D input becomes one column."""
    arr = np.asarray(value, dtype=float)
    if arr.ndim == 1:
        arr = arr[:, None]
    if arr.ndim != 2:
        raise ValueError(f"{name} must be 1-D or 2-D (samples x channels), got shape {arr.shape}")
    if n_samples is not None and arr.shape[0] != n_samples:
        raise ValueError(f"{name} has {arr.shape[0]} samples, expected {n_samples}")
    if n_columns is not None and arr.shape[1] != n_columns:
        raise ValueError(f"{name} has {arr.shape[1]} channels, expected {n_columns}")
    if not allow_nonfinite and not np.all(np.isfinite(arr)):
        bad = np.argwhere(~np.isfinite(arr))[0]
        raise ValueError(f"{name} has a non-finite value at sample {bad[0]}, channel {bad[1]}")
    return arr


def check_alpha(alpha) -> float:
    """A finite, non-negative regularization coefficient."""
    try:
        value = float(alpha)
    except (TypeError, ValueError):
        raise ValueError(f"alpha must be a non-negative number, got {alpha!r}") from None
    if not np.isfinite(value) or value < 0:
        raise ValueError(f"alpha must be a non-negative number, got {alpha!r}")
    return value


def check_choice(value, name: str, choices: tuple[str, ...]) -> str:
    """One of a fixed set of options."""
    if value not in choices:
        raise ValueError(f"unknown {name} {value!r}; expected one of {', '.join(map(repr, choices))}")
    return value


def check_nonneg_int(value, name: str, minimum: int = 0) -> int:
    """An integer at least ``minimum``."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


def check_loop_controller(
    ctrl: DiscreteStateSpace,
    measured: list[int],
    n_f: int,
    dt: float | None,
    episode: Trajectory | EpisodeShape | None = None,
) -> None:
    """A controller fits the loop's signals (and, given, the episode recorded under it).

    The closed-loop estimators' check (:class:`~qube_koopman.identify.estimators.cl_edmd.ClosedLoopKoopman`
    and :class:`~qube_koopman.identify.ClEdmdSdp`): a :class:`DiscreteStateSpace` taking the
    tracking errors of the ``measured`` states (and, when it has more inputs, the ``n_f``
    feedforward channels), driving the ``n_f`` plant inputs, at the data's sample period ``dt``.
    """
    if not isinstance(ctrl, DiscreteStateSpace):
        raise ValueError(f"controller must be a DiscreteStateSpace, got {type(ctrl).__name__}")
    where = "" if episode is None else f"episode {episode.name or '(unnamed)'}: "
    n_references = None
    if episode is not None:
        n_xc = episode.width("xc")
        if n_xc is None:
            raise ValueError(f"{where}closed-loop data need the controller state 'xc'")
        if ctrl.n_states != n_xc:
            raise ValueError(
                f"{where}the controller has {ctrl.n_states} states but the data's controller state has {n_xc} channels"
            )
        n_references = episode.width("r")
        assert n_references is not None  # the estimators' check_trajectories required it
    references = "" if n_references is None else f"{n_references} references and "
    n_errors = ctrl.n_inputs - (n_f if ctrl.n_inputs > len(measured) else 0)  # less a feedforward input
    if n_errors != len(measured) or (n_references is not None and n_errors != n_references):
        seen = f"{ctrl.n_inputs} inputs" if n_errors != ctrl.n_inputs else f"{ctrl.n_inputs} tracking errors"
        raise ValueError(
            f"{where}the controller takes {seen}; the data has {references}{len(measured)} fed-back "
            f"states{f' and {n_f} feedforward channels' if n_f else ' and no feedforward'}"
        )
    if n_f and ctrl.n_outputs != n_f:
        raise ValueError(
            f"{where}the controller drives {ctrl.n_outputs} plant inputs, the feedforward has {n_f} channels"
        )
    if dt is not None and abs(dt - ctrl.dt) > 1e-12 * ctrl.dt:
        raise ValueError(f"{where}the data's sample period {dt} s differs from the controller's {ctrl.dt} s")
