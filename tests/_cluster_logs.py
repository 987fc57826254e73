"""What the cluster tests (tests/identify/test_dask_cluster.py, test_dask_tls.py) fit on: a few of the
dataset's episodes, cut short, and a small search space. The ``cluster_logs`` fixture writes them (module
scope), registered for the whole suite in tests/conftest.py."""

from __future__ import annotations

from pathlib import Path

import pytest

N_TRAIN = 5
SAMPLES = 3500  # of the dataset's ~10,000 an episode (qube-identify drops the first 500): a quick search
SPACE = (
    "delays = [0, 2, 5, 10]\npoly = [1, 2]\nconst = [false, true]\ntrig = [false]\nfriction = [false]\n"
    "rbf = [0]\nalphas = [1e-3, 1.0]\noffsets = [false]\n"
)


@pytest.fixture(scope="module")
def cluster_logs(qube_csv_files, tmp_path_factory) -> Path:
    """Five training and two test logs of the dataset (imported from its CSV files), their first 7 s."""
    from qube_koopman.daq.episode import Episode
    from qube_koopman.daq.legacy_csv import legacy_episode, load_legacy_controller
    from qube_koopman.daq.log import write_episode
    from qube_koopman.daq.log.names import log_path

    root = tmp_path_factory.mktemp("cluster_logs")
    controller = load_legacy_controller(qube_csv_files[0].parent / "controller.toml")
    for name, chosen in (("train", qube_csv_files[:N_TRAIN]), ("test", qube_csv_files[28:30])):
        (root / name).mkdir()
        for path in chosen:
            whole = legacy_episode(path, controller)
            cut = {key: value[:SAMPLES] for key, value in whole.arrays().items() if value is not None}
            write_episode(log_path(root / name, path.stem), Episode(**cut, metadata=whole.metadata))
    (root / "space.toml").write_text(SPACE)
    return root
