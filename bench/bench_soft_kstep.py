"""What the soft loop's K-step predictions miss, and what the rig's training episodes cannot settle.

    python bench/bench_soft_kstep.py [--rig DIR] [--soft DIR] [--lifting "FLAGS"]

The plant is fitted on the paper's 28 training episodes of the rig (``--lifting``, default: the
paper-split search's winner, with ``--offsets alpha``) and scored with ``--horizon 0.1,1`` on the soft
controller's episodes, as ``bench_kstep.py --soft`` does. This bench prints:

1. the free run's R^2 per channel beside the K-step R^2, and where in frequency the free run's pendulum
   error lies (its share of the error's power per band);
2. the input random walk at the rig's own ``q``, 10 and 100 times it, and a first-order process of 0.4 s
   at each, scored on the paper's test episodes and on the soft ones (what the training loop can tell
   apart, and what the soft loop needs);
3. the soft episodes with the two recording days' calibrated tilts' difference taken out of their pendulum
   angle and its reference (``calibrated-with-load``'s ``tilt_x`` per day), scored again;
4. each soft episode's load (the one-step residuals' load signature) regressed on the arm angle: the
   stiffness it suggests, the share of the slow load (low-passed at 1 s) the arm angle explains, and the
   free run with that stiffness added to the model (the arm's R^2 before and after);
5. a drifting balance point followed by the filter (``--disturbance alpha``, a random walk, ``q`` set by hand):
   each soft episode's mean and RMS error of the arm 1 s ahead without a disturbance, the soft episodes' K-step
   scores with the filter, and the cost on the rig's training episodes beside no disturbance's (what
   ``auto`` weighs);
6. the soft loop's own ceiling: the same lifting trained on the soft episodes and scored on them (their copies
   under other names, as ``bench_two_controllers.py`` scores in sample), with ``auto`` and with the drifting
   balance point of 5: what a model of the soft loop's own episodes reaches at each horizon.

Each fit is one ``qube-identify`` run in this process; the figures are deterministic (no timing).
"""

from __future__ import annotations

import argparse
import glob
import json
import math
import shlex
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
from bench_two_controllers import data_arguments, identify_report, in_sample_copies, read_datasets

from qube_koopman.identify.metrics import r2_score

SEARCH_LIFTING = "--poly 1 --trig --delays 35 --rbf thin-plate --rbf-centers 25 --friction --alpha 1e-5 --offsets alpha"
#: Frequency bands (Hz) of the free run's pendulum error.
BANDS = ((0, 0.3), (0.3, 1), (1, 3), (3, 6), (6, 12), (12, 250))
#: The rig's own q multiplied by these (the disturbance's size the soft loop would want).
Q_FACTORS = (1, 10, 100)
#: A drifting balance point followed by the filter: the pendulum's rate as a random walk of these q (rad^2 per
#: sample), set by hand (the rig's episodes choose none).
BALANCE_Q = (1e-12, 1e-11)


def balance_flags(q: float) -> list[str]:
    """qube-identify's flags for that filter: the pendulum's rate as a random walk of variance ``q`` per sample."""
    return ["--disturbance", "alpha", "--disturbance-pole", "1", "--disturbance-q", f"{q:g}"]


def identify(train, test, flags: list[str], out: Path) -> dict:
    """One ``qube-identify`` run; its report.json."""
    return identify_report(["--train", *map(str, train), "--test", *map(str, test), *flags], out)


def kstep(report: dict) -> str:
    """The K-step R^2 per horizon, theta / alpha, mean (worst episode)."""
    return "; ".join(
        f"{h} s {s['r2_mean'][0]:.4f} / {s['r2_mean'][1]:.4f} ({s['r2_worst'][0]:.4f} / {s['r2_worst'][1]:.4f})"
        for h, s in report["ahead"]["horizons"].items()
    )


