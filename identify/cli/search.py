"""``qube-identify --search``: the lifting search's command-line side (space file, report)."""

from __future__ import annotations

import logging
import math
import os
import sys
import tomllib
from dataclasses import fields
from pathlib import Path

from qube_koopman.core.command import CliError, progress
from qube_koopman.core.files import loads_toml, read_bounded_text

_log = logging.getLogger(__name__)
_LISTS = {
    "delays": int,
    "poly": int,
    "rbf": int,
    "alphas": float,
    "const": bool,
    "trig": bool,
    "offsets": bool,
    "friction": bool,
}
#: Single values a space file may set: how many candidates of a screened stage are evaluated in full (0: all),
#: whether a finalist must beat the stage's lead scored as a screen, whether every stage scores with offsets,
#: and how many standard errors of the best objective tie (0: the best objective wins).
_NUMBERS = {"n_finalists": int, "screen_against_lead": bool, "offsets_first": bool, "tie_standard_errors": float}


#: The largest search-space file read (a few lists of numbers).
MAX_SPACE_BYTES = 2**20


def load_space(path: str | None):
    """The search space: the defaults, with the lists of a TOML file replacing theirs."""
    from qube_koopman.identify.model_selection.lifting_space import SearchSpace

    if path is None:
        return SearchSpace()
    try:
        text = read_bounded_text(path, MAX_SPACE_BYTES, "search space")
        data = loads_toml(text, path)
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise CliError(f"{path}: not a readable TOML search space ({exc})") from None
    except ValueError as exc:  # a FIFO, a device, too large or nested too deep: the message names the file
        raise CliError(str(exc)) from None
    unknown = set(data) - set(_LISTS) - set(_NUMBERS)
    if unknown:
        raise CliError(f"{path}: unknown search-space keys {sorted(unknown)}; known: {', '.join([*_LISTS, *_NUMBERS])}")
    values: dict = {}  # SearchSpace's fields, of several types
    for key, value in data.items():
        if key in _NUMBERS and _NUMBERS[key] is bool:
            if not isinstance(value, bool):
                raise CliError(f"{path}: {key} must be true or false")
            values[key] = value
            continue
        if key in _NUMBERS and _NUMBERS[key] is float:
            if not isinstance(value, (int, float)) or isinstance(value, bool) or not 0 <= value < float("inf"):
                raise CliError(f"{path}: {key} must be a number >= 0")
            values[key] = float(value)
            continue
        if key in _NUMBERS:
            if not isinstance(value, int) or isinstance(value, bool) or value < 0:
                raise CliError(f"{path}: {key} must be a whole number >= 0")
            values[key] = value
            continue
        kind = _LISTS[key]
        if (
            not isinstance(value, list)
            or not value
            or not all(
                isinstance(v, kind) or (kind is float and isinstance(v, int) and not isinstance(v, bool)) for v in value
            )
            or (kind is int and any(isinstance(v, bool) for v in value))
        ):
            raise CliError(f"{path}: {key} must be a non-empty list of {kind.__name__} values")
        values[key] = tuple(kind(v) for v in value)
    try:
        return SearchSpace(**values)
    except ValueError as exc:
        raise CliError(f"{path}: {exc}") from None


def probe_cache() -> Path:
    """Where the search keeps twin probe sets: ``$QUBE_KOOPMAN_PROBE_CACHE``, else the toolkit's
    cache folder's ``probes`` (:func:`qube_koopman.core.files.cache_root`)."""
    from qube_koopman.core.files import cache_root

    return Path(os.environ.get("QUBE_KOOPMAN_PROBE_CACHE") or cache_root() / "probes")


def search_space(args):
    """The space of ``--search-space`` (the defaults without it), with ``--no-screen``: no screening
    (every candidate evaluated in full)."""
    from dataclasses import replace

    space = load_space(args.search_space)
    return space if getattr(args, "screen", True) else replace(space, n_finalists=0)


def search_options(args):
    """The search's options from the command line's (parsed and checked) arguments."""
    from qube_koopman.identify.workflow import SearchOptions

    return SearchOptions(
        space=search_space(args),
        estimate_window=args.estimate_window,
        offset_bound=args.offset_bound,
        cv_splits=args.cv_splits,
        cv_seed=args.cv_seed,
        transfer=args.transfer,
        probe_cache=probe_cache() if args.probe_cache else None,
        rbf_seed=args.rbf_seed,
        n_jobs=args.n_jobs,
        scheduler=args.scheduler,
        security=args.security,
        worker_timeout=args.worker_timeout,
    )


def run_search(args, train, controller):
    """Run the search on the training logs (:func:`~qube_koopman.identify.workflow.run_search`); logs its
    time per stage and prints the winner's line."""
    from qube_koopman.identify.model_selection.ranking import TIMING_KEYS
    from qube_koopman.identify.workflow import run_search as search

    try:
        result = search(train, controller, search_options(args), progress=progress)
    except ValueError as exc:
        raise CliError(str(exc).replace("an estimation window of", "--estimate-window")) from None
    if result.probes is not None:
        _log.info("search: %d twin probe episodes simulated in %.1f s", result.probes.n_episodes, result.probe_seconds)
    _log.info(
        "search: time per stage (wall; candidates' statistics / fits / predictions / offsets / probe fits / "
        "probe scoring, summed over workers): %s",
        "; ".join(
            f"{stage} {t['wall']:.1f} s ({' / '.join(f'{t[k]:.1f}' for k in TIMING_KEYS)})"
            for stage, t in result.timing()["stages"].items()
        ),
    )
    for r in result.screened:
        _log.info(
            "search: %s screened out (%s): screen objective %s",
            r.stage,
            r.spec.label(),
            f"{r.score:.4f}" if math.isfinite(r.score) else "diverged",
        )
    best = result.winner
    transfer = "" if best.transfer_score is None else f", transfer R^2 {best.transfer_score:.4f}"
    screened = f" (and {len(result.screened)} screened out)" if result.screened else ""
    print(
        f"search: {len(result.candidates)} candidates{screened} in {result.seconds:.0f} s; "
        f"winner {best.spec.label()}, alpha {best.best_alpha:g}, cross-validated R^2 {best.cv_score:.4f}{transfer}",
        file=sys.stderr,
    )
    return result


