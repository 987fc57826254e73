# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # Tutorial: a Koopman model of the QUBE-Servo, from the paper's data to another controller
#
# This notebook walks through what `qube-import`, `qube-identify` and `qube-run` do, in Python:
#
# 1. import a few episodes of the paper's QUBE-Servo dataset (CSV) into episode logs (MCAP);
# 2. identify a closed-loop Koopman model (CL EDMD) and score it on test episodes;
# 3. look at its figures: measured vs predicted trajectories, eigenvalues, the alpha sweep;
# 4. run the simulated pendulum (the calibrated twin) under another controller, `soft-theta`,
#    and predict those episodes with the identified plant, estimating each episode's
#    pendulum encoder offset from its first second.
#
# **What it needs.** The package with its figures (`pip install -e ".[figures]"` from the
# repository's root) and the paper's dataset: the folder `dataset/controller_20230828` of the
# public repository `decargroup/closed_loop_koopman` (MIT licence), 48 CSV files and their
# `controller.toml`, anywhere on your disk. It runs in about a minute.
#
# **As a script**, from the repository's root (figures are saved, not shown):
#
#     python examples/tutorial.py DATASET_DIR [OUT_DIR]
#
# **As a notebook**: it is stored as a jupytext "percent" script, not as .ipynb, so the
# repository keeps reviewable text with no outputs, images or execution counts in its history.
# Install `pip install jupytext nbconvert ipykernel`, set `QUBE_DATASET_DIR` to the dataset's
# folder (and `QUBE_TUTORIAL_OUT` to keep the logs and figures), then either execute it into
# a notebook with its outputs, `jupytext --to ipynb --execute examples/tutorial.py` (writes
# `examples/tutorial.ipynb`), or open it in Jupyter (with jupytext installed, *Open as
# notebook*) and run it cell by cell.
#
# Without `OUT_DIR` / `QUBE_TUTORIAL_OUT` the logs and figures go to a temporary folder that
# the last cell removes; with it they go there (a new or empty folder) and stay.
#
# The test suite runs it both ways (`tests/docs/test_tutorial.py`). To keep that quick it uses few
# episodes and a small lifting; the parameters below can be raised for the paper's setting
# (28 training and 20 test episodes, 180 alphas: `qube-reproduce qube`).

# %% tags=["parameters"]
N_TRAIN = 8  # training episodes (the paper: 28)
N_TEST = 3  # test episodes, from the paper's test set (the paper: 20)
POLY = 1  # monomial order of the lifting (1: the angles themselves; the paper: 2)
DELAYS = 35  # time delays of the lifting (the paper: 10)
ALPHAS = (1e-5, 1e-4, 1e-3, 1e-1, 1e1)  # regularization coefficients compared by cross-validation
N_TWIN = 3  # episodes run on the twin under soft-theta
TWIN_SECONDS = 12.0  # their length (the rig's: 20 s)

# %% [markdown]
# ## 1. Import the dataset
#
# The dataset is the paper's: 48 episodes of 20 s at 500 Hz under the rig's PD controller,
# one CSV file each, with the controller's gains in `controller.toml`. Its folder is the
# script's first argument, or `$QUBE_DATASET_DIR`; the output folder the second argument, or
# `$QUBE_TUTORIAL_OUT`. The files sorted by name are the paper's split: the first 28 train,
# the rest test. Each is converted into an MCAP episode log, as `qube-import` does.

# %%
import os
import sys
import tempfile
from pathlib import Path

import numpy as np
from qube_koopman.daq import (
    legacy_episode,
    load_legacy_controller,
    log_path,
    write_episode,
)

IN_NOTEBOOK = "ipykernel" in sys.modules  # a Jupyter kernel's argv is its own, not ours
ARGS = [] if IN_NOTEBOOK else sys.argv[1:]
if ARGS[:1] in (["-h"], ["--help"]) or len(ARGS) > 2:
    raise SystemExit(
        "usage: python examples/tutorial.py [DATASET_DIR] [OUT_DIR]\n"
        "  DATASET_DIR: the paper's QUBE-Servo dataset (default: $QUBE_DATASET_DIR)\n"
        "  OUT_DIR: a new or empty folder for the logs and figures (default: $QUBE_TUTORIAL_OUT,\n"
        "           else a temporary folder removed at the end)"
    )
DATASET = ARGS[0] if ARGS else os.environ.get("QUBE_DATASET_DIR")
OUT = ARGS[1] if len(ARGS) > 1 else os.environ.get("QUBE_TUTORIAL_OUT")
csv_files = sorted(Path(DATASET).glob("*.csv")) if DATASET else []
if len(csv_files) < 28 + N_TEST or not (Path(DATASET) / "controller.toml").is_file():
    raise SystemExit(
        f"{DATASET or 'no dataset given'}: not the paper's QUBE-Servo dataset (48 CSV files and "
        "controller.toml). Pass its folder as the first argument or set QUBE_DATASET_DIR; it is "
        "the folder dataset/controller_20230828 of the public repository "
        "decargroup/closed_loop_koopman (MIT licence)."
    )
