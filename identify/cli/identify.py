"""``qube-identify``: identify Koopman models from episode logs, score them, report."""

from __future__ import annotations

import argparse
import contextlib
import io
import logging
import math
import sys
import warnings
from pathlib import Path

from qube_koopman.core.cli import (
    OneLineParser,
    add_force_option,
    add_renamed_option,
    add_standard_options,
    finite_number,
    n_jobs,
    number_in,
    path,
    positive_number,
    seed,
    whole_number,
)
from qube_koopman.core.command import (
    CliError,
    check_output_folder,
    check_rerun_target,
    output_dir,
    progress,
    run_command,
    write_json,
)
from qube_koopman.core.qube import SKIP_SAMPLES
from qube_koopman.identify.cli.cluster import add_cluster_options, check_cluster_options, cluster_report
from qube_koopman.identify.model_selection.distributed import NoWorkersError
from qube_koopman.identify.cli.common import expand_logs
from qube_koopman.identify.command_warnings import ONE_LINE_WARNINGS
from qube_koopman.identify.report.figure_options import add_figure_options, check_figure_options, write_report_figures

PROG = "qube-identify"

DESCRIPTION = """\
Identify a Koopman model of the closed loop and of the plant from MCAP episode
logs (qube-run or qube-import), score it on test episodes and write a report.

Examples:
  qube-identify logs/*.mcap --split paper --out model            # the paper's split, CL EDMD
  qube-identify --train a/*.mcap --test b/*.mcap --alpha-sweep 1e-3 1e3 30
  qube-identify logs/ --split paper --method edmd --score plant --alpha 1
  qube-identify logs/ --split paper --search --n-jobs 2            # choose the lifting by CV

With --search the lifting, alpha and offset protocol are chosen on the
training episodes only, in stages (delays; monomial order x constant x sin/cos;
friction on/off; RBF centres; offsets on the best few; with training logs of several
controllers every stage with offsets). Each candidate is scored twice: by
episode-grouped cross-validation (closed-loop prediction under the training
controller, from the end of the --estimate-window on; with training logs of
several controllers as many folds per controller, one holding it out whole) and, with --transfer twin
(the default), by transfer: its plant, wrapped with three probe PD controllers
unlike the training one, predicts twin episodes (the training excitations
replayed on the calibrated twin under those controllers). Candidates rank by
the lower of the two, since users identify the plant to predict loops it has
not run. The winner is fitted on all training episodes, written to model.json
and scored on the test episodes from the same sample as the candidates;
report.md lists every candidate with both scores and the flags that refit the
winner by hand. --search-space FILE.toml narrows or widens the space (keys:
delays, poly, const, trig, friction, rbf, alphas, offsets: lists; n_finalists,
screen_against_lead, offsets_first: single values).

Training logs may come from several controllers (the plant is common, each
loop differs by its known controller): each episode is fitted with the
controller its log records, one plant for all; model.json's closed loop is
that of the controller with the most training episodes. Cross-validation
(--alpha-sweep, --search) then holds out one controller per fold.

Test episodes are predicted in closed loop under the controller recorded in
each test log (a plant model is wrapped with it), or from their plant input
with --score plant. Every predicted sample gets an interval at --interval
(default 0.95; 0: none): bootstrap refits of the model on the training
episodes, the offsets' standard errors, and a scale of the model's error
calibrated on training episodes held out in turn (never the test episodes).
Outputs in --out: model.json (see identify/MODEL_FORMAT.md), report.json,
report.md, predictions/<log>.npz (t, measured, predicted, lower, upper, level
over the scored samples) with --interval, and with --rerun-save FILE.rrd a
rerun recording; with --figures, PNG and PDF figures in figures/, embedded in
report.md.
"""

METHODS = ("cl-edmd", "cl-edmd-known-rows", "edmd", "cl-edmd-lstsq", "arx", "cl-arx")

# Bounds of the counts that size the fit: beyond them numpy fails (10**30 centres: "Maximum allowed
# dimension exceeded") or the monomials never end. Ten times the search space's largest.
MAX_POLY = 10
MAX_RBF_CENTERS = 1000
MAX_ALPHAS = 1000
#: The lifting's monomial order and delays when --poly and --delays are not given.
DEFAULT_POLY, DEFAULT_DELAYS = 2, 10
#: What every run writes in --out (figures and the search's files beside them are replaced with these).
OUTPUT_FILES = ("model.json", "report.json", "report.md")
#: The folder of the test episodes' predictions and intervals in --out (with --interval).
PREDICTIONS = "predictions"
#: --interval's level when it is not given (a Koopman method).
DEFAULT_LEVEL = 0.95


def _add_search_options(p: argparse.ArgumentParser) -> None:
    search = p.add_argument_group("lifting search")
    search.add_argument(
        "--search", action="store_true", help="choose lifting, alpha and offsets by cross-validation (see above)"
    )
    search.add_argument(
        "--search-space",
        type=path,
        metavar="FILE.toml",
        help="the values to try (default: delays 0-40 by 5, poly 1-3, const, sin/cos and friction "
        "on/off, 0/25/50/100 RBF centres, alpha 1e-6 to 1e2 at two per decade, offsets on/off)",
    )
    search.add_argument(
        "--transfer",
        choices=["twin", "none"],
        default="twin",
        help="twin (default): rank candidates by the lower of their cross-validated R^2 and their "
        "transfer R^2, the plant predicting twin episodes under three probe PD controllers "
        "unlike the training one (the training excitations replayed on the calibrated twin); "
        "none: by cross-validated R^2 alone (sees only the training controller)",
    )
    search.add_argument(
        "--no-screen",
        dest="screen",
        action="store_false",
        help="evaluate every candidate in full (by default the delays, form and RBF stages screen "
        "theirs on one fold and one probe alpha and evaluate the 3 best in full; report.md "
        "lists the others with their screen scores)",
    )
    search.add_argument(
        "--no-probe-cache",
        dest="probe_cache",
        action="store_false",
        help="simulate the twin probes even when the same ones are in the cache (by default they "
        "are kept in $QUBE_KOOPMAN_PROBE_CACHE, else ~/.cache/qube-koopman/probes, and read "
        "back when the training excitations, the twin and the simulator are the same)",
    )
    add_cluster_options(p)


