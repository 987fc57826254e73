"""The README's command blocks, read for tests/test_readme*.py.

Three test files share them so that pytest-xdist (``--dist loadfile``, a file to a worker) can
run the long blocks (the design cycle, the calibration) on other workers than the rest.
"""

from __future__ import annotations

import os
import re
import subprocess
from pathlib import Path

import pytest

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


def blocks_running(command: str) -> list[int]:
    """The indices of the blocks with a line that runs ``command``."""
    return [i for i, block in enumerate(BLOCKS) if any(command in line for _, line in block)]


#: Commands whose blocks are long and tested in files of their own (tests/test_readme_<name>.py).
OWN_FILES = ("qube-design", "qube-calibrate")
#: The other blocks (tests/test_readme.py).
OTHER_BLOCKS = [i for i in range(len(BLOCKS)) if not any(i in blocks_running(c) for c in OWN_FILES)]


def block_id(index: int) -> str:
    """A test id naming the block and its first line."""
    return f"block{index + 1}-line{BLOCKS[index][0][0]}"



@pytest.fixture
def clone(tmp_path, qube_dataset):
    """A folder laid out like a fresh clone: main/ to work in, ../shared/datasets beside it."""
    datasets = tmp_path / "shared" / "datasets"
    datasets.mkdir(parents=True)
    (datasets / "qube_servo_20230828").symlink_to(qube_dataset.resolve(), target_is_directory=True)
    (tmp_path / "main").mkdir()
    return tmp_path / "main"


def run_block(index: int, clone: Path) -> None:
    """Run the README's block ``index`` line by line in ``clone``; each line must exit as it shows."""
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
