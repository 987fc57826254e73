"""Controller file kinds beyond the built-in ones: a registry in core, a builder registered from above, and a
controller with a runtime that the loop runs (output then update each tick) and whose per-tick record it logs."""

from __future__ import annotations

import numpy as np
import pytest

import qube_koopman.core.controller_file as cf
from qube_koopman.core.controller import pd_controller, load_pd_gains
from qube_koopman.daq.backends import SimBackend
from qube_koopman.daq.excitation import Excitation
from qube_koopman.daq.log import read_episode
from qube_koopman.daq.loop import EpisodePlan, run_episode
from qube_koopman.daq.sinks import McapSink, MemorySink


class _Toy:
    """A controller beyond LTI: the rig's PD, its output halved, counting its calls."""

    TICK_FIELDS = ("calls", "half")

    def __init__(self, system):
        self.system = system
        self.calls = []
        self.tick_record = (0.0, 0.0)

    def step(self):
        from qube_koopman.daq.controller_step import controller_step

        out, upd = controller_step(self.system)

        def output(e0, e1, f, r_theta):
            self.calls.append("output")
            u, x = out(e0, e1, f)
            self.tick_record = (float(len(self.calls)), 0.5 * u)
            return 0.5 * u, x

        def update(e0, e1, f):
            self.calls.append("update")
            upd(e0, e1, f)

        return output, update


def _toy_builder(data, path, dt):
    system = pd_controller(load_pd_gains("rig"), dt)
    return cf.ControllerInfo(system, "given", {}, "toy", {}, {"scale": 0.5}, _Toy.TICK_FIELDS, _Toy(system))


@pytest.fixture
def toy_kind(monkeypatch):
    monkeypatch.setitem(cf._BUILDERS, "toy", _toy_builder)


def test_a_registered_kind_is_built_by_its_builder_and_named_when_unknown(toy_kind, tmp_path):
    path = tmp_path / "toy.toml"
    path.write_text('format = "qube-controller/1"\nkind = "toy"\ndt = 0.002\n')
    info = cf.load_controller(path)
    assert info.kind == "toy" and info.settings == {"scale": 0.5} and isinstance(info.runtime, _Toy)
    path.write_text('format = "qube-controller/1"\nkind = "other"\ndt = 0.002\n')
    with pytest.raises(ValueError, match=r"unknown controller kind 'other'; expected \"state-space\".*\"toy\""):
        cf.load_controller(path)
    with pytest.raises(ValueError, match="built in"):
        cf.register_controller_kind("state-space", _toy_builder)


def test_the_loop_runs_a_runtime_output_then_update_and_logs_its_record(toy_kind, tmp_path):
    info = _toy_builder({}, tmp_path, 0.002)
    n = 300
    ex = Excitation(np.full(n, 0.05), np.zeros(n), np.zeros(n))
    memory = MemorySink()
    backend = SimBackend(seed=1)
    try:
        result = run_episode(backend, EpisodePlan(info, ex), [memory, McapSink(tmp_path)], handle_signals=False)
    finally:
        backend.close()
    assert result.complete
    assert info.runtime.calls[:4] == ["output", "update", "output", "update"] and len(info.runtime.calls) == 2 * n
    for episode in (memory.episodes[0].episode(), read_episode(next(tmp_path.glob("*.mcap")))):
        assert episode.metadata.controller.tick_fields == ("calls", "half")
        np.testing.assert_array_equal(episode.controller_record[:, 0], 2 * np.arange(n) + 1)
        np.testing.assert_array_equal(episode.controller_record[:, 1], episode.control_output)
