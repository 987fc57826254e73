"""How far off are the pendulum's offset estimates, against the standard errors they report?

On twin episodes the encoder zeros are known: a model fitted on twin episodes under the rig's gains
(exact zeros, so its upright is the true one) estimates each test episode's alpha offset from its
first second (``qube-identify --offsets alpha``), under the rig's gains and under soft-theta, with two
liftings. Printed per case: the estimates' RMS error, their median reported standard error, and the
RMS of error / standard error (1 if the standard errors were honest) with the share beyond 2.

Measured (the default twin, 24 training and 24 test episodes of 12 s per case, 1 s window):

| lifting | test loop | RMS error | median std error | RMS error / std error |
|---|---|---|---|---|
| poly 1, 20 delays | soft-theta | 8.9e-4 rad | 5.8e-5 rad | 16.1 |
| poly 1, 20 delays | rig | 4.9e-4 | 1.1e-4 | 4.4 |
| poly 3, 35 delays, friction | soft-theta | 6.6e-4 | 2.2e-5 | 32.3 |
| poly 3, 35 delays, friction | rig | 4.0e-4 | 6.1e-5 | 6.5 |

The standard error is the window's residual taken as independent samples (``sigma^2 (J^T J)^-1``): it
sees the encoders' noise, not the model's error over the window nor the residuals' correlation, so
the errors are 4-32 times what it says. The prediction intervals do not rely on it alone: their
calibration on held-out episodes (and the twin's probes) takes in the whole prediction error, the
offset's included.

Usage: python bench/bench_offset_errors.py --data DIR (the paper's 48 episodes as .mcap logs; their
first eight training excitations drive the twin)
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import numpy as np

from qube_koopman.core.controller import load_pd_gains
from qube_koopman.identify import ClEdmd
from qube_koopman.identify.data.logs import load_logs
from qube_koopman.identify.estimators.structure import close_loop
from qube_koopman.identify.model_selection.search import LiftingSpec
from qube_koopman.identify.model_selection.transfer import twin_probes
from qube_koopman.identify.models.offsets import estimate_offsets_many

WINDOW = 500  # samples: the default --estimate-window of 1 s


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True, help="folder of the 48 imported .mcap logs")
    args = parser.parse_args()
    logs = sorted(args.data.glob("*.mcap"))
    if len(logs) != 48:
        raise SystemExit(f"{args.data}: expected the paper's 48 logs, found {len(logs)}")
    cut = {k: slice(0, 6000) for k in ("x", "u", "r", "f", "xc")}
    excitations = [
        replace(log.trajectory, **{k: getattr(log.trajectory, k)[s] for k, s in cut.items()})
        for log in load_logs(logs[:8], skip=500)
    ]
    gains = {name: load_pd_gains(name) for name in ("rig", "soft-theta")}
    as_tuple = {n: (g.kp_theta, g.kd_theta, g.kp_alpha, g.kd_alpha, g.tau) for n, g in gains.items()}
    train = twin_probes(excitations, gains=[as_tuple["rig"]], per_controller=24, seed=11, zero_offsets=None)
    tests = {
        name: twin_probes(excitations, gains=[as_tuple[name]], per_controller=24, seed=12 + k)
        for k, name in enumerate(("soft-theta", "rig"))
    }
    print(f"{'lifting':<30}{'test loop':<12}{'RMS error':>12}{'median SE':>12}{'RMS err/SE':>12}{'beyond 2':>10}")
    for spec in (LiftingSpec(delays=20, poly=1), LiftingSpec(delays=35, poly=3, friction=True)):
        plant = ClEdmd(train.controllers[0], lifting=spec.steps(), alpha=1e-3).fit(train.episodes[0]).plant_model_
        for name, test in tests.items():
            closed = close_loop(plant, test.controllers[0], [0, 1])
            estimates = estimate_offsets_many(closed, test.episodes[0], ["alpha"], WINDOW)
            error = np.array([e.values[0] for e in estimates]) - test.alpha_offsets[0]
            se = np.array([e.std_error[0] for e in estimates])
            z = error / se
            print(
                f"{spec.label():<30}{name:<12}{np.sqrt(np.mean(error**2)):>12.1e}{np.median(se):>12.1e}"
                f"{np.sqrt(np.mean(z**2)):>12.1f}{np.mean(np.abs(z) > 2):>10.2f}",
                flush=True,
            )


if __name__ == "__main__":
    main()
