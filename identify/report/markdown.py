"""Readable reports of an identification run."""

from __future__ import annotations

import math
from collections import Counter
from pathlib import Path

from qube_koopman.core.files import atomic_path


def format_number(value, spec: str) -> str:
    """``format(value, spec)``, with "-" for None and "inf"/"-inf" for infinities."""
    if value is None:
        return "-"
    if isinstance(value, float) and math.isinf(value):
        return "-inf" if value < 0 else "inf"
    return format(value, spec)


def _score_row(label: str, t: dict) -> str:
    return (
        f"| {label} | {format_number(t['r2_mean'], '.4f')} | {format_number(t['r2_std'], '.4f')} "
        f"| {format_number(t['nrmse_mean'], '.2f')} | {format_number(t['nrmse_std'], '.2f')} |"
    )


def _test_section(report: dict) -> list[str]:
    t = report["test"]
    lines = ["## Test scores", "", f"Protocol: {report.get('protocol', 'the paper’s')}.", ""]
    if t is None:
        return lines + ["No test episode was recorded under the what-if controller: nothing to score.", ""]
    plain = report.get("test_without_offsets")
    lines += [
        "| prediction | R^2 mean | R^2 std | NRMSE mean (%) | NRMSE std (%) |",
        "|---|---|---|---|---|",
        _score_row("with estimated offsets" if plain else "as identified", t),
    ]
    if plain:
        lines.append(_score_row("without offsets, same samples", plain))
    scored = report.get("scored_logs", report["test_logs"])
    offsets = {e["log"]: e for e in report.get("offsets", [])}
    header = "| test episode | R^2 |" + (" R^2 without offsets | offsets (used?) |" if plain else "")
    lines += ["", header, "|---|---|" + ("---|---|" if plain else "")]
    for i, name in enumerate(scored):
        row = f"| {name} | {format_number(t['r2_per_episode'][i], '.4f')} |"
        if plain:
            e = offsets[name]
            values = ", ".join(
                f"{k} {v:+.5f}" + (f" ± {e[k + '_std_error']:.5f}" if e.get(k + "_std_error") else "")
                for k, v in e.items()
                if isinstance(v, float) and k not in ("rms_before", "rms_after") and not k.endswith("_std_error")
            )
            used = {
                "ok": "yes",
                "flat": "yes, but the cost is flat: poorly determined",
                "beyond bound": "NO: beyond the bound " + format(report["offset_bound"], "g"),
            }[e["status"]]
            row += f" {format_number(plain['r2_per_episode'][i], '.4f')} | {values} ({used}) |"
        lines.append(row)
    return lines


def _intervals_section(intervals: dict | None) -> list[str]:
    """The prediction intervals: pooled coverage, half-width and error per channel, and their calibration."""
    if not intervals or not intervals.get("pooled"):
        return []
    pooled, calibration = intervals["pooled"], intervals["calibration"]["channels"]
    source = (
        "the disturbance model's Kalman filter variance (no bootstrap refits)"
        if intervals.get("interval_method") == "disturbance"
        else f"{intervals['n_members']} bootstrap refits on the training episodes, the offsets' standard errors"
    )
    lines = [
        "",
        "## Prediction intervals",
        "",
        f"Every predicted sample's interval at level {intervals['level']:g}: {source}, and the model's error "
        f"calibrated on {intervals['n_folds']} groups of training episodes held out in turn (never the test "
        f"episodes). Method: {intervals.get('interval_method', 'bootstrap')} ({intervals.get('why', '')}). "
        f"Pooled over the scored test samples ({pooled['n_samples']}"
        + (
            f"; {pooled['n_infinite']} episode(s) with an infinite interval where a prediction diverged"
            if pooled["n_infinite"]
            else ""
        )
        + "):",
        "",
        (
            "| channel | coverage | worst episode | mean half-width (rad) | RMS error (rad) | calibrated factor k "
            "| model error sqrt(q) (rad) |"
        ),
        "|---|---|---|---|---|---|---|",
    ]
    for name in pooled["coverage"]:
        c = calibration[name]
        lines.append(
            f"| {name} | {format_number(pooled['coverage'][name], '.3f')} "
            f"| {format_number(pooled['worst_episode_coverage'][name], '.3f')} "
            f"| {format_number(pooled['mean_half_width'][name], '.4f')} "
            f"| {format_number(pooled['rms_error'][name], '.4f')} | {format_number(c['factor'], '.2f')} "
            f"| {format_number(c['scale'], '.4f')} |"
        )
    if pooled.get("n_probe_calibrated"):
        lines += [
            "",
            (
                f"{pooled['n_probe_calibrated']} scored episode(s) ran a loop the training did not (another "
                "controller): their model error is calibrated on the twin's probe episodes under other "
                "controllers, not on held-out training episodes."
            ),
        ]
    if pooled.get("n_uncalibrated_loop"):
        lines += [
            "",
            (
                f"{pooled['n_uncalibrated_loop']} scored episode(s) ran a loop the calibration's held-out "
                "episodes did not (another controller): the model's error there is unknown, and their "
                "intervals are the training loops'."
            ),
        ]
    return lines


