"""``qube-import``: convert the legacy rig's CSV episodes into MCAP episode logs."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from qube_koopman.core.cli import OneLineParser, add_force_option, parse_args
from qube_koopman.core.command import CliError, check_output_folder, output_dir, run_command
from qube_koopman.daq.cli.batch import Progress, expand_sources, summarize
from qube_koopman.daq.log.names import log_path

_log = logging.getLogger(__name__)

PROG = "qube-import"

_DESCRIPTION = """\
Convert the QUBE-Servo rig's legacy CSV episodes (the paper's dataset) into
MCAP episode logs, one OUT/<CSV base name>.mcap per file (format: daq/log/FORMAT.md).

Each file is checked before it is converted: the header must hold the columns
t, target_theta, target_alpha, theta, alpha, control_output, feedforward,
plant_input, saturation; every row must be complete and finite, sampled at
500 Hz; and the controller from controller.toml (backward-Euler derivative
filter, as the rig ran it), run on the tracking error, must reproduce the
logged control_output to 1e-9 V after the first second. The recomputed
controller state is stored in the log. A file that fails is refused with one
line on stderr naming it and the problem; the other files still import. A file
cut short (its last line without a newline) is imported without that line,
with a warning, and its log is marked incomplete (qube-identify skips it).
"""

_EPILOG = """\
exit status: 0 when every file was imported, 1 when any was refused,
2 on a usage error (also a SRC that does not exist or a folder without CSV
files; the other files are still imported).

example (DATASET_DIR: the paper's dataset, folder dataset/controller_20230828 of the repository
decargroup/closed_loop_koopman):
  qube-import DATASET_DIR --out qube_logs/
"""


def build_parser() -> argparse.ArgumentParser:
    """The command-line parser (also documents the options)."""
    from qube_koopman.core.cli import add_standard_options, path

    parser = OneLineParser(
        prog=PROG, description=_DESCRIPTION, epilog=_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "sources",
        nargs="+",
        type=path,
        metavar="SRC",
        help="a legacy CSV file, or a folder whose *.csv files are all imported",
    )
    parser.add_argument("--out", required=True, type=path, metavar="DIR", help="output folder (created if missing)")
    parser.add_argument(
        "--controller",
        type=path,
        metavar="FILE",
        help="controller gains (TOML: kp_theta, kd_theta, kp_alpha, kd_alpha, tau) for "
        "every file; default: the controller.toml beside each CSV file",
    )
    add_force_option(parser)
    add_standard_options(parser, "no progress counter")
    return parser


class _Controllers:
    """The controller of each CSV file: --controller's, else the controller.toml beside the file.

    One per controller.toml; a file that cannot give one is remembered as its problem, so
    each CSV beside it is refused with it.

    Raises
    ------
    ValueError
        From the constructor, when --controller's file cannot be used (a usage error).
    """

    def __init__(self, given: Path | None) -> None:
        from qube_koopman.daq.legacy_csv import load_legacy_controller

        self.given = given
        self.found: dict[Path, object] = {}
        if given is not None:
            self.found[given] = load_legacy_controller(given)

    def __call__(self, csv: Path):
        from qube_koopman.daq.legacy_csv import LegacyCsvError, load_legacy_controller

        toml = self.given or csv.parent / "controller.toml"
        if toml not in self.found:
            if not toml.is_file():
                self.found[toml] = f"no controller file {toml} (give one with --controller FILE)"
            else:
                try:
                    self.found[toml] = load_legacy_controller(toml)
                except ValueError as exc:
                    self.found[toml] = str(exc)
        found = self.found[toml]
        if isinstance(found, str):
            raise LegacyCsvError(f"{csv}: {found}")
        return found


def main(argv: list[str] | None = None) -> int:
    """Run ``qube-import``; returns the exit status (0 all imported, 1 some refused, 2 usage or a missing SRC)."""
    args = parse_args(build_parser(), argv)
    if isinstance(args, int):  # --help, or a usage error argparse has already explained
        return args
    return run_command(PROG, _import, args)  # stopped: every file written so far is whole


def _import(args) -> int:
    """The command itself: each file in turn, a refused one said above the progress bar (exit 1)."""
    from qube_koopman.daq.legacy_csv import LegacyCsvError, legacy_episode
    from qube_koopman.daq.log import write_episode
    from qube_koopman.daq.log.writer import remove_stale_temp_files

    def refuse(message: str) -> None:
        progress.say(f"{PROG}: error: {message}")

    problems: list[str] = []
    files = expand_sources(args.sources, ".csv", problems)
    check_output_folder(args.out)  # not a folder, read-only: before any work
    progress = Progress(len(files), not args.quiet)
    for problem in problems:
        refuse(problem)

    try:
        controller_for = _Controllers(args.controller)
    except ValueError as exc:
        raise CliError(str(exc)) from None
    for stale in remove_stale_temp_files(args.out):
        _log.info("%s: removed, a temporary file an interrupted import left", stale)
    imported, refused = 0, 0
    claimed: dict[Path, Path] = {}
    for done, csv in enumerate(files, start=1):
        out = log_path(args.out, csv.stem)
        try:
            if out in claimed:
                raise LegacyCsvError(f"{csv}: same base name as {claimed[out]}; both would write {out}")
            claimed[out] = csv
            if out.exists() and not args.force:
                raise LegacyCsvError(f"{csv}: {out} exists (use --force to overwrite)")
            episode = legacy_episode(csv, controller_for(csv))
            if not episode.is_complete:  # cut short, or exported from a log that did not complete
                meta = episode.metadata
                progress.say(
                    f"{PROG}: warning: {csv}: {meta.status_reason.removeprefix('legacy CSV ')}; "
                    f"imported as an {meta.status} episode of {len(episode)} samples"
                )
            # Through the toolkit: a folder it made is removed again if the command ends with
            # nothing written into it (the write failed, or Ctrl-C during it).
            output_dir(args.out)
            write_episode(out, episode, overwrite=args.force)
            imported += 1
            _log.info("%s: imported into %s", csv, out)
        except LegacyCsvError as exc:
            refused += 1
            refuse(str(exc))
        except OSError as exc:
            refused += 1
            refuse(f"{csv}: cannot write {out}: {exc.strerror or exc}")
        progress.step(done, csv.name)

    return summarize("imported", imported, len(files), "file", f"into {args.out}", refused, problems)


if __name__ == "__main__":
    sys.exit(main())
