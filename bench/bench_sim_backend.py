"""Benchmark: the free-running simulator backend, one 20 s episode, logging included.

Target (issue, part 5): a 20 s episode (10,000 ticks at 500 Hz) through the
acquisition loop with the MCAP episode log at least 50x faster than real
time. Rows, each the median of ``--repeats`` episodes:

- the loop into an MCAP log (what ``qube-run`` does; the target row);
- the loop into memory, and with no sink at all (what the log costs);
- reference: the same closed loop stepped with numpy, one array call per
  operation per tick (``sim.pendulum.simulate_closed_loop`` with a batch of
  one), no logging, as a ratio.

Usage::

    PYTHONPATH=. python bench/bench_sim_backend.py [--repeats N]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

SECONDS = 20.0
TARGET = 50.0


def main(argv=None) -> int:
    """Run the benchmark and print the table."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=5, help="episodes per row (median)")
    args = parser.parse_args(argv)

    import numpy as np

    from qube_koopman.daq.backends import SimBackend
    from qube_koopman.daq.episode import REFERENCE_SIGNALS, stack_signals
    from qube_koopman.daq.loop import run_episode
    from qube_koopman.daq.log import read_episode
    from qube_koopman.daq.session import excitation_settings, plan_episodes, run_seeds
    from qube_koopman.core.controller_file import load_controller
    from qube_koopman.daq.sinks import McapSink, MemorySink
    from qube_koopman.sim.pendulum import simulate_closed_loop

    controller = load_controller()
    seeds, backend_seed = run_seeds(0, args.repeats)
    plans = plan_episodes(controller, seeds, excitation_settings(SECONDS), source="bench")

    def loop_row(make_sinks):
        times = []
        backend = SimBackend(seed=backend_seed)
        for plan in plans:
            sinks = make_sinks()
            start = time.perf_counter()
            result = run_episode(backend, plan, sinks, handle_signals=False)
            times.append(time.perf_counter() - start)
            assert result.complete and result.n_samples == plan.n_samples, result.reason
        return statistics.median(times), sinks

    rows = []
    with tempfile.TemporaryDirectory() as folder:
        elapsed, sinks = loop_row(lambda: [McapSink(Path(folder))])
        n_logged = len(read_episode(sinks[0].paths[-1]))
        assert n_logged == plans[-1].n_samples
        rows.append(("loop + MCAP episode log (qube-run)", elapsed))
    rows.append(("loop + in-memory sink", loop_row(lambda: [MemorySink()])[0]))
    rows.append(("loop, no sink", loop_row(lambda: [])[0]))

    ref = []
    for plan in plans:
        ex = plan.excitation
        refs = stack_signals(ex, REFERENCE_SIGNALS)
        start = time.perf_counter()
        simulate_closed_loop([0.0, 0.01, 0.0, 0.0], controller.system, refs, np.asarray(ex.feedforward))
        ref.append(time.perf_counter() - start)
    rows.append(("reference: numpy step per tick, no log", statistics.median(ref)))

    print(f"one {SECONDS:g} s episode ({plans[0].n_samples} ticks), median of {args.repeats}")
    print(f"{'':42s}{'seconds':>10s}{'us/tick':>10s}{'x real time':>13s}")
    for label, seconds in rows:
        print(f"{label:42s}{seconds:10.3f}{seconds / plans[0].n_samples * 1e6:10.1f}{SECONDS / seconds:13.1f}")
    speedup = SECONDS / rows[0][1]
    print(
        f"speed-up with logging: {speedup:.1f}x real time (target >= {TARGET:g}x: "
        f"{'met' if speedup >= TARGET else 'NOT met'}); "
        f"{rows[3][1] / rows[0][1]:.1f}x faster than the numpy-per-tick reference"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
