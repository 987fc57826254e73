"""Identify from two controllers: training set (rig only, soft only, both) x test set, on real logs.

    python bench/bench_two_controllers.py [--rig DIR] [--soft DIR] [--lifting "FLAGS"] [--out DIR]

``--rig``: the paper's 48 episodes (CSV files as published, or MCAP logs); ``--soft``: the same
rig's episodes under the softer second controller (kp_theta 2, kd_theta 2, kp_alpha 35,
kd_alpha 3). The soft episodes are split in two halves by name; every training set is scored on
the paper's 20 test episodes and on the soft episodes it did not see:

- rig only: the paper's 28 training episodes; tested on all soft episodes;
- soft only: one half of the soft episodes; tested on the other half (both ways round);
- both: the paper's 28 and one soft half; tested on the other half (both ways round);
- both, scored in sample: the paper's 28 and every soft episode, scored on those same soft episodes
  (copies under another name, since ``qube-identify`` refuses a test log it trained on). Not a
  transfer score: the ceiling of the lifting on these episodes, what no held-out score of a model
  of this lifting can be expected to beat. What it leaves is what the logged references, the
  first second and this lifting do not determine (the arm's slow wander under the soft gains).

Below the table, what that in-sample arm error is made of: its share below 0.3 Hz, its RMS in
each third of the scored samples (an error of the initial state would fade; a disturbance does
not), and how much of it any linear time-invariant response to the excitation could explain: a
FIR filter of the logged arm reference and feedforward (1, 3 and 6 s long, at 25 Hz), fitted on
the other episodes and scored on each one (leave one episode out; the median share of the error's
energy it removes, overall and below 0.3 Hz). A share near zero says the error is not a response
to anything the model is given; as a control, the same FIR is scored on the error plus a response
to the reference (the reference low-passed at 0.2 Hz, scaled to the error's RMS).

Each row gives mean / worst R^2 (closed-loop prediction under each test log's own controller,
scored after the 1 s offset-estimation window) with per-episode alpha offsets and without them on
the same samples. The lifting is fixed (``--lifting``, default: the paper-split search's winner),
so the rows differ only in their training logs.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import shlex
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

from qube_koopman.identify.cli.identify import main as identify_main

#: The analysis' sample rate (Hz): the 500 Hz logs decimated by 20, for FIRs of a few seconds.
ANALYSIS_RATE = 25.0
#: Where the arm error counts as slow (Hz).
SLOW_HZ = 0.3

HERE = Path(__file__).resolve().parent
DEFAULT_LIFTING = "--poly 3 --delays 35 --friction --const --alpha 3.2e-4"


def mcap_logs(folder: Path, out: Path) -> list[Path]:
    """The folder's MCAP logs, or its CSV episodes imported into ``out`` (sorted by name)."""
    logs = sorted(folder.glob("*.mcap"))
    if logs:
        return logs
    from qube_koopman.daq.legacy_csv import legacy_episode, load_legacy_controller
    from qube_koopman.daq.log import write_episode
    from qube_koopman.daq.log.names import log_path

    controller = load_legacy_controller(folder / "controller.toml")
    out.mkdir(parents=True, exist_ok=True)
    for path in sorted(folder.glob("*.csv")):
        write_episode(log_path(out, path.stem), legacy_episode(path, controller))
    return sorted(out.glob("*.mcap"))


def read_datasets(
    args: argparse.Namespace, root: Path, min_soft: int, max_soft: int | None = None
) -> tuple[list[Path], list[Path]]:
    """The paper's 48 logs and the soft ones (``--rig``, ``--soft``; CSV folders imported under ``root``),
    sorted by name; exits naming the folder when it does not hold the paper's 48, or ``min_soft`` to
    ``max_soft`` soft episodes."""
    rig = mcap_logs(args.rig, root / "rig_logs")
    soft = mcap_logs(args.soft, root / "soft_logs")
    if len(rig) != 48:
        raise SystemExit(f"{args.rig}: need the paper's 48 episodes, found {len(rig)}")
    if len(soft) < min_soft or (max_soft is not None and len(soft) > max_soft):
        wanted = (
            f"at least {min_soft}"
            if max_soft is None
            else f"{min_soft}"
            if max_soft == min_soft
            else f"{min_soft}-{max_soft}"
        )
        raise SystemExit(f"{args.soft}: need {wanted} soft episodes, found {len(soft)}")
    return rig, soft


