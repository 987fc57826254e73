"""Plumbing every command-line tool shares (qube-emulate, qube-run, qube-import, qube-identify, ...).

It lives in ``sim``, the lowest package whose commands exist (``qube-emulate``) and one that
every other command already imports; it holds nothing but command-line plumbing: the standard
library, and tqdm for progress bars (imported when a bar is made).
"""

from __future__ import annotations

import argparse
import sys

__all__ = ["package_version", "add_version", "progress_bar", "ProgressCallback"]

DISTRIBUTION = "qube-koopman"


def package_version() -> str:
    """The installed distribution's version, or "unknown" when running from a source tree."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(DISTRIBUTION)
    except PackageNotFoundError:
        return "unknown"


def add_version(parser: argparse.ArgumentParser) -> None:
    """Give ``parser`` a ``--version`` that prints ``<prog> <version>`` and exits 0."""
    parser.add_argument("--version", action="version", version=f"%(prog)s {package_version()}",
                        help="print the version and exit")


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
