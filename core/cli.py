"""The command-line pieces every command shares and no package owns."""

from __future__ import annotations

import argparse
from typing import Any

__all__ = ["OneLineParser", "add_force_option", "add_renamed_option"]


class OneLineParser(argparse.ArgumentParser):
    """An argument parser whose usage errors are one line: ``<prog>: error: <problem> (see <prog> --help)``.

    argparse's default prints the whole usage block (5-17 lines in these commands) before the
    error; the exit status stays argparse's 2. Subcommands' parsers are of the same class.
    """

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def add_force_option(parser) -> None:
    """``--force``, the one switch (the same in every command) that lets existing output files be replaced.

    Without it a command refuses an output file that exists, before any work
    (``qube_koopman.core.files.output_file_problem``).
    """
    parser.add_argument("--force", action="store_true",
                        help="replace output files that exist (without it the command refuses them)")


def add_renamed_option(parser, old: str, new: str, why: str) -> None:
    """Refuse ``old`` (an option's earlier name) in one line that gives ``new``, hidden from ``--help``.

    Without it argparse would take ``old`` as an abbreviation of any longer option it begins, or
    call it ambiguous, and the user would not learn the name.
    """

    class _Renamed(argparse.Action):
        def __call__(self, parser: argparse.ArgumentParser, namespace: Any, values: Any, option_string=None):
            parser.error(f"{old} is now {new} ({why})")

    parser.add_argument(old, nargs="?", action=_Renamed, help=argparse.SUPPRESS)