def identify_report(argv: list[str], out: Path) -> dict:
    """report.json of one ``qube-identify`` run writing to ``out`` (its summary lines swallowed: the benches'
    tables say it); exits naming the flags when it fails. Shared with bench_soft_kstep.py and
    bench_mixed_search.py."""
    with contextlib.redirect_stdout(io.StringIO()):
        status = identify_main([*argv, "--out", str(out), "-q"])
    if status != 0:
        raise SystemExit(f"qube-identify failed: {shlex.join(argv)}")
    return json.loads((out / "report.json").read_text())


def in_sample_copies(logs: list[Path], folder: Path) -> list[Path]:
    """``logs`` copied under other names (``in_sample_<name>``) into ``folder``: qube-identify refuses a log among
    both its training and its test logs, and scores these copies of training logs in sample (a ceiling)."""
    folder.mkdir(parents=True, exist_ok=True)
    for log in logs:
        shutil.copyfile(log, folder / f"in_sample_{log.name}")
    return sorted(folder.glob("*.mcap"))


def per_episode(train: list[Path], test: list[Path], lifting: str, out: Path) -> dict[str, tuple[float, float]]:
    """{test log name: (R^2 with offsets, R^2 without)} of one fit."""
    argv = ["--train", *map(str, train), "--test", *map(str, test), *shlex.split(lifting), "--offsets", "alpha"]
    report = identify_report(argv, out)
    names = report["scored_logs"]
    return dict(zip(names, zip(report["test"]["r2_per_episode"], report["test_without_offsets"]["r2_per_episode"])))


def arm_errors(predictions: Path, logs: list[Path]) -> list[dict[str, np.ndarray]]:
    """Per episode, at :data:`ANALYSIS_RATE`: the arm's prediction error, its reference and feedforward.

    ``predictions``: a ``qube-identify`` run's predictions folder (one ``.npz`` per test log, over the
    scored samples); ``logs``: those test logs.
    """
    from scipy import signal

    from qube_koopman.core.qube import SKIP_SAMPLES
    from qube_koopman.identify.data.logs import load_logs

    def decimated(x: np.ndarray) -> np.ndarray:
        return signal.decimate(signal.decimate(x, 4, ftype="fir"), 5, ftype="fir")

    episodes = []
    for log in load_logs(logs, skip=SKIP_SAMPLES):
        saved = np.load(predictions / f"{log.path.stem}.npz")
        t = log.trajectory
        first = int(round(saved["t"][0] / log.dt))
        scored = slice(first, first + len(saved["t"]))
        if not np.array_equal(t.x[scored, 0], saved["measured"][:, 0]):
            raise SystemExit(f"{log.path.name}: its prediction file does not line up with the log")
        error = saved["measured"][:, 0] - saved["predicted"][:, 0]
        episodes.append({"error": error, "reference": t.r[scored, 0], "feedforward": t.f[scored, 0]})
    return [{k: decimated(v) for k, v in e.items()} for e in episodes]


def _lagged(x: np.ndarray, taps: int) -> np.ndarray:
    out = np.zeros((len(x), taps))
    for k in range(taps):
        out[k:, k] = x[: len(x) - k]
    return out


def excitation_share(episodes: list[dict[str, np.ndarray]], seconds: float) -> tuple[float, float]:
    """Median share of each episode's arm-error energy (overall, below :data:`SLOW_HZ`) that a FIR of
    the reference and feedforward, ``seconds`` long and fitted on the other episodes, removes."""
    from scipy import signal

    b, a = signal.butter(2, SLOW_HZ / (ANALYSIS_RATE / 2))
    taps = int(round(seconds * ANALYSIS_RATE)) + 1
    X = [
        np.column_stack([_lagged(e["reference"], taps), _lagged(e["feedforward"], taps), np.ones(len(e["error"]))])
        for e in episodes
    ]
    y = [e["error"] for e in episodes]
    overall, slow = [], []
    for j in range(len(episodes)):
        others = [i for i in range(len(episodes)) if i != j]
        w = np.linalg.lstsq(np.vstack([X[i] for i in others]), np.concatenate([y[i] for i in others]), rcond=None)[0]
        left = y[j] - X[j] @ w
        overall.append(1 - np.sum(left**2) / np.sum(y[j] ** 2))
        slow.append(1 - np.sum(signal.filtfilt(b, a, left) ** 2) / np.sum(signal.filtfilt(b, a, y[j]) ** 2))
    return float(np.median(overall)), float(np.median(slow))