def _horizons(text: str) -> tuple[float, ...]:
    """``--horizon``: seconds, comma-separated, each 0 or more."""
    try:
        values = tuple(float(part) for part in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"horizons are seconds separated by commas (0.1,1), got {text!r}") from None
    if not values or any(not (v >= 0 and v < 1e4) for v in values):
        raise argparse.ArgumentTypeError(f"horizons are seconds from 0 to 10000, got {text!r}")
    return values


def _add_data_options(p: argparse.ArgumentParser) -> None:
    """The logs and how they are read."""
    data = p.add_argument_group("data")
    data.add_argument(
        "logs", nargs="*", type=path, metavar="LOGS", help="episode logs (.mcap files or folders), with --split"
    )
    data.add_argument("--split", choices=["paper"], help="paper: names sorted, first 28 train, the rest test")
    data.add_argument("--train", nargs="+", type=path, metavar="LOG", help="training logs (files or folders)")
    data.add_argument("--test", nargs="+", type=path, metavar="LOG", help="test logs (files or folders)")
    data.add_argument(
        "--skip",
        type=whole_number(0),
        default=SKIP_SAMPLES,
        metavar="N",
        help="samples dropped at the start of each episode (default %(default)s: the rig's hand-raising second)",
    )
    data.add_argument("--strict", action="store_true", help="refuse incomplete logs instead of skipping them")


def _add_lifting_options(p: argparse.ArgumentParser) -> None:
    """The lifting of the plant states."""
    lift = p.add_argument_group("lifting (applied in this order: monomials, delays, RBFs)")
    lift.add_argument(
        "--poly", type=whole_number(1), metavar="ORDER", help=f"monomial order (1: none; default 2; at most {MAX_POLY})"
    )
    lift.add_argument(
        "--trig",
        action="store_true",
        help="append sin and cos of theta and alpha (after the monomials, before the delays)",
    )
    lift.add_argument("--delays", type=whole_number(0), metavar="N", help="time delays (default 10)")
    lift.add_argument(
        "--rbf", choices=["none", "thin-plate", "gaussian"], default="none", help="radial basis functions"
    )
    lift.add_argument(
        "--rbf-centers",
        type=whole_number(1, MAX_RBF_CENTERS),
        default=50,
        metavar="N",
        help=f"RBF centres, Latin hypercube (default %(default)s, at most {MAX_RBF_CENTERS})",
    )
    lift.add_argument(
        "--rbf-shape", type=float, default=1.0, metavar="A", help="RBF shape parameter (default %(default)s)"
    )
    lift.add_argument(
        "--rbf-offset", type=float, default=1e-3, metavar="D", help="thin-plate offset (default %(default)s)"
    )
    lift.add_argument(
        "--rbf-seed", type=seed, default=0, metavar="K", help="seed of the RBF centres (default %(default)s)"
    )
    lift.add_argument(
        "--friction",
        action="store_true",
        help="append the arm's Coulomb friction shape, tanh((theta_k - theta_k-10) / 0.002 rad), "
        "after the RBFs (needs --delays 10 or more)",
    )
    lift.add_argument(
        "--const",
        action="store_true",
        help="append a constant lifting function (an affine term: the model's equilibrium is "
        "not pinned at the measured zero)",
    )


def _add_regularization_options(fit: argparse._ArgumentGroup) -> None:
    """Alpha, or its cross-validated choice."""
    reg = fit.add_mutually_exclusive_group()
    reg.add_argument("--alpha", type=float, metavar="A", help="Tikhonov coefficient (default 1e-3)")
    reg.add_argument(
        "--alpha-sweep",
        nargs=3,
        metavar=("MIN", "MAX", "N"),
        help="choose alpha among N log-spaced values by cross-validation: episode-grouped, or "
        "per controller when the training logs ran two or more controllers (--cv-splits folds each)",
    )
    fit.add_argument(
        "--cv-splits",
        type=whole_number(1),
        default=3,
        metavar="K",
        help="random splits holding out 20%% of the training episodes (default %(default)s; with "
        "training logs of several controllers, K folds per controller: the first holds it out whole when the "
        "others are at least half of the episodes)",
    )
    fit.add_argument("--cv-seed", type=seed, default=1234, metavar="K", help="seed of the splits (default %(default)s)")


def _add_fit_options(p: argparse.ArgumentParser) -> None:
    """The method and how it is fitted."""
    fit = p.add_argument_group("identification")
    fit.add_argument(
        "--n-jobs",
        type=n_jobs,
        default=-1,
        metavar="N",
        help="cores to use: the search's worker processes, and the threads that factor a fit's "
        "training episodes side by side (default %(default)s: every core; the model is the same "
        "whatever N; unused with --scheduler)",
    )
    fit.add_argument(
        "--method",
        choices=METHODS,
        default="cl-edmd",
        help="cl-edmd: the paper's CL EDMD (controller rows of the closed-loop matrix fitted); "
        "cl-edmd-known-rows: the same plant, controller rows fixed to the known controller; "
        "default: %(default)s",
    )
    _add_regularization_options(fit)
    fit.add_argument(
        "--score",
        choices=["cl", "plant"],
        default="cl",
        help="closed-loop or plant predictions, for selection and test scores (default %(default)s)",
    )
    fit.add_argument(
        "--arx-lags",
        type=whole_number(1),
        default=10,
        metavar="N",
        help="ARX output and input lags (default %(default)s)",
    )
    fit.add_argument(
        "--max-radius",
        type=float,
        metavar="R",
        help="constrain the closed loop's eigenvalues to |lambda - C| <= R (C: --pole-center, "
        "default 0: the spectral radius), the plant left free; CL EDMD with the controller "
        "rows known, solved as an LMI with cvxpy + Clarabel",
    )
    fit.add_argument(
        "--pole-center",
        type=float,
        default=0.0,
        metavar="C",
        help="centre of the eigenvalue disc of --max-radius (default %(default)s)",
    )


