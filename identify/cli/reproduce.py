"""``qube-reproduce``: the paper's results, recomputed and printed beside the paper's values."""

from __future__ import annotations

import argparse
import os
import sys

from identify.cli.common import CliError, fail, output_dir, write_json

DESCRIPTION = """\
Reproduce the closed-loop Koopman paper's results.

  duffing   Section 4: a simulated Duffing oscillator under PI control. Fits
            EDMD, CL EDMD, ARX and CL ARX with the paper's settings, prints the
            normalized mean and RMS plant errors on the test episode beside the
            paper's table, and writes OUT/duffing.json.
"""


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="qube-reproduce", description=DESCRIPTION,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="experiment", required=True, metavar="EXPERIMENT")
    duffing = sub.add_parser("duffing", help="paper section 4 (simulated Duffing oscillator)",
                             description="Paper section 4: simulate the Duffing experiment, fit four models, "
                                         "score their plant predictions on the noise-free test episode.")
    duffing.add_argument("--out", default="results", metavar="DIR",
                         help="folder for duffing.json (created if missing; default: %(default)s)")
    duffing.add_argument("--seed", type=int, default=1234,
                         help="seed of the whole experiment: references, noise, RBF centres (default: %(default)s)")
    duffing.add_argument("--alpha", type=float, default=None, metavar="A",
                         help="Tikhonov coefficient of EDMD and CL EDMD (default: 1e-6, numerically zero; "
                              "the paper's exact 0 is ill-posed for its collinear RBF features)")
    return parser


def _duffing(args) -> int:
    from identify.reproduce.duffing import DEFAULT_ALPHA, PAPER_DUFFING, reproduce_duffing

    alpha = DEFAULT_ALPHA if args.alpha is None else args.alpha
    if not alpha >= 0:
        raise CliError(f"--alpha must be a non-negative number, got {args.alpha}")
    out = output_dir(args.out)
    results = reproduce_duffing(seed=args.seed, alpha=alpha)
    names = {"edmd": "EDMD", "cl_edmd": "CL EDMD", "arx": "ARX", "cl_arx": "CL ARX"}
    print(f"Duffing oscillator, seed {args.seed}, alpha {alpha:g}: plant errors on the test episode (%)")
    print(f"{'method':<10}{'mean (ours)':>13}{'mean (paper)':>14}{'RMS (ours)':>12}{'RMS (paper)':>13}")
    for key, label in names.items():
        ours, paper = results[key], PAPER_DUFFING[key]
        print(f"{label:<10}{ours['nme_pct']:>13.2f}{paper['nme_pct']:>14.1f}"
              f"{ours['nrmse_pct']:>12.2f}{paper['nrmse_pct']:>13.1f}")
    results["paper"] = PAPER_DUFFING
    path = out / "duffing.json"
    write_json(path, results)
    print(f"wrote {path}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``qube-reproduce``; returns the exit status."""
    args = _parser().parse_args(argv)
    try:
        return {"duffing": _duffing}[args.experiment](args)
    except CliError as exc:
        return fail(str(exc))
    except KeyboardInterrupt:
        return fail("interrupted")
    except BrokenPipeError:
        # The reader went away (e.g. piped into `head`): nothing left to tell it.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1


if __name__ == "__main__":
    sys.exit(main())