def _why_it_won(search: dict) -> str:
    """One sentence: the winner's scores against the best cross-validated candidate's, and, where a
    candidate tied with it has the better objective, why it won over that one."""
    w, candidates = search["winner"], search["candidates"]
    if w.get("transfer_r2") is None:
        return "It has the best cross-validated R^2."
    top = max(candidates, key=lambda c: -math.inf if c.get("objective") is None else c["objective"])
    if top["label"] != w["label"] or top["alpha"] != w["alpha"]:
        return (
            f"{top['label']} (alpha {top['alpha']:g}) has the best objective, "
            f"{format_number(top['objective'], '.4f')}; the winner's is {format_number(w['objective_gap'], '.4f')} "
            f"lower, within {search.get('tie_standard_errors', 1):g} standard error(s) of the difference "
            f"({format_number(w.get('objective_gap_se'), '.4f')}), so the two are tied, and of the "
            f"{sum(bool(c.get('tied_with_best')) for c in candidates)} tied candidates it transfers best: "
            f"transfer R^2 {format_number(w['transfer_r2'], '.4f')} against "
            f"{format_number(top['transfer_r2'], '.4f')}."
        )
    by_cv = max(candidates, key=lambda c: -math.inf if c["cv_r2"] is None else c["cv_r2"])
    if by_cv["label"] == w["label"] and by_cv["alpha"] == w["alpha"]:
        return "It has both the best objective and the best cross-validated R^2."
    return (
        f"The best cross-validated candidate, {by_cv['label']} (alpha {by_cv['alpha']:g}, CV R^2 "
        f"{format_number(by_cv['cv_r2'], '.4f')}), transfers worse: transfer R^2 "
        f"{format_number(by_cv['transfer_r2'], '.4f')} "
        f"(worst probe {format_number(by_cv['transfer_r2_worst'], '.3f')}) "
        f"against the winner's {format_number(w['transfer_r2'], '.4f')} "
        f"(worst {format_number(w['transfer_r2_worst'], '.3f')})."
    )


