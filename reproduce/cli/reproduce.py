"""``qube-reproduce``: the paper's results, recomputed and printed beside the paper's values."""

from __future__ import annotations

import argparse
import math
import sys

from qube_koopman.core.cli import OneLineParser, add_force_option, add_standard_options, path, seed, whole_number
from qube_koopman.core.command import CliError, check_output_folder, output_dir, progress, run_command, write_json
from qube_koopman.core.files import atomic_path
from qube_koopman.identify.command_warnings import ONE_LINE_WARNINGS
from qube_koopman.identify.report.figure_options import check_figure_options, write_report_figures

PROG = "qube-reproduce"

DESCRIPTION = """\
Reproduce the closed-loop Koopman paper's results.

  duffing   Section 4: a simulated Duffing oscillator under PI control. Fits
            EDMD, CL EDMD, ARX and CL ARX with the paper's settings, prints the
            normalized mean and RMS plant errors on the test episode beside the
            paper's table, and writes OUT/duffing.json.
  qube      Section 5: the QUBE-Servo regularization study and test table from
            the imported episode logs (qube-import), beside the paper's values;
            writes OUT/qube.json and OUT/qube.md (with --figures, the paper's
            QUBE figures in OUT/figures/, embedded in qube.md). Unreadable or
            incomplete logs are skipped with a warning naming each (--strict: refused).
"""


