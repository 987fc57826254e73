"""``qube-design``: a controller from an identified plant model, with its predicted cost.

    qube-design MODEL --out FILE.toml [--q-theta Q] [--q-alpha Q] [--r-voltage R]
                [--q-integral Q | --no-integral] [--seed K] [--episodes N] [--duration S] [--npz]
                [--interval LEVEL] [--robust] [--rerun FILE.rrd [--rerun-episodes N]]
                [--mpc [--voltage-limit V] [--horizon N] [--disturbances E[,E]] [--no-offset-free]]
                [--figures DIR]

Reads a ``model.json`` of ``qube-identify`` (or its output folder), designs an LQ state
feedback on the plant's history of measurements (with integral action on the arm's tracking
error), realizes it as a discrete controller on the tracking errors and writes it as a
state-space controller file (core/CONTROLLER_FORMAT.md) that ``qube-run --controller`` runs. It
prints the plant designed on (the identified plant itself for a lifting of order-1 monomials,
delays and a constant; its linearization at upright otherwise), the closed loop's spectral
radius, the margins at the plant input and the cost the model predicts on the rig's excitation
of ``qube-run --seed K --episodes N`` beside the model's training controller. A model it cannot
design on (not a plant model, the arm's friction shape in its lifting, not stabilizable) or a
predicted closed loop that is unstable is refused, exit 2, and nothing is written.

The predicted J and voltage come with an interval at ``--interval LEVEL`` (0.95; 0: none) from the
model file's bootstrap plants and the model's error on held-out training episodes, that error
propagated through the designed loop (the figures "with the model's error" are its expectation; a
model file without them, written with ``qube-identify --interval 0`` or by an older version, gets
none, and the report says so). ``--robust`` designs against that uncertainty: among the weights with the
voltage weight scaled up (x1, x2, x4), the design whose worst case of J over the bootstrap
plants is lowest, and the report gives what it costs in predicted J against the nominal design.

With ``--mpc`` it writes a model predictive controller instead (a controller file of kind
``mpc``): on the same plant and with the same weights, over ``--horizon N`` ticks (default 20),
the LQ design's Riccati cost as the terminal cost (so that without active constraints it is that
LQ design), the voltage kept within ``--voltage-limit V`` (default the rig's 10 V) and the arm
kept within 0.2 rad of the safety stop (a soft bound: a penalty, so every tick's problem is
feasible). The report above it is the LQ design's, the MPC's law while no constraint binds. When
the model file has a disturbance model (``qube-identify --horizon S[,S...]``), the MPC is
offset-free: with that model's covariances it estimates a load at the plant input and a rate on
the arm's angle each tick (``--disturbances ENTRIES``), the prediction carries the estimates and
the steady-state target moves the voltage so that the arm tracks its reference with no offset
under a constant load or a plant the model did not see (``--no-offset-free``: the model's own
estimate is only logged). A line says which.

With ``--figures DIR`` it also writes the design's frequency responses into DIR, named after the
controller file: ``STEM_bode.png``, Bode plots of the identified plant (voltage to each angle), of the
controller (each tracking error to the voltage) and of the loop broken at the plant input, and
``STEM_margins.png``, the loop's Bode plot with its crossings and its margins in the title (those printed).

With ``--rerun-save FILE.rrd`` it also runs the first episodes of that excitation on the twin (as
``qube-run --seed K --episodes N --controller FILE.toml`` runs them, and under the model's
training controller) and writes a rerun recording: predicted vs twin trajectories of theta,
alpha and the voltage, and the closed-loop eigenvalues of the design and of the training
controller beside the unit circle (``rerun FILE.rrd`` opens it; rerun-sdk is the optional
``viz`` extra).
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import fields
from pathlib import Path

from qube_koopman.core.cli import (
    OneLineParser,
    add_force_option,
    add_renamed_option,
    add_standard_options,
    path,
    seed,
    whole_number,
)
from qube_koopman.core.command import (
    CliError,
    check_output_file,
    check_output_folder,
    check_rerun_target,
    run_command,
)
from qube_koopman.design.lq import Weights
from qube_koopman.identify.command_warnings import ONE_LINE_WARNINGS

__all__ = ["main"]

#: Defaults of the weights: design.lq.Weights's own.
DEFAULTS = {f.name: f.default for f in fields(Weights) if f.name != "integral"}


def _parser() -> argparse.ArgumentParser:
    p = OneLineParser(
        prog="qube-design",
        description=__doc__.split("\n\n")[0].replace("``", ""),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("model", type=path, metavar="MODEL.json", help="model file of qube-identify (or its --out folder)")
    p.add_argument("--out", type=path, required=True, metavar="FILE.toml", help="controller file to write")
    p.add_argument(
        "--q-theta",
        type=float,
        default=DEFAULTS["q_theta"],
        metavar="Q",
        help=f"LQ weight on the arm's tracking error, per sample, rad^-2 (default {DEFAULTS['q_theta']:g})",
    )
    p.add_argument(
        "--q-alpha",
        type=float,
        default=DEFAULTS["q_alpha"],
        metavar="Q",
        help=f"LQ weight on the pendulum angle, rad^-2 (default {DEFAULTS['q_alpha']:g})",
    )
    p.add_argument(
        "--r-voltage",
        type=float,
        default=DEFAULTS["r_voltage"],
        metavar="R",
        help=f"LQ weight on the voltage, V^-2, > 0 (default {DEFAULTS['r_voltage']:g})",
    )
    integral = p.add_mutually_exclusive_group()
    integral.add_argument(
        "--q-integral",
        type=float,
        default=DEFAULTS["q_integral"],
        metavar="Q",
        help=f"LQ weight on the integral of the arm's tracking error, (rad s)^-2 (default {DEFAULTS['q_integral']:g})",
    )
    integral.add_argument("--no-integral", action="store_true", help="no integral action on the arm")
    p.add_argument(
        "--seed", type=seed, default=1, metavar="K", help="predict on the excitation of qube-run --seed K (default 1)"
    )
    p.add_argument(
        "--episodes",
        type=whole_number(1, 100),
        default=20,
        metavar="N",
        help="episodes of that excitation predicted (default 20)",
    )
    p.add_argument(
        "--duration", type=float, default=20.0, metavar="S", help="seconds per predicted episode, 2 to 60 (default 20)"
    )
    p.add_argument(
        "--interval",
        type=float,
        default=0.95,
        metavar="LEVEL",
        help="give the predicted J and voltage an interval at this level, 0 for none (default 0.95)",
    )
    p.add_argument(
        "--robust",
        action="store_true",
        help="design against the model's uncertainty (its bootstrap plants) and say what it costs in J",
    )
    p.add_argument(
        "--npz", action="store_true", help="write the matrices to FILE.npz beside the controller file (loads faster)"
    )
    add_renamed_option(p, "--rerun", "--rerun-save FILE.rrd", "a file; qube-run --rerun streams to a viewer")
    p.add_argument(
        "--rerun-save",
        dest="rerun",
        type=path,
        metavar="FILE.rrd",
        help="also write a rerun recording: predicted vs twin trajectories, closed-loop eigenvalues",
    )
    p.add_argument(
        "--rerun-episodes",
        type=whole_number(1, 20),
        default=3,
        metavar="N",
        help="episodes of the excitation the recording shows, run on the twin (default 3)",
    )
    p.add_argument(
        "--figures",
        type=path,
        default=None,
        metavar="DIR",
        help="also write Bode plots of the plant, the controller and the loop at the plant input, and the loop's "
        "margins, as DIR/STEM_bode.png and DIR/STEM_margins.png (STEM: the controller file's)",
    )
    mpc = p.add_argument_group("model predictive control")
    mpc.add_argument("--mpc", action="store_true", help="write a model predictive controller (kind mpc)")
    mpc.add_argument(
        "--voltage-limit",
        type=float,
        default=None,
        metavar="V",
        help="with --mpc: keep |V| within this, up to the rig's 10 V (default 10)",
    )
    mpc.add_argument(
        "--horizon",
        type=whole_number(1, 200),
        default=None,
        metavar="N",
        help="with --mpc: inputs predicted, ticks of 2 ms (default 20)",
    )
    mpc.add_argument(
        "--disturbances",
        type=_entries,
        default=None,
        metavar="ENTRY[,ENTRY]",
        help="with --mpc: the disturbances the offset-free MPC estimates, one or two of input (a load at the plant "
        "input), theta, alpha (a rate on that angle) (default input,theta: one per measured angle, so that a plant "
        "the model did not see leaves no offset either)",
    )
    mpc.add_argument(
        "--no-offset-free",
        action="store_true",
        help="with --mpc: do not use the model file's disturbance estimate (offset-free control is on when the "
        "model file has a disturbance model, qube-identify --horizon)",
    )
    add_force_option(p)
    add_standard_options(p, "nothing to quiet")
    return p


def _weights(args):
    from qube_koopman.design.plant import DesignError

    try:
        return Weights(
            args.q_theta,
            args.q_alpha,
            args.r_voltage,
            0.0 if args.no_integral else args.q_integral,
            not args.no_integral,
        )
    except DesignError as exc:
        raise CliError(str(exc)) from None


def _entries(text: str) -> tuple[str, ...]:
    """``--disturbances``: one or two distinct entries."""
    from qube_koopman.identify.models.disturbance import ENTRIES

    entries = tuple(e.strip() for e in text.split(","))
    if not (1 <= len(entries) <= 2 and len(set(entries)) == len(entries) and set(entries) <= set(ENTRIES)):
        raise argparse.ArgumentTypeError(f"one or two distinct of {', '.join(ENTRIES)}, got {text!r}")
    return entries


def _mpc_settings(args):
    """The MPC's settings with --mpc, else None (--voltage-limit and --horizon refused without it)."""
    from qube_koopman.design.mpc import MpcSettings
    from qube_koopman.design.plant import DesignError

    if not args.mpc:
        for name in ("voltage_limit", "horizon"):
            if getattr(args, name) is not None:
                raise CliError(f"--{name.replace('_', '-')} is a setting of --mpc")
        for flag, value in (("--no-offset-free", args.no_offset_free), ("--disturbances", args.disturbances)):
            if value:
                raise CliError(f"{flag} is a setting of --mpc")
        return None
    if args.npz or args.robust or args.rerun:
        raise CliError("--mpc writes its matrices in the file and takes no --npz, --robust or --rerun-save")
    if args.disturbances and args.no_offset_free:
        raise CliError("--disturbances are what offset-free control estimates; --no-offset-free turns it off")
    values = {"voltage_limit": args.voltage_limit, "horizon": args.horizon, "offset_free": not args.no_offset_free}
    try:
        return MpcSettings(**{k: v for k, v in values.items() if v is not None})
    except DesignError as exc:
        raise CliError(str(exc)) from None