DATASET = Path(DATASET)
if OUT:
    work = Path(OUT)  # the logs and figures go here, and stay
    if work.exists() and any(work.iterdir()):
        raise SystemExit(f"{work}: not empty; give a new or empty folder for the tutorial's logs and figures")
    work.mkdir(parents=True, exist_ok=True)
    temporary = None
else:
    temporary = tempfile.TemporaryDirectory(prefix="qube_tutorial_")  # removed by the last cell
    work = Path(temporary.name)
rig_controller = load_legacy_controller(DATASET / "controller.toml")
for split, files in (("train", csv_files[:N_TRAIN]), ("test", csv_files[28 : 28 + N_TEST])):
    (work / split).mkdir()
    for csv in files:
        write_episode(log_path(work / split, csv.stem), legacy_episode(csv, rig_controller))
print(f"{len(csv_files)} episodes in the dataset; imported {N_TRAIN} training and {N_TEST} test episodes into {work}")


def show(png: Path) -> None:
    """A saved figure: shown in a notebook, named in a script."""
    if IN_NOTEBOOK:
        from IPython.display import Image, display

        display(Image(filename=str(png)))  # embedded: the notebook keeps it after the folder is gone
    else:
        print(f"figure: {png}")


# %% [markdown]
# `load_logs` reads the logs back as `LoggedTrajectory` objects: the measured angles `x`
# (theta, alpha), plant input `u`, references `r`, feedforward `f` and controller state `xc`
# of each episode, with the controller its log records. The first second (500 samples), where
# the pendulum was raised by hand, is dropped.

# %%
from qube_koopman.daq import find_logs
from qube_koopman.identify import load_logs

train = load_logs(find_logs(work / "train"), skip=500)
test = load_logs(find_logs(work / "test"), skip=500)
controller = train[0].controller  # the rig's PD, discretized as the rig ran it
episode = train[0].trajectory
print(
    f"{episode.n_samples} samples of {episode.dt} s; states {episode.state_names}; "
    f"controller with {controller.n_states} states"
)

# %% [markdown]
# ## 2. Identify
#
# CL EDMD (the paper's method) fits the closed loop's Koopman matrix with the known
# controller, so a plant model comes with it. The lifting: monomials of (theta, alpha) up to
# order `POLY`, then `DELAYS` time delays, then a constant (an affine term). The paper used
# second-order monomials and 10 delays; the linear lifting with 35 delays and a constant is
# the one `qube-design` starts from (docs/design.md): it predicts the rig's test episodes
# better and, below, transfers to another controller far better (the paper's lifting
# scored about 0.6 there when we tried). `identify_and_score` is what `qube-identify` runs: it
# chooses alpha among `ALPHAS` by episode-grouped cross-validation of the closed-loop
# prediction, fits all training episodes, and predicts each test episode in closed loop from
# its initial condition, references and feedforward.

# %%
from qube_koopman.identify import Constant, Delay, FitOptions, IdentifyOptions, Polynomial, identify_and_score

fit = FitOptions("cl-edmd", [Polynomial(POLY), Delay(DELAYS), Constant()], alphas=ALPHAS, cv_splits=2)
result = identify_and_score(train, test, controller, IdentifyOptions(fit))
r2_test = result.report["test"]["r2_mean"]
print(f"alpha {result.report['alpha']:g}: test R^2 {r2_test:.4f} over {result.report['test']['n_episodes']} episodes")
print("spectral radius: closed loop {closed_loop:.5f}, plant {plant:.5f}".format(**result.report["spectral_radius"]))

# %% [markdown]
# The closed loop is asymptotically stable (spectral radius below 1) and the plant is not:
# the pendulum falls without its controller, as it should.
#
# ## 3. Figures
#
# `identification_figures` returns the figures `qube-identify --figures` writes, each as a
# small data object of arrays (the same arrays the report's numbers come from); `draw` turns
# one into a matplotlib figure and `write_figures` saves them as PNG and PDF.

# %%
from qube_koopman.identify import identification_figures, write_figures

specs = identification_figures(result)
for spec, png in zip(specs, write_figures(specs, work / "figures")):
    print(spec.caption)
    show(png)

# %% [markdown]
# ## 4. Another controller, on the twin
#
# Users identify the plant to predict loops it has not run. The repository ships a second
# controller, `soft-theta` (a softer arm: kp_theta 2 instead of 6). The simulator's default
# parameters are the calibrated twin of the rig; its episodes under `soft-theta` are run
# with the rig's excitation and with each episode's pendulum encoder zero a few counts off
# upright, drawn as on the rig (as `qube-run --controller soft-theta` does).

# %%
from qube_koopman.core import ControllerInfo, load_pd_gains, pd_controller
from qube_koopman.daq import (
    McapSink,
    SimBackend,
    excitation_settings,
    plan_episodes,
    read_episode_metadata,
    run_episodes,
    run_seeds,
)
from qube_koopman.sim import PendulumParameters, SensorModel, ZeroOffsetDistribution