def _parser() -> argparse.ArgumentParser:
    from qube_koopman.identify.report.figure_options import add_figure_options

    parser = OneLineParser(prog=PROG, description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_standard_options(parser)
    sub = parser.add_subparsers(dest="experiment", required=True, metavar="EXPERIMENT")
    duffing = sub.add_parser(
        "duffing",
        help="paper section 4 (simulated Duffing oscillator)",
        description="Paper section 4: simulate the Duffing experiment, fit four models, "
        "score their plant predictions on the noise-free test episode.",
    )
    duffing.add_argument(
        "--out",
        type=path,
        default="results",
        metavar="DIR",
        help="folder for duffing.json (created if missing; default: %(default)s)",
    )
    duffing.add_argument(
        "--seed",
        type=seed,
        default=1234,
        help="seed of the whole experiment: references, noise, RBF centres (default: %(default)s)",
    )
    duffing.add_argument(
        "--alpha",
        type=float,
        default=None,
        metavar="A",
        help="Tikhonov coefficient of EDMD and CL EDMD (default: 1e-6, numerically zero; "
        "the paper's exact 0 is ill-posed for its collinear RBF features)",
    )
    qube = sub.add_parser(
        "qube",
        help="paper section 5 (the real QUBE-Servo dataset)",
        description="Paper section 5 from the 48 imported episode logs: 180-alpha "
        "regularization study with cross-validation, the four method/scoring "
        "combinations, closed-loop ARX, and a row beyond the paper.",
    )
    qube.add_argument(
        "--data",
        type=path,
        required=True,
        metavar="DIR",
        help="folder with the imported .mcap logs (qube-import DATASET_DIR --out DIR, DATASET_DIR the paper's CSV "
        "folder)",
    )
    qube.add_argument(
        "--out",
        type=path,
        default="results",
        metavar="DIR",
        help="folder for qube.json and qube.md (default: %(default)s)",
    )
    qube.add_argument(
        "--n-alphas",
        type=int,
        default=180,
        metavar="N",
        help="alphas in the study, log-spaced 1e-3..1e3 (default: %(default)s)",
    )
    qube.add_argument(
        "--n-jobs",
        type=int,
        default=-1,
        metavar="N",
        help="worker processes for the regularization sweeps (default: one per core; 1: none)",
    )
    qube.add_argument(
        "--strict", action="store_true", help="refuse unreadable or incomplete logs in --data instead of skipping them"
    )
    group = add_figure_options(qube, episodes=False, report="qube.md")
    group.add_argument(
        "--figure-episode",
        type=whole_number(1),
        metavar="N",
        help="the test episode (1-based, of the 20) whose inputs and prediction errors are drawn (default 1)",
    )
    for experiment in (duffing, qube):
        add_force_option(experiment)
        add_standard_options(experiment, subcommand=True)
    return parser


def _qube(args) -> int:
    import warnings
    from pathlib import Path

    from qube_koopman.identify.data.logs import IncompleteLogSkipped
    from qube_koopman.reproduce.qube_study import reproduce_qube
    from qube_koopman.reproduce.qube_tables import qube_markdown, qube_table

    if not Path(args.data).is_dir():
        raise CliError(f"--data {args.data}: no such folder")
    if args.n_alphas < 2:
        raise CliError(f"--n-alphas must be at least 2, got {args.n_alphas}")
    if args.n_jobs == 0 or args.n_jobs < -1:
        raise CliError(f"--n-jobs must be -1 (every core) or at least 1, got {args.n_jobs}")
    check_figure_options(args)
    check_output_folder(args.out, ("qube.json", "qube.md"), force=args.force)
    out = output_dir(args.out)
    try:
        with warnings.catch_warnings():
            if args.strict:  # the first log load_logs would skip stops the study instead
                warnings.simplefilter("error", IncompleteLogSkipped)
            results = reproduce_qube(
                args.data,
                n_alphas=args.n_alphas,
                progress=progress,
                n_jobs=args.n_jobs,
                figure_episode=(args.figure_episode or 1) - 1 if args.figures else None,
            )
    except IncompleteLogSkipped as exc:
        raise CliError(f"{str(exc).removesuffix('; skipped')}; refused because of --strict") from None
    except ValueError as exc:
        raise CliError(str(exc)) from None
    print(qube_table(results))
    for name, ok in results["checks"].items():
        print(f"{'PASS' if ok else 'FAIL'}  {name}")
    print(f"computed in {results['timing_s']:.1f} s")
    if args.figures:
        from qube_koopman.reproduce.qube_figures import qube_figures

        results["figures"] = write_report_figures(out, qube_figures(results))
        episode = results.pop("figure_episode")  # arrays: drawn, not written to qube.json
        results["figure_episode"] = {"name": episode["name"], "index": episode["index"]}
    write_json(out / "qube.json", results)
    try:
        with atomic_path(out / "qube.md") as tmp:
            tmp.write_text(qube_markdown(results))
    except OSError as exc:
        raise CliError(f"{out / 'qube.md'}: cannot write: {exc.strerror or exc}", status=1) from None
    print(f"wrote {out / 'qube.json'} and {out / 'qube.md'}")
    return 0


def _duffing(args) -> int:
    from qube_koopman.reproduce.duffing_study import DEFAULT_ALPHA, PAPER_DUFFING, reproduce_duffing

    alpha = DEFAULT_ALPHA if args.alpha is None else args.alpha
    if not 0 <= alpha < math.inf:  # inf reached the fit as a traceback
        raise CliError(f"--alpha must be a finite number >= 0, got {args.alpha}")
    check_output_folder(args.out, ("duffing.json",), force=args.force)
    out = output_dir(args.out)
    results = reproduce_duffing(seed=args.seed, alpha=alpha)
    names = {"edmd": "EDMD", "cl_edmd": "CL EDMD", "arx": "ARX", "cl_arx": "CL ARX"}
    print(f"Duffing oscillator, seed {args.seed}, alpha {alpha:g}: plant errors on the test episode (%)")
    print(f"{'method':<10}{'mean (ours)':>13}{'mean (paper)':>14}{'RMS (ours)':>12}{'RMS (paper)':>13}")
    for key, label in names.items():
        ours, paper = results[key], PAPER_DUFFING[key]
        print(
            f"{label:<10}{ours['nme_pct']:>13.2f}{paper['nme_pct']:>14.1f}"
            f"{ours['nrmse_pct']:>12.2f}{paper['nrmse_pct']:>13.1f}"
        )
    results["paper"] = PAPER_DUFFING
    path = out / "duffing.json"
    write_json(path, results)
    print(f"wrote {path}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``qube-reproduce``; returns the exit status."""
    args = _parser().parse_args(argv)
    return run_command(
        PROG, lambda a: {"duffing": _duffing, "qube": _qube}[a.experiment](a), args, one_line_warnings=ONE_LINE_WARNINGS
    )


if __name__ == "__main__":
    sys.exit(main())
