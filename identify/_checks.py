"""Input validation shared by the estimators: errors that name the problem."""

from __future__ import annotations

import numpy as np


def as_signal(value, name: str, n_samples: int | None = None, n_columns: int | None = None,
              allow_nonfinite: bool = False) -> np.ndarray:
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
