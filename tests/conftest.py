"""Shared fixtures: where the paper's QUBE-Servo dataset lives."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

DATASET_ENV = "QUBE_DATASET_DIR"
DEFAULT_DATASET = Path(__file__).resolve().parents[2] / "shared" / "datasets" / "qube_servo_20230828"
DATASET_SOURCE = ("the paper's QUBE-Servo dataset (public repository decargroup/closed_loop_koopman, "
                  "folder dataset/controller_20230828, MIT licence)")


def dataset_dir() -> Path | None:
    """The dataset folder: $QUBE_DATASET_DIR, else ../shared/datasets/qube_servo_20230828."""
    path = Path(os.environ.get(DATASET_ENV, DEFAULT_DATASET))
    return path if path.is_dir() and any(path.glob("*.csv")) else None


@pytest.fixture(scope="session")
def qube_dataset() -> Path:
    """Path of the dataset folder; skips with a message saying where the data comes from."""
    path = dataset_dir()
    if path is None:
        pytest.skip(f"dataset not found: set {DATASET_ENV} or place {DATASET_SOURCE} "
                    f"at {DEFAULT_DATASET}")
    return path


@pytest.fixture(scope="session")
def qube_csv_files(qube_dataset: Path) -> list[Path]:
    """The dataset's 48 episode files, sorted by name (the paper's split order)."""
    return sorted(qube_dataset.glob("*.csv"))
