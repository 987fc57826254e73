"""Where the twin's slow power sits: the soft episodes' replays split at 0.1 Hz, against the Welch band;
and how long the arm holds still, real and replayed.

    python bench/bench_slow_bands.py --soft DIR [--plant NAME_OR_FILE] [--draws N] [--last N]

The calibration page's band table (``identify.calibrate.replay_spectra.band_std_ratios``) takes the
power below 0.3 Hz from Welch segments of 4096 samples (8.2 s): its bins at 0.12 and 0.24 Hz, each
segment's mean removed. Here each soft-controller episode (``--soft``: the 10 as MCAP logs) is
replayed on the plant (default ``calibrated-with-load``: each with its day's cables, delay, load
and tilt) ``--draws`` times, and the real and replayed theta, alpha and voltage are split by
zero-phase Butterworth filters (order 4) over the whole episode: below 0.1 Hz, 0.1-0.3 Hz and below
0.3 Hz. Printed: the median over episodes of the twin's standard deviation (mean over the draws)
over the real one, per band and channel, and the Welch band's ratio of the same replays. ``--soft``
may be any folder of one controller's logs; ``--last 20`` on the paper's 48 takes its test episodes.

Measured (``calibrated-with-load``, 4 draws; the soft episodes were among its fitted logs), theta /
alpha / voltage:

| band | std ratio twin / real |
|---|---|
| below 0.1 Hz | 1.017 / 0.713 / 1.176 |
| 0.1-0.3 Hz | 0.925 / 0.967 / 0.758 |
| below 0.3 Hz | 1.001 / 0.928 / 0.980 |
| Welch, below 0.3 Hz | 0.969 / 0.988 / 0.912 |

Under the soft loop the twin's arm wanders as far as the rig's, its voltage with it, but more
slowly: the voltage's slow power is all there below 0.3 Hz (0.98), shifted below 0.1 Hz (1.18
there, 0.76 above), and the Welch band, which sees 0.12-0.3 Hz, reads that shift as a shortfall.
On the rig's 20 test episodes (``--soft DIR --last 20``) the split is even (voltage 0.96 / 0.95).

Also printed: the share of each episode's time its arm's encoder count holds still for at least
0.1, 0.2 and 0.4 s (mean over episodes and draws). Measured, real / twin: soft 0.221 / 0.164,
0.124 / 0.073, 0.038 / 0.009; rig test 0.153 / 0.115, 0.048 / 0.019, 0.000 / 0.000. The real arm
stays put longer than the twin's, most under the soft loop, whose small arm gain builds the
voltage that moves it again slowest; the twin's friction (Coulomb's, its sign smoothed by ``tanh``
over 0.05 rad/s) lets a stuck arm creep. ``--plant FILE`` replays a plant file with other friction
(``Cs``, ``stribeck_speed``, ``coulomb_speed`` in its ``[parameters]``; docs/calibration.md), or with the
cables' relaxation (its ``[relaxation]`` tables, each log replayed with its day's).

With the relaxation (``qube-calibrate --load --tilt --relaxation`` on the paper's 28 and soft episodes
1-3, 6-8; against the same recipe without it), the soft episodes' voltage below 0.1 Hz is 1.04
(1.38 without), from 0.1 to 0.3 Hz 0.84 (0.77), the Welch band 0.97 (0.88), the arm 1.01 / 1.01
(1.04 / 0.94): the slow power moves up in frequency, where the rig's is. The arm holds still for
0.4 s or more 1.8 % of the time (1.0 % without; the rig's 3.8 %).

The shipped ``calibrated-with-relaxation`` (the relaxation fitted with the physics, all ten soft episodes
among its logs; ``--plant calibrated-with-relaxation``, 4 draws): theta / alpha / voltage below 0.1 Hz
1.008 / 0.717 / 0.964, 0.1-0.3 Hz 1.015 / 1.052 / 0.960, below 0.3 Hz 1.005 / 0.978 / 0.954, Welch 1.017 /
1.034 / 1.012: the soft voltage's slow power where the real one's is, in both halves of the band. The
pendulum's slowest band stays at 0.72, as with ``calibrated-with-load``. The arm holds still for 0.4 s or
more 1.0 % of the time.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy.signal import butter, sosfiltfilt

from qube_koopman.daq.log import read_episode
from qube_koopman.identify.calibrate.replay_spectra import CHANNELS, band_std_ratios
from qube_koopman.identify.calibrate.validate import replay_episodes
from qube_koopman.sim.pendulum.params_file import PlantFileError, plant_file

#: (label, low Hz or 0, high Hz): the bands the replays are split into.
SPLIT = (("below 0.1 Hz", 0.0, 0.1), ("0.1-0.3 Hz", 0.1, 0.3), ("below 0.3 Hz", 0.0, 0.3))
#: Durations (s) of the arm holding still whose share of the time is printed.
STILL = (0.1, 0.2, 0.4)
#: One count of the QUBE's 2048-count encoders (rad).
COUNT = 2 * np.pi / 2048


def band_std(signals: np.ndarray, low: float, high: float, dt: float) -> np.ndarray:
    """Standard deviation over time (axis 0) of ``signals`` band-passed to ``[low, high)`` Hz (zero phase)."""
    if low > 0:
        sos = butter(4, [low, high], btype="band", fs=1.0 / dt, output="sos")
    else:
        sos = butter(4, high, fs=1.0 / dt, output="sos")
    return sosfiltfilt(sos, signals - signals.mean(axis=0), axis=0).std(axis=0)


def still_share(theta: np.ndarray, dt: float, at_least: float) -> float:
    """The share of the time ``theta`` (one episode, rad) stays on one encoder count for ``at_least`` s or more."""
    counts = np.round(theta / COUNT).astype(int)
    edges = np.concatenate([[0], np.flatnonzero(np.diff(counts)) + 1, [counts.size]])
    durations = np.diff(edges) * dt
    return float(durations[durations >= at_least].sum() / (counts.size * dt))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--soft", type=Path, required=True, help="the soft controller's episodes as MCAP logs")
    parser.add_argument("--plant", default="calibrated-with-load", help="named plant or plant file")
    parser.add_argument("--draws", type=int, default=4, help="replays per episode (start angles and load draws)")
    parser.add_argument("--last", type=int, default=0, help="only the folder's last N logs (0: all)")
    args = parser.parse_args()
    episodes = [read_episode(p) for p in sorted(args.soft.glob("*.mcap"))[-args.last :]]
    if not episodes:
        raise SystemExit(f"{args.soft}: no .mcap logs")
    try:
        plant = plant_file(args.plant)
    except PlantFileError as exc:
        raise SystemExit(str(exc)) from None
    times = [e.metadata.start_time for e in episodes]
    loads = plant.loads_for_logs(times) if plant.load is not None else None
    relaxations = plant.relaxations_for_logs(times) if plant.relaxation is not None else None
    replay = replay_episodes(
        episodes, plant.params_for_logs(times), n_draws=args.draws, load=loads, relaxation=relaxations
    )
    dt = episodes[0].dt
    twins = np.asarray(replay.twins, float)  # (time, draw, episode, channel)
    print(f"{len(episodes)} episodes, {args.draws} draws, plant {args.plant}; twin / real, {' / '.join(CHANNELS)}")
    for label, low, high in SPLIT:
        ratio = band_std(twins, low, high, dt).mean(axis=0) / band_std(replay.real, low, high, dt)
        print(f"{label:<22}" + " / ".join(f"{r:.3f}" for r in np.median(ratio, axis=0)))
    welch = band_std_ratios(replay, dt, all_draws=True)[0]
    print(f"{'Welch, below 0.3 Hz':<22}" + " / ".join(f"{r:.3f}" for r in welch))
    for at_least in STILL:
        real = np.mean([still_share(replay.real[:, e, 0], dt, at_least) for e in range(len(episodes))])
        each = twins.reshape(twins.shape[0], -1, twins.shape[-1])  # (time, draw x episode, channel)
        twin = np.mean([still_share(each[:, i, 0], dt, at_least) for i in range(each.shape[1])])
        print(f"arm still >= {at_least} s: real {real:.3f}, twin {twin:.3f} of the time")


if __name__ == "__main__":
    main()
