"""Shared command-line plumbing (sim.cli.common): every command answers --version."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("module, prog", [("daq.cli.run", "qube-run"), ("daq.cli.import_csv", "qube-import"),
                                          ("sim.cli.emulate", "qube-emulate"),
                                          ("identify.cli.reproduce", "qube-reproduce")])
def test_version(module, prog):
    from sim.cli.common import package_version

    proc = subprocess.run([sys.executable, "-m", module, "--version"], capture_output=True, text=True,
                          cwd=REPO, timeout=60)
    assert proc.returncode == 0 and proc.stdout == f"{prog} {package_version()}\n", proc.stderr
    assert package_version() != ""


@pytest.mark.parametrize("terminal", [True, False])
def test_the_progress_callback_draws_on_a_terminal_only(terminal, capsys, monkeypatch):
    from sim.cli.common import ProgressCallback

    monkeypatch.setattr(sys.stderr, "isatty", lambda: terminal)
    progress = ProgressCallback()
    for done in range(4):
        progress("cross-validation", done, 3)
    progress("alpha sweep", 1, 2)  # a new label: a new bar
    progress.close()
    err = capsys.readouterr().err
    if terminal:
        assert "cross-validation" in err and "3/3" in err and "alpha sweep" in err and "1/2" in err
    else:
        assert err == ""
