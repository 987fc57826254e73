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


@pytest.fixture(scope="session")
def qube_logs(qube_csv_files, tmp_path_factory) -> Path:
    """All 48 episodes imported into MCAP logs once per session (about 6 s)."""
    from daq.legacy_csv import legacy_episode, load_legacy_controller
    from daq.log import write_episode

    out = tmp_path_factory.mktemp("qube_logs")
    controller = load_legacy_controller(qube_csv_files[0].parent / "controller.toml")
    for path in qube_csv_files:
        write_episode(out / f"{path.stem}.mcap", legacy_episode(path, controller))
    return out
