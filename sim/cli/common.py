"""Plumbing every command-line tool shares (qube-emulate, qube-run, qube-import, qube-identify, ...).

It lives in ``sim``, the lowest package whose commands exist (``qube-emulate``) and one that
every other command already imports; it holds nothing but command-line plumbing, standard
library only.
"""

from __future__ import annotations

import argparse

__all__ = ["package_version", "add_version"]

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