def free_run(out: Path) -> tuple[np.ndarray, np.ndarray]:
    """The free run's mean R^2 per channel over the predictions files' samples, and the pendulum error's power
    per band of :data:`BANDS` (summed over the episodes)."""
    from scipy.signal import welch

    r2, power = [], np.zeros(len(BANDS))
    for path in sorted(glob.glob(str(out / "predictions" / "*.npz"))):
        with np.load(path) as z:
            y, p = z["measured"], z["predicted"]
        r2.append([r2_score(y[:, [c]], p[:, [c]]) for c in range(y.shape[1])])
        f, psd = welch(y[:, 1] - p[:, 1], fs=500, nperseg=2048)
        power += [psd[(f >= lo) & (f < hi)].sum() for lo, hi in BANDS]
    return np.mean(r2, axis=0), power / power.sum()


def one_second_arm_errors(out: Path) -> tuple[np.ndarray, np.ndarray]:
    """Each episode's mean and RMS error of the arm's predictions 1 s ahead (a drift shows as a mean of its own)."""
    means, rms = [], []
    for path in sorted(glob.glob(str(out / "predictions" / "*.npz"))):
        with np.load(path) as z:
            error = z["ahead_1"][:, 0] - z["measured"][:, 0]
        error = error[np.isfinite(error)]
        means.append(error.mean())
        rms.append(np.sqrt(np.mean(error**2)))
    return np.array(means), np.array(rms)


def tilted(soft: list[Path], out: Path) -> list[Path]:
    """The soft logs with the two days' tilt difference taken out of the pendulum angle and its reference:
    as the rig's day would have measured them."""
    from qube_koopman.daq.log import read_episode, write_episode
    from qube_koopman.sim.pendulum.params_file import plant_file

    setups = plant_file("calibrated-with-load").setups
    slope = setups["2023-08-28"]["tilt_x"] - setups["2023-09-15"]["tilt_x"]
    out.mkdir(parents=True, exist_ok=True)
    for path in soft:
        episode = read_episode(path)
        shift = slope * np.sin(episode.theta)
        write_episode(
            out / path.name, replace(episode, alpha=episode.alpha + shift, target_alpha=episode.target_alpha + shift)
        )
    print(f"the tilts' difference: {slope * 1e3:.2f} mrad per radian of arm angle (sin theta)")
    return sorted(out.glob("*.mcap"))