def _run(args) -> int:
    from qube_koopman.core.controller_file import write_controller_file
    from qube_koopman.design.plant import DesignError
    from qube_koopman.design.controller_design import design_from_model, provenance, report_text, saturation_warning

    weights = _weights(args)
    settings = _mpc_settings(args)
    check_output_file(args.out, force=args.force)  # before the design's minutes of work, not after
    if args.npz:
        check_output_file(Path(args.out).with_suffix(".npz"), "--npz", args.force)
    check_rerun_target(args.rerun, "--rerun-save", args.force)
    if args.figures is not None:
        check_output_folder(args.figures, tuple(f.name for f in _figure_files(args)), "--figures", args.force)
    if not (math.isfinite(args.duration) and 2.0 <= args.duration <= 60.0):
        raise CliError(f"--duration must be between 2 and 60 s, got {args.duration}")
    if round(args.duration * 500) != args.duration * 500:
        raise CliError(f"--duration {args.duration} s is not a whole number of 2 ms samples")
    if not (args.interval == 0 or 0 < args.interval < 1):
        raise CliError(f"--interval must be a level between 0 and 1 (0: no interval), got {args.interval}")
    try:
        report = design_from_model(
            args.model,
            weights,
            seed=args.seed,
            episodes=args.episodes,
            duration=args.duration,
            level=args.interval or None,
            robust=args.robust,
        )
    except DesignError as exc:
        raise CliError(str(exc)) from None
    print(report_text(report))
    warning = saturation_warning(report)
    if warning:
        print(f"qube-design: warning: {warning}", file=sys.stderr)
    try:
        if settings is not None:
            from qube_koopman.design.controller_design import offset_free_settings, write_mpc

            settings, line = offset_free_settings(report, settings, args.disturbances)
            print(line)
            written = write_mpc(args.out, report, settings, args.disturbances)
        else:
            written = write_controller_file(args.out, report.controller, provenance(report), npz=args.npz)
    except DesignError as exc:
        raise CliError(str(exc)) from None
    except OSError as exc:
        raise CliError(f"{args.out}: cannot write: {exc.strerror or exc}", status=1) from None
    print(
        f"wrote {written}"
        + (f" and {written.with_suffix('.npz')}" if args.npz else "")
        + f": qube-run --controller {written}"
    )
    if args.rerun:
        _record(args, report, written)
    if args.figures is not None:
        _figures(args, report)
    return 0


