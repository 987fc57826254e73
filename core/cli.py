"""The command-line pieces every command shares and no package owns: the parser, the standard
options, and the argument types (each refuses a bad value in one usage line naming the option)."""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

__all__ = [
    "OneLineParser",
    "add_force_option",
    "add_renamed_option",
    "add_standard_options",
    "finite_number",
    "n_jobs",
    "non_negative_number",
    "number_in",
    "package_version",
    "parse_args",
    "path",
    "positive_number",
    "positive_whole_number",
    "seed",
    "whole_number",
]

DISTRIBUTION = "qube-koopman"


class OneLineParser(argparse.ArgumentParser):
    """An argument parser whose usage errors are one line: ``<prog>: error: <problem> (see <prog> --help)``.

    argparse's default prints the whole usage block (5-17 lines in these commands) before the
    error; the exit status stays argparse's 2. Subcommands' parsers are of the same class.
    """

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def parse_args(parser: argparse.ArgumentParser, argv: list[str] | None) -> argparse.Namespace | int:
    """The parsed arguments, or the exit status when argparse has already answered (--help, a usage error)."""
    try:
        return parser.parse_args(argv)
    except SystemExit as exc:
        return int(exc.code or 0)


def package_version() -> str:
    """The installed distribution's version, or "unknown" when running from a source tree."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(DISTRIBUTION)
    except PackageNotFoundError:
        return "unknown"


def add_standard_options(
    parser: argparse.ArgumentParser, quiet_help: str = "no progress bar", *, subcommand: bool = False
) -> None:
    """Give ``parser`` the options every command has: ``--version``, ``-v/--verbose``, ``-q/--quiet``.

    Parameters
    ----------
    parser : argparse.ArgumentParser
        A command's parser (or one of its subcommands' parsers).
    quiet_help : str
        What ``-q`` quiets besides log lines below errors (always: progress bars).
    subcommand : bool
        For a subcommand's parser: no ``--version`` (the command has it); ``-v``/``-q`` are
        then taken before or after the subcommand (when both, those after it count).
    """
    default = argparse.SUPPRESS if subcommand else None
    if not subcommand:
        parser.add_argument(
            "--version", action="version", version=f"%(prog)s {package_version()}", help="print the version and exit"
        )
    parser.add_argument(
        "-v",
        "--verbose",
        action="count",
        default=default if subcommand else 0,
        help="say more on stderr: -v what is done (info), -vv details (debug)",
    )
    parser.add_argument(
        "-q",
        "--quiet",
        action="store_true",
        default=default if subcommand else False,
        help=f"{quiet_help}; log only errors",
    )


def add_force_option(parser) -> None:
    """``--force``, the one switch (the same in every command) that lets existing output files be replaced.

    Without it a command refuses an output file that exists, before any work
    (``qube_koopman.core.files.output_file_problem``).
    """
    parser.add_argument(
        "--force", action="store_true", help="replace output files that exist (without it the command refuses them)"
    )


def add_renamed_option(parser, old: str, new: str, why: str) -> None:
    """Refuse ``old`` (an option's earlier name) in one line that gives ``new``, hidden from ``--help``.

    Without it argparse would take ``old`` as an abbreviation of any longer option it begins, or
    call it ambiguous, and the user would not learn the name.
    """

    class _Renamed(argparse.Action):
        def __call__(self, parser: argparse.ArgumentParser, namespace: Any, values: Any, option_string=None):
            parser.error(f"{old} is now {new} ({why})")

    parser.add_argument(old, nargs="?", action=_Renamed, help=argparse.SUPPRESS)


# The argument types: argparse ``type`` callables raising ArgumentTypeError, which argparse turns
# into one usage line naming the option (``argument --seed: must be a whole number >= 0, got -5``).


def _integer(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None


def whole_number(minimum: int, maximum: int | None = None):
    """An argparse ``type``: a whole number of at least ``minimum``, else a usage error naming the value.

    Parameters
    ----------
    minimum : int
        The smallest value accepted.
    maximum : int, optional
        The largest value accepted (default: no limit).

    Returns
    -------
    callable
        ``parse(text) -> int``, raising :class:`argparse.ArgumentTypeError` (argparse then
        names the option: ``argument --seed: must be a whole number >= 0, got -5``).
    """

    def parse(text: str) -> int:
        value = _integer(text)
        if value < minimum or (maximum is not None and value > maximum):
            raise argparse.ArgumentTypeError(f"must be a whole number {bounds}, got {value}")
        return value

    bounds = f">= {minimum}" if maximum is None else f"in [{minimum}, {maximum}]"
    parse.__name__ = f"whole number {bounds}"
    return parse


#: The argparse ``type`` of every seed option: numpy seeds are non-negative whole numbers.
seed = whole_number(0)
seed.__doc__ = "The argparse ``type`` of every seed option: a whole number >= 0 (numpy seeds are non-negative)."


def positive_whole_number(text: str) -> int:
    """The argparse ``type`` of a count (qube-run's episodes, baud rate): a whole number, at least 1."""
    value = _integer(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def n_jobs(text: str) -> int:
    """The argparse ``type`` of a number of worker processes: -1 (one per core) or a whole number >= 1."""
    value = _integer(text)
    if value == 0 or value < -1:
        raise argparse.ArgumentTypeError(f"must be -1 (every core) or at least 1, got {value}")
    return value


def path(text: str) -> Path:
    """The argparse ``type`` of every file or folder argument: a Path, not the empty string.

    ``Path("")`` is the current folder: an unset shell variable (``--out "$DIR"``) would write
    there, or read every file in it, without a word. argparse names the option in the error.
    """
    if not text:
        raise argparse.ArgumentTypeError("an empty path (an unset shell variable?): give a file or folder")
    return Path(text)


def _float(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None


def finite_number(text: str) -> float:
    """The argparse ``type`` of a number that must be finite (not nan, not inf)."""
    value = _float(text)
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text}")
    return value


def positive_number(text: str) -> float:
    """The argparse ``type`` of a finite number above zero (a duration, a limit)."""
    value = finite_number(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text}")
    return value


def non_negative_number(text: str) -> float:
    """The argparse ``type`` of a finite number, zero or above (``-0`` reads as 0)."""
    value = finite_number(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be zero or positive, got {text}")
    return abs(value)  # -0.0 reads as 0


def number_in(low: float, high: float, what: str):
    """An argparse ``type``: a number in ``[low, high]``, else ``<what> must be in [low, high], got <text>``.

    Parameters
    ----------
    low, high : float
        The bounds, both accepted.
    what : str
        What the value is, first in the error (``a rate``, ``--latency``).

    Returns
    -------
    callable
        ``parse(text) -> float``, raising :class:`argparse.ArgumentTypeError`.
    """

    def parse(text: str) -> float:
        value = _float(text)
        if not (math.isfinite(value) and low <= value <= high):
            raise argparse.ArgumentTypeError(f"{what} must be in [{low:g}, {high:g}], got {text}")
        return value

    return parse
