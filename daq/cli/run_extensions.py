"""Options of ``qube-run`` that packages above ``daq`` provide (``qube-run --identify``, from ``identify``).

``daq`` imports nothing above it: a package registers an object under the entry-point group
:data:`ENTRY_POINT_GROUP` (``[project.entry-points."qube_koopman.qube_run"]`` in pyproject.toml), and
``qube-run`` adds its options to the parser, asks it for sinks (fed every episode as the episode log is)
before the episodes, and lets it finish (print, write its files) after them. An extension that stops the run
through the stop request (its goal reached) ends the run as planned, not as an error.
"""

from __future__ import annotations

import argparse
from typing import Protocol

__all__ = ["ENTRY_POINT_GROUP", "RunExtension", "run_extensions"]

#: The entry-point group of qube-run's extensions.
ENTRY_POINT_GROUP = "qube_koopman.qube_run"


class RunExtension(Protocol):
    """What ``qube-run`` asks of an extension (an object, or a class made with no arguments)."""

    #: The option that asks for it (named when it needs the episodes run one at a time).
    option: str

    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        """Add its options (in their own group) to ``qube-run``'s parser."""

    def active(self, args: argparse.Namespace) -> bool:
        """Whether the command line asked for it (its options alone may be refused here: raise ``CliError``)."""

    def start(self, args: argparse.Namespace, logs, stop, recording=None) -> list:
        """Sinks for every episode, made before the first: ``logs`` is the episode log sink (``paths``: the logs
        written, closed before these sinks), ``stop`` the run's stop request (set between episodes, it ends the
        run before the next), ``recording`` the run's rerun view or recording (``--rerun``, ``--rerun-save``) or
        None; its ``send_scalars`` and static ``log`` calls may come from any thread."""

    def finish(self, args: argparse.Namespace) -> None:
        """After the episodes (their summary printed): print, write files; a ``CliError`` sets the exit status."""

    def ended_run(self) -> bool:
        """Whether it stopped the run (a planned end: the exit status is then that of the episodes run)."""


def run_extensions() -> list[RunExtension]:
    """The installed extensions, in the entry points' name order."""
    from importlib.metadata import entry_points

    found = sorted(entry_points(group=ENTRY_POINT_GROUP), key=lambda e: e.name)
    out = []
    for entry in found:
        obj = entry.load()
        out.append(obj() if isinstance(obj, type) else obj)
    return out
