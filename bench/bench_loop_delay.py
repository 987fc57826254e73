"""How much of a plant model's error on another controller's episodes is the loop's own delay.

    python bench/bench_loop_delay.py [--rig DIR] [--soft DIR] [--lifting "FLAGS"] [--extra "0 0.5 ..."]
                                     [--estimate-window S]

Fits the plant on the paper's 28 training episodes of the rig (``--lifting``, default: the
paper-split search's winner) and predicts each soft-controller episode with its own controller
wrapped in an extra delay between the command and the motor (:func:`~qube_koopman.core.lti.with_output_delay`,
the feedforward delayed alike), for each delay of ``--extra`` (in samples), with the episode's
pendulum encoder zero estimated from its first second as ``qube-identify --offsets alpha`` does.
It prints R^2 after that second per episode and delay, the episodes' recording sessions (a gap
of more than ten minutes starts a new one), and, per episode, the extra delay that predicts the
first ``--estimate-window`` seconds best, with R^2 after that window with and without it.

Calibrated on each session alone, the twin puts the soft controller's later session's
command-to-motor delay 3 ms (1.5 samples) above its earlier one's; this bench shows what the same
extra delay does to a model identified under the rig's gains, which carries the rig's.
"""

from __future__ import annotations

import argparse
import shlex
import tempfile
import warnings
from dataclasses import replace
from datetime import datetime
from pathlib import Path

import numpy as np
from bench_two_controllers import data_arguments, mcap_logs

from qube_koopman.core.qube import SKIP_SAMPLES
from qube_koopman.identify.cli.identify import main as identify_main
from qube_koopman.identify.data.logs import load_logs
from qube_koopman.identify.estimators.structure import close_loop, command_delayed
from qube_koopman.identify.metrics import r2_score
from qube_koopman.identify.models.model_file import load_model

MEASURED = (0, 1)
WINDOW = 500  # the offsets' estimation window: the first second after the skipped one


def predict_with_delay(plant, log, samples: float, window: int) -> np.ndarray:
    """The episode predicted by ``plant`` under its own controller held ``samples`` late (on these logs the
    controller's output recomputed from its states is the logged plant input less the feedforward)."""
    t = log.trajectory
    delayed, xc, f = command_delayed(log.controller, samples, t.xc, t.r, t.x[:, list(MEASURED)], t.f)
    return close_loop(plant, delayed, MEASURED).predict(replace(t, xc=xc, f=f), offsets=["alpha"], window=window)


def session_of(names: list[str]) -> list[int]:
    """Session numbers from the logs' recording times (``qube_YYYYmmddTHHMMSS_...``)."""
    times = [datetime.strptime(name.split("_")[1], "%Y%m%dT%H%M%S") for name in names]
    sessions, current = [], 0
    for i, time in enumerate(times):
        if i and (time - times[i - 1]).total_seconds() > 600:
            current += 1
        sessions.append(current)
    return sessions


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    data_arguments(p)
    p.add_argument("--extra", default="0 0.5 1 1.5 2 2.5 3", help="extra delays in samples (default %(default)s)")
    p.add_argument("--estimate-window", type=float, default=4.0, help="seconds (default %(default)s)")
    args = p.parse_args(argv)
    extra = [float(e) for e in args.extra.split()]
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        rig = mcap_logs(args.rig, root / "rig_logs")
        soft = mcap_logs(args.soft, root / "soft_logs")
        fit = [
            "--train",
            *map(str, rig[:28]),
            "--test",
            *map(str, rig[28:]),
            *shlex.split(args.lifting),
            "--interval",
            "0",
            "--out",
            str(root / "fit"),
            "-q",
        ]
        if identify_main(fit) != 0:
            raise SystemExit("qube-identify failed")
        plant = load_model(root / "fit" / "model.json").plant
        logs = load_logs(soft, skip=SKIP_SAMPLES)
    names = [log.path.name for log in logs]
    sessions = session_of(names)
    estimate = int(round(args.estimate_window / logs[0].trajectory.dt))
    warnings.simplefilter("ignore")  # the offsets' estimates are checked by their own tests
    print(f"R^2 after the first second, by extra delay (samples of {1e3 * logs[0].trajectory.dt:g} ms):\n")
    print("| episode | session | " + " | ".join(f"{e:g}" for e in extra) + " |")
    print("|---|---|" + "---|" * len(extra))
    scores = np.empty((len(logs), len(extra)))
    chosen, fixed, free = [], [], []
    for i, log in enumerate(logs):
        x = log.trajectory.x
        window_error, estimated = [], []  # with the offset estimated over the longer window
        for j, e in enumerate(extra):
            scores[i, j] = r2_score(x[WINDOW:], predict_with_delay(plant, log, e, WINDOW)[WINDOW:])
            estimated.append(predict_with_delay(plant, log, e, estimate))
            window_error.append(
                np.sum(
                    np.mean((x[WINDOW:estimate] - estimated[j][WINDOW:estimate]) ** 2, axis=0)
                    / np.var(x[WINDOW:estimate], axis=0)
                )
            )
        best = int(np.argmin(window_error))
        chosen.append(extra[best])
        free.append(r2_score(x[estimate:], estimated[best][estimate:]))
        none = estimated[extra.index(0.0)] if 0.0 in extra else predict_with_delay(plant, log, 0.0, estimate)
        fixed.append(r2_score(x[estimate:], none[estimate:]))
        print(f"| {names[i]} | {sessions[i] + 1} | " + " | ".join(f"{s:.3f}" for s in scores[i]) + " |")
    for s in sorted(set(sessions)):
        rows = np.array(sessions) == s
        print(
            f"\nsession {s + 1} ({rows.sum()} episodes): mean R^2 by extra delay "
            + ", ".join(f"{e:g}: {m:.3f}" for e, m in zip(extra, scores[rows].mean(axis=0)))
        )
    best_per_session = {s: int(np.argmax(scores[np.array(sessions) == s].mean(axis=0))) for s in set(sessions)}
    per_episode = np.array([scores[i, best_per_session[s]] for i, s in enumerate(sessions)])
    print(
        f"\nall: mean / worst R^2 with no extra delay {scores[:, 0].mean():.3f} / {scores[:, 0].min():.3f}; "
        f"with each session's best {per_episode.mean():.3f} / {per_episode.min():.3f}"
    )
    print(f"\nestimated from the first {args.estimate_window:g} s (after the skipped one), R^2 after them:")
    print("| episode | session | extra delay | R^2 with it | without |\n|---|---|---|---|---|")
    for name, s, e, a, b in zip(names, sessions, chosen, free, fixed):
        print(f"| {name} | {s + 1} | {e:g} | {a:.3f} | {b:.3f} |")
    print(
        f"mean / worst: {np.mean(free):.3f} / {np.min(free):.3f} with the estimate, "
        f"{np.mean(fixed):.3f} / {np.min(fixed):.3f} without"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
