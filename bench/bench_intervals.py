"""How well do the prediction intervals hold, on the rig's loop and under controllers the training never ran?

Trains on the paper's 28 training episodes (real logs) and gives every predicted sample an interval
at 0.95 (``qube-identify``'s default), then reports, per test set and channel: the pooled coverage,
the worst episode's coverage, and the mean half-width against the RMS error (rad). Test sets:

- the paper's 20 test episodes (the rig's loop: calibrated on held-out training episodes);
- the soft-controller episodes, when ``--soft`` names their folder (real logs of the same rig
  under kp_theta 2, kd_theta 2, kp_alpha 35, kd_alpha 3);
- twin episodes under the four judge controllers of ``bench_transfer.py`` (20 each).

Episodes under another controller than the training's are calibrated on the twin's probe episodes
(``--interval-other-loops twin``, the default); ``--other-loops none`` shows the training loop's
calibration instead. Targets (held-out data): pooled coverage within 0.90-0.98, no episode below
0.80, mean half-width at most 2.5 times the RMS error.

Measured with the default lifting (2 shared cores, the default twin: the cables per day and the
command delay per session), coverage, worst episode, half-width / RMS error:

| test episodes | theta | alpha |
|---|---|---|
| paper test (rig loop) | 0.957, 0.901, ratio 2.09 | 0.959, 0.926, ratio 2.14 |
| soft controller (real) | 0.972, 0.766, ratio 2.26 | 0.973, 0.919, ratio 2.31 |
| twin, soft-theta | 0.952, 0.838, ratio 1.98 | 0.991, 0.969, ratio 2.73 |
| twin, softer-pd | 0.999, 0.985, ratio 3.16 | 0.961, 0.930, ratio 2.13 |
| twin, lqr-q1 | 1.000, 0.998, ratio 3.78 | 0.983, 0.969, ratio 2.82 |
| twin, lqr-q3 | 1.000, 0.996, ratio 4.31 | 0.946, 0.910, ratio 2.07 |

The judge sets run the one calibrated twin while the probes that calibrate their bands run its six
session variants (command delay and cables, as the rig's sessions differed), so theta's band is 3-4
times the error under the stiffer loops: honest for the rig's sessions, wider than one twin needs.
Each judge loop is predicted with its estimated command delay (0.5-1 sample here: under a loop the
training never ran, the model's error looks like a little delay) and its band still takes its own
gains' probes: without them alpha's band under lqr-q3 was half as wide and covered 0.77. With the
search's lifting (``--flags "--poly 1 --trig --delays 35 --rbf thin-plate --rbf-centers 25
--friction --alpha 1e-5"``) theta covers 0.983-1.000 at 2.8-5.0 times the error and alpha 0.920-1.000
at 1.7-4.1 (worst episode 0.842, under lqr-q3); one episode of 20 under soft-theta, softer-pd and
lqr-q3 each gets an infinite band from some second on (a bootstrap refit at that small alpha diverges
under those loops); the half-width is then given over the other episodes.

With ``--judge-twins sessions`` (each judge's 20 episodes spread over the six session variants) the
default lifting gives theta 0.926-1.000 at 1.7-4.6 times the error and alpha 0.958-0.991 at 2.1-3.1;
the search's lifting theta 0.969-1.000 at 2.2-5.6 and alpha 0.972-1.000 at 2.5-4.9.

Usage: python bench/bench_intervals.py --data DIR_WITH_48_MCAP_LOGS [--soft DIR_WITH_SOFT_LOGS]
       [--flags "--poly 2 --delays 10 --alpha 1e-3"] [--other-loops twin|none] [--out DIR]
       [--judge-twins calibrated|sessions|both]
(import the datasets first with qube-import). About 5 minutes on 2 cores.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_transfer import JUDGES, judge_sets, run  # noqa: E402  (the judge controllers and their twin episodes)


def coverage_row(report: dict) -> list[str]:
    """Per channel: pooled coverage, worst episode, half-width / RMS error (their ratio).

    An episode whose band turns infinite (a bootstrap refit diverging under its loop) makes the pooled
    half-width infinite: the half-width is then the mean over the other episodes, and the cell says how
    many were left out.
    """
    intervals = report["intervals"]
    pooled = intervals["pooled"]
    # JSON has no infinity: an infinite half-width is written "inf"
    finite = [e for e in intervals["episodes"] if "inf" not in map(str, e["mean_half_width"].values())]
    cells = []
    for name in pooled["coverage"]:
        half, rms = float(pooled["mean_half_width"][name]), float(pooled["rms_error"][name])
        note = ""
        if not np.isfinite(half):
            half = float(np.mean([e["mean_half_width"][name] for e in finite]))
            rms = float(np.sqrt(np.mean([e["rms_error"][name] ** 2 for e in finite])))
            note = f", {len(intervals['episodes']) - len(finite)} infinite"
        cells.append(
            f"{pooled['coverage'][name]:.3f}, {pooled['worst_episode_coverage'][name]:.3f}, "
            f"{half:.4f} / {rms:.4f} ({half / rms:.2f}{note})"
        )
    return cells


def session_judge_sets(root: Path, judges: dict[str, Path], per_judge: int = 20) -> dict[str, Path]:
    """Twin episodes under each judge controller spread over the twin's six session variants (the command
    delays and cable stiffnesses the rig's sessions showed, ``session_twins``): the judge episodes then
    vary between sessions as the rig's did, which is what the probes calibrate the band for. The
    controllers are those of ``judges`` (their folders hold the controller files ``judge_sets`` wrote);
    seeds 201..., each variant its own."""
    from qube_koopman.identify.model_selection.transfer import session_twins
    from qube_koopman.sim.pendulum.params_file import PlantFile, save_plant

    twins = session_twins()
    counts = [len(part) for part in np.array_split(np.arange(per_judge), len(twins))]
    plants = []
    for k, params in enumerate(twins):
        plants.append(root / f"session_twin_{k}.toml")
        save_plant(plants[-1], PlantFile(params, provenance={"note": f"session variant {k} of the default twin"}))
    out = {}
    for j, name in enumerate(judges):
        gains = JUDGES[name]
        controller = gains if isinstance(gains, str) else str(root / f"{name}.toml")
        folder = root / f"sessions_{name}"
        for k, (plant, n) in enumerate(zip(plants, counts)):
            part = folder / f"twin_{k}"
            if not part.exists():
                run(
                    "qube-run",
                    "--episodes",
                    str(n),
                    "--seed",
                    str(201 + 10 * j + k),
                    "--controller",
                    controller,
                    "--plant",
                    plant,
                    "--out",
                    part,
                    "-q",
                )
        out[name] = folder
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True, help="folder of the 48 imported .mcap logs")
    parser.add_argument("--soft", type=Path, help="folder of the soft-controller .mcap logs")
    parser.add_argument("--flags", default="--poly 2 --delays 10 --alpha 1e-3", help="the lifting's flags")
    parser.add_argument("--other-loops", choices=("twin", "none"), default="twin")
    parser.add_argument("--out", type=Path, help="working folder (default: a temporary one)")
    parser.add_argument(
        "--judge-twins",
        choices=("calibrated", "sessions", "both"),
        default="calibrated",
        help="run the judge episodes on the calibrated twin (default), spread over its six session variants, or both",
    )
    args = parser.parse_args()
    root = args.out or Path(tempfile.mkdtemp(prefix="bench_intervals_"))
    root.mkdir(parents=True, exist_ok=True)
    logs = sorted(args.data.glob("*.mcap"))
    train, paper_test = logs[:28], logs[28:]
    tests = {"paper test (rig loop)": paper_test}
    if args.soft is not None:
        tests["soft controller (real)"] = sorted(args.soft.glob("*.mcap"))
    judges = judge_sets(root)
    if args.judge_twins in ("calibrated", "both"):
        tests.update({f"twin, {name}": sorted(folder.glob("*.mcap")) for name, folder in judges.items()})
    if args.judge_twins in ("sessions", "both"):
        tests.update(
            {
                f"session twins, {name}": sorted(folder.rglob("*.mcap"))
                for name, folder in session_judge_sets(root, judges).items()
            }
        )
    print(f"lifting {args.flags}, --offsets alpha, intervals at 0.95, other loops: {args.other_loops}\n")
    print("| test episodes | theta: coverage, worst, half-width / RMS | alpha: coverage, worst, half-width / RMS |")
    print("|---|---|---|")
    for label, test in tests.items():
        out = root / ("run_" + "".join(c if c.isalnum() else "_" for c in label))
        run(
            "qube-identify",
            "--train",
            *train,
            "--test",
            *test,
            *args.flags.split(),
            "--offsets",
            "alpha",
            "--interval-other-loops",
            args.other_loops,
            "--out",
            out,
            "--force",
            "-q",
        )
        report = json.loads((out / "report.json").read_text())
        print(f"| {label} | " + " | ".join(coverage_row(report)) + " |", flush=True)


if __name__ == "__main__":
    main()
