"""``qube-export``: episode logs out to legacy CSV, Parquet or MATLAB (formats: daq/export.py)."""

from __future__ import annotations

import argparse
import logging
import sys
import warnings

from qube_koopman.core.cli import (
    OneLineParser,
    add_force_option,
    add_standard_options,
    parse_args,
    path,
)
from qube_koopman.core.command import check_output_folder, output_dir, run_command
from qube_koopman.daq.cli.batch import Progress, expand_sources, summarize
from qube_koopman.daq.log.names import LOG_SUFFIX

_log = logging.getLogger(__name__)

PROG = "qube-export"

_DESCRIPTION = """\
Export MCAP episode logs, one OUT/<log base name>.<ext> per log:

  csv      the rig's legacy layout (the paper's dataset; qube-import reads it
           back, and an imported dataset file exports to its original bytes)
  parquet  one table per episode, every signal a column, the episode's
           metadata (controller, excitation, status...) in the schema
           metadata (needs pyarrow)
  mat      MATLAB .mat: one column vector per signal and a struct `metadata`

A log that cannot be read is refused with one line on stderr naming it and
the problem; the other logs are still exported. A log cut short is exported
up to its last readable sample, with a warning. The CSV layout has no status:
for an episode that did not complete (aborted, or cut short) the status is
written beside the CSV in <name>.status.json, with a warning, and qube-import
gives it back.
"""

_EPILOG = """\
exit status: 0 when every log was exported, 1 when any was refused,
2 on a usage error (also a LOG that does not exist or a folder without .mcap
logs; the other logs are still exported).

example:
  qube-export episodes/ --format parquet --out exported/
"""


def build_parser() -> argparse.ArgumentParser:
    """The command-line parser (also documents the options)."""
    from qube_koopman.daq.export import FORMATS

    parser = OneLineParser(
        prog=PROG, description=_DESCRIPTION, epilog=_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "logs",
        nargs="+",
        type=path,
        metavar="LOG",
        help="an episode log (.mcap), or a folder whose *.mcap files are all exported",
    )
    parser.add_argument("--format", required=True, choices=tuple(FORMATS), help="output format")
    parser.add_argument("--out", required=True, type=path, metavar="DIR", help="output folder (created if missing)")
    add_force_option(parser)
    add_standard_options(parser, "no progress counter")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run ``qube-export``; returns the exit status (0 all exported, 1 some refused, 2 usage or a missing LOG)."""
    args = parse_args(build_parser(), argv)
    if isinstance(args, int):  # --help, or a usage error argparse has already explained
        return args
    return run_command(PROG, _export, args)  # stopped: every file written so far is whole


def _export(args) -> int:
    """The command itself: each log in turn, a refused one said above the progress bar (exit 1)."""
    from qube_koopman.daq.export import ExportError, export_episode
    from qube_koopman.daq.legacy_csv import status_sidecar
    from qube_koopman.daq.log import IncompleteEpisodeWarning

    check_output_folder(args.out)  # not a folder, read-only: before any work
    problems: list[str] = []
    logs = expand_sources(args.logs, LOG_SUFFIX, problems)
    # Made here, through the toolkit: a folder it made is removed again if nothing could be
    # written into it (every log refused, or Ctrl-C before the first file).
    output_dir(args.out)
    progress = Progress(len(logs), not args.quiet)

    def say(kind: str, message: str) -> None:
        progress.say(f"{PROG}: {kind}: {message}")

    for problem in problems:
        say("error", problem)
    exported = refused = 0
    for done, log in enumerate(logs, start=1):
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always", IncompleteEpisodeWarning)
                written = export_episode(log, args.format, args.out, overwrite=args.force)
            for warning in caught:
                say("warning", str(warning.message))
            if args.format == "csv" and status_sidecar(written).exists():
                say(
                    "warning",
                    f"{log}: not a complete episode; its status is in {status_sidecar(written)} "
                    "(the CSV layout has no place for it)",
                )
            exported += 1
            _log.info("%s: exported as %s into %s", log, args.format, args.out)
        except ExportError as exc:
            refused += 1
            say("error", str(exc))
            if str(exc).startswith("--format"):  # pyarrow missing: the same for every log
                return 1
        progress.step(done, log.name)

    return summarize("exported", exported, len(logs), "log", f"as {args.format} into {args.out}", refused, problems)


if __name__ == "__main__":
    sys.exit(main())