def _same_controller_report(scores) -> dict | None:
    """The winner's same-controller folds: the mean, and each controller's mean and folds (1-based numbers)."""
    if not scores:
        return None
    by: dict[int, list[float]] = {}
    for label, r2 in scores:
        by.setdefault(label + 1, []).append(r2)
    return {
        "cv_r2": float(sum(r for _, r in scores) / len(scores)),
        "description": "folds holding out 20% of one controller's training episodes, trained on all the others",
        "controllers": [{"controller": c, "cv_r2": float(sum(v) / len(v)), "folds": v} for c, v in by.items()],
    }


OBJECTIVE = {
    "twin": (
        "the lower of the cross-validated R^2 (the training controller) and the transfer R^2 (the plant "
        "wrapped with each probe controller predicting the twin's probe episodes, with the candidate's "
        "offset protocol, scored from the same sample): a model must predict both the loop it was trained "
        "under and loops it was not"
    ),
    "none": "the cross-validated R^2 alone (it sees only the training controller)",
}


SCREENING = (
    "successive halving: each candidate of a screened stage is first scored on its first {folds} "
    "fold(s) over the alpha grid and probed at the alpha best there (its screen); the {k} best whose "
    "screens did not diverge{lead} are evaluated in full (the other folds and probe alphas added: the same "
    "scores as a full evaluation), the others are screened out and not ranked (--no-screen: all in full)"
)
SCREENING_LEAD = (
    " and, after the first stage, beat the stage's lead (the best candidate so far) scored on the same "
    "folds and probes (screen_against_lead = false in the --search-space file: the best whatever the lead)"
)


SELECTION = (
    "the candidates within {k} standard error(s) of the best objective are tied (the standard error of the "
    "paired difference over the folds, or over the probe episodes where the best one's transfer R^2 is the "
    "lower of its two); of them the one with the highest transfer R^2 wins (tie_standard_errors = 0 in a "
    "--search-space file: the best objective)"
)


def _ranked_report(result) -> list[dict]:
    """The candidates as ranked, each with its gap to the best objective, the gap's standard error and
    whether the two are tied (:meth:`~.SearchResult.tied`)."""
    from qube_koopman.identify.model_selection.ranking import objective_gap

    ranked, tied = result.ranked(), result.tied()
    best = tied[0] if tied else None
    out = []
    for r in ranked:
        entry = r.as_dict()
        if best is not None:
            gap, standard_error = objective_gap(best, r)
            entry["objective_gap"] = float(gap) if math.isfinite(gap) else None
            entry["objective_gap_se"] = float(standard_error) if math.isfinite(standard_error) else None
            entry["tied_with_best"] = any(r is t for t in tied)
        out.append(entry)
    return out


def search_report(result, args, names) -> dict:
    """The search's part of report.json (``names``: the training logs')."""
    from qube_koopman.identify.model_selection.split import FOLD_KINDS
    from qube_koopman.identify.model_selection.lifting_space import STAGES

    space = search_space(args)
    candidates = _ranked_report(result)
    return {
        "winner": {
            **candidates[0],
            "flags": " ".join(
                result.winner.spec.flags(args.rbf_seed)
                + ["--alpha", f"{result.winner.best_alpha:g}", "--estimate-window", f"{args.estimate_window:g}"]
                + (["--session-delays", str(args.session_delays)] if args.session_delays else [])
            ),
        },
        "candidates": candidates,
        "tie_standard_errors": result.tie_standard_errors,
        "selection": SELECTION.format(k=f"{result.tie_standard_errors:g}"),
        "screening": {
            "n_finalists": space.n_finalists,
            "screen_folds": space.screen_folds,
            "screen_against_lead": space.screen_against_lead,
            "stages": list(space.screened_stages) if space.n_finalists else [],
            "description": SCREENING.format(
                folds=space.screen_folds, k=space.n_finalists, lead=SCREENING_LEAD if space.screen_against_lead else ""
            )
            if space.n_finalists
            else "none: every candidate evaluated in full (--no-screen)",
            "lead_screen_objective": {stage: float(bar) for stage, bar in result.screen_bars.items()},
        },
        "screened": [r.as_dict() for r in result.screened],
        "stages": list(STAGES),
        "offsets_first": result.offsets_first,
        "space": {f.name: getattr(space, f.name) for f in fields(space) if f.name in _LISTS},
        "alphas": list(space.alphas),
        "cv_kind": result.folds.kind,
        "cv_description": FOLD_KINDS[result.folds.kind],
        "cv_splits": len(result.folds.splits),
        "cv_seed": None if result.folds.kind == "leave-one-controller-out" else args.cv_seed,
        "folds": result.folds.report(names, result.winner.cv_r2[:, result.winner.best_index]),
        "score": (
            f"mean R^2 of theta and alpha over each fold's validation episodes, closed-loop prediction "
            f"from the episode's start, scored from sample {result.window} on"
        ),
        "objective": OBJECTIVE[args.transfer],
        "transfer": None if result.probes is None else result.probes.describe(),
        "same_controller": _same_controller_report(result.same_controller),
        "seconds": result.seconds,
        "timing": result.timing(),
        "n_jobs": args.n_jobs,
        "scheduler": args.scheduler,
    }
