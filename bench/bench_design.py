"""A controller designed by ``qube-design`` against the rig's PD on the twin.

    python bench/bench_design.py MODEL.json [--seed 7] [--episodes 20] [--draws 50] [--serial lockstep|realtime]
                                 [--reidentify SEED] [--other-logs DIR] [--out DIR]

MODEL.json is a plant identified by ``qube-identify`` (the issue: the paper's 28 training
episodes, e.g. ``qube-identify qube_logs --split paper --poly 1 --delays 35 --const --out m``).
With the default weights it designs a controller (``qube-design``), then measures, printing each
figure beside its target:

- the PD and the design on the same ``--episodes`` twin excitations (``qube-run --seed``):
  completion, J = mean((theta - target_theta)^2) + mean(alpha^2) after the first second, tracking,
  alpha and voltage RMS, saturated samples, the voltage RMS of the quiet seconds 1-4;
- the model's prediction: J predicted on the same excitations against the measured J, the
  interval of J and of the voltage's RMS and peak (``qube-design --interval 0.95``) against the
  twin's, and the closed-loop prediction of the design's episodes (the plant model under the designed controller,
  from each log's first samples, references and feedforward) scored by R^2 per angle;
- robustness: ``--draws`` twins with km, Lp, mp and Jh drawn uniformly within +-10 % of the
  calibrated values and the command delay doubled, one episode each (encoder offsets drawn per
  episode, as the twin does by default), under the design and under the PD;
- with ``--reidentify SEED``: 48 twin episodes of ``qube-run --seed SEED`` under
  each controller, CL EDMD (``--poly 1 --delays 35 --const --alpha 1e-3``) on the first 28 of one
  controller scored on the last 20 of each: the design re-identified under itself, and the plants
  identified under the design and under the PD predicting each other's closed loops;
- with ``--other-logs DIR``: real (or twin) logs of another controller, each predicted by the model under
  its own controller from the log's start: measured J and voltage RMS against the prediction, the
  prediction with the training controller's held-out ratio, and with the held-out error propagated
  through that controller (design.error_transfer);
- with ``--serial``: one episode through ``qube-emulate`` (the firmware's C core; lockstep or real
  time) and ``qube-run --backend serial``: completion and the ticks the link missed.
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np

from qube_koopman.daq.cli.run import main as run_main
from qube_koopman.daq.log import read_episode
from qube_koopman.design.cli.design import main as design_main
from qube_koopman.design.predict import episode_cost
from qube_koopman.identify.data.logs import load_logs
from qube_koopman.identify.models.model_file import load_model
from qube_koopman.identify.metrics import r2_scores
from qube_koopman.identify.estimators.structure import close_loop
from qube_koopman.core.controller_file import load_controller
from qube_koopman.sim.pendulum import PendulumParameters
from qube_koopman.sim.pendulum.params_file import PlantFile, save_plant


def figures(folder: Path) -> dict:
    """Completion and the cost figures of a folder of logs (after the first second)."""
    episodes = [read_episode(p, warn=False) for p in sorted(folder.glob("*.mcap"))]
    done = [e for e in episodes if e.metadata.status == "complete"]
    rows = np.array([episode_cost(e.theta, e.target_theta, e.alpha, e.plant_input) for e in done]).reshape(-1, 5)
    if not done:  # every episode stopped (a perturbed twin's draw): no cost to average
        return {
            "episodes": len(episodes),
            "complete": 0,
            "J": np.nan,
            "tracking_rms": np.nan,
            "alpha_rms": np.nan,
            "voltage_rms": np.nan,
            "voltage_peak": np.nan,
            "saturated": 0,
            "quiet_voltage_rms": np.nan,
        }
    return {
        "episodes": len(episodes),
        "complete": len(done),
        "J": float(rows[:, 0].mean()),
        "tracking_rms": float(np.sqrt(np.mean(rows[:, 1] ** 2))),
        "alpha_rms": float(np.sqrt(np.mean(rows[:, 2] ** 2))),
        "voltage_rms": float(np.sqrt(np.mean(rows[:, 3] ** 2))),
        "voltage_peak": float(rows[:, 4].max()),
        "saturated": int(sum(e.saturation[500:].sum() for e in done)),
        "quiet_voltage_rms": float(np.mean([np.sqrt(np.mean(e.plant_input[500:2000] ** 2)) for e in done])),
    }


def prediction_r2(model_path: Path, controller_path: Path, folder: Path) -> np.ndarray:
    """R^2 of theta and alpha, per episode: the plant model under the controller, from each log's start."""
    plant = load_model(model_path).plant
    loop = close_loop(plant, load_controller(controller_path).system)
    logs = load_logs(sorted(folder.glob("*.mcap")))
    scores = []
    for log in logs:
        predicted = loop.predict(log.trajectory)
        true = log.trajectory.x
        scores.append([float(r2_scores(true[1:, [c]], predicted[1:, [c]])) for c in (0, 1)])
    return np.array(scores)


