"""Cost of one simulated 500 Hz tick: PendulumSimulator.step against numpy's rk4_step.

Target (issue): a 20 s episode at 500 Hz at least 50x faster than real time
including the loop and logging, so the plant step should take well under
40 us. Run: ``PYTHONPATH=. python bench/pendulum_step.py``.
"""

from __future__ import annotations

import gc
import time

import numpy as np

from qube_koopman.sim.pendulum import PendulumSimulator, SensorModel, rk4_step

TICKS = 10_000  # one 20 s episode at 500 Hz
PERIOD_US = 2000.0


def _per_tick_us(step, repeats: int = 5) -> np.ndarray:
    """Per-tick times (us) of the fastest of ``repeats`` runs of TICKS ticks."""
    volts = (0.5 * np.sin(np.arange(TICKS) * 0.01)).tolist()
    best = None
    for _ in range(repeats):
        times = np.empty(TICKS)
        gc.disable()
        try:
            for i in range(TICKS):
                t0 = time.perf_counter()
                step(volts[i])
                times[i] = time.perf_counter() - t0
        finally:
            gc.enable()
        if best is None or times.sum() < best.sum():
            best = times
    return best * 1e6


def main() -> None:
    rows = []
    for label, sensor in (
        ("PendulumSimulator.step (encoders)", SensorModel()),
        ("PendulumSimulator.step (encoders + noise)", SensorModel(noise_std=1e-3)),
    ):
        sim = PendulumSimulator(sensor=sensor, seed=0)
        sim.reset([0.0, 0.05, 0.0, 0.0])
        rows.append((label, _per_tick_us(sim.step)))
    state = np.array([0.0, 0.05, 0.0, 0.0])

    def numpy_step(v):
        nonlocal state
        state = rk4_step(state, v)

    rows.append(("reference: rk4_step on one numpy state", _per_tick_us(numpy_step)))
    header = ("mean us", "p50 us", "p99 us", "max us", "x real time")
    print(f"{'per tick':45s}" + "".join(f"{h:>12s}" for h in header))
    for label, us in rows:
        values = (us.mean(), np.median(us), np.percentile(us, 99), us.max(), PERIOD_US / us.mean())
        print(f"{label:45s}" + "".join(f"{v:12.2f}" for v in values))
    print(f"speed-up of the float path over numpy: {rows[2][1].mean() / rows[0][1].mean():.1f}x")


if __name__ == "__main__":
    main()
