"""``qube-compare``: episodes run under a designed controller against what its design predicted.

    qube-compare CONTROLLER.toml LOG [LOG ...] [--model MODEL.json]

Reads a controller file ``qube-design`` wrote and the episode logs ``qube-run --controller`` recorded under
it (files, or folders of them). It designs the controller again from the model file and the weights its
provenance names (the same matrices, or it stops: the model changed), predicts the model's closed loop on
exactly the logs' excitations (their recorded seeds and settings) with the interval of the design's level,
and prints, for J, the arm's tracking RMS and the voltage's RMS (after each episode's first second), the
measured figure, the predicted one, the interval, and whether the measured figure lies inside. Episodes the
safety supervisor stopped are left out and counted. A log recorded under another controller, or a
controller file qube-design did not write, is one line naming it, exit 1.
"""

from __future__ import annotations

import argparse
import sys

from qube_koopman.core.cli import OneLineParser, add_standard_options, parse_args, path
from qube_koopman.core.command import CliError, run_command
from qube_koopman.identify.command_warnings import ONE_LINE_WARNINGS

__all__ = ["main"]

PROG = "qube-compare"

_EPILOG = """\
exit status: 0 when the comparison was printed, whether or not the measured figures lie inside their
intervals; 1 when a file cannot be compared (named: a log of another controller, a controller file
qube-design did not write, a model file missing or not the one designed on); 2 on a usage error or
a file or folder that does not exist.

examples:
  qube-design twin_plant --out designed.toml --seed 7
  qube-run --episodes 20 --seed 7 --controller designed.toml --out designed_runs
  qube-compare designed.toml designed_runs           # the run the design predicted, measured against it
"""


def _parser() -> argparse.ArgumentParser:
    p = OneLineParser(
        prog=PROG,
        description=__doc__.split("\n\n", 2)[2].replace("``", "") if __doc__ else None,
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("controller", type=path, metavar="CONTROLLER.toml", help="a controller file qube-design wrote")
    p.add_argument(
        "logs", type=path, nargs="+", metavar="LOG", help="episode logs run under it, or folders of them (.mcap)"
    )
    p.add_argument(
        "--model",
        type=path,
        default=None,
        metavar="MODEL.json",
        help="the model file it was designed on, when not where its provenance says (by default: as qube-design "
        "was given it, else beside the controller file)",
    )
    add_standard_options(p, "nothing to quiet")
    return p


def _run(args) -> int:
    from qube_koopman.daq.log.names import expand_logs
    from qube_koopman.design.compare import compare_runs, comparison_text
    from qube_koopman.design.plant import DesignError

    if not args.controller.is_file():
        raise CliError(f"{args.controller}: no such controller file")
    if args.model is not None and not args.model.exists():
        raise CliError(f"{args.model}: no such model file (--model)")
    logs = expand_logs(args.logs)
    try:
        comparison = compare_runs(args.controller, logs, model=args.model)
    except DesignError as exc:
        raise CliError(str(exc), status=1) from None
    print(comparison_text(comparison))
    return 0


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``qube-compare``; returns the exit status."""
    args = parse_args(_parser(), argv)
    if isinstance(args, int):
        return args
    return run_command(PROG, _run, args, one_line_warnings=ONE_LINE_WARNINGS)


if __name__ == "__main__":
    sys.exit(main())