def robustness(controller: str | None, draws: int, root: Path) -> int:
    """Episodes completed of ``draws`` perturbed twins (one episode each), under ``controller`` (None: the PD)."""
    base = PendulumParameters()  # the default twin, as the rest of the bench runs
    rng = np.random.default_rng(2028)
    complete = 0
    for i in range(draws):
        scale = rng.uniform(0.9, 1.1, 4)
        params = replace(
            base,
            km=base.km * scale[0],
            Lp=base.Lp * scale[1],
            mp=base.mp * scale[2],
            Jh=base.Jh * scale[3],
            delay=2 * base.delay,
        )
        plant_file = root / f"plant_{i}.toml"
        save_plant(plant_file, PlantFile(params, provenance={"draw": i}))
        out = root / f"draw_{i}_{'pd' if controller is None else 'design'}"
        argv = ["--episodes", "1", "--seed", str(1000 + i), "--plant", str(plant_file), "--out", str(out), "-q"]
        assert run_main(argv + ([] if controller is None else ["--controller", controller])) == 0
        complete += figures(out)["complete"]
    return complete


def serial_lockstep(controller: str, root: Path) -> str:
    """One 20 s episode through the emulated bridge in lockstep (as tests/core/test_state_space_controller.py runs it).

    The emulator (the firmware's C core) ticks when the host has answered, up to 0.1 s apart, so
    the machine's load does not decide the outcome; what is measured is the firmware's path.
    """
    from qube_koopman.daq.backends.serial import SerialBackend
    from qube_koopman.daq.loop import run_episode
    from qube_koopman.daq.session import excitation_settings, plan_episodes, run_seeds
    from qube_koopman.daq.sinks import McapSink
    from qube_koopman.sim.bridge import BridgeEmulator

    (plan,) = plan_episodes(
        load_controller(controller), run_seeds(7, 1)[0], excitation_settings(20.0), source="bench_design"
    )
    emulator = BridgeEmulator(seed=3, lockstep=True, lockstep_timeout=0.1)
    (root / "serial").mkdir(exist_ok=True)
    backend, sink = SerialBackend(emulator.start(), link_timeout=1.0), McapSink(root / "serial")
    try:
        result = run_episode(backend, plan, [sink])
    finally:
        backend.close()
        emulator.stop()
    episode = read_episode(sink.paths[0])
    stats = {k: v for k, v in episode.metadata.backend_stats.items() if k != "decoder"}
    return (
        f"lockstep: {'complete' if result.complete else 'aborted: ' + str(result.reason)}, {len(episode)} samples, "
        f"link {stats}"
    )


