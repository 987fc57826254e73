"""The what-if question on the simulator: a plant identified under the rig's gains predicts
episodes run under softer theta gains, whose encoder zeros are off by a few counts.

Under a PD loop the arm settles where kp_theta (theta - r) balances kp_alpha alpha, so an
alpha offset moves the arm by kp_alpha / kp_theta times itself: 17x under these gains
(FACTS 6a). Estimating each test episode's offset from its first second fixes that.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from qube_koopman.daq.backends.sim import SimBackend
from qube_koopman.daq.controller import PdGains, pd_controller
from qube_koopman.daq.episode import ControllerInfo
from qube_koopman.daq.log import read_episode_metadata
from qube_koopman.daq.session import excitation_settings, plan_episodes, run_episodes, run_seeds
from qube_koopman.daq.sinks import McapSink
from qube_koopman.identify.cli.identify import main as qube_identify
from qube_koopman.sim.pendulum import ZeroOffsetDistribution

pytestmark = pytest.mark.slow

COUNT = 2 * math.pi / 2048
RIG = PdGains(kp_theta=6.0, kd_theta=1.8, kp_alpha=30.0, kd_alpha=2.5, tau=50.0)
SOFT = PdGains(kp_theta=2.0, kd_theta=1.0, kp_alpha=35.0, kd_alpha=3.0, tau=50.0)


def _collect(out, gains, n, seed, zero_offsets):
    info = ControllerInfo(pd_controller(gains), "backward-euler", gains.as_dict(), "pd")
    seeds, backend_seed = run_seeds(seed, n)
    out.mkdir(parents=True)
    run_episodes(SimBackend(seed=backend_seed, zero_offsets=zero_offsets),
                 plan_episodes(info, seeds, excitation_settings(20.0), source="test"), [McapSink(out)])
    return out


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    root = tmp_path_factory.mktemp("transfer")
    # Training under the rig's gains with exact encoder zeros; test episodes under soft theta
    # gains with zeros drawn a few counts off (spread 2 counts around the dataset's mean).
    train = _collect(root / "train", RIG, 8, 1, None)
    test = _collect(root / "test", SOFT, 4, 2, ZeroOffsetDistribution(0.0025, 2 * COUNT))
    return root, train, test


def _identify(root, train, test, name, *extra):
    out = root / name
    assert qube_identify(["--train", str(train), "--test", str(test), "--delays", "20", "--out", str(out),
                          *extra]) == 0
    return json.loads((out / "report.json").read_text())


def test_offsets_estimated_per_episode_recover_the_injected_ones(logs):
    root, train, test = logs
    report = _identify(root, train, test, "offsets", "--offsets", "alpha")
    injected = {p.name: read_episode_metadata(p).extra["backend"]["sensor"]["alpha_offset"]
                for p in test.glob("*.mcap")}
    estimated = {e["log"]: e["alpha"] for e in report["offsets"]}
    assert set(estimated) <= set(injected) and len(estimated) >= 3
    errors = np.array([estimated[k] - injected[k] for k in estimated])
    print("offset errors (counts):", np.round(errors / COUNT, 2))
    assert np.all(np.abs(errors) <= COUNT)
    with_offsets, without = report["test"], report["test_without_offsets"]
    print(f"transfer R^2 {with_offsets['r2_mean']:.4f} with offsets, {without['r2_mean']:.4f} without")
    assert with_offsets["r2_mean"] >= 0.95
    assert without["r2_mean"] <= with_offsets["r2_mean"] - 0.05   # clearly lower without them
    assert report["scored_from_sample"] == 500 and "first 1 s" in report["protocol"]


def test_an_affine_model_trained_on_offset_data_transfers_too(logs, tmp_path):
    # Training data with the rig's per-episode zeros: the constant lifting absorbs their mean.
    root, _, test = logs
    train = _collect(tmp_path / "train", RIG, 8, 3, ZeroOffsetDistribution())
    report = _identify(root, train, test, "const", "--offsets", "alpha", "--const")
    assert report["lifting"]["steps"][-1] == {"type": "Constant"}
    assert report["test"]["r2_mean"] >= 0.95 > report["test_without_offsets"]["r2_mean"]


def test_what_if_controller_predicts_under_the_given_gains(logs, tmp_path):
    root, train, test = logs
    soft = tmp_path / "soft.toml"
    soft.write_text("".join(f"{k} = {v}\n" for k, v in SOFT.as_dict().items()))
    report = _identify(root, train, test, "whatif", "--controller", str(soft), "--offsets", "alpha")
    assert report["what_if"]["n_scored"] == report["test"]["n_episodes"] >= 3
    assert report["test"]["r2_mean"] >= 0.95
    # Asked about the rig's own gains, nothing in the test set was recorded under them.
    rig = tmp_path / "rig.toml"
    rig.write_text("".join(f"{k} = {v}\n" for k, v in RIG.as_dict().items()))
    report = _identify(root, train, test, "whatif_rig", "--controller", str(rig))
    assert report["test"] is None and len(report["what_if"]["unscored_logs"]) >= 3
