"""Readable reports of an identification run."""

from __future__ import annotations

import math
from pathlib import Path


def format_number(value, spec: str) -> str:
    """``format(value, spec)``, with "-" for None and "inf"/"-inf" for infinities."""
    if value is None:
        return "-"
    if isinstance(value, float) and math.isinf(value):
        return "-inf" if value < 0 else "inf"
    return format(value, spec)


def markdown_report(report: dict) -> str:
    """report.json as a short markdown document."""
    t = report["test"]
    rho = report.get("spectral_radius", {})
    lines = [
        f"# Identification report: {report['method']}",
        "",
        f"- regularization alpha: {format_number(report.get('alpha'), 'g')}",
        f"- scoring: {'closed loop (r, f inputs)' if report['score'] == 'cl' else 'plant (u input)'}",
        f"- training episodes: {len(report['train_logs'])}; test episodes: {t['n_episodes']}",
        f"- spectral radius: closed loop {format_number(rho.get('closed_loop'), '.6f')}, plant {format_number(rho.get('plant'), '.6f')}",
        "",
        "## Test scores",
        "",
        "| R^2 mean | R^2 std | NRMSE mean (%) | NRMSE std (%) |",
        "|---|---|---|---|",
        f"| {format_number(t['r2_mean'], '.4f')} | {format_number(t['r2_std'], '.4f')} | {format_number(t['nrmse_mean'], '.2f')} "
        f"| {format_number(t['nrmse_std'], '.2f')} |",
        "",
        "| test episode | R^2 |",
        "|---|---|",
    ]
    lines += [f"| {name} | {format_number(r2, '.4f')} |" for name, r2 in zip(report["test_logs"], t["r2_per_episode"])]
    sweep = report.get("sweep")
    if sweep:
        best = max(range(len(sweep["alpha"])), key=lambda i: sweep["cv_r2_mean"][i])
        lines += ["", "## Regularization sweep", "",
                  f"{len(sweep['alpha'])} alphas from {sweep['alpha'][0]:g} to {sweep['alpha'][-1]:g}, "
                  f"{sweep['cv_splits']} episode-grouped splits; best cross-validated R^2 "
                  f"{format_number(sweep['cv_r2_mean'][best], '.4f')} at alpha {sweep['alpha'][best]:g}."]
    return "\n".join(lines) + "\n"


def write_markdown_report(path: str | Path, report: dict) -> None:
    """Write :func:`markdown_report` to ``path``."""
    Path(path).write_text(markdown_report(report))