soft = load_pd_gains("soft-theta")
soft_info = ControllerInfo(pd_controller(soft), "backward-euler", soft.as_dict(), "pd")
seeds, backend_seed = run_seeds(2, N_TWIN)
(work / "twin").mkdir()
run = run_episodes(
    SimBackend(PendulumParameters(), seed=backend_seed, zero_offsets=ZeroOffsetDistribution()),
    plan_episodes(soft_info, seeds, excitation_settings(TWIN_SECONDS), source="tutorial"),
    [McapSink(work / "twin")],
)
twin = load_logs(find_logs(work / "twin"), skip=500)
injected = [read_episode_metadata(log.path).extra["backend"]["sensor"]["alpha_offset"] for log in twin]
print(f"{len(twin)} twin episodes under soft-theta; their encoder zeros (rad): {np.round(injected, 5)}")

# %% [markdown]
# The identified plant, wrapped with `soft-theta`, predicts these episodes from their start.
# Under a PD loop the arm settles `kp_alpha / kp_theta` times the pendulum's encoder offset
# away (17.5 times under `soft-theta`), so each episode's offset is estimated from its first
# second (the window) and the prediction is scored on the samples after it, with and without
# the estimate (`qube-identify --offsets alpha` does the same).

# %%
from qube_koopman.identify import (
    close_loop,
    estimate_offsets_many,
    predict_with_offsets_many,
    scores_after_window,
)

window = 500  # samples: 1 s
soft_loop = close_loop(result.plant, twin[0].controller, [0, 1])
trajectories = [log.trajectory for log in twin]
estimates = estimate_offsets_many(soft_loop, trajectories, ["alpha"], window)
r2_soft_offsets = float(np.mean(scores_after_window(soft_loop, trajectories, window, offsets=True)))
r2_soft_plain = float(np.mean(scores_after_window(soft_loop, trajectories, window, offsets=False)))
count = SensorModel().resolution  # rad per encoder count (2048 a turn)
for log, est, zero in zip(twin, estimates, injected):
    apart = (est.as_mapping()[1] - zero) / count
    status = "" if est.status == "ok" else f"; the estimate: {est.status}"
    print(
        f"{log.path.name}: alpha offset estimated {est.as_mapping()[1]:+.5f} rad, injected {zero:+.5f} rad "
        f"({apart:+.2f} encoder counts apart{status})"
    )
change = "raise" if r2_soft_offsets > r2_soft_plain else "lower"
print(
    f"soft-theta episodes: mean R^2 {r2_soft_offsets:.4f} with the offsets estimated, {r2_soft_plain:.4f} without "
    f"(the estimates {change} it by {abs(r2_soft_offsets - r2_soft_plain):.4f})"
)

# %% [markdown]
# The estimates are offsets from the model's own zero, which is that of the training
# episodes: in the paper's dataset the pendulum's mean angle over an episode (after its first
# second) is +0.0025 rad, with a spread of about 0.001 rad between episodes, so the rig's
# encoder zero was itself about that far off upright, and the estimates fall about that much
# below the twin's injected offsets. The twin is not the
# rig either (its arm moves less under soft gains), which caps these scores below the test
# episodes' own.
#
# An estimate helps only when the offset it corrects is larger than its own error. The twin
# draws its zeros about the rig's, so they lie within a fraction of a count of the model's
# zero, while an estimate from one second of a loop's data is off by up to about a count: the
# correction can then lower the score rather than raise it, as the line above says for this
# run. Offsets of several counts (another rig, or a zero reset elsewhere) are where it pays.
#
# The same figure object as above shows one of these predictions: a `SeriesPlot` of the
# measured and predicted angles, drawn with `draw`.

# %%
from qube_koopman.identify import Curve, SeriesPlot, draw

predicted = predict_with_offsets_many(soft_loop, trajectories[:1], estimates[:1])[0]
x = trajectories[0].x
t = np.arange(len(x)) * trajectories[0].dt
plot = SeriesPlot(
    f"{twin[0].path.stem} under soft-theta (offset estimated)",
    t,
    "time (s)",
    ("theta (rad)", "alpha (rad)"),
    tuple(
        Curve(f"{s} {kind}", y[:, j], panel=j)
        for j, s in enumerate(("theta", "alpha"))
        for kind, y in (("measured", x), ("predicted", predicted))
    ),
    marks={"end of the estimation window": t[window]},
)
draw(plot).savefig(work / "soft_theta.png", dpi=100)
show(work / "soft_theta.png")

# %% [markdown]
# ## Summary
#
# The scores of this run (the test suite checks them). Without an output folder of your
# choice, the temporary one with the logs and figures is removed here.

# %%
summary = {
    "r2_test": round(r2_test, 4),
    "r2_soft_offsets": round(r2_soft_offsets, 4),
    "r2_soft_plain": round(r2_soft_plain, 4),
    "n_twin": len(twin),
    "offset_errors_rad": [round(est.as_mapping()[1] - zero, 5) for est, zero in zip(estimates, injected)],
}
print(summary)
if temporary is not None:
    temporary.cleanup()
    print(f"removed {work} (give an output folder to keep the logs and figures)")
