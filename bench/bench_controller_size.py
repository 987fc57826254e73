"""Benchmark: the loop's per-tick cost of a controller, from today's PD to 200 states.

Target: a discrete state-space controller of up to 200 states runs within the
500 Hz loop's 2 ms budget. Rows: the rig's PD from its gains file (2 states, plain floats),
then state-space files of 2 states (the same PD as matrices), 50, 100 and 200 states (the
PD with stable extra states, mixed by a random orthogonal change of coordinates,
``core.lti.padded_realization``: the same transfer function, so every episode balances, every
state coupled to every other). Columns,
each a median over ``--repeats`` runs:

- loop compute p50 / p99: the loop's own per-tick compute-time statistics (read, safety,
  controller output, saturation, write; the simulator's step included) over free-running
  episodes on the simulator into an MCAP log, as ``qube-run`` runs them;
- step p50 / p99: the controller's whole per-tick step (output and state update, the
  functions the loop calls: ``daq.controller_step``) timed alone, per call;
- ratios of the p99s against the PD's, measured in the same run.

Measured on the 2-core CI-like VM, shared with another job (``--repeats 3``)::

    controller                     states  loop p50 us  loop p99 us  x PD  step p50 us  step p99 us  x PD
    PD gains (rig)                      2         15.3         39.5  1.00         2.31         4.90  1.00
    state-space (PD as matrices)        2         15.6         39.5  1.00         2.28         3.09  0.63
    state-space                        50         19.7         69.8  1.77         3.56         7.22  1.47
    state-space                       100         22.0         78.8  2.00         5.27        11.69  2.39
    state-space                       200         26.7         94.0  2.38        10.49        26.42  5.39
    200 states: loop p99 + step p99 = 120 us of the 2000 us budget (6.0 %)

Plain floats, the PD's realization before this benchmark, took about 2.2 ms a step at 200
states (over the budget alone): above 4 states the step runs on numpy. The loop's p99 also
grows with the writer thread's share of the interpreter (a 200-state sample is 1.7 kB).
The benchmark exits 1 if the 200-state row exceeds the budget.

Usage::

    PYTHONPATH=. python bench/bench_controller_size.py [--repeats N] [--seconds S]
"""

from __future__ import annotations

import argparse
import gc
import statistics
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

BUDGET = 2e-3
SIZES = (2, 50, 100, 200)
STEP_CALLS = 20_000


def step_times(system) -> tuple[float, float]:
    """p50 and p99 (s) of the controller's per-tick step (output then update) timed alone."""
    import numpy as np

    from qube_koopman.daq.controller_step import controller_step

    output, update = controller_step(system)
    rng = np.random.default_rng(1)
    errors = (rng.standard_normal((STEP_CALLS, 2)) * 1e-3).tolist()
    spent = np.empty(STEP_CALLS)
    clock = time.perf_counter
    gc.freeze()
    try:
        for k, (e0, e1) in enumerate(errors):
            t0 = clock()
            output(e0, e1, 0.0)
            update(e0, e1, 0.0)
            spent[k] = clock() - t0
    finally:
        gc.unfreeze()
    return float(np.percentile(spent, 50)), float(np.percentile(spent, 99))


def loop_times(info, seconds: float, folder: Path) -> tuple[float, float]:
    """The loop's own compute-time p50 and p99 (s) over one free-running episode into an MCAP log."""
    from qube_koopman.daq.backends import SimBackend
    from qube_koopman.daq.loop import run_episode
    from qube_koopman.daq.session import excitation_settings, plan_episodes, run_seeds
    from qube_koopman.daq.sinks import McapSink

    seeds, backend_seed = run_seeds(5, 1)
    (plan,) = plan_episodes(info, seeds, excitation_settings(seconds), source="bench")
    result = run_episode(SimBackend(seed=backend_seed), plan, [McapSink(folder)], handle_signals=False)
    assert result.complete, result.reason
    return result.timing.compute_p50, result.timing.compute_p99


def controllers(folder: Path) -> list[tuple[str, object]]:
    """(label, ControllerInfo) of each row, the state-space ones through their files."""
    from qube_koopman.core.controller_file import load_controller, write_controller_file
    from qube_koopman.core.lti import padded_realization

    pd = load_controller("rig")
    rows = [("PD gains (rig)", pd)]
    for n in SIZES:
        path = write_controller_file(folder / f"ss_{n}.toml", padded_realization(pd.system, n))
        rows.append(("state-space (PD as matrices)" if n == 2 else "state-space", load_controller(path)))
    return rows


def main(argv=None) -> int:
    """Run the benchmark and print the table."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=3, help="runs per row (median)")
    parser.add_argument("--seconds", type=float, default=10.0, help="episode length of each loop run")
    args = parser.parse_args(argv)

    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        rows = controllers(folder)
        measured = {label_n: [] for label_n in range(len(rows))}
        for _ in range(args.repeats):  # interleaved: a burst of load hits every row alike
            for i, (_, info) in enumerate(rows):
                measured[i].append(loop_times(info, args.seconds, folder) + step_times(info.system))
    medians = [[statistics.median(column) for column in zip(*measured[i])] for i in range(len(rows))]
    pd_loop, pd_step = medians[0][1], medians[0][3]
    print(
        f"{'controller':<30} {'states':>6}  {'loop p50 us':>11}  {'loop p99 us':>11}  {'x PD':>4}  "
        f"{'step p50 us':>11}  {'step p99 us':>11}  {'x PD':>4}"
    )
    for (label, info), (lp50, lp99, sp50, sp99) in zip(rows, medians):
        print(
            f"{label:<30} {info.system.n_states:>6}  {lp50 * 1e6:>11.1f}  {lp99 * 1e6:>11.1f}  {lp99 / pd_loop:>4.2f}  "
            f"{sp50 * 1e6:>11.2f}  {sp99 * 1e6:>11.2f}  {sp99 / pd_step:>4.2f}"
        )
    worst = medians[-1][1] + medians[-1][3]
    print(
        f"{rows[-1][1].system.n_states} states: loop p99 + step p99 = {worst * 1e6:.0f} us of the "
        f"{BUDGET * 1e6:.0f} us budget ({100 * worst / BUDGET:.1f} %)"
    )
    return 0 if worst < BUDGET else 1


if __name__ == "__main__":
    sys.exit(main())
