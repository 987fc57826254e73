"""Every command block of the README runs as written, with the exit code it shows (issue 11).

Each ``bash`` block runs in a fresh folder laid out like a clone (``main/`` as the working
folder, ``../shared/datasets/qube_servo_20230828`` beside it), one line at a time through
bash, in order, so later lines see what earlier ones wrote. Every command line must show its
exit code in its comment (``# exit 0: ...``); the test compares. Install steps are not run
(the environment running the suite is the installed one): a line's leading
``pip install ... &&`` and ``tools/install_system_deps.sh &&`` are dropped, and the test
command itself (``python -m pytest``) is what ``.ci/run`` runs, so it is checked to be the
same line as there instead of being run again from inside the suite.
"""

from __future__ import annotations

import os
import re
import subprocess
from pathlib import Path

import pytest

pytestmark = [pytest.mark.slow, pytest.mark.dataset]

REPO = Path(__file__).resolve().parents[1]
EXIT = re.compile(r"#.*\bexit (\d+)\b")
INSTALL = re.compile(r"^(pip install [^&]*|tools/install_system_deps\.sh)\s*&&\s*")


def bash_blocks(text: str) -> list[list[tuple[int, str]]]:
    """The README's ``bash`` blocks: lists of (line number, command line), continuations joined."""
    blocks, current, pending = [], None, ""
    for number, line in enumerate(text.splitlines(), start=1):
        if current is None:
            if line.strip() == "```bash":
                current = []
            continue
        if line.strip() == "```":
            blocks.append(current)
            current = None
            continue
        if line.rstrip().endswith("\\"):
            pending += line.rstrip()[:-1] + " "
            continue
        if (pending + line).strip():
            current.append((number, pending + line))
        pending = ""
    return blocks


def expected_exit(line: str) -> int | None:
    match = EXIT.search(line)
    return None if match is None else int(match.group(1))


def runnable(line: str) -> str | None:
    """The part of a README line that the test runs (None: the suite's own command)."""
    command = line
    while INSTALL.match(command):
        command = INSTALL.sub("", command, count=1)
    return None if command.lstrip().startswith("python -m pytest") else command


BLOCKS = bash_blocks((REPO / "README.md").read_text())


def test_the_readme_has_command_blocks_and_each_line_shows_its_exit_code():
    assert len(BLOCKS) >= 4
    missing = [number for block in BLOCKS for number, line in block if expected_exit(line) is None]
    assert not missing, f"README lines without '# exit N' in their comment: {missing}"


def test_the_readme_test_command_is_what_ci_runs():
    ci = (REPO / ".ci" / "run").read_text().splitlines()[-1].strip()
    test_line = BLOCKS[0][1][1].split("#")[0].strip()
    assert ci == test_line


@pytest.fixture
def clone(tmp_path, qube_dataset):
    """A folder laid out like a fresh clone: main/ to work in, ../shared/datasets beside it."""
    datasets = tmp_path / "shared" / "datasets"
    datasets.mkdir(parents=True)
    (datasets / "qube_servo_20230828").symlink_to(qube_dataset.resolve(), target_is_directory=True)
    (tmp_path / "main").mkdir()
    return tmp_path / "main"


@pytest.mark.parametrize("index", range(len(BLOCKS)), ids=[f"block{i + 1}-line{b[0][0]}" for i, b in
                                                           enumerate(BLOCKS)])
def test_readme_block_runs_as_written(index, clone):
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    for number, line in BLOCKS[index]:
        command = runnable(line)
        if command is None:
            continue
        done = subprocess.run(["bash", "-c", command], cwd=clone, env=env, capture_output=True, text=True,
                              timeout=600, stdin=subprocess.DEVNULL)
        assert done.returncode == expected_exit(line), (
            f"README line {number}: {command!r} exited {done.returncode}, the README shows "
            f"{expected_exit(line)}\n--- stdout\n{done.stdout[-3000:]}\n--- stderr\n{done.stderr[-3000:]}")