def _figure_files(args) -> list[Path]:
    """The files --figures writes (none without it)."""
    if args.figures is None:
        return []
    stem = Path(args.out).stem
    return [args.figures / f"{stem}_bode.png", args.figures / f"{stem}_margins.png"]


def _figures(args, report) -> None:
    """The --figures files: Bode plots of the plant, the controller and the loop, and the loop's margins."""
    from qube_koopman.design.frequency import write_frequency_figures

    try:
        figures = write_frequency_figures(args.figures, Path(args.out).stem, report.design.plant, report.controller)
    except OSError as exc:
        raise CliError(f"{args.figures}: cannot write: {exc.strerror or exc}", status=1) from None
    print(
        f"wrote {figures.bode} (Bode plots of the plant, the controller and the loop) and {figures.margins_figure} "
        "(the loop's margins)"
    )


def _record(args, report, written) -> None:
    """The --rerun-save recording, with the controller as qube-run loads it from the written file."""
    from qube_koopman.core.controller_file import load_controller
    from qube_koopman.design.controller_design import record_design

    n = min(args.rerun_episodes, args.episodes)
    try:
        record_design(args.rerun, report, load_controller(written), n)
    except OSError as exc:
        raise CliError(f"{args.rerun}: cannot write: {exc.strerror or exc}", status=1) from None
    print(f"wrote {args.rerun}: the first {n} episodes predicted and on the twin, the closed-loop eigenvalues")


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``qube-design``; returns the exit status."""
    args = _parser().parse_args(argv)
    return run_command("qube-design", _run, args, one_line_warnings=ONE_LINE_WARNINGS)


if __name__ == "__main__":
    sys.exit(main())
