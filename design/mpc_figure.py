"""A figure of one MPC episode: what the loop did, where the limit bound, and what one tick predicted.

:func:`write_mpc_episode_figure` reads a ``qube-run`` log of an ``mpc`` controller and the controller
file it ran, and writes a PNG of three panels:

- the arm (``theta``, its reference) and the pendulum (``alpha``) over the episode;
- the plant input with the voltage limit, the ticks whose QP had an active constraint (the log's
  per-tick ``constraint_active``) shaded;
- at one tick (by default the first after the first second whose constraint was active), the
  horizon: the arm's angle and the input the tick's plan predicted against what was then measured
  and applied.

The plan of that tick is recomputed: the log's tracking errors, feedforward and references are run
through the controller file's MPC again from the episode's start (as the loop ran it, without a
time budget), so the tick's plan is the one the controller solved there unless the loop fell back
on that tick (the figure's title says so). Matplotlib runs on its Agg backend, imported only here.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from qube_koopman.core.controller_file import load_controller
from qube_koopman.daq.log import read_episode

__all__ = ["MpcEpisodeFigure", "replay_plan", "write_mpc_episode_figure"]


@dataclass(frozen=True)
class MpcEpisodeFigure:
    """What :func:`write_mpc_episode_figure` wrote and showed.

    Parameters
    ----------
    path : Path
        The PNG.
    tick : int
        The tick whose horizon the figure shows.
    predicted_theta : ndarray (N,)
        The arm's angle that tick's plan predicted for the next ``N`` ticks (rad).
    measured_theta : ndarray (N,)
        The arm's angle measured at those ticks (rad; shorter at the episode's end).
    plan : ndarray (N,)
        The tick's planned plant inputs (V, the feedforward included).
    active_fraction : float
        The share of the episode's ticks with an active constraint.
    voltage_limit : float
        The MPC's limit (V).
    """

    path: Path
    tick: int
    predicted_theta: np.ndarray
    measured_theta: np.ndarray
    plan: np.ndarray
    active_fraction: float
    voltage_limit: float


def replay_plan(controller: str | Path, episode, tick: int) -> tuple[np.ndarray, np.ndarray]:
    """The plan and the arm's predicted angles of one tick, the log's inputs run through the MPC again.

    Parameters
    ----------
    controller : str or Path
        The ``mpc`` controller file the episode ran.
    episode : Episode
        The episode's log (:func:`daq.log.read_episode`).
    tick : int
        The tick (sample index).

    Returns
    -------
    plan : ndarray (N,)
        The plant inputs planned (V, the feedforward included).
    theta : ndarray (N,)
        The arm's angle predicted after each of them (rad).
    """
    runtime = load_controller(controller).runtime
    if not hasattr(runtime, "problem"):
        raise ValueError(f"{controller}: not an mpc controller file")
    runtime.clock = lambda: 0.0  # no budget: the tick's plan is the solver's, whatever the host
    output, update = runtime.step()
    err = episode.references - episode.states
    f, r = episode.feedforward, episode.target_theta
    for k in range(tick + 1):
        output(err[k, 0], err[k, 1], f[k], r[k])
        if k < tick:
            update(err[k, 0], err[k, 1], f[k])
    mz, r_theta, shift = runtime.prediction
    p = runtime.problem
    deviation = runtime.plan - shift  # the QP's variables: the inputs less the steady state's
    theta = r_theta + p.theta_U @ deviation + mz
    return runtime.plan + f[tick], theta


def write_mpc_episode_figure(
    log: str | Path, controller: str | Path, out: str | Path, tick: int | None = None
) -> MpcEpisodeFigure:
    """Write the PNG of one MPC episode (module docstring).

    Parameters
    ----------
    log : str or Path
        A ``qube-run`` log (MCAP) of the controller.
    controller : str or Path
        The ``mpc`` controller file it ran.
    out : str or Path
        The PNG to write.
    tick : int, optional
        The tick whose horizon to show; default the first after the first second with an active
        constraint (the first after the first second if none was).

    Returns
    -------
    MpcEpisodeFigure
    """
    episode = read_episode(log, warn=False)
    meta = episode.metadata.controller
    if "constraint_active" not in (meta.tick_fields or ()):
        raise ValueError(f"{log}: not a log of an mpc controller (no per-tick constraint_active)")
    record = dict(zip(meta.tick_fields, np.asarray(episode.controller_record).T))
    active = record["constraint_active"] > 0
    fallback = record["fallback"] > 0
    dt, n = float(episode.dt), len(episode)
    t = np.arange(n) * dt
    start = min(round(1.0 / dt), n - 1)
    if tick is None:
        hits = np.flatnonzero(active[start:])
        tick = start + (int(hits[0]) if len(hits) else 0)
    if not 0 <= tick < n:
        raise ValueError(f"{log}: tick {tick} outside the episode's {n} ticks")
    plan, predicted = replay_plan(controller, episode, tick)
    N = len(plan)
    limit = float(load_controller(controller).runtime.problem.settings.voltage_limit)
    measured = episode.theta[tick + 1 : tick + 1 + N]

    import matplotlib

    matplotlib.use("Agg")  # lazily, and never a window: the figure goes to a file
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(3, 1, figsize=(9, 9), constrained_layout=True)
    ax[0].plot(t, episode.target_theta, color="0.6", lw=1, label="theta reference")
    ax[0].plot(t, episode.theta, lw=1, label="theta")
    ax[0].plot(t, episode.alpha, lw=1, label="alpha")
    ax[0].set_ylabel("angle (rad)")
    ax[0].legend(loc="upper right", fontsize=8)
    ax[1].plot(t, episode.plant_input, lw=0.8, label="plant input")
    for sign in (1, -1):
        ax[1].axhline(sign * limit, color="k", ls="--", lw=0.8, label="voltage limit" if sign > 0 else None)
    ax[1].fill_between(t, -limit, limit, where=active, color="tab:red", alpha=0.25, lw=0, label="constraint active")
    ax[1].axvline(tick * dt, color="tab:green", lw=0.8, label="tick below")
    ax[1].set_ylabel("voltage (V)")
    ax[1].set_xlabel("time (s)")
    ax[1].legend(loc="upper right", fontsize=8)
    th = (tick + 1 + np.arange(N)) * dt
    ax[2].plot(th, predicted, "o-", ms=3, label="theta predicted at the tick")
    ax[2].plot(th[: len(measured)], measured, "s-", ms=3, label="theta measured")
    reference = episode.target_theta[tick + 1 : tick + 1 + N]
    ax[2].plot(th[: len(reference)], reference, color="0.6", lw=1, label="theta reference")
    ax[2].set_ylabel("angle (rad)")
    ax[2].set_xlabel("time (s)")
    right = ax[2].twinx()
    right.step(tick * dt + np.arange(N) * dt, plan, where="post", color="tab:purple", lw=1, label="input planned")
    applied = episode.plant_input[tick : tick + N]
    right.step(
        tick * dt + np.arange(len(applied)) * dt,
        applied,
        where="post",
        color="tab:red",
        lw=1,
        ls=":",
        label="input applied",
    )
    right.axhline(limit, color="k", ls="--", lw=0.6)
    right.axhline(-limit, color="k", ls="--", lw=0.6)
    right.set_ylabel("voltage (V)")
    lines = ax[2].get_legend_handles_labels()
    more = right.get_legend_handles_labels()
    ax[2].legend(lines[0] + more[0], lines[1] + more[1], loc="upper right", fontsize=8)
    share = float(active.mean())
    title = (
        f"MPC episode: limit {limit:g} V, constraint active on {100 * share:.1f} % of ticks; horizon of tick "
        f"{tick} ({tick * dt:.3f} s){' (the loop fell back there)' if fallback[tick] else ''}"
    )
    fig.suptitle(title, fontsize=10)
    out = Path(out)
    fig.savefig(out, dpi=90, metadata={"Title": title})
    plt.close(fig)
    return MpcEpisodeFigure(out, tick, predicted, measured, plan, share, limit)
