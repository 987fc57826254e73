"""What a command writes on stderr besides its errors: log lines and progress bars.

The standard library, and tqdm for progress bars (imported when a bar is made).
"""

from __future__ import annotations

import argparse
import logging
import platform
import sys

from qube_koopman.core.cli import package_version

__all__ = ["LOGGER", "ProgressCallback", "configure_logging", "progress_bar"]

#: The project's logger namespace: modules log with ``logging.getLogger(__name__)`` under it.
LOGGER = "qube_koopman"

# The handler configure_logging installed last (replaced, not stacked, when called again).
_handler: logging.Handler | None = None


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

    return tqdm(
        total=total,
        desc=desc,
        unit=unit,
        file=sys.stderr,
        dynamic_ncols=True,
        disable=None if enabled else True,
        **options,
    )


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
