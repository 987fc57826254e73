"""Text renderings of the reproduction results (terminal table, markdown)."""

from __future__ import annotations

from qube_koopman.identify.report.markdown import figures_markdown
from qube_koopman.identify.report.markdown import format_number as _num


def qube_table(results: dict, markdown: bool = False) -> str:
    """The test table, ours beside the paper's, as text or markdown."""
    head = ["row", "alpha", "R2 mean", "R2 std", "NRMSE %", "NRMSE std", "paper R2", "paper NRMSE %"]
    lines = []
    for key, row in results["rows"].items():
        paper = results["paper"].get(key, {})
        lines.append(
            [
                results["labels"][key],
                _num(row["alpha"], ".3g"),
                _num(row["r2_mean"], ".3f"),
                _num(row["r2_std"], ".3f"),
                _num(row["nrmse_mean"], ".2f"),
                _num(row["nrmse_std"], ".2f"),
                _num(paper.get("r2_mean"), ".3f"),
                _num(paper.get("nrmse_mean"), ".1f"),
            ]
        )
    if markdown:
        out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        out += ["| " + " | ".join(line) + " |" for line in lines]
        return "\n".join(out)
    widths = [max(len(str(c)) for c in col) for col in zip(head, *lines)]
    fmt = "  ".join(f"{{:<{w}}}" if i == 0 else f"{{:>{w}}}" for i, w in enumerate(widths))
    return "\n".join(fmt.format(*line) for line in [head] + lines)


def qube_markdown(results: dict) -> str:
    """The whole report: table, checks, spectral radii, timing."""
    sweep = results["sweep"]
    cl = sweep["cl-edmd"]
    ed = sweep["edmd"]
    checks = "\n".join(f"- {'PASS' if ok else 'FAIL'}: {name}" for name, ok in results["checks"].items())

    def radii(label: str, method: dict) -> str:
        """One row of the spectral radii table."""
        closed, plant = method["spectral_radius_closed_loop"], method["spectral_radius_plant"]
        return f"| {label} | {min(closed):.6f} | {max(closed):.6f} | {plant[0]:.4f} | {plant[-1]:.4f} |"

    return (
        f"""# QUBE-Servo: paper section 5 reproduced

{results["n_train"]} training and {results["n_test"]} test episodes, the first {results["skip"]} samples
of each dropped; lifting: second-order monomials then delays; {len(sweep["alpha"])} alphas from
{sweep["alpha"][0]:g} to {sweep["alpha"][-1]:g}, three episode-grouped cross-validation splits.
Test scores are closed-loop predictions of theta and alpha over the test episodes.

{qube_table(results, markdown=True)}

## Checks

{checks}

## Spectral radii over the sweep

| | closed loop, min | closed loop, max | plant, at smallest alpha | plant, at largest alpha |
|---|---|---|---|---|
{radii("CL EDMD", cl)}
{radii("EDMD (wrapped)", ed)}

Computed in {results["timing_s"]:.1f} s.
"""
        + "\n".join(figures_markdown(results.get("figures")))
        + ("\n" if results.get("figures") else "")
    )