def print_error_analysis(episodes: list[dict[str, np.ndarray]]) -> None:
    """The lines below the table (see the module's docstring)."""
    from scipy import signal

    b, a = signal.butter(2, SLOW_HZ / (ANALYSIS_RATE / 2))
    slow = [np.var(signal.filtfilt(b, a, e["error"])) / np.var(e["error"]) for e in episodes]
    thirds = np.median([[np.sqrt(np.mean(part**2)) for part in np.array_split(e["error"], 3)] for e in episodes], 0)
    print(
        f"\nin-sample arm error: median share of its variance below {SLOW_HZ:g} Hz {np.median(slow):.2f}; "
        f"median RMS by third of the scored samples {' / '.join(f'{v:.4f}' for v in thirds)} rad"
    )
    for seconds in (1.0, 3.0, 6.0):
        overall, below = excitation_share(episodes, seconds)
        print(
            f"a {seconds:g} s FIR of the reference and feedforward, fitted on the other episodes, removes "
            f"{overall:+.3f} of its energy ({below:+.3f} below {SLOW_HZ:g} Hz)",
            flush=True,
        )
    # The control: an error that is a response to the reference (low-passed at 0.2 Hz, its RMS the error's).
    b, a = signal.butter(1, 0.2 / (ANALYSIS_RATE / 2))
    control = []
    for e in episodes:
        response = signal.lfilter(b, a, e["reference"])
        control.append({**e, "error": e["error"] + response * np.std(e["error"]) / np.std(response)})
    overall, below = excitation_share(control, 3.0)
    print(
        f"control: the error plus a response to the reference of the same RMS; the 3 s FIR removes {overall:+.3f} "
        f"({below:+.3f} below {SLOW_HZ:g} Hz)",
        flush=True,
    )


def data_arguments(p: argparse.ArgumentParser, lifting: bool = True) -> None:
    """``--rig``, ``--soft`` (the two datasets' folders) and, with ``lifting``, ``--lifting``; shared with
    bench_loop_delay.py and bench_mixed_search.py."""
    shared = HERE.parents[1] / "shared" / "datasets"
    p.add_argument("--rig", type=Path, default=Path(os.environ.get("QUBE_DATASET_DIR", shared / "qube_servo_20230828")))
    p.add_argument(
        "--soft", type=Path, default=Path(os.environ.get("QUBE_SOFT_DATASET_DIR", shared / "qube_servo_20230915_soft"))
    )
    if lifting:
        p.add_argument("--lifting", default=DEFAULT_LIFTING, help=f"qube-identify flags (default: {DEFAULT_LIFTING})")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    data_arguments(p)
    p.add_argument("--out", type=Path, default=None, help="keep the fits' reports here")
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        root = args.out or Path(tmp)
        rig, soft = read_datasets(args, root, 2)
        train, paper_test = rig[:28], rig[28:]
        half = len(soft) // 2
        halves = (soft[:half], soft[half:])
        sets = {
            "rig only": [(train, soft)],
            "soft only": [(halves[0], halves[1]), (halves[1], halves[0])],
            "both": [(train + halves[0], halves[1]), (train + halves[1], halves[0])],
        }
        paper_names = {p.name for p in paper_test}
        print(f"lifting: {args.lifting}; soft episodes: {len(soft)} (halves of {half} and {len(soft) - half})")
        print("| training set | paper test (20), offsets | without | soft held-out, offsets | without |")
        print("|---|---|---|---|---|")
        for label, fits in sets.items():
            paper, held = [], []
            for k, (fit_logs, soft_test) in enumerate(fits):
                scores = per_episode(
                    fit_logs, paper_test + soft_test, args.lifting, root / f"{label.replace(' ', '_')}_{k}"
                )
                paper.append([v for n, v in scores.items() if n in paper_names])
                held += [v for n, v in scores.items() if n not in paper_names]
            paper_mean = np.mean(np.array(paper, float), axis=0)  # each paper episode: mean over the fits
            held = np.array(held, float)

            def cell(values):
                return f"{values.mean():.3f} / {values.min():.3f}"

            print(
                f"| {label} | {cell(paper_mean[:, 0])} | {cell(paper_mean[:, 1])} | {cell(held[:, 0])} "
                f"| {cell(held[:, 1])} |",
                flush=True,
            )
        copies = in_sample_copies(soft, root / "soft_in_sample")  # the training's soft logs: scored in sample
        scores = per_episode(train + soft, copies, args.lifting, root / "in_sample")
        fitted = np.array(list(scores.values()), float)
        print(
            f"| both, scored in sample (28 + {len(soft)}; a ceiling, not a transfer score) | - | - "
            f"| {fitted[:, 0].mean():.3f} / {fitted[:, 0].min():.3f} "
            f"| {fitted[:, 1].mean():.3f} / {fitted[:, 1].min():.3f} |",
            flush=True,
        )
        print_error_analysis(arm_errors(root / "in_sample" / "predictions", copies))
    return 0


if __name__ == "__main__":
    sys.exit(main())