def stiffness_check(out: Path, soft: list[Path]) -> None:
    """Each soft episode's slow load against its arm angle, and the free run with that stiffness in the model."""
    from scipy.signal import lfilter

    from qube_koopman.identify.data.logs import load_logs
    from qube_koopman.identify.estimators.structure import close_loop, with_command_delay
    from qube_koopman.identify.models import disturbance as dm
    from qube_koopman.identify.models.model_file import load_model
    from qube_koopman.identify.models.offsets import shift_trajectory

    fitted = load_model(out / "model.json")
    report = json.loads((out / "report.json").read_text())
    delays = {row["log"]: row["samples"] for row in report["command_delay"]["logs"]}
    offsets = {row["log"]: row["alpha"] for row in report["offsets"]}
    pole = math.exp(-1.0 / 500)  # the slow load: low-passed at 1 s
    print(f"{'episode':<24}{'V/rad':>8}{'explained':>11}   arm's free-run R^2 without, with it")
    before, after = [], []
    for log in load_logs(soft):
        delayed = with_command_delay(log, delays[log.path.name])
        loop = close_loop(fitted.plant, delayed.controller, list(fitted.measured))
        E = dm.disturbance_direction(loop, "input")
        trajectory = shift_trajectory(loop, delayed.trajectory, {1: offsets[log.path.name]})
        residuals, _ = dm.one_step_residuals(loop, trajectory)
        k = np.flatnonzero(np.isfinite(residuals).all(axis=1))[1:]
        load = np.linalg.lstsq((loop.C @ E)[:, None], residuals[k].T, rcond=None)[0][0]
        slow = lfilter([1 - pole], [1, -pole], load)
        theta = trajectory.x[k - 1, 0]
        X = np.column_stack([np.ones_like(theta), theta])
        stiffness = np.linalg.lstsq(X, load, rcond=None)[0][1]  # the load per radian of arm angle, all frequencies
        slow_fit = X @ np.linalg.lstsq(X, slow, rcond=None)[0]
        explained = 1 - np.var(slow - slow_fit) / np.var(slow)  # the slow load's share the arm angle explains
        scores = []
        for added in (0.0, stiffness):
            stiffer = replace(loop, A=loop.A + added * np.outer(E, np.eye(loop.A.shape[0])[loop.n_passthrough]))
            scores.append(r2_score(trajectory.x[500:, :1], stiffer.predict(trajectory)[500:, :1]))
        before.append(scores[0])
        after.append(scores[1])
        print(f"{log.path.stem[:24]:<24}{stiffness:>8.3f}{explained:>11.2f}   {scores[0]:.4f}, {scores[1]:.4f}")
    print(f"{'mean':<43}   {np.mean(before):.4f}, {np.mean(after):.4f}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    data_arguments(p)
    p.set_defaults(lifting=SEARCH_LIFTING)
    args = p.parse_args(argv)
    flags = shlex.split(args.lifting)
    ahead = ["--horizon", "0.1,1"]
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        rig, soft = read_datasets(args, root, 1)
        train, paper_test = rig[:28], rig[28:]

        print(f"1. trained on the paper's 28 ({args.lifting}), tested on the {len(soft)} soft episodes")
        report = identify(train, soft, [*flags, *ahead], root / "soft")
        r2, shares = free_run(root / "soft")
        print(f"free run theta / alpha {r2[0]:.4f} / {r2[1]:.4f}; K-step {kstep(report)}")
        print("the free run's pendulum error, share of its power: " + ", ".join(
            f"{lo:g}-{hi:g} Hz {share:.2f}" for (lo, hi), share in zip(BANDS, shares)
        ))  # fmt: skip
        q = report["disturbance"]["model"]["q"]

        print(f"\n2. the input disturbance's size (the rig's q {q:.3g} V^2 per sample), K-step theta / alpha (worst)")
        for name, test in (("paper test", paper_test), ("soft", soft)):
            for pole in ("1", "0.995"):
                for factor in Q_FACTORS:
                    hand = [
                        "--disturbance",
                        "input",
                        "--disturbance-pole",
                        pole,
                        "--disturbance-q",
                        f"{factor * q:.3g}",
                    ]
                    scored = identify(
                        train, test, [*flags, *ahead, *hand, "--interval", "0"], root / f"q_{name}_{pole}_{factor}"
                    )
                    print(f"{name:<11} pole {pole:<6} q x{factor:<4} {kstep(scored)}")

        print("\n3. the two days' tilts")
        level = tilted(soft, root / "tilted_logs")
        report = identify(train, level, [*flags, *ahead], root / "tilted")
        r2, _ = free_run(root / "tilted")
        print(f"free run theta / alpha {r2[0]:.4f} / {r2[1]:.4f}; K-step {kstep(report)}")

        print("\n4. the slow load against the arm angle (each soft episode), and that stiffness in the model")
        stiffness_check(root / "soft", soft)

        print("\n5. a drifting balance point: the pendulum's rate as a random walk, q set by hand")
        identify(train, soft, [*flags, *ahead, "--disturbance", "none", "--interval", "0"], root / "none")
        means, rms = one_second_arm_errors(root / "none")
        print(
            f"without a disturbance, each episode's 1 s arm error: mean {means.min() * 1e3:+.0f} to "
            f"{means.max() * 1e3:+.0f} mrad, RMS {rms.min() * 1e3:.0f} to {rms.max() * 1e3:.0f} mrad"
        )
        for q in BALANCE_Q:
            scored = identify(
                train, soft, [*flags, *ahead, *balance_flags(q), "--interval", "0"], root / f"balance_{q:g}"
            )
            cost = scored["disturbance"]["training_cost"]
            print(
                f"q {q:g}: soft K-step {kstep(scored)}; the rig's training cost {cost['alpha']:.4f} "
                f"against {cost['none']:.4f} without"
            )

        print("\n6. the soft loop's own ceiling: trained on the soft episodes, scored in sample")
        in_sample = in_sample_copies(soft, root / "soft_in_sample")
        for name, hand in (("auto", []), (f"balance q {BALANCE_Q[0]:g}", balance_flags(BALANCE_Q[0]))):
            scored = identify(
                soft, in_sample, [*flags, *ahead, *hand, "--interval", "0"], root / f"ceiling_{len(hand)}"
            )
            print(f"{name:<17} (disturbance {scored['disturbance']['entry']}): K-step {kstep(scored)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