def _search_section(search: dict) -> list[str]:
    w = search["winner"]
    lines = [
        "",
        "## Lifting search",
        "",
        f"{len(search['candidates'])} candidates in {format_number(search['seconds'], '.0f')} s, "
        f"{_folds_phrase(search)} of the training episodes; "
        f"score: {search['score']}. Stages: {', '.join(search['stages'])}."
        + (
            " Every stage scored its candidates with per-episode offsets (the training logs ran several "
            "controllers: scored without them, a loop that amplifies the encoder zeros ranks liftings by the "
            "zeros; `offsets_first = false` in a --search-space file scores as with one controller)."
            if search.get("offsets_first")
            else ""
        ),
        "",
        f"Ranked by {search.get('objective', 'the cross-validated R^2')}"
        + (f"; {search['selection']}." if search.get("selection") else ".")
        + (f" Transfer probes: {search['transfer']}." if search.get("transfer") else ""),
        "",
        f"Winner: **{w['label']}**, alpha {w['alpha']:g}, cross-validated R^2 {format_number(w['cv_r2'], '.4f')}"
        + (f", transfer R^2 {format_number(w['transfer_r2'], '.4f')}" if w.get("transfer_r2") is not None else "")
        + f". {_why_it_won(search)}"
        + (f" Refit by hand with `qube-identify ... {w['flags']}`." if w.get("flags") else "")
        + _same_controller_phrase(search.get("same_controller"), w),
        "",
        "| rank | stage | lifting | features | alpha | CV R^2 | CV R^2 std | transfer R^2 | worst probe "
        "| objective | gap to the best (SE) | seconds |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for i, c in enumerate(search["candidates"], start=1):
        lines.append(
            f"| {i} | {c['stage']} | {c['label']} | {c['n_features']} | {c['alpha']:g} "
            f"| {format_number(c['cv_r2'], '.4f')} | {format_number(c['cv_r2_std'], '.4f')} "
            f"| {format_number(c.get('transfer_r2'), '.4f')} "
            f"| {format_number(c.get('transfer_r2_worst'), '.3f')} "
            f"| {format_number(c.get('objective', c['cv_r2']), '.4f')} "
            f"| {_gap(c)} "
            f"| {format_number(c['seconds'], '.1f')} |"
        )
    return lines + _screened_lines(search)


def _gap(candidate: dict) -> str:
    """A candidate's objective below the best one's and the standard error of that gap, marked when tied."""
    gap = candidate.get("objective_gap")
    if gap is None:
        return "-"
    tied = ", tied" if candidate.get("tied_with_best") else ""
    return f"{gap:.4f} ({format_number(candidate.get('objective_gap_se'), '.4f')}{tied})"


def _screened_lines(search: dict) -> list[str]:
    """The candidates the search's screening left out, with their screen scores (none: no lines)."""
    screened = search.get("screened") or []
    if not screened:
        return []
    lines = [
        "",
        f"Screened out, not ranked ({search['screening']['description']}):",
        "",
        "| stage | lifting | features | alpha | screen CV R^2 | screen transfer R^2 | screen objective |",
        "|---|---|---|---|---|---|---|",
    ]
    for c in screened:
        lines.append(
            f"| {c['stage']} | {c['label']} | {c['n_features']} | {c['alpha']:g} "
            f"| {format_number(c['cv_r2'], '.4f')} | {format_number(c.get('transfer_r2'), '.4f')} "
            f"| {format_number(c.get('objective'), '.4f')} |"
        )
    bars = search["screening"].get("lead_screen_objective") or {}
    if bars:
        each = ", ".join(f"{stage} {format_number(bar, '.4f')}" for stage, bar in bars.items())
        lines += ["", f"The stage's lead scored as a screen (what a finalist's screen beat): {each}."]
    return lines


def _same_controller_phrase(same: dict | None, winner: dict) -> str:
    """With several training controllers: the winner's three scores side by side."""
    if not same:
        return ""
    each = ", ".join(f"controller {c['controller']} {format_number(c['cv_r2'], '.4f')}" for c in same["controllers"])
    transfer = winner.get("transfer_r2")
    return (
        f" Its scores side by side: same-controller R^2 {format_number(same['cv_r2'], '.4f')} ({each}; "
        f"{same['description']}), per-controller folds' R^2 {format_number(winner['cv_r2'], '.4f')}"
        + (
            f", twin transfer probes {format_number(transfer, '.4f')} (worst "
            f"{format_number(winner.get('transfer_r2_worst'), '.3f')})"
            if transfer is not None
            else ""
        )
        + "."
    )


def _folds_phrase(cv: dict) -> str:
    """The cross-validation's folds in words (reports written before training logs of several
    controllers were accepted have no ``cv_kind``)."""
    if cv.get("cv_kind") == "leave-one-controller-out":
        return f"{cv['cv_splits']} leave-one-controller-out folds (each holds out one training controller's episodes)"
    if cv.get("cv_kind") == "per-controller":
        return (
            f"{cv['cv_splits']} per-controller folds (as many for each training controller: one holding out all its "
            "episodes when the others are at least half of them, the others 20% of its episodes)"
        )
    return f"{cv['cv_splits']} episode-grouped splits (seed {cv['cv_seed']})"


def _folds_table(folds: list | None) -> list[str]:
    """Each fold's held-out episodes (or controller) and score at the chosen alpha."""
    if not folds:
        return []
    by_controller = "held_out_controller" in folds[0]
    lines = ["", "| fold | held out | training episodes | CV R^2 at the chosen alpha |", "|---|---|---|---|"]
    for f in folds:
        n = len(f["validation_logs"])
        held = f"controller {f['held_out_controller']} ({n} episodes)" if by_controller else f"{n} episodes"
        lines.append(f"| {f['fold']} | {held} | {f['n_train']} | {format_number(f.get('cv_r2'), '.4f')} |")
    return lines


def _session_delay_lines(sessions: dict | None) -> list[str]:
    """With --session-delays: each distinct extra command delay and how many logs have it."""
    if not sessions:
        return []
    counts = Counter(round(extra, 3) for extra in sessions["extra_ms"].values())
    each = ", ".join(f"{extra:g} ms ({n} log{'s' if n > 1 else ''})" for extra, n in sorted(counts.items()))
    return [
        f"- each log's loop is its recording session's (`--session-delays {sessions['plant']}`): its command "
        f"reached the motor this much later than in the session of least delay ({sessions['reference_ms']:.3g} ms): "
        f"{each}; report.json lists the logs"
    ]


def _controllers_lines(training: dict | None) -> list[str]:
    """The training controllers: how many, episodes each, whose closed loop the model is."""
    if not training:
        return []
    lines = [f"- training controllers: {training['n_controllers']} ({training['note']})"]
    for c in training["controllers"]:
        gains = ", ".join(f"{k} {v:g}" for k, v in (c.get("gains") or {}).items())
        lines.append(
            f"  - controller {c['controller']}: {c['n_episodes']} episodes"
            + (f", gains {gains}" if gains else "")
            + ("; the model's closed loop" if c["model_closed_loop"] else "")
        )
    return lines


def figures_markdown(figures: list[dict] | None) -> list[str]:
    """A "Figures" section embedding each figure (``png``, ``pdf``: paths relative to the report; ``caption``)."""
    if not figures:
        return []
    lines = ["", "## Figures", ""]
    for f in figures:
        lines += [f"![{Path(f['png']).stem}]({f['png']})", "", f"{f['caption']} ([PDF]({f['pdf']}))", ""]
    return lines


def markdown_report(report: dict) -> str:
    """report.json as a short markdown document."""
    rho = report.get("spectral_radius", {})
    t = report["test"]
    lines = [
        f"# Identification report: {report['method']}",
        "",
        f"- regularization alpha: {format_number(report.get('alpha'), 'g')}",
        f"- scoring: {'closed loop (r, f inputs)' if report['score'] == 'cl' else 'plant (u input)'}",
        f"- training episodes: {len(report['train_logs'])}; test episodes: {len(report['test_logs'])}"
        + (f" ({t['n_episodes']} scored)" if t else " (none scored)"),
        f"- spectral radius: closed loop {format_number(rho.get('closed_loop'), '.6f')}, "
        f"plant {format_number(rho.get('plant'), '.6f')}",
    ]
    lines += _controllers_lines(report.get("training_controllers"))
    what_if = report.get("what_if")
    if what_if:
        lines.append(
            f"- what-if controller: {what_if['note']}; {len(what_if['unscored_logs'])} episode(s) predicted "
            "without a recording to score against"
        )
    delay = report.get("command_delay")
    if delay and delay.get("estimated"):
        lines += _estimated_delay_lines(delay)
    elif delay:
        lines.append(
            f"- command delay: {delay['seconds'] * 1e3:g} ms ({delay['samples']:g} samples): {delay['note']} "
            f"(`--command-delay {delay['seconds'] * 1e3:g}`)"
        )
    lines += _session_delay_lines(report.get("session_delays"))
    lines += [""] + _test_section(report)
    lines += _intervals_section(report.get("intervals"))
    lines += _ahead_section(report.get("ahead"), report.get("disturbance"), t)
    sweep = report.get("sweep")
    if sweep:
        best = max(range(len(sweep["alpha"])), key=lambda i: sweep["cv_r2_mean"][i])
        lines += [
            "",
            "## Regularization sweep",
            "",
            f"{len(sweep['alpha'])} alphas from {sweep['alpha'][0]:g} to {sweep['alpha'][-1]:g}, "
            f"{_folds_phrase(sweep)}; best cross-validated R^2 "
            f"{format_number(sweep['cv_r2_mean'][best], '.4f')} at alpha {sweep['alpha'][best]:g}.",
        ]
        lines += _folds_table(sweep.get("folds"))
    if report.get("search"):
        lines += _search_section(report["search"])
    lines += figures_markdown(report.get("figures"))
    return "\n".join(lines) + "\n"


def _ahead_section(ahead: dict | None, disturbance: dict | None, test: dict | None) -> list[str]:
    """K-step predictions: R^2 and RMS error per horizon and channel, beside the free run; the disturbance model."""
    if not ahead or not ahead.get("horizons"):
        return []
    lines = ["", "## Predictions that use the measurements", ""]
    d = disturbance or {}
    costs = d.get("training_cost", {})
    better, n = d.get("episodes_better", {}), d.get("training_episodes")
    lines.append(
        f"Disturbance: {d.get('entry', 'none')} ({d.get('why', '')}). Training K-step cost (1 - R^2 summed over "
        "horizons and channels) by entry point: "
        + ", ".join(
            f"{k} {format_number(v, '.4g')}" + (f" (better on {better[k]} of {n} episodes)" if k in better else "")
            for k, v in costs.items()
        )
        + "."
    )
    by_pole = d.get("training_cost_by_pole", {}).get(d.get("entry"))
    if by_pole:
        lines.append(
            f"Its pole ({d.get('pole_choice', '')}), cost by pole: "
            + ", ".join(f"{p} {format_number(v, '.5g')}" for p, v in by_pole.items())
            + "."
        )
    if d.get("model"):
        m = d["model"]
        lines.append(
            f"Its {m['kind']} (pole {format_number(m['pole'], 'g')}) has q {format_number(m['q'], '.3g')} per "
            "sample and filter gain "
            f"[{', '.join(format_number(g, '.3g') for g in m['gain'])}] (theta, alpha)."
        )
    lines += [
        "",
        "| horizon | R^2 theta (worst) | R^2 alpha (worst) | RMS theta | RMS alpha |",
        "|---|---|---|---|---|",
    ]
    for label, h in ahead["horizons"].items():
        r2, worst, rms = h["r2_mean"], h["r2_worst"], h["rms_mean"]
        lines.append(
            f"| {label} s | {format_number(r2[0], '.4f')} ({format_number(worst[0], '.4f')}) | "
            f"{format_number(r2[1], '.4f')} ({format_number(worst[1], '.4f')}) | "
            f"{format_number(rms[0], '.4g')} | {format_number(rms[1], '.4g')} |"
        )
    if test:
        lines.append(f"| free run | R^2 mean {format_number(test.get('r2_mean'), '.4f')} (both channels) | | | |")
    lines += ["", ahead["note"] + "."]
    banded = {label: h["band"] for label, h in ahead["horizons"].items() if h.get("band")}
    if banded:
        lines += [
            "",
            "Their bands (the filter's variance, calibrated on held-out training episodes):",
            "",
            "| horizon | coverage theta (worst) | coverage alpha (worst) | half-width theta | half-width alpha |",
            "|---|---|---|---|---|",
        ]
        for label, b in banded.items():
            cov, worst, half = b["coverage"], b["worst_episode_coverage"], b["half_width"]
            lines.append(
                f"| {label} s | {format_number(cov[0], '.3f')} ({format_number(worst[0], '.3f')}) | "
                f"{format_number(cov[1], '.3f')} ({format_number(worst[1], '.3f')}) | "
                f"{format_number(half[0], '.4g')} | {format_number(half[1], '.4g')} |"
            )
    return lines


def _estimated_delay_lines(delay: dict) -> list[str]:
    """The estimated command delays of the test loops, grouped by value."""
    groups: dict[float, list[str]] = {}
    for entry in delay["logs"]:
        groups.setdefault(entry["seconds"] * 1e3, []).append(entry["log"])
    unestimated = [e["log"] for e in delay["logs"] if e["raw_samples"] is None]
    parts = [f"{ms:g} ms: {len(logs)} log(s)" for ms, logs in sorted(groups.items())]
    return [
        f"- command delay of the test loops, estimated (`--command-delay estimate`): {'; '.join(parts)}"
        + (f"; {len(unestimated)} alone in their session, not estimated" if unestimated else "")
        + f". {delay['note'][0].upper()}{delay['note'][1:]}."
    ]


def write_markdown_report(path: str | Path, report: dict) -> None:
    """Write :func:`markdown_report` to ``path``."""
    with atomic_path(path) as tmp:
        tmp.write_text(markdown_report(report))
