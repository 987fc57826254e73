"""Plumbing every command-line tool shares (qube-emulate, qube-run, qube-import, qube-identify, ...).

It lives in ``sim``, the lowest package whose commands exist (``qube-emulate``) and one that
every other command already imports; it holds nothing but command-line plumbing: the standard
library, and tqdm for progress bars (imported when a bar is made).
"""

from __future__ import annotations

import argparse
import logging
import platform
import sys
from pathlib import Path

__all__ = ["package_version", "add_standard_options", "add_version", "configure_logging", "LOGGER",
           "progress_bar", "ProgressCallback", "whole_number", "seed", "path"]

#: The project's logger namespace: modules log with ``logging.getLogger(__name__)`` under it.
LOGGER = "qube_koopman"

# The handler configure_logging installed last (replaced, not stacked, when called again).
_handler: logging.Handler | None = None

DISTRIBUTION = "qube-koopman"


def package_version() -> str:
    """The installed distribution's version, or "unknown" when running from a source tree."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(DISTRIBUTION)
    except PackageNotFoundError:
        return "unknown"


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
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
        if value < minimum or (maximum is not None and value > maximum):
            raise argparse.ArgumentTypeError(f"must be a whole number {bounds}, got {value}")
        return value

    bounds = f">= {minimum}" if maximum is None else f"in [{minimum}, {maximum}]"
    parse.__name__ = f"whole number {bounds}"
    return parse


#: The argparse ``type`` of every seed option: numpy seeds are non-negative whole numbers.
seed = whole_number(0)
seed.__doc__ = "The argparse ``type`` of every seed option: a whole number >= 0 (numpy seeds are non-negative)."


def path(text: str) -> Path:
    """The argparse ``type`` of every file or folder argument: a Path, not the empty string.

    ``Path("")`` is the current folder: an unset shell variable (``--out "$DIR"``) would write
    there, or read every file in it, without a word. argparse names the option in the error.
    """
    if not text:
        raise argparse.ArgumentTypeError("an empty path (an unset shell variable?): give a file or folder")
    return Path(text)


def add_standard_options(parser: argparse.ArgumentParser, quiet_help: str = "no progress bar", *,
                         subcommand: bool = False) -> None:
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
        parser.add_argument("--version", action="version", version=f"%(prog)s {package_version()}",
                            help="print the version and exit")
    parser.add_argument("-v", "--verbose", action="count", default=default if subcommand else 0,
                        help="say more on stderr: -v what is done (info), -vv details (debug)")
    parser.add_argument("-q", "--quiet", action="store_true", default=default if subcommand else False,
                        help=f"{quiet_help}; log only errors")


def add_version(parser: argparse.ArgumentParser) -> None:
    """The standard options under their first name (``--version`` came first): :func:`add_standard_options`."""
    add_standard_options(parser)


def configure_logging(prog: str, args: argparse.Namespace) -> logging.Logger:
    """Send the project's log records to stderr as ``<prog>: <level>: <message>``, at the level asked for.

    Warnings and errors by default, info with ``-v``, debug with ``-vv``, errors only with
    ``-q``. Call it once the arguments are parsed; calling it again replaces the handler.

    Parameters
    ----------
    prog : str
        The command's name, first on every line.
    args : argparse.Namespace
        Parsed arguments with ``verbose`` (count) and ``quiet`` (missing ones count as unset).

    Returns
    -------
    logging.Logger
        The project's logger (:data:`LOGGER`).
    """
    global _handler
    verbose, quiet = getattr(args, "verbose", 0) or 0, bool(getattr(args, "quiet", False))
    level = logging.ERROR if quiet else {0: logging.WARNING, 1: logging.INFO}.get(verbose, logging.DEBUG)
    logger = logging.getLogger(LOGGER)
    if _handler is not None:
        logger.removeHandler(_handler)
    _handler = logging.StreamHandler(sys.stderr)
    _handler.setFormatter(_CommandFormatter(prog))
    logger.addHandler(_handler)
    logger.setLevel(level)
    logger.propagate = False  # the command owns stderr: no second copy through the root logger
    logger.info("%s %s on Python %s (%s)", prog, package_version(), platform.python_version(), sys.executable)
    return logger


class _CommandFormatter(logging.Formatter):
    """``<prog>: <level>: <message>``, the style of the commands' error lines."""

    def __init__(self, prog: str) -> None:
        super().__init__()
        self.prog = prog

    def format(self, record: logging.LogRecord) -> str:
        text = f"{self.prog}: {record.levelname.lower()}: {record.getMessage()}"
        return text + ("\n" + self.formatException(record.exc_info) if record.exc_info else "")


def progress_bar(total: float, desc: str | None = None, unit: str = "it", enabled: bool = True, **options):
    """A tqdm bar on stderr, silent when stderr is not a terminal (or when ``enabled`` is false).

    Parameters
    ----------
    total : float
        The count that means done.
    desc : str, optional
        The label before the bar.
    unit : str, default "it"
        What is counted.
    enabled : bool, default True
        False for ``-q``: no bar at all.
    **options
        Passed on to :class:`tqdm.tqdm`.

    Returns
    -------
    tqdm.tqdm
        Use ``update``, ``set_postfix_str``, ``write`` (a line above the bar) and ``close``.
    """
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit=unit, file=sys.stderr, dynamic_ncols=True,
                disable=None if enabled else True, **options)


class ProgressCallback:
    """The ``progress(label, done, total)`` callback of the library's long steps, drawn with tqdm.

    A new label, or a count that starts again, closes the current bar and opens the next;
    a bar closes when ``done`` reaches ``total``.
    """

    def __init__(self, enabled: bool = True) -> None:
        self.enabled = enabled
        self._bar = None
        self._label: str | None = None

    def __call__(self, label: str, done: int, total: int) -> None:
        bar = self._bar
        if bar is None or label != self._label or done < bar.n or total != bar.total:
            self.close()
            self._bar = bar = progress_bar(total, desc=label, enabled=self.enabled)
            self._label = label
        bar.update(done - bar.n)
        if done >= total:
            self.close()

    def close(self) -> None:
        """Close the open bar, if any."""
        if self._bar is not None:
            self._bar.close()
            self._bar = None