def _add_ahead_options(pred: argparse._ArgumentGroup) -> None:
    """K-step predictions and their disturbance model."""
    pred.add_argument(
        "--horizon",
        type=_horizons,
        metavar="S[,S...]",
        help="also predict every test episode these seconds ahead from the measurements up to each start "
        "(for example 0.1,1), with a disturbance model fitted on the training episodes and its Kalman "
        "filter (stored in model.json); report.json's 'ahead' and report.md give R^2 and RMS error per "
        "horizon and channel beside the free run, and predictions/<log>.npz gains ahead_<S>. Default: "
        "free run only",
    )
    pred.add_argument(
        "--disturbance",
        choices=["auto", "none", "input", "theta", "alpha"],
        default="auto",
        help="with --horizon, where the disturbance enters: a load at the plant input (input), a rate on an "
        "angle's equation (theta, alpha), none, or auto: the one that predicts the training episodes best at "
        "the horizons (default %(default)s)",
    )
    pred.add_argument(
        "--disturbance-q",
        type=positive_number,
        metavar="Q",
        help="with --horizon, the disturbance's variance per sample, set by hand (default: chosen on the "
        "training episodes; report.json's 'disturbance' says which)",
    )
    pred.add_argument(
        "--disturbance-pole",
        type=number_in(0.0, 1.0, "--disturbance-pole"),
        metavar="P",
        help="with --horizon, the disturbance's pole, set by hand: 1 a random walk (integrated white noise), "
        "below 1 a first-order process (0.995: a time constant of 0.4 s at 500 Hz) (default: for each entry, "
        "the one of 1, 0.999, 0.998, 0.995, 0.99, 0.98, 0.95 that predicts the training episodes best; "
        "report.json's 'disturbance' gives each one's cost)",
    )


def _add_interval_options(pred: argparse._ArgumentGroup) -> None:
    """The test predictions' intervals."""
    pred.add_argument(
        "--interval",
        type=float,
        metavar="LEVEL",
        help=f"give every predicted sample an interval at this level (default {DEFAULT_LEVEL} with a "
        "Koopman method; 0: none): bootstrap refits, the offsets' standard errors and a model error "
        f"calibrated on held-out training episodes; written to OUT/{PREDICTIONS}/<log>.npz, with "
        "each episode's coverage in the reports",
    )
    pred.add_argument(
        "--interval-members",
        type=whole_number(2),
        default=20,
        metavar="B",
        help="bootstrap refits of the intervals (default %(default)s)",
    )
    pred.add_argument(
        "--interval-method",
        choices=["auto", "bootstrap", "disturbance"],
        default="auto",
        help="the intervals' source of uncertainty: bootstrap, the spread of bootstrap refits with a "
        "model error calibrated on held-out training episodes (model.json keeps the refits for qube-design); "
        "disturbance, the disturbance model's Kalman "
        "filter variance calibrated the same way, without bootstrap refits (the disturbance model --horizon fits; "
        "without --horizon, the filter of the measured history alone), and with --horizon bands for the K-step "
        "predictions too (ahead_<S>_lower/upper); auto (default): disturbance with --horizon, bootstrap without; "
        "report.json's intervals say which and why",
    )
    pred.add_argument(
        "--interval-seed",
        type=seed,
        default=0,
        metavar="K",
        help="seed of the intervals' resampling and folds (default %(default)s)",
    )
    pred.add_argument(
        "--interval-other-loops",
        choices=["twin", "none"],
        default="twin",
        help="how the interval of an episode under a controller the training did not run is "
        "calibrated: twin (default), on the twin's probe episodes (run on six variants of the "
        "twin, as the rig's sessions differed in command delay and cable stiffness), per channel the wider of "
        "those under its own controller (PD gains known) and under the default probe "
        "controllers (cached as --no-probe-cache says); none, as the training loop's held-out "
        "episodes (flagged in the report)",
    )


def _add_loop_options(pred: argparse._ArgumentGroup) -> None:
    """The test episodes' loops: a what-if controller, their command delays."""
    pred.add_argument(
        "--controller",
        type=path,
        metavar="FILE.toml",
        help="what-if: predict every test episode under this controller instead of its "
        "log's own: PD gains (kp_theta, kd_theta, kp_alpha, kd_alpha, tau; backward Euler as "
        "on the rig) or a state-space file at the logs' sample period "
        "(core/CONTROLLER_FORMAT.md); a file, or a shipped name: rig, soft-theta; only "
        "episodes recorded under it are scored",
    )
    pred.add_argument(
        "--command-delay",
        type=_command_delay,
        default=None,
        metavar="MS|estimate",
        help="predict every test episode's loop with its command reaching the motor this many "
        "milliseconds later than in the training logs (a host with more latency; the feedforward "
        "held as late): a what-if of the loop's timing, alone or with --controller. estimate: each "
        "test loop's own extra delay, from how the identified plant's 40 ms predictions line up with "
        "the logged voltage on up to four other test logs of its recording session (never the log's "
        "own samples), rounded to a quarter sample (0.5 ms at 500 Hz); listed in the reports. Default: "
        "estimate with the window protocol (--search, --offsets) unless --session-delays or --controller "
        "is given, else 0",
    )
    pred.add_argument(
        "--session-delays",
        type=path,
        default=None,
        metavar="PLANT.toml",
        help="a plant file of qube-calibrate --setups cables-and-delay (a command delay per recording "
        "session): every training and test log's loop is its session's, its command reaching the motor "
        "its session's delay after the controller computed it, counted above the least delay among "
        "the logs' sessions; a plant fitted to logs of several sessions then sees each loop as it ran",
    )


def _add_prediction_options(p: argparse.ArgumentParser) -> None:
    """How the test episodes are predicted and scored."""
    pred = p.add_argument_group("prediction of the test episodes")
    pred.add_argument(
        "--offsets",
        nargs="+",
        choices=["theta", "alpha"],
        metavar="CHANNEL",
        help="estimate a constant sensor offset of these channels on each test episode from its "
        "first --estimate-window seconds, then predict with it (for example: alpha, whose "
        "encoder zero is a few counts off upright); scores then cover the samples after the "
        "window, beside the plain prediction's on the same samples. Default: none (the "
        "paper's protocol)",
    )
    _add_ahead_options(pred)
    pred.add_argument(
        "--estimate-window",
        type=float,
        default=1.0,
        metavar="S",
        help="offset estimation window in seconds (default %(default)s)",
    )
    pred.add_argument(
        "--offset-bound",
        type=float,
        default=0.05,
        metavar="RAD",
        help="estimates beyond this are flagged in the report and not used (default %(default)s)",
    )
    pred.add_argument(
        "--protocol",
        choices=["paper", "window"],
        help="window: score the test episodes from the end of --estimate-window, as --search scores "
        "its candidates (the default with --search or --offsets); paper: from the second "
        "sample, the paper's protocol (the default otherwise; not with --offsets)",
    )
    _add_interval_options(pred)
    _add_loop_options(pred)


