"""Identification equivalence of the twin (issue 11): identified on the simulator's replays of the
dataset's 48 excitations, the paper's methods score as on the real logs.

The default simulator (the twin calibrated on the 28 training episodes) reruns every logged
excitation (``qube-run --replay``: the generator is bit-exact, so the same seeds give the same
references and feedforward) under the logs' own controller; ``qube-reproduce qube`` then runs the
paper's protocol on those simulated logs. CL EDMD's test R^2 must be within 0.02 of the real
logs' at 10 delays (0.897) and 20 delays (0.982), and the table's methods must rank as on the
real data (pairs closer than 0.01 on the real data count as ties).

The replays run with a fixed ``--seed`` (it draws the simulator's start perturbations): the test
is then the same every run. The closed-loop radius check is close to its bound on real and
simulated logs alike: the largest CL EDMD closed-loop spectral radius over the 180 alphas is
1.0000979 on the real logs and 1.0000959-1.0000980 on six replays (seeds 1-4 and two fresh ones;
1.0000964 with seed 1), against the check's 1.0001. With a fresh seed every run, a loaded run drew one above it.
The twin with the arm's cable spring (calibrated on two controllers) gives 1.0001014 with seed 1:
so the test holds the twin's largest radius within 1e-5 of the real logs' rather than under the
bound the paper's real logs only just meet.
"""

from __future__ import annotations

import itertools
import json

import numpy as np
import pytest

from qube_koopman.daq.cli.run import main as qube_run
from qube_koopman.daq.log import read_episode_metadata
from qube_koopman.reproduce.cli.reproduce import main as qube_reproduce

pytestmark = [pytest.mark.dataset, pytest.mark.slow]

TIE = 0.01


@pytest.fixture(scope="module")
def twin(qube_logs, tmp_path_factory):
    logs = tmp_path_factory.mktemp("twin_logs")
    out = tmp_path_factory.mktemp("twin_out")
    assert (
        qube_run(["--replay", *map(str, sorted(qube_logs.glob("*.mcap"))), "--seed", "1", "--out", str(logs), "-q"])
        == 0
    )
    assert qube_reproduce(["qube", "--data", str(logs), "--out", str(out), "-q"]) == 0
    return logs, json.loads((out / "qube.json").read_text())


def _r2(result: dict) -> dict[str, float]:
    return {key: float(row["r2_mean"]) for key, row in result["rows"].items()}


def test_the_twin_replays_all_48_excitations_to_the_end(twin, qube_logs):
    logs, result = twin
    metas = [read_episode_metadata(p) for p in sorted(logs.glob("*.mcap"))]
    assert len(metas) == 48 and all(m.status == "complete" for m in metas)
    assert result["n_train"] == 28 and result["n_test"] == 20

    def seeds(meta):
        return tuple(sorted(meta.excitation["seeds"].items()))

    real = sorted(seeds(read_episode_metadata(p)) for p in qube_logs.glob("*.mcap"))
    assert sorted(seeds(m) for m in metas) == real


def test_cl_edmd_scores_within_0_02_of_the_real_logs(twin, qube_reproduction):
    real, sim = _r2(qube_reproduction[0]), _r2(twin[1])
    for key in ("cl_edmd_cl_cl", "cl_edmd_20_delays"):  # 10 delays (paper: 0.897), 20 delays (0.982)
        assert abs(sim[key] - real[key]) <= 0.02, (key, sim[key], real[key])
    assert twin[1]["rows"]["cl_edmd_20_delays"]["n_episodes"] == 20


def test_the_methods_rank_as_on_the_real_logs(twin, qube_reproduction):
    real, sim = _r2(qube_reproduction[0]), _r2(twin[1])
    assert set(real) == set(sim)
    swapped = []
    for a, b in itertools.permutations(real, 2):
        if real[a] - real[b] > TIE and not sim[a] > sim[b]:
            swapped.append((a, b))
    assert not swapped, f"ranked otherwise than on the real logs: {swapped}; real {real}, twin {sim}"
    # The paper's qualitative results hold on the twin too (its R^2 thresholds are the real data's).
    assert sim["edmd_plant_plant"] == -np.inf
    checks = twin[1]["checks"]
    assert checks["edmd_plant_plant_diverges"] and checks["plant_radius_above_1_at_small_alpha"]
    radius = (max(r["sweep"]["cl-edmd"]["spectral_radius_closed_loop"]) for r in (qube_reproduction[0], twin[1]))
    assert abs(next(radius) - next(radius)) < 1e-5