def serial_realtime(controller: str, root: Path) -> str:
    """One 20 s episode through ``qube-emulate`` at 500 Hz of wall time, both under SCHED_FIFO (needs root)."""
    emulator = subprocess.Popen(
        ["chrt", "-f", "30", "qube-emulate", "--seed", "3"],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    try:
        port = emulator.stdout.readline().split()[-1]
        run = subprocess.run(
            [
                "qube-run",
                "--backend",
                "serial",
                "--port",
                port,
                "--episodes",
                "1",
                "--seed",
                "7",
                "--controller",
                controller,
                "--out",
                str(root / "serial_rt"),
                "--rt-priority",
                "20",
            ],
            capture_output=True,
            text=True,
            timeout=180,
        )
    finally:
        emulator.terminate()
        emulator.wait(timeout=10)
    lines = [line for line in (run.stdout + run.stderr).splitlines() if re.search(r"complete|serial link|ticks", line)]
    return f"real time, exit {run.returncode}\n" + "\n".join(lines)


def reidentification(controller: str, seed: int, root: Path) -> dict[str, float]:
    """Test R^2 of CL EDMD trained on 28 episodes under one controller and tested on 20 under each."""
    from qube_koopman.identify.cli.identify import main as identify_main

    logs = {}
    for name, extra in (("PD", []), ("design", ["--controller", controller])):
        folder = root / f"reidentify_{name}"
        assert run_main(["--episodes", "48", "--seed", str(seed), "--out", str(folder), "-q", *extra]) == 0
        logs[name] = sorted(map(str, folder.glob("*.mcap")))
    scores = {}
    for train in logs:
        for test in logs:
            out = root / f"reidentify_{train}_{test}"
            assert (
                identify_main(
                    [
                        "--train",
                        *logs[train][:28],
                        "--test",
                        *logs[test][28:],
                        "--poly",
                        "1",
                        "--delays",
                        "35",
                        "--const",
                        "--alpha",
                        "1e-3",
                        "--out",
                        str(out),
                        "-q",
                    ]
                )
                == 0
            )
            scores[f"{train} -> {test}"] = json.loads((out / "report.json").read_text())["test"]["r2_mean"]
    return scores


def other_controller(model_path: Path, folder: Path) -> str:
    """Measured, predicted, ratio-corrected and propagated J and voltage RMS of logs of another controller."""
    from qube_koopman.design import linear_plant
    from qube_koopman.design.error_transfer import loop_spectra, propagate_error
    from qube_koopman.design.uncertainty import model_uncertainty
    from qube_koopman.identify.estimators.structure import controller_states, plant_input
    from qube_koopman.identify.uncertainty import loop_figures

    model = load_model(model_path)
    plant, uncertainty = model.plant, model_uncertainty(model)
    if uncertainty is None or uncertainty.spectra is None or uncertainty.held_out is None:
        raise SystemExit(f"{model_path}: no held-out error spectra (identify it with intervals, the default)")
    rows, runs = [], []
    logs = load_logs(sorted(folder.glob("*.mcap")))
    for log in logs:
        t, c = log.trajectory, log.controller
        x = close_loop(plant, c).predict(t)
        f = None if t.f is None else t.f[None]
        u = plant_input(c, controller_states(c, t.r[None], x[None], f), t.r[None], x[None], f)[0, :, 0]
        rows.append([loop_figures(t.x, t.r[:, 0], t.u[:, 0], 500), loop_figures(x, t.r[:, 0], u, 500)])
        runs.append((x[:, 0], t.r[:, 0], x[:, 1], u))
    rows, n = np.array(rows), min(len(run[0]) for run in runs)
    uu, eu = loop_spectra(
        *(np.array([run[i][:n] for run in runs]) for i in range(4)),
        uncertainty.spectra.edges,
        uncertainty.spectra.dt,
        500,
    )
    J, V = rows[:, 1, 0].mean(), np.sqrt(np.mean(rows[:, 1, 1] ** 2))
    found = propagate_error(
        uncertainty.spectra, uncertainty.held_out, linear_plant(plant), logs[0].controller, uu, eu, (J, V)
    )
    ratio = np.exp(np.mean(np.log(uncertainty.held_out[:, 0, :2] / uncertainty.held_out[:, 1, :2]), axis=0))
    return (
        f"{len(logs)} logs of {folder}: J measured {rows[:, 0, 0].mean():.4g}, predicted {J:.4g}, with the "
        f"ratio {J * ratio[0]:.4g}, propagated {J * np.exp(found.shift[0]):.4g}; voltage RMS measured "
        f"{np.sqrt(np.mean(rows[:, 0, 1] ** 2)):.4g}, predicted {V:.4g}, with the ratio {V * ratio[1]:.4g}, "
        f"propagated {V * np.exp(found.shift[1]):.4g}"
    )


def main() -> None:
    """Run the comparison and print it."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("model", type=Path)
    p.add_argument("--seed", type=int, default=7)
    p.add_argument("--episodes", type=int, default=20)
    p.add_argument("--draws", type=int, default=50)
    p.add_argument("--serial", choices=("lockstep", "realtime"), default=None)
    p.add_argument("--reidentify", type=int, default=None, metavar="SEED")
    p.add_argument("--out", type=Path, default=None)
    p.add_argument("--other-logs", type=Path, default=None, metavar="DIR")
    args = p.parse_args()
    if args.other_logs is not None:
        print(other_controller(args.model, args.other_logs))
    root = args.out or Path(tempfile.mkdtemp(prefix="bench_design_"))
    root.mkdir(parents=True, exist_ok=True)
    controller = root / "designed.toml"
    n = str(args.episodes)
    assert design_main([str(args.model), "--out", str(controller), "--seed", str(args.seed), "--episodes", n]) == 0
    for name, extra in (("pd", []), ("design", ["--controller", str(controller)])):
        assert run_main(["--episodes", n, "--seed", str(args.seed), "--out", str(root / name), "-q", *extra]) == 0
    pd, design = figures(root / "pd"), figures(root / "design")
    print(f"\n{'':<20}{'complete':>9}{'J':>11}{'tracking':>10}{'alpha':>9}{'voltage':>9}{'quiet V':>9}{'sat':>5}")
    for name, f in (("rig's PD", pd), ("design", design)):
        print(
            f"{name:<20}{f['complete']:>4}/{f['episodes']:<4}{f['J']:>11.3e}{f['tracking_rms']:>10.4f}"
            f"{f['alpha_rms']:>9.4f}{f['voltage_rms']:>9.3f}{f['quiet_voltage_rms']:>9.3f}{f['saturated']:>5}"
        )
    print(
        f"J {100 * (design['J'] / pd['J'] - 1):+.1f} % (target <= -40 %), voltage RMS "
        f"{design['voltage_rms'] / pd['voltage_rms']:.2f} x the PD's (target <= 1.45)"
    )
    predicted = load_controller(controller).provenance["predicted"]["J"]
    r2 = prediction_r2(args.model, controller, root / "design")
    print(
        f"predicted J {predicted:.3e} vs measured {design['J']:.3e}: {100 * (predicted / design['J'] - 1):+.1f} % "
        f"(target within 15 %); closed-loop prediction R^2 theta {r2[:, 0].mean():.4f} (min {r2[:, 0].min():.4f}), "
        f"alpha {r2[:, 1].mean():.4f} (min {r2[:, 1].min():.4f}) (target >= 0.9)"
    )
    interval = load_controller(controller).provenance.get("interval", {})
    for name, label in (("J", "J"), ("voltage_rms", "voltage RMS"), ("voltage_peak", "voltage peak")):
        if name in interval:
            iv, measured = interval[name], design[name]
            inside = "inside" if iv["lower"] <= measured <= iv["upper"] else "OUTSIDE"
            print(
                f"{label}: predicted {iv['predicted']:.4g}, with the model's error {iv['expected']:.4g}, interval "
                f"{iv['lower']:.4g} to {iv['upper']:.4g} at {interval['level']:g}; twin {measured:.4g} ({inside})"
            )
    if args.draws:
        ok, ok_pd = robustness(str(controller), args.draws, root), robustness(None, args.draws, root)
        print(
            f"robustness: {ok}/{args.draws} perturbed twins complete under the design (target >= 95 %), "
            f"{ok_pd}/{args.draws} under the PD"
        )
    if args.reidentify is not None:
        scores = reidentification(str(controller), args.reidentify, root)
        print(
            "re-identified (train -> test, 28 -> 20 episodes, target >= 0.95): "
            + ", ".join(f"{k} {v:.4f}" for k, v in scores.items())
        )
    if args.serial:
        serial = serial_realtime if args.serial == "realtime" else serial_lockstep
        print("serial path:", serial(str(controller), root))
    print(f"logs and files in {root}")


if __name__ == "__main__":
    sys.exit(main())
