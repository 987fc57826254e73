"""Read each dataset CSV once per test session, whichever test module asks first."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np

# Column order of the dataset's CSV files (README of the dataset).
COLUMNS = (
    "t",
    "target_theta",
    "target_alpha",
    "theta",
    "alpha",
    "control_output",
    "feedforward",
    "plant_input",
    "saturation",
)


@lru_cache(maxsize=None)
def _load(path: str) -> np.ndarray:
    data = np.loadtxt(path, delimiter=",", skiprows=1)
    data.setflags(write=False)
    return data


def load_episode(path: Path) -> dict[str, np.ndarray]:
    """One episode's columns by name (read-only arrays, cached)."""
    data = _load(str(path))
    return {name: data[:, i] for i, name in enumerate(COLUMNS)}
