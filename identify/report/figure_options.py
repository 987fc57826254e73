"""The ``--figures`` options of ``qube-identify`` and ``qube-reproduce qube``: adding them, checking them before
any work, writing the figures they ask for (drawn by :mod:`~qube_koopman.identify.report.figures`).

Here, beside the figures, rather than in ``identify.cli``: the applications above identify share them."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Sequence

from qube_koopman.core.command import CliError

__all__ = ["FOLDER", "add_figure_options", "check_figure_options", "write_report_figures"]

#: The output folder's sub-folder the figures go to.
FOLDER = "figures"


def add_figure_options(parser: argparse.ArgumentParser, episodes: bool = True, report: str = "report.md"):
    """Add ``--figures`` (and ``--figure-episodes``) to ``parser``; returns their argument group."""
    group = parser.add_argument_group('figures (needs matplotlib: pip install "qube-koopman[figures]")')
    group.add_argument(
        "--figures",
        action="store_true",
        help=f"also write figures as PNG and PDF in OUT/{FOLDER}/, embedded in {report}",
    )
    if episodes:
        group.add_argument(
            "--figure-episodes",
            nargs="+",
            metavar="EPISODE",
            help="test episodes whose measured and predicted trajectories are drawn: 1-based "
            "positions among the test logs or their file names (default: the best and the "
            "worst scored)",
        )
    return group


def check_figure_options(args: argparse.Namespace, test_names: Sequence[str] | None = None) -> None:
    """Refuse figure options before any work: matplotlib missing (status 1), unknown episodes (status 2)."""
    from qube_koopman.identify.report.figures import FiguresUnavailable, choose_episodes, require_matplotlib

    wanted = getattr(args, "figure_episodes", None)
    for option, given in (("--figure-episodes", wanted), ("--figure-episode", getattr(args, "figure_episode", None))):
        if given and not args.figures:
            raise CliError(f"{option} chooses what --figures draws: add --figures")
    if not args.figures:
        return
    try:
        require_matplotlib()
    except FiguresUnavailable as exc:
        raise CliError(str(exc), status=1) from None
    if wanted and test_names is not None:
        try:
            choose_episodes(list(test_names), wanted, None)
        except ValueError as exc:
            raise CliError(str(exc)) from None


def write_report_figures(out: Path, specs) -> list[dict]:
    """Write ``specs`` in ``out/figures``; their entries for report.json (paths relative to ``out``)."""
    from qube_koopman.identify.report.figures import write_figures

    try:
        written = write_figures(specs, out / FOLDER)
    except OSError as exc:
        raise CliError(
            f"{exc.filename or out / FOLDER}: cannot write a figure: {exc.strerror or exc}", status=1
        ) from None
    return [
        {"png": f"{FOLDER}/{png.name}", "pdf": f"{FOLDER}/{png.stem}.pdf", "caption": spec.caption}
        for spec, png in zip(specs, written)
    ]
