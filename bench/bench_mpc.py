"""The MPC of ``qube-design --mpc`` on the twin: its solve time per tick, and its cost against the LQ design clipped.

    python bench/bench_mpc.py [MODEL.json] [--seeds 5,6,7] [--episodes 2] [--duration 10] [--voltage-limit V]
                              [--horizons 10,20,40] [--out DIR] [--only timing|offset-free|j-table|stiff-cables|paced]
                              [--load 0.5] [--load-seeds 1,2,3,4,5] [--j-episodes 20] [--j-seed 7] [--j-horizon 20]
                              [--plant NAME]
    python bench/bench_mpc.py --only predictors --data DIR [--predictor-horizons 5,20,50,100,250] [--starts 200]

MODEL.json is a plant identified by ``qube-identify`` (without one, the bench identifies one on 6
twin episodes of the rig's PD, ``--poly 1 --delays 35 --const``, as the design page's cycle). It prints:

- the solve time per tick in ``qube-run``'s loop on the twin (free-running, one process, the
  default weights, the voltage limit below) for each horizon: p50 / p99 / max against the targets
  (p99 <= 0.5 ms, max <= 1.5 ms at the default horizon), the ticks out of the budget (fallbacks),
  the ticks with an active constraint, the tick's compute time p99; at the default horizon also
  with OSQP (warm-started) on the same problem, the reference solver;
- the twin's J = mean((theta - target_theta)^2) + mean(alpha^2) after the first second, per seed,
  of the MPC and of the LQ design of the same weights run clipped at the same limit
  (``qube-run --max-voltage``), beside the LQ unclipped; the limit is, unless given, 0.7 times the
  LQ's voltage peak on those excitations (so that the limit binds).

- offset-free control under a constant load: a plant identified on 6 twin episodes with a disturbance model
  (``--horizon 0.1,1 --disturbance input --disturbance-q 1e-5 --disturbance-pole 1``: the twin's episodes have
  no load to set ``q`` and the pole from), the MPC designed on it with ``--no-offset-free`` ("off": the model's
  load estimated and logged), ``--disturbances input`` ("input": the load alone estimated and used) and by
  default ("input,theta": a load and the arm's rate), with the arm's integral (the default) and without
  (``--no-integral``), and (offset-free "none") the same file without its disturbance table, the MPC
  estimating nothing; each run on the twin for 10 s, ``--load`` volts added at
  the plant input from 1 s on (the controller does not see it), the arm's reference a step every 2.5 s (to
  +-0.05 rad, drawn from the seed: steps of 0.3 rad lose the pendulum under the MPC of the default weights,
  with or without a load), per seed of ``--load-seeds``: J after the first second, the arm's
  steady-state offset (mean of theta - target_theta over the last second of each step, in absolute value,
  averaged), the estimate's final value against the load, and the solve time per tick (the thread's CPU
  time) p50 / p99.

- ``--only j-table``: the design bench's excitations (``qube-run --seed 7 --episodes 20``, 20 s each) under
  the rig's PD, the LQ design, the LQ clipped at the limit (``qube-run --max-voltage``), the MPC
  (``--no-offset-free``) and the offset-free MPC at the limit (``--voltage-limit``, default 4 V), and the MPC at
  the rig's 10 V beside the LQ: per controller the episodes completed, J over the complete ones and over the
  episodes every controller completed, the ticks over the limit and at it, the fallbacks. MODEL.json should
  carry a disturbance model (``qube-identify ... --horizon 0.1,1 --disturbance input --disturbance-pole 1``).
  The MPC files run without their time budget (the algorithm's J, not the host's luck: the timing table
  measures the host). ``--plant NAME``: on that twin (``calibrated-with-load``: with the rig's random load).
- ``--only figure``: the docs' figure of an MPC episode (:mod:`design.mpc_figure`): the offset-free MPC at the
  limit (default 4 V), the first episode of ``qube-run --seed 7`` (20 s), written to ``--figure PNG``
  (default ``docs/_static/mpc_episode.png``).
- ``--only stiff-cables``: offset-free control on a twin the model did not see, the cables' stiffness ``Kr``
  twice the calibrated one: the MPC designed on MODEL.json with ``--no-offset-free``, ``--disturbances input``
  and the default two disturbances (with and without the arm's integral), from a start drawn from the seed
  (the arm within 0.02 rad of 0, the pendulum 0.01-0.03 rad off upright), the arm's reference stepped to
  +-0.1 rad at 0.5 s (the sign from the seed; ``--stiff-ramp 0.3``: ramped to +-0.3 rad from 0.5 s to 2.5 s
  instead), 12 s per seed of ``--load-seeds``: the arm's mean tracking error from 5 s on (``mean(theta - target)``, in
  absolute value, averaged over the seeds), beside the same on the calibrated twin.

- ``--only paced``: the MPC at the limit (default 4 V) replayed on one logged twin episode's ticks (8 s), its
  output step's wall time per tick p50 / p99 / max, with nothing between the ticks (as the free-running
  loop), with the rest of a 2 ms tick asleep (as a paced loop waits for its deadline or the bridge's
  sample) and with it spinning: what waiting asleep costs the next tick's compute on this machine. Then the
  same controller in the twin's paced loop (``qube-run --realtime``), waiting asleep and with ``--spin``,
  alternating, two episodes each: the loop's compute per tick and the MPC's solve time, p50 / p99 / max.

- ``--only predictors``: the multi-step predictors (:mod:`design.predictors`) on the paper's real data (``--data
  DIR``, its 48 episodes as .mcap logs, ``qube-import``'s): plants fitted on the 28 training episodes
  (``qube-identify DIR --split paper --interval 0``) with ``--poly 1 --delays 35 --const`` (the design's
  plant: the MPC's prediction is the model itself), ``--poly 3 --delays 35`` (the MPC's prediction is its
  linearization at upright) and ``--poly 3 --delays 35 --friction`` (a plant the design refuses); on the 20
  test episodes, from ``--starts`` samples of each (after the skipped first second), the logged plant input
  applied, each predictor's prediction ``K`` ticks ahead for each of ``--predictor-horizons``: the model's
  own (``relifted``, qube-identify's free run), Korda & Mezić's lifted map without re-lifting (``lifted``)
  and the MPC's (``upright``); R^2 per channel (averaged over the episodes) and the RMS error (mrad). Under
  the logged input, not in closed loop: the MPC predicts the plant under the inputs it plans, and the logged
  input is the one the plant received. The open-loop plant is unstable, so long horizons diverge whatever
  the predictor. One to two minutes on two shared cores (three fits; the scores take seconds).

Timing is the host's: on a machine shared with other work the tails (p99, max) of the loop's
(wall-clock) solve time are the machine's as much as the solver's; the bench therefore also runs
the logged ticks' inputs through the controller again and times each solve in the thread's CPU
time (the solver's own cost), and the iterations per tick do not depend on the machine.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import re
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from qube_koopman.core.controller import QUBE_SAMPLE_PERIOD
from qube_koopman.core.controller_file import load_controller
from qube_koopman.daq.cli.run import main as _run_main
from qube_koopman.daq.log import read_episode
from qube_koopman.design.cli.design import main as _design_main
from qube_koopman.design.predict import episode_cost
from qube_koopman.identify.cli.identify import main as _identify_main
from qube_koopman.sim.pendulum.simulator import PendulumSimulator

TARGET_P99 = 0.5e-3
TARGET_MAX = 1.5e-3


def _quiet(command):
    """The command with its terminal output swallowed (the bench prints its own table)."""

    def run(argv):
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            return command(argv)

    return run


run_main, design_main, identify_main = _quiet(_run_main), _quiet(_design_main), _quiet(_identify_main)


def _cpu_solve_times(controller: Path, episodes: list) -> np.ndarray:
    """The solve time per tick in the thread's CPU time: the logged ticks' inputs through the controller again.

    The loop's solve time is wall time, preemption by the machine's other work included; this one is
    the solver's own cost on the same ticks (same inputs, same warm starts, no budget).
    """
    info = load_controller(controller)
    runtime = info.runtime
    runtime.clock = time.thread_time
    times = []
    for e in episodes:
        output, update = runtime.step()
        err = e.references - e.states
        for k in range(len(e)):
            output(err[k, 0], err[k, 1], e.feedforward[k], e.target_theta[k])
            times.append(runtime.tick_record[2])
            update(err[k, 0], err[k, 1], e.feedforward[k])
    return np.array(times)


def _run(out: Path, controller: Path, seed: int, episodes: int, duration: float, *extra: str) -> list:
    argv = ["--controller", str(controller), "--episodes", str(episodes), "--duration", f"{duration:g}"]
    run_main([*argv, "--seed", str(seed), "--out", str(out), "--n-jobs", "1", "-q", *extra])
    return [read_episode(p) for p in sorted(out.glob("*.mcap"))]


def _paced(root: Path, model: Path, limit: float, ticks: int = 4000) -> None:
    """The MPC's output step per tick (wall time), the logged ticks replayed back to back and with the rest of a
    2 ms tick between them spent asleep (as a paced loop waits) or spinning."""
    controller = root / "mpc_paced.toml"
    design_main([str(model), "--mpc", "--voltage-limit", f"{limit:g}", "--out", str(controller), "--interval", "0"])
    episode = _run(root / "paced_runs", controller, 7, 1, ticks * QUBE_SAMPLE_PERIOD)[0]
    print(f"MPC at {limit:g} V on {model}: its output step per tick over {len(episode)} logged ticks, in us")
    print(f"{'between ticks':<28}{'p50':>8}{'p99':>8}{'max':>8}")
    for label, pause in (("nothing", 0.0), ("1.5 ms asleep", 1.5e-3), ("1.5 ms spinning", -1.5e-3)):
        runtime = load_controller(controller).runtime
        runtime.clock = lambda: 0.0  # no budget: every tick solves
        output, update = runtime.step()
        err = episode.references - episode.states
        spent = []
        for k in range(len(episode)):
            if pause > 0:
                time.sleep(pause)
            elif pause < 0:
                end = time.perf_counter() - pause
                while time.perf_counter() < end:
                    pass
            t = time.perf_counter()
            output(err[k, 0], err[k, 1], episode.feedforward[k], episode.target_theta[k])
            spent.append(time.perf_counter() - t)
            update(err[k, 0], err[k, 1], episode.feedforward[k])
        p50, p99 = np.percentile(spent, [50, 99]) * 1e6
        print(f"{label:<28}{p50:8.0f}{p99:8.0f}{max(spent) * 1e6:8.0f}")
    # The same controller in the twin's paced loop (qube-run --realtime), the loop asleep between ticks or spinning
    # (--spin), alternating, two episodes each: the tick's compute (the loop's, the log's) and the MPC's solve.
    print(f"\nin qube-run --realtime, {2 * ticks * QUBE_SAMPLE_PERIOD:g} s each way, alternating; in us")
    print(f"{'the loop waits':<28}{'compute p50':>12}{'p99':>8}{'max':>8}{'solve p50':>10}{'p99':>8}{'max':>8}")
    runs: dict[str, list] = {"asleep": [], "spinning (--spin)": []}
    for round_ in range(2):
        for label, extra in (("asleep", ()), ("spinning (--spin)", ("--spin",))):
            out = root / f"paced_{'spin' if extra else 'sleep'}_{round_}"
            shutil.rmtree(out, ignore_errors=True)
            runs[label] += _run(out, controller, 7, 1, ticks * QUBE_SAMPLE_PERIOD, "--realtime", *extra)
    for label, episodes in runs.items():
        compute = np.concatenate([e.compute_time for e in episodes]) * 1e6
        fields = episodes[0].metadata.controller.tick_fields
        solve = np.concatenate([e.controller_record[:, fields.index("solve_time")] for e in episodes]) * 1e6
        c50, c99 = np.percentile(compute, [50, 99])
        s50, s99 = np.percentile(solve, [50, 99])
        print(f"{label:<28}{c50:12.0f}{c99:8.0f}{compute.max():8.0f}{s50:10.0f}{s99:8.0f}{solve.max():8.0f}")


def _cost(episodes: list) -> tuple[float, int, float]:
    """(mean J over the complete episodes, complete episodes, voltage peak)."""
    done = [e for e in episodes if e.metadata.status == "complete"]
    J = [episode_cost(e.theta, e.target_theta, e.alpha, e.plant_input)[0] for e in done]
    peak = max((float(np.max(np.abs(e.plant_input))) for e in episodes if len(e)), default=0.0)
    return (float(np.mean(J)) if J else float("nan")), len(done), peak


def _model(root: Path, *extra: str) -> Path:
    if not (root / "train").is_dir():
        for out, n, seed in (("train", 6, 3), ("test", 2, 4)):
            run_main(["--episodes", str(n), "--seed", str(seed), "--out", str(root / out), "-q"])
    name = "model" if not extra else "model_disturbance"
    identify_main(
        [
            "--train",
            *map(str, sorted((root / "train").glob("*.mcap"))),
            "--test",
            *map(str, (root / "test").glob("*.mcap")),
            "--poly",
            "1",
            "--delays",
            "35",
            "--const",
            "--out",
            str(root / name),
            "-q",
            *extra,
        ]
    )
    return root / name / "model.json"


def _loaded_run(controller: Path, seed: int, load: float, seconds: float = 10.0) -> dict:
    """The controller on the twin, ``load`` V at the plant input from 1 s on, the arm's reference a step every 2.5 s."""
    rng = np.random.default_rng(seed)
    dt, n = 0.002, round(seconds / 0.002)
    step = round(2.5 / dt)
    r = np.repeat(np.concatenate([[0.0], rng.uniform(-0.05, 0.05, n // step)]), step)[:n]
    runtime = load_controller(controller).runtime
    runtime.clock = time.thread_time
    out, upd = runtime.step()
    sim = PendulumSimulator(seed=seed)
    theta, alpha = sim.reset((0.0, rng.uniform(-0.02, 0.02), 0.0, 0.0))
    x, estimate, solve = np.zeros((n, 2)), np.zeros(n), np.zeros(n)
    for k in range(n):
        e0, e1 = r[k] - theta, -alpha
        u, _ = out(e0, e1, 0.0, r[k])
        x[k], estimate[k], solve[k] = (theta, alpha), _load_estimate(runtime), runtime.tick_record[2]
        theta, alpha = sim.step(u + (load if k * dt >= 1.0 else 0.0))
        upd(e0, e1, 0.0)
        if abs(theta) > 2.0 or abs(alpha) > 0.5:  # lost (the rig's supervisor would stop it)
            return {"lost": True}
    after = slice(round(1.0 / dt), None)
    J = float(np.mean((x[after, 0] - r[after]) ** 2) + np.mean(x[after, 1] ** 2))
    ends = [slice(i - round(1.0 / dt), i) for i in range(step, n + 1, step)]
    offset = float(np.mean([abs(np.mean(x[e, 0] - r[e])) for e in ends]))
    return {"lost": False, "J": J, "offset": offset, "estimate": float(estimate[-1]), "solve": solve}


def _load_estimate(runtime) -> float:
    """The MPC's estimate of the load at the plant input (V), 0 when it estimates none."""
    entries = runtime.disturbance.entries if runtime.disturbance is not None else ()
    return float(runtime.estimate[entries.index("input")]) if "input" in entries else 0.0


#: The offset-free variants the tables compare: qube-design's flags for each.
OFFSET_FREE_VARIANTS = {
    "off": ["--no-offset-free"],
    "input": ["--disturbances", "input"],
    "input,theta": [],  # the default
}


def _offset_free(root: Path, seeds: list[int], load: float) -> None:
    """J, the steady-state offset and the solve time under a constant load, with and without offset-free control."""
    model = _model(
        root, "--horizon", "0.1,1", "--disturbance", "input", "--disturbance-q", "1e-5", "--disturbance-pole", "1"
    )
    quiet = ["--episodes", "1", "--duration", "2", "--interval", "0", "-q", "--force"]
    print(f"\noffset-free MPC: {load:g} V added at the plant input from 1 s on, 10 s on the twin per seed {seeds}")
    print(
        f"{'integral':>8} {'offset-free':>11} {'J mean':>10} {'offset mean mrad':>16} {'offset max mrad':>15} "
        f"{'estimate / load':>15} {'CPU solve p50/p99 us':>20} {'lost':>4}"
    )
    for integral in (True, False):
        for offset_free in ("none", *OFFSET_FREE_VARIANTS):
            flags = ([] if integral else ["--no-integral"]) + OFFSET_FREE_VARIANTS.get(
                offset_free, ["--no-offset-free"]
            )
            f = root / f"mpc_load_{int(integral)}{offset_free.replace(',', '_')}.toml"
            design_main([str(model), "--mpc", *flags, "--out", str(f), *quiet])
            text = f.read_text().replace("time_budget = 0.001", "time_budget = 10.0")  # no host luck
            if offset_free == "none":  # the same MPC without the disturbance table: no estimate at all
                text = "\n".join(line for line in text.splitlines() if not line.startswith("disturbance =")) + "\n"
            f.write_text(text)
            runs = [_loaded_run(f, s, load) for s in seeds]
            kept = [run for run in runs if not run["lost"]]
            solve = np.concatenate([run["solve"] for run in kept])
            offsets = [1e3 * run["offset"] for run in kept]
            print(
                f"{'on' if integral else 'off':>8} {offset_free:>11} "
                f"{np.mean([run['J'] for run in kept]):>10.3e} {np.mean(offsets):>16.2f} {np.max(offsets):>15.2f} "
                f"{np.mean([run['estimate'] for run in kept]) / load:>15.3f} "
                f"{1e6 * np.percentile(solve, 50):>9.0f}/{1e6 * np.percentile(solve, 99):<10.0f} "
                f"{len(runs) - len(kept):>4d}"
            )


def _no_budget(path: Path) -> Path:
    path.write_text(path.read_text().replace("time_budget = 0.001", "time_budget = 10.0"))
    return path


def _episodes_figures(folder: Path, limit: float) -> dict:
    """Completion, J per complete episode (by name), ticks over and at the limit, fallbacks, of a folder of logs."""
    eps = {p.name[-16:]: read_episode(p, warn=False) for p in sorted(folder.glob("*.mcap"))}
    J = {
        k: episode_cost(e.theta, e.target_theta, e.alpha, e.plant_input)[0]
        for k, e in eps.items()
        if e.metadata.status == "complete"
    }
    u = np.concatenate([e.plant_input[round(1.0 / e.dt) :] for e in eps.values()])
    fallback = 0
    for e in eps.values():
        fields = e.metadata.controller.tick_fields or ()
        if "fallback" in fields:
            fallback += int(e.controller_record[:, fields.index("fallback")].sum())
    return {
        "n": len(eps),
        "J": J,
        "over": int(np.sum(np.abs(u) > limit + 1e-9)),
        "at": float(np.mean(np.abs(u) >= limit - 1e-6)),
        "fallback": fallback,
        "peaks": [float(np.max(np.abs(e.plant_input))) for e in eps.values()],
    }


def _j_table(root: Path, model: Path, limit: float, episodes: int, seed: int, horizon: int, plant=None) -> None:
    """The design bench's excitations under the PD, the LQ, the LQ clipped, the MPC and the offset-free MPC
    (on ``plant``, a ``qube-run --plant`` name or file, when given)."""
    quiet = ["--episodes", "2", "--duration", "4", "--interval", "0", "-q", "--force"]
    mpc = ["--mpc", "--horizon", str(horizon)]
    files = {"LQ": root / "j_lq.toml"}
    design_main([str(model), "--out", str(files["LQ"]), *quiet])
    for name, flags in (
        ("MPC", ["--voltage-limit", f"{limit:g}", "--no-offset-free"]),
        ("MPC offset-free", ["--voltage-limit", f"{limit:g}"]),
        ("MPC 10 V", ["--voltage-limit", "10", "--no-offset-free"]),
    ):
        files[name] = root / f"j_{name.replace(' ', '_')}.toml"
        design_main([str(model), *mpc, *flags, "--out", str(files[name]), *quiet])
        _no_budget(files[name])
    runs = {
        "rig's PD": [],
        "LQ": ["--controller", str(files["LQ"])],
        f"LQ clipped at {limit:g} V": ["--controller", str(files["LQ"]), "--max-voltage", f"{limit:g}"],
        f"MPC at {limit:g} V": ["--controller", str(files["MPC"])],
        f"MPC offset-free at {limit:g} V": ["--controller", str(files["MPC offset-free"])],
        "MPC at 10 V": ["--controller", str(files["MPC 10 V"])],
    }
    rows = {}
    for name, extra in runs.items():
        out = root / ("j_" + re.sub(r"[^A-Za-z0-9]+", "_", name))
        argv = ["--episodes", str(episodes), "--seed", str(seed), "--out", str(out), "-q", "--force", *extra]
        run_main([*argv, *([] if plant is None else ["--plant", str(plant)])])
        rows[name] = _episodes_figures(out, limit if "10 V" not in name and name not in ("LQ", "rig's PD") else 10.0)
    lq_peaks = np.array(rows["LQ"]["peaks"])
    print(
        f"\nJ table: {episodes} episodes of qube-run --seed {seed} (20 s), model {model}, limit {limit:g} V; the LQ "
        f"design's voltage peak per episode: median {np.median(lq_peaks):.2f} V, max {lq_peaks.max():.2f} V; MPC "
        f"horizon {horizon}" + ("" if plant is None else f"; the twin: --plant {plant}")
    )
    common = set.intersection(*(set(r["J"]) for r in rows.values()))
    clipped = rows[f"LQ clipped at {limit:g} V"]
    print(
        f"{'controller':<30} {'complete':>8} {'J complete':>11} {'J common':>10} {'vs LQc':>7} "
        f"{'over':>5} {'at limit %':>10} {'fallback':>8}"
    )
    for name, r in rows.items():
        Jc = np.mean([r["J"][k] for k in common]) if common else np.nan
        Jq = np.mean([clipped["J"][k] for k in common]) if common else np.nan
        print(
            f"{name:<30} {len(r['J']):>4}/{r['n']:<3} {np.mean(list(r['J'].values())):>11.3e} {Jc:>10.3e} "
            f"{100 * (Jc / Jq - 1):>+6.1f}% {r['over']:>5d} {100 * r['at']:>10.2f} {r['fallback']:>8d}"
        )
    print(f"J common: the {len(common)} episodes every controller completed; over / at limit: after the first second")
    a, b = rows["MPC at 10 V"]["J"], rows["LQ"]["J"]
    both = set(a) & set(b)
    print(
        f"MPC at 10 V / LQ: J {np.mean([a[k] for k in both]) / np.mean([b[k] for k in both]):.4f} (target within 2 %)"
    )


def _figure(root: Path, model: Path, limit: float, png: Path) -> None:
    """The offset-free MPC at the limit on the first excitation of ``qube-run --seed 7``, as a figure."""
    from qube_koopman.design.mpc_figure import write_mpc_episode_figure

    f = root / "figure_mpc.toml"
    quiet = ["--episodes", "1", "--duration", "2", "--interval", "0", "-q", "--force"]
    design_main([str(model), "--mpc", "--voltage-limit", f"{limit:g}", "--out", str(f), *quiet])
    _no_budget(f)
    run_main(["--controller", str(f), "--episodes", "1", "--seed", "7", "--out", str(root / "figure"), "-q", "--force"])
    (log,) = sorted((root / "figure").glob("*.mcap"))
    png.parent.mkdir(parents=True, exist_ok=True)
    fig = write_mpc_episode_figure(log, f, png)
    error = 1e3 * np.abs(fig.predicted_theta[: len(fig.measured_theta)] - fig.measured_theta)
    print(
        f"wrote {png}: constraint active on {100 * fig.active_fraction:.1f} % of the ticks; tick {fig.tick}'s "
        f"horizon: theta predicted within {error.max():.2f} mrad of the twin (first step {error[0]:.2f} mrad)"
    )


def _stiff_cables(
    root: Path, model: Path, seeds: list[int], step: float = 0.1, seconds: float = 12.0, ramp: bool = False
) -> None:
    """The arm's mean tracking error from 5 s on, on a twin whose cables are twice as stiff as the calibrated one."""
    from dataclasses import replace

    from qube_koopman.sim.pendulum import PendulumParameters

    base = PendulumParameters()
    twins = {"calibrated": base, "cables x2": replace(base, Kr=2 * base.Kr)}
    quiet = ["--episodes", "1", "--duration", "2", "--interval", "0", "-q", "--force"]
    dt, n = 0.002, round(seconds / 0.002)
    print(
        f"\nstiff cables: the arm's reference {'ramped' if ramp else 'stepped'} to +-{step:g} rad at 0.5 s, "
        f"{seconds:g} s per seed {seeds}; "
        f"mean |mean(theta - target)| from 5 s on (mrad)"
    )
    print(f"{'integral':>8} {'offset-free':>11} " + " ".join(f"{k:>12}" for k in twins) + f" {'|load est.| x2 V':>16}")
    for integral in (True, False):
        for offset_free, variant in OFFSET_FREE_VARIANTS.items():
            flags = ([] if integral else ["--no-integral"]) + variant
            f = root / f"stiff_{int(integral)}{offset_free.replace(',', '_')}.toml"
            design_main([str(model), "--mpc", *flags, "--out", str(f), *quiet])
            _no_budget(f)
            cells, estimate = [], []
            for twin in twins.values():
                errors = []
                for s in seeds:
                    r_step = step * (1 if s % 2 else -1)
                    runtime = load_controller(f).runtime
                    out, upd = runtime.step()
                    sim = PendulumSimulator(params=twin, seed=s)
                    # The start from the seed too: with no load the twin is deterministic, and a fixed start
                    # left two distinct runs (the step's sign) however many seeds.
                    start = np.random.default_rng(s).uniform(-1.0, 1.0, 2) * (0.02, 0.01)
                    theta, alpha = sim.reset((start[0], 0.02 + start[1], 0.0, 0.0))
                    err = np.zeros(n)
                    for k in range(n):
                        r = r_step * (min(max((k * dt - 0.5) / 2.0, 0.0), 1.0) if ramp else float(k * dt >= 0.5))
                        e0, e1 = r - theta, -alpha
                        u, _ = out(e0, e1, 0.0, r)
                        err[k] = theta - r
                        theta, alpha = sim.step(u)
                        upd(e0, e1, 0.0)
                        if abs(alpha) > 0.5:  # lost (the rig's supervisor would stop it)
                            raise SystemExit(f"stiff cables: the pendulum fell (seed {s}); try a smaller step")
                    errors.append(abs(err[round(5.0 / dt) :].mean()))
                    if twin is not base:
                        estimate.append(abs(_load_estimate(runtime)))
                cells.append(1e3 * np.mean(errors))
            print(
                f"{'on' if integral else 'off':>8} {offset_free:>11} "
                + " ".join(f"{c:>12.3f}" for c in cells)
                + f" {np.mean(estimate):>16.4f}"
            )


#: The plants the predictors part fits on the paper's split (qube-identify's lifting flags).
PREDICTOR_PLANTS = ("--poly 1 --delays 35 --const", "--poly 3 --delays 35", "--poly 3 --delays 35 --friction")


def _fixed(value: float, decimals: int) -> str:
    """``value`` with ``decimals`` decimals, or in 3 significant digits when that would not fit 8 characters."""
    text = f"{value:.{decimals}f}"
    return text if len(text) <= 8 or not np.isfinite(value) else f"{value:.3g}"


def _predictors(root: Path, data: Path, horizons: list[int], n_starts: int) -> None:
    """The three multi-step predictors of each plant on the paper's test episodes, under the logged plant input."""
    from qube_koopman.core.qube import SKIP_SAMPLES
    from qube_koopman.design.predictors import score_predictors
    from qube_koopman.identify import load_logs, load_model
    from qube_koopman.identify.model_selection.split import paper_split

    logs = sorted(data.glob("*.mcap"))
    if not logs:
        raise SystemExit(f"{data}: no .mcap logs (qube-import the paper's dataset into it)")
    _, test = paper_split(logs)
    episodes = [log.trajectory for log in load_logs(test, skip=SKIP_SAMPLES)]
    print(
        f"\npredictors: plants fitted on the paper's 28 training episodes, each predictor's prediction K ticks ahead "
        f"on its {len(episodes)} test episodes from {n_starts} starts each, under the logged plant input"
    )
    cells = " ".join(f"{f'K={K}':>17}" for K in horizons)
    print(f"{'plant':<32} {'predictor':<9} {'':<5} {cells}")
    cols = range(len(horizons))
    for flags in PREDICTOR_PLANTS:
        out = root / ("predictors_" + re.sub(r"[^A-Za-z0-9]+", "_", flags).strip("_"))
        identify_main(
            [str(data), "--split", "paper", *flags.split(), "--interval", "0", "--out", str(out), "-q", "--force"]
        )
        scores = score_predictors(load_model(out / "model.json").plant, episodes, horizons, n_starts)
        for p, name in enumerate(scores.predictors):
            r2 = " ".join(f"{_fixed(scores.r2[p, h, 0], 4):>8}/{_fixed(scores.r2[p, h, 1], 4):<8}" for h in cols)
            rms = " ".join(
                f"{_fixed(1e3 * scores.rms[p, h, 0], 2):>8}/{_fixed(1e3 * scores.rms[p, h, 1], 2):<8}" for h in cols
            )
            print(f"{flags if p == 0 else '':<32} {name:<9} {'R^2':<5} {r2}")
            print(f"{'':<32} {'':<9} {'RMS':<5} {rms}")
            if scores.n_diverged[p].any():
                lost = ", ".join(f"K={K}: {n}" for K, n in zip(horizons, scores.n_diverged[p]) if n)
                print(f"{'':<32} {'':<9} diverged of {scores.n_windows}: {lost}")
        if scores.refused:
            print(f"{'':<32} {'upright':<9} refused: {scores.refused.split(',')[0]}")
        else:  # episode by episode: does the lifted map predict better than the MPC's linearization?
            e = scores.episode_rms
            a, b = scores.predictors.index("lifted"), scores.predictors.index("upright")
            wins = " ".join(
                f"{np.sum(e[:, a, h, 0] < e[:, b, h, 0]):>8}/{np.sum(e[:, a, h, 1] < e[:, b, h, 1]):<8}" for h in cols
            )
            print(f"{'':<32} {'lifted < upright':<15} {wins}  (episodes of {len(e)})")
    print(
        "R^2 and RMS error (mrad) as theta/alpha; R^2 per episode against its variance, averaged; RMS pooled; "
        "one diverged prediction makes them inf"
    )


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("model", nargs="?", type=Path)
    p.add_argument("--seeds", default="5,6,7")
    p.add_argument("--episodes", type=int, default=2)
    p.add_argument("--duration", type=float, default=10.0)
    p.add_argument("--voltage-limit", type=float, default=None)
    p.add_argument("--horizons", default="10,20,40")
    p.add_argument("--out", type=Path, default=None)
    p.add_argument(
        "--only",
        choices=("timing", "offset-free", "j-table", "stiff-cables", "figure", "predictors", "paced"),
        default=None,
    )
    p.add_argument("--data", type=Path, default=None, help="the paper's 48 episodes as .mcap logs (--only predictors)")
    p.add_argument("--predictor-horizons", default="5,20,50,100,250")
    p.add_argument("--starts", type=int, default=200)
    p.add_argument("--figure", type=Path, default=Path(__file__).parents[1] / "docs" / "_static" / "mpc_episode.png")
    p.add_argument("--stiff-ramp", type=float, default=None, metavar="RAD")
    p.add_argument("--j-episodes", type=int, default=20)
    p.add_argument("--j-seed", type=int, default=7)
    p.add_argument("--j-horizon", type=int, default=20)
    p.add_argument("--load", type=float, default=0.5)
    p.add_argument("--load-seeds", default="1,2,3,4,5")
    p.add_argument(
        "--plant", default=None, help="--only j-table: the twin's qube-run --plant (default: the default twin)"
    )
    args = p.parse_args(argv)
    root = args.out or Path(tempfile.mkdtemp(prefix="bench_mpc_"))
    root.mkdir(parents=True, exist_ok=True)
    if args.only == "predictors":
        if args.data is None:
            p.error("--only predictors needs --data DIR (the paper's 48 episodes as .mcap logs)")
        _predictors(root, args.data, [int(h) for h in args.predictor_horizons.split(",")], args.starts)
        return 0
    if args.only in ("j-table", "stiff-cables", "figure"):
        if args.model is None:
            p.error(f"--only {args.only} needs MODEL.json (with a disturbance model)")
        if args.only == "figure":
            _figure(root, args.model, args.voltage_limit or 4.0, args.figure)
        elif args.only == "j-table":
            limit = args.voltage_limit or 4.0
            _j_table(root, args.model, limit, args.j_episodes, args.j_seed, args.j_horizon, args.plant)
        else:
            seeds = [int(s) for s in args.load_seeds.split(",")]
            if args.stiff_ramp is None:
                _stiff_cables(root, args.model, seeds)
            else:
                _stiff_cables(root, args.model, seeds, step=args.stiff_ramp, ramp=True)
        return 0
    if args.only == "paced":
        _paced(root, args.model or _model(root), args.voltage_limit or 4.0)
        return 0
    if args.only != "timing":
        _offset_free(root, [int(s) for s in args.load_seeds.split(",")], args.load)
    if args.only == "offset-free":
        return 0
    model = args.model or _model(root)
    seeds = [int(s) for s in args.seeds.split(",")]
    horizons = [int(h) for h in args.horizons.split(",")]
    quiet = ["--episodes", "2", "--duration", "4", "--interval", "0", "-q", "--force"]

    lq = root / "lq.toml"
    design_main([str(model), "--out", str(lq), *quiet])
    lq_runs = {s: _run(root / f"lq_{s}", lq, s, args.episodes, args.duration) for s in seeds}
    lq_peak = max(_cost(runs)[2] for runs in lq_runs.values())
    limit = args.voltage_limit or round(0.7 * lq_peak, 1)
    print(f"model {model}; the LQ design's voltage peak on the twin {lq_peak:.2f} V; voltage limit {limit:g} V")
    print(f"seeds {seeds}, {args.episodes} episodes of {args.duration:g} s each, free-running, one process\n")

    print("solve time per tick in the loop (target at the default horizon 20: p99 <= 0.5 ms, max <= 1.5 ms)")
    header = (
        f"{'horizon':>7} {'solver':>7} {'wall p50/p99/max us':>20} {'CPU p50/p99/max us':>19} {'iter p99':>8} "
        f"{'fallback':>8} {'active %':>8} {'compute p99 us':>14} {'J':>10}"
    )
    print(header)
    mpc_files = {}
    for N in horizons:
        for solver in ("newton", "osqp") if N == 20 else ("newton",):
            f = root / f"mpc_{N}_{solver}.toml"
            design_main(
                [str(model), "--mpc", "--horizon", str(N), "--voltage-limit", f"{limit:g}", "--out", str(f), *quiet]
            )
            if solver != "newton":
                f.write_text(re.sub(r'solver = "newton"', f'solver = "{solver}"', f.read_text()))
            mpc_files[(N, solver)] = f
            episodes = _run(root / f"mpc_{N}_{solver}_{seeds[0]}", f, seeds[0], args.episodes, args.duration)
            rec = np.vstack([e.controller_record for e in episodes])
            fields = episodes[0].metadata.controller.tick_fields
            r = dict(zip(fields, rec.T))
            t = r["solve_time"]
            compute = np.concatenate([e.compute_time for e in episodes])
            J = _cost(episodes)[0]
            cpu = _cpu_solve_times(f, episodes)
            ok = N != 20 or (np.percentile(t, 99) <= TARGET_P99 and t.max() <= TARGET_MAX)
            wall = "/".join(f"{1e6 * v:.0f}" for v in (np.percentile(t, 50), np.percentile(t, 99), t.max()))
            own = "/".join(f"{1e6 * v:.0f}" for v in (np.percentile(cpu, 50), np.percentile(cpu, 99), cpu.max()))
            print(
                f"{N:>7} {solver:>7} {wall:>20} {own:>19} {np.percentile(r['solver_iterations'], 99):>8.0f} "
                f"{int(r['fallback'].sum()):>8d} {100 * r['constraint_active'].mean():>8.1f} "
                f"{1e6 * np.percentile(compute, 99):>14.0f} {J:>10.3e}" + ("" if ok else "  (wall time over target)")
            )

    print(f"\ntwin J per seed at {limit:g} V (complete episodes of {args.episodes}); MPC horizon 20")
    print(f"{'seed':>5} {'MPC J':>10} {'LQ clipped J':>13} {'MPC/LQc':>8} {'LQ 10 V J':>10} {'MPC peak V':>10}")
    ratios = []
    for s in seeds:
        mpc = _cost(_run(root / f"mpc_J_{s}", mpc_files[(20, "newton")], s, args.episodes, args.duration))
        clipped = _cost(_run(root / f"lqc_{s}", lq, s, args.episodes, args.duration, "--max-voltage", f"{limit:g}"))
        free = _cost(lq_runs[s])
        ratios.append(mpc[0] / clipped[0])
        print(
            f"{s:>5} {mpc[0]:>10.3e} ({mpc[1]}) {clipped[0]:>10.3e} ({clipped[1]}) {ratios[-1]:>8.3f} "
            f"{free[0]:>10.3e} {mpc[2]:>10.2f}"
        )
    print(f"MPC J / clipped LQ J: mean {np.mean(ratios):.3f} over {len(seeds)} seeds")
    return 0


if __name__ == "__main__":
    sys.exit(main())
