"""Episode logs of a PD loop on the simulated pendulum, written as qube-run writes them, for the tests."""

from __future__ import annotations

from pathlib import Path

from qube_koopman.core.controller import PdGains, pd_controller
from qube_koopman.core.controller_file import ControllerInfo
from qube_koopman.daq.backends.sim import SimBackend
from qube_koopman.daq.session import excitation_settings, plan_episodes, run_episodes, run_seeds
from qube_koopman.daq.sinks import McapSink
from qube_koopman.sim.pendulum import PendulumParameters, ZeroOffsetDistribution


def collect_pd_logs(
    out: Path,
    gains: PdGains,
    n: int,
    seed: int,
    params: PendulumParameters,
    *,
    duration: float = 20.0,
    zero_offsets: ZeroOffsetDistribution | None = ZeroOffsetDistribution(),
) -> Path:
    """``n`` episodes of the PD loop with ``gains`` on the pendulum ``params``, the run's seed ``seed``,
    logged into the new folder ``out`` (returned); the pendulum encoder's zero drawn from ``zero_offsets``
    (the simulator's default; None: exact)."""
    info = ControllerInfo(pd_controller(gains), "backward-euler", gains.as_dict(), "pd")
    seeds, backend_seed = run_seeds(seed, n)
    out.mkdir(parents=True)
    run_episodes(
        SimBackend(params, seed=backend_seed, zero_offsets=zero_offsets),
        plan_episodes(info, seeds, excitation_settings(duration), source="test"),
        [McapSink(out)],
    )
    return out