def _add_output_options(p: argparse.ArgumentParser) -> None:
    """What is written, and where."""
    out = p.add_argument_group("output")
    out.add_argument(
        "--out", type=path, default="identified", metavar="DIR", help="output folder (default %(default)s)"
    )
    out.add_argument(
        "--rerun-save", dest="rerun", type=path, metavar="FILE.rrd", help="also write a rerun recording of the results"
    )
    add_renamed_option(out, "--rerun", "--rerun-save FILE.rrd", "a file; qube-run --rerun streams to a viewer")
    add_force_option(out)


def _parser() -> argparse.ArgumentParser:
    p = OneLineParser(prog=PROG, description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_standard_options(p)
    _add_data_options(p)
    _add_lifting_options(p)
    _add_fit_options(p)
    _add_prediction_options(p)
    _add_search_options(p)
    _add_output_options(p)
    add_figure_options(p)
    return p


def _lifting(args) -> list:
    """The lifting the options give: one builder with the search's (``LiftingSpec.steps``)."""
    from qube_koopman.identify.model_selection.lifting_space import LiftingSpec

    spec = LiftingSpec(
        delays=args.delays,
        poly=args.poly,
        trig=args.trig,
        friction=args.friction,
        const=args.const,
        rbf=0 if args.rbf == "none" else args.rbf_centers,
    )
    return spec.steps(args.rbf_seed, args.rbf, args.rbf_shape, args.rbf_offset)


#: What a fit from episodes added one at a time takes of qube-identify's options (qube-run --identify).
LIVE_FIT_OPTIONS = (
    "--poly, --trig, --delays, --rbf, --rbf-centers, --rbf-shape, --rbf-offset, --rbf-seed, --friction, "
    "--const, --method (cl-edmd, cl-edmd-known-rows, edmd), --alpha, --skip"
)


def live_fit_options(text: str, option: str = "--identify") -> argparse.Namespace:
    """qube-identify's lifting and fit options from one string (``"--poly 1 --delays 35 --const"``), checked.

    The result has ``lifting`` (the lifting functions), ``method``, ``alpha`` and ``skip``. Options beyond
    :data:`LIVE_FIT_OPTIONS` (the data, the search, cross-validation, offsets, intervals, outputs) are refused
    with a one-line :class:`CliError` naming ``option``.
    """
    import shlex

    try:
        tokens = shlex.split(text)
    except ValueError as exc:
        raise CliError(f"{option} {text!r}: {exc}") from None
    parser = _parser()
    defaults = vars(parser.parse_args(["--train", ".", "--test", "."]))
    said = io.StringIO()
    try:
        with contextlib.redirect_stderr(said), contextlib.redirect_stdout(said):
            args = parser.parse_args([*tokens, "--train", ".", "--test", "."])
    except SystemExit:
        errors = [
            line.split(": error: ", 1)[1].split(" (see ")[0]
            for line in said.getvalue().splitlines()
            if ": error: " in line
        ]
        problem = errors[0] if errors else "qube-identify --help describes them"
        raise CliError(f"{option} {text!r}: {problem} (it takes {LIVE_FIT_OPTIONS})") from None
    allowed = {"poly", "trig", "delays", "rbf", "rbf_centers", "rbf_shape", "rbf_offset", "rbf_seed", "friction"}
    allowed |= {"const", "method", "alpha", "skip"}
    other = sorted(k for k, v in vars(args).items() if k not in allowed and v != defaults[k])
    if other:
        raise CliError(
            f"{option}: --{other[0].replace('_', '-')} is not for a fit from episodes added one at a time "
            f"(it takes {LIVE_FIT_OPTIONS})"
        )
    from qube_koopman.identify.live import LIVE_METHODS

    if args.method not in LIVE_METHODS:
        raise CliError(f"{option}: --method {args.method}: an incremental fit takes {', '.join(LIVE_METHODS)}")
    args.poly = DEFAULT_POLY if args.poly is None else args.poly
    args.delays = DEFAULT_DELAYS if args.delays is None else args.delays
    if args.poly > MAX_POLY:
        raise CliError(f"{option}: --poly must be at most {MAX_POLY}, got {args.poly}")
    if args.alpha is None:
        args.alpha = 1e-3
    if not 0 <= args.alpha < math.inf:
        raise CliError(f"{option}: --alpha must be a finite number >= 0, got {args.alpha}")
    if args.friction:
        from qube_koopman.identify.lifting import CoulombFriction

        if args.delays < CoulombFriction().lag:
            raise CliError(f"{option}: --friction needs --delays {CoulombFriction().lag} or more")
    try:
        args.lifting = _lifting(args)
    except ValueError as exc:
        raise CliError(f"{option}: {exc}") from None
    return args


def _check_cross_validation(args, train) -> None:
    """Cross-validation (--search, --alpha-sweep) holds out whole training episodes: two at least."""
    option = "--search" if args.search else "--alpha-sweep" if args.alpha_sweep else None
    if option and len(train) < 2:
        raise CliError(
            f"{option} cross-validates by holding out whole training episodes: it needs at least 2 "
            f"training logs, got {len(train)} ({train[0].path})"
        )


def _check_delays(args, logs) -> None:
    """A lifting of N delays consumes N samples of each episode and predicts from the next two."""
    shortest = min(logs, key=lambda log: log.n_samples)
    if not args.search and args.delays + 2 > shortest.n_samples:
        raise CliError(
            f"--delays {args.delays} needs episodes of at least {args.delays + 2} samples; "
            f"{shortest.path} has {shortest.n_samples} (after --skip {args.skip})"
        )


def _check_search_args(args) -> None:
    chosen = [
        flag
        for flag, given in (
            ("--poly", args.poly is not None),
            ("--delays", args.delays is not None),
            ("--trig", args.trig),
            ("--friction", args.friction),
            ("--rbf", args.rbf != "none"),
            ("--const", args.const),
            ("--alpha", args.alpha is not None),
            ("--alpha-sweep", args.alpha_sweep),
            ("--offsets", args.offsets),
            ("--max-radius", args.max_radius is not None),
        )
        if given
    ]
    if chosen:
        raise CliError(f"--search chooses the lifting, alpha and offsets itself: leave out {', '.join(chosen)}")
    if args.method != "cl-edmd" or args.score != "cl":
        raise CliError("--search selects CL EDMD models scored in closed loop (--method cl-edmd, --score cl)")


def _command_delay(text: str) -> float | str:
    """``--command-delay``'s type: milliseconds, or ``estimate``."""
    if text == "estimate":
        return text
    try:
        return finite_number(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"{text!r} is neither a number of milliseconds nor 'estimate'") from None


def _check_args(args) -> None:
    """Refuse what cannot run, before any work: the options together, then each option's value; then the
    defaults that depend on other options."""
    _check_combinations(args)
    check_cluster_options(args, PROG)  # the address, and TLS or the loopback
    _check_values(args)
    _resolve_defaults(args)
    _check_interval(args)
    check_rerun_target(args.rerun, "--rerun-save", args.force)  # before any work, not after the fit
    check_output_folder(args.out, OUTPUT_FILES + ((PREDICTIONS,) if args.interval else ()), force=args.force)


def _check_combinations(args) -> None:
    """The options that do not go together, as given (before their defaults)."""
    arx = args.method in ("arx", "cl-arx")
    if args.search:
        _check_search_args(args)
    elif args.search_space or args.transfer != "twin":
        raise CliError("--search-space and --transfer belong to --search")
    if args.worker_logs and not args.scheduler:
        raise CliError("--worker-logs says how dask workers read the logs: it needs --scheduler")
    if args.scheduler and arx:
        raise CliError(
            f"--scheduler computes the Koopman methods' per-episode statistics; --method {args.method} "
            "fits here (leave out --scheduler)"
        )
    if args.command_delay and (args.score != "cl" or arx):
        raise CliError("--command-delay changes the predicted loop: it needs --score cl and a Koopman method")
    _check_session_delays(args)
    if args.protocol == "paper" and args.offsets:
        raise CliError("--offsets scores from the end of --estimate-window: it cannot use --protocol paper")
    if args.split and (args.train or args.test):
        raise CliError("give either LOGS with --split, or --train and --test")
    if not args.split and not (args.train and args.test):
        raise CliError("no data: give LOGS --split paper, or --train LOGS... --test LOGS...")
    if args.split and not args.logs:
        raise CliError("--split paper needs LOGS")
    if args.friction:
        from qube_koopman.identify.lifting import CoulombFriction

        lag, delays = CoulombFriction().lag, DEFAULT_DELAYS if args.delays is None else args.delays
        if delays < lag:
            raise CliError(
                f"--friction measures the arm's motion over {lag} samples: it needs --delays {lag} or "
                f"more, got --delays {delays}"
            )
    if arx and args.alpha_sweep:
        raise CliError("--alpha-sweep is for the Koopman methods (edmd, cl-edmd, cl-edmd-lstsq)")
    if args.method == "arx" and args.score == "cl":
        raise CliError("--method arx models the plant only; use --score plant, or --method cl-arx")
    if (args.offsets or args.controller) and arx:
        raise CliError("--offsets and --controller need a Koopman method (edmd, cl-edmd, cl-edmd-lstsq)")
    if args.controller and args.score != "cl":
        raise CliError("--controller predicts the closed loop: use --score cl")
    if args.max_radius is not None and (args.method != "cl-edmd" or args.alpha_sweep):
        raise CliError("--max-radius constrains a single CL EDMD fit (--method cl-edmd, no --alpha-sweep)")


def _check_session_delays(args) -> None:
    """--session-delays makes each log's loop its session's: refused with what would undo or ignore that."""
    if not args.session_delays:
        return
    if args.command_delay == "estimate":
        raise CliError("--session-delays gives every test log its session's delay: leave out --command-delay estimate")
    if args.method in ("arx", "cl-arx"):
        raise CliError("--session-delays changes the logs' loops: it needs a Koopman method")
    if args.controller:
        raise CliError(
            "--session-delays predicts each test log under its own session's loop; a --controller what-if "
            "would score only logs of its controller in the least delayed session: give the what-if's "
            "latency with --command-delay instead"
        )
    if args.scheduler:
        raise CliError(
            "--session-delays needs the logs' loops built here: the cluster's workers read the logs as recorded"
        )


def _check_values(args) -> None:
    """Each option's own value (``--alpha-sweep``'s made numbers)."""
    if isinstance(args.command_delay, float) and args.command_delay < 0:
        raise CliError(f"--command-delay must be 0 or more milliseconds, got {args.command_delay:g}")
    if args.poly is not None and args.poly > MAX_POLY:  # 10**30: the monomials were never all listed
        raise CliError(f"--poly must be at most {MAX_POLY}, got {args.poly}")
    if args.alpha is not None and not 0 <= args.alpha < math.inf:
        raise CliError(f"--alpha must be a finite number >= 0, got {args.alpha}")
    if args.alpha_sweep:
        args.alpha_sweep = _alpha_sweep(args.alpha_sweep)
    if args.max_radius is not None and not 0 < args.max_radius < math.inf:
        raise CliError(f"--max-radius must be a finite positive number, got {args.max_radius}")
    if args.max_radius is not None and not math.isfinite(args.pole_center):
        raise CliError(f"--pole-center must be a finite number, got {args.pole_center}")
    for option, value in (
        ("--estimate-window", args.estimate_window),
        ("--offset-bound", args.offset_bound),
        ("--rbf-shape", args.rbf_shape),
        ("--rbf-offset", args.rbf_offset),
    ):
        if not value > 0:
            raise CliError(f"{option} must be positive, got {value}")
    from qube_koopman.core.qube import MAX_DURATION

    if not args.estimate_window <= MAX_DURATION:  # inf, 1e308: no whole number of samples (a traceback)
        raise CliError(
            f"--estimate-window must be at most {MAX_DURATION:g} s (the longest episode), got {args.estimate_window}"
        )


def _alpha_sweep(given: list[str]) -> tuple[float, float, int]:
    """--alpha-sweep MIN MAX N as numbers, checked."""
    try:
        lo, hi, n = float(given[0]), float(given[1]), int(given[2])
    except ValueError:
        raise CliError(f"--alpha-sweep takes MIN MAX N, for example 1e-3 1e3 30, got {' '.join(given)}") from None
    if not (0 < lo < hi) or n < 2:
        raise CliError(f"--alpha-sweep needs 0 < MIN < MAX and N >= 2, got {' '.join(given)}")
    if hi == math.inf or n > MAX_ALPHAS:
        raise CliError(f"--alpha-sweep needs a finite MAX and N <= {MAX_ALPHAS}, got {' '.join(given)}")
    return lo, hi, n


def _resolve_defaults(args) -> None:
    """The defaults that depend on other options: the protocol, the command delay, the lifting's, the method."""
    if args.protocol is None:
        args.protocol = "window" if args.search or args.offsets else "paper"
    if args.command_delay is None:  # the window protocol estimates the test loops' nuisances: offsets and latency
        estimate = args.protocol == "window" and args.score == "cl" and args.method not in ("arx", "cl-arx")
        args.command_delay = "estimate" if estimate and not (args.session_delays or args.controller) else 0.0
    args.poly = DEFAULT_POLY if args.poly is None else args.poly
    args.delays = DEFAULT_DELAYS if args.delays is None else args.delays
    if args.max_radius is not None:
        args.method = "cl-edmd-stable"


def _interval_method(args) -> tuple[str, str]:
    """--interval-method resolved (auto: the filter's band with --horizon, the bootstrap's without) and why."""
    if args.interval_method != "auto":
        return args.interval_method, f"asked for (--interval-method {args.interval_method})"
    if args.horizon is not None:
        return "disturbance", (
            "the default with --horizon: on the paper's data the disturbance filter's band covers the test episodes "
            "as the bootstrap band does (pooled 0.953 / 0.956 against 0.955 / 0.960 with the default lifting) "
            "for a fifth to a third of its added time, and bands the K-step predictions too"
        )
    return "bootstrap", (
        "the default without --horizon: the bootstrap refits also give model.json the plants qube-design "
        "takes (--interval-method disturbance: the filter's band, cheaper, without them)"
    )


def _check_interval(args) -> None:
    """--interval: 0 or a level in (0, 1); on by default for the Koopman methods, refused for ARX."""
    args.interval_asked = args.interval is not None
    koopman = args.method not in ("arx", "cl-arx")
    if args.interval is None:
        args.interval = DEFAULT_LEVEL if koopman else 0.0
    if not (args.interval == 0 or 0 < args.interval < 1):
        raise CliError(f"--interval must be a level between 0 and 1 (0: no intervals), got {args.interval}")
    if args.interval and not koopman:
        raise CliError(f"--interval bootstraps a Koopman method's fit; --method {args.method} has none (--interval 0)")


def _check_interval_data(args, train) -> None:
    """The intervals are calibrated on held-out training episodes: two at least (else off unless asked for)."""
    if not args.interval or len(train) >= 2:
        return
    if args.interval_asked:
        raise CliError(
            f"--interval calibrates on held-out training episodes: it needs at least 2 training logs, got "
            f"{len(train)} ({train[0].path})"
        )
    logging.getLogger(__name__).info(
        "one training log: no prediction intervals (they are calibrated on held-out training episodes)"
    )
    args.interval = 0.0


def _check_disjoint(train_paths: list[Path], test_paths: list[Path]) -> None:
    """Refuse a log among both the training and the test logs: its test score would be meaningless."""

    def key(path: Path):
        info = path.stat()
        return info.st_dev, info.st_ino  # the same file by any name (a link, another path)

    training = {key(p) for p in train_paths}
    both = list(dict.fromkeys(str(p) for p in test_paths if key(p) in training))
    if both:
        more = f" and {len(both) - 3} more" if len(both) > 3 else ""
        raise CliError(
            f"{', '.join(both[:3])}{more}: among both the training and the test logs (a test "
            "score on training data means nothing)"
        )


def _load(args):
    from qube_koopman.identify.data.logs import IncompleteLogSkipped, check_same_rate, load_logs
    from qube_koopman.identify.model_selection.split import paper_split
    from qube_koopman.identify.estimators.mixed import majority_controller

    if args.split:
        train_paths, test_paths = paper_split(expand_logs(args.logs))
    else:
        train_paths, test_paths = expand_logs(args.train), expand_logs(args.test)
    _check_disjoint(train_paths, test_paths)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", IncompleteLogSkipped)
        # Kept on disk, read again when needed: memory does not grow with the number of logs.
        train = load_logs(train_paths, skip=args.skip, strict=args.strict, stored=True)
        test = load_logs(test_paths, skip=args.skip, strict=args.strict, stored=True)
    for w in caught:
        print(f"{PROG}: warning: {w.message}", file=sys.stderr)
    if not train or not test:
        raise CliError("no complete training or test logs left")
    check_same_rate(train + test, "training and test")
    sessions = None
    if args.session_delays:
        train, test, sessions = _session_delayed(args.session_delays, train, test)
    # Logs of several controllers share one plant fit; the model's closed loop is the majority's.
    controller = majority_controller([log.controller for log in train])
    return train, test, controller, sessions


def _session_delayed(plant, train, test):
    """The logs' loops with their sessions' command delays (--session-delays), and what report.json says of them."""
    from qube_koopman.identify.data.sessions import session_delays
    from qube_koopman.identify.estimators.structure import with_command_delay

    logs = train + test
    delays = session_delays([log.path for log in logs], plant)
    reference = float(delays.min())
    dt = logs[0].dt
    delayed = [with_command_delay(log, (d - reference) / dt) for log, d in zip(logs, delays)]
    report = {
        "plant": str(plant),
        "reference_ms": reference * 1e3,
        "extra_ms": {log.path.name: float(d - reference) * 1e3 for log, d in zip(logs, delays)},
    }
    return delayed[: len(train)], delayed[len(train) :], report


def _cluster_statistics(args, train, cleanup: contextlib.ExitStack):
    """With --scheduler: the training logs' per-episode statistics on its workers (the client closed by ``cleanup``)."""
    if not args.scheduler:
        return None
    from qube_koopman.identify.model_selection.distributed import ClusterStatistics, connect

    client = connect(args.scheduler, security=args.security)
    cleanup.callback(client.close)
    return ClusterStatistics(
        client,
        [log.path for log in train],
        args.skip,
        shared=args.worker_logs == "shared",
        worker_timeout=args.worker_timeout,
    )


def _run(args) -> int:
    from qube_koopman.core.files import StagedFiles

    _check_args(args)
    # model.json and its reports are written under hidden names and moved into place together once
    # all are written: a write that fails (a full disk, a folder made read-only) leaves none of them.
    with contextlib.ExitStack() as cleanup:
        staged = cleanup.enter_context(StagedFiles(args.out, OUTPUT_FILES))
        try:
            return _identify(args, cleanup, staged)
        except OSError as exc:
            final = staged.final_path(exc.filename)
            if final is None:
                raise
            raise CliError(f"{final}: cannot write: {exc.strerror or exc}; nothing written", status=1) from None


def _identify(args, cleanup: contextlib.ExitStack, staged) -> int:
    from qube_koopman.identify.report.markdown import write_markdown_report
    from qube_koopman.identify.workflow import OffsetProtocol, identify_and_score

    try:
        check_figure_options(args)  # matplotlib there, before the logs load
        train, test, controller, sessions = _load(args)
        check_figure_options(args, [log.path.name for log in test])
        _check_cross_validation(args, train)
        _check_interval_data(args, train)
        _check_delays(args, train + test)
        statistics = _cluster_statistics(args, train, cleanup)
        what_if = _what_if_controller(args.controller, train[0].dt) if args.controller else None
        out = output_dir(args.out)  # after the logs and --controller load (no empty folder for a bad one)
        predictions = output_dir(out / PREDICTIONS) if args.interval or args.horizon else None
        logging.getLogger(__name__).info(
            "%d training and %d test episodes, %d samples dropped from each", len(train), len(test), args.skip
        )
        offsets = OffsetProtocol(tuple(args.offsets), args.estimate_window, args.offset_bound) if args.offsets else None
        if offsets and min(log.n_samples for log in test) <= offsets.window(train[0].dt) + 2:
            raise CliError(
                f"--estimate-window {args.estimate_window} s leaves nothing to score in the shortest test episode"
            )
        search = None
        if args.search:
            from qube_koopman.identify.cli.search import run_search

            search = run_search(args, train, controller)
            args.offsets = ["alpha"] if search.winner.spec.offsets else None
            offsets = OffsetProtocol(("alpha",), args.estimate_window, args.offset_bound) if args.offsets else None
            args.alpha = search.winner.best_alpha
        options = _identify_options(args, train, search, offsets, what_if, predictions, staged.path("model.json"))
        result = identify_and_score(train, test, controller, options, progress=progress, episode_statistics=statistics)
    except ValueError as exc:
        raise CliError(str(exc)) from None
    except NoWorkersError as exc:
        raise CliError(str(exc), status=1) from None
    _complete_report(args, result, train, sessions, statistics, search, out)
    write_json(staged.path("report.json"), result.report, shown=out / "report.json")
    write_markdown_report(staged.path("report.md"), result.report)
    staged.commit()
    _print_controllers(result.report["training_controllers"], sessions is not None)
    _print_scores(args, result.report)
    _print_intervals(result.report.get("intervals"))
    _print_ahead(result.report.get("ahead"), result.report.get("disturbance"))
    written = (
        ["model.json", "report.json", "report.md"]
        + ([PREDICTIONS] if args.interval or args.horizon else [])
        + (["figures"] if args.figures else [])
    )
    problem = _record(args.rerun, result) if args.rerun else None
    recorded = f" and {args.rerun}" if args.rerun and not problem else ""
    print(f"wrote {', '.join(str(out / w) for w in written)}{recorded}")
    if problem:  # after the scores and the files written: the model is there whatever became of the recording
        raise CliError(problem, status=1)
    return 0


def _identify_options(args, train, search, offsets, what_if, predictions, model_path):
    """identify_and_score's options from the command line's (after --search, which chose the lifting and alpha)."""
    import numpy as np

    from qube_koopman.identify.cli.search import probe_cache
    from qube_koopman.identify.models.kstep import AheadOptions
    from qube_koopman.identify.uncertainty import IntervalOptions
    from qube_koopman.identify.workflow import FitOptions, IdentifyOptions, OutputOptions, ScoreOptions

    alphas = (
        None
        if not args.alpha_sweep
        else np.logspace(np.log10(args.alpha_sweep[0]), np.log10(args.alpha_sweep[1]), args.alpha_sweep[2])
    )
    return IdentifyOptions(
        fit=FitOptions(
            method=args.method,
            lifting=search.winner.spec.steps(args.rbf_seed) if search else _lifting(args),
            alpha=1e-3 if args.alpha is None else args.alpha,
            alphas=alphas,
            cv_splits=args.cv_splits,
            cv_seed=args.cv_seed,
            arx_lags=args.arx_lags,
            estimator_options=(
                {"max_radius": args.max_radius, "center": args.pole_center} if args.max_radius is not None else None
            ),
            n_threads=args.n_jobs,
        ),
        scoring=ScoreOptions(
            score=args.score,
            offsets=offsets,
            score_from=(
                int(round(args.estimate_window / train[0].dt))
                if args.protocol == "window" and offsets is None
                else None
            ),
            what_if=what_if,
            command_delay=(
                args.command_delay if args.command_delay == "estimate" else args.command_delay * 1e-3 / train[0].dt
            ),
        ),
        intervals=(
            IntervalOptions(
                args.interval,
                args.interval_members,
                seed=args.interval_seed,
                other_loops=args.interval_other_loops,
                method=_interval_method(args)[0],
            )
            if args.interval
            else None
        ),
        probe_cache=probe_cache() if args.probe_cache else None,
        ahead=(
            None
            if args.horizon is None
            else AheadOptions(args.horizon, entry=args.disturbance, q=args.disturbance_q, pole=args.disturbance_pole)
        ),
        output=OutputOptions(
            model_path=model_path,
            predictions_folder=predictions,
            keep_predictions=bool(args.rerun or args.figures),  # the figures pick episodes by their scores
        ),
    )


def _complete_report(args, result, train, sessions, statistics, search, out) -> None:
    """What the command adds to the workflow's report: why the intervals' method, the session delays, the
    cluster, the search, the figures."""
    if "intervals" in result.report:
        result.report["intervals"]["why"] = _interval_method(args)[1]
    if sessions is not None:
        result.report["session_delays"] = sessions
    if statistics is not None:  # where the training statistics were computed
        result.report["cluster"] = cluster_report(args)
    if search is not None:
        from qube_koopman.identify.cli.search import search_report

        result.report["search"] = search_report(search, args, [log.path.name for log in train])
    if args.figures:
        from qube_koopman.identify.report.figures import identification_figures

        result.report["figures"] = write_report_figures(out, identification_figures(result, args.figure_episodes))


def _record(path, result) -> str | None:
    """Write the --rerun-save recording; why it could not be written, or None."""
    from qube_koopman.identify.report.rerun import write_recording

    try:
        write_recording(path, result)
    except OSError as exc:
        return f"{exc.filename or path}: {exc.strerror or exc}; the rerun recording was not written"
    return None


def _what_if_controller(path: str, dt: float):
    """The --controller file's controller at the logs' period: PD gains (discretized like the rig's)
    or a state-space file written at that period."""
    from qube_koopman.core.controller_file import load_controller
    from qube_koopman.core.lti import spectral_radius

    system = load_controller(path, "backward-euler", dt).system
    # An integrator (eigenvalue 1, a designed controller's integral action) is a controller; a state
    # that grows on its own is not: its predictions overflow long before they say why.
    radius = spectral_radius(system.A)
    if radius > 1.0 + 1e-9:
        raise CliError(
            f"{path}: the controller is unstable on its own (spectral radius of A {radius:.6g} > 1): "
            "its state grows without bound whatever the errors"
        )
    return system


def _print_controllers(training: dict, sessions: bool = False) -> None:
    """With training logs of several controllers: how many episodes each, and whose loop the model is
    (``sessions``: the loops of --session-delays, a controller with a session's command delay each)."""
    if training["n_controllers"] < 2:
        return
    word = "loop" if sessions else "controller"
    each = ", ".join(
        f"{word} {c['controller']}: {c['n_episodes']}"
        + (" (the model's closed loop)" if c["model_closed_loop"] else "")
        for c in training["controllers"]
    )
    n = training["n_controllers"]
    under = (
        f"in {n} loops, a controller with its session's command delay each" if sessions else f"under {n} controllers"
    )
    print(f"training episodes {under} ({each}); one plant fitted to all")


def _print_scores(args, report: dict) -> None:
    t = report["test"]
    if t is None:
        print(
            f"{args.method}, alpha {report['alpha'] if report['alpha'] is not None else '-'}: no test episode "
            f"was recorded under --controller "
            f"{args.controller}; predictions only (nothing to score)"
        )
        return
    alpha = "-" if report["alpha"] is None else f"{report['alpha']:g}"  # ARX has no regularization
    if t["n_diverged"]:
        converged = t["r2_mean_converged"]
        scores = f"test R^2 -inf: {t['n_diverged']} of {t['n_episodes']} predictions diverged" + (
            f" (the others' mean {converged:.4f})" if converged is not None else ""
        )
    else:
        scores = (
            f"test R^2 {t['r2_mean']:.4f} +- {t['r2_std'] or 0:.4f}, NRMSE {t['nrmse_mean']:.2f} +- "
            f"{t['nrmse_std'] or 0:.2f} %"
        )
    over = "" if t["n_diverged"] else f" over {t['n_episodes']} episodes"
    line = f"{args.method}, alpha {alpha}: {scores}{over} ({args.score})"
    plain = report.get("test_without_offsets")
    if plain is not None:
        flagged = sum(not e["plausible"] for e in report["offsets"])
        line += f" with offsets estimated; without them on the same samples R^2 {plain['r2_mean']:.4f}" + (
            f"; {flagged} implausible estimate(s) not used" if flagged else ""
        )
    print(line)


def _print_ahead(ahead: dict | None, disturbance: dict | None) -> None:
    """One line: each horizon's mean R^2 per channel, and the disturbance model behind them."""
    if not ahead or not ahead.get("horizons"):
        return
    each = "; ".join(
        f"{label} s ahead R^2 " + " / ".join(f"{v:.4f}" for v in h["r2_mean"]) for label, h in ahead["horizons"].items()
    )
    entry = (disturbance or {}).get("entry", "none")
    print(f"K-step (theta / alpha, disturbance {entry}): {each}")


def _print_intervals(intervals: dict | None) -> None:
    """One line: the intervals' pooled coverage and mean half-width per channel, and the worst episode's."""
    if not intervals or not intervals.get("pooled"):
        return
    pooled = intervals["pooled"]
    each = "; ".join(
        f"{name} coverage {pooled['coverage'][name]:.3f} (worst episode "
        f"{pooled['worst_episode_coverage'][name]:.3f}), mean half-width "
        f"{pooled['mean_half_width'][name]:.4g} rad"
        for name in pooled["coverage"]
    )
    elsewhere, probed = pooled.get("n_uncalibrated_loop"), pooled.get("n_probe_calibrated")
    print(
        f"intervals at {intervals['level']:g}: {each}"
        + (
            f"; {probed} episode(s) under a controller the training did not run: calibrated on the twin's probes"
            if probed
            else ""
        )
        + (
            f"; {elsewhere} episode(s) under a controller the calibration did not see: their intervals are the "
            "training loops'"
            if elsewhere
            else ""
        )
    )


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``qube-identify``; returns the exit status."""
    args = _parser().parse_args(argv)
    return run_command(PROG, _run, args, one_line_warnings=ONE_LINE_WARNINGS)


if __name__ == "__main__":
    sys.exit(main())
