"""Every command block of the README and of the documentation's pages runs as written, with the exit
code it shows and the figures its comments quote.

Each ``bash`` block runs in a fresh folder (a clone's root, with the paper's dataset named by
``$QUBE_DATASET_DIR``), one line at a time through bash, in order, so later lines see what earlier
ones wrote. Every command line must show its exit code in its comment (``# exit 0: ...``); the test
compares it, and finds each number the comment quotes in what the command printed
(tests/readme_blocks.py). Install steps are not run (the environment running the suite is the
installed one): a line's leading ``pip install ... &&`` and ``tools/install_system_deps.sh &&``
are dropped, and the test command itself (``python -m pytest``) is what ``.ci/run`` runs, so it
is checked to be the same line as there instead of being run again from inside the suite. The
blocks that run ``qube-design`` or ``qube-calibrate`` run in tests/docs/test_readme_design.py and
tests/docs/test_readme_calibrate.py.
"""

from __future__ import annotations

import pytest
from readme_blocks import (
    BLOCK_SOURCES,
    BLOCKS,
    OTHER_BLOCKS,
    REPO,
    block_id,
    blocks_of,
    expected_exit,
    run_block,
)

pytestmark = [pytest.mark.slow, pytest.mark.dataset]


def test_the_readme_has_command_blocks_and_each_line_shows_its_exit_code():
    assert len(BLOCKS) >= 4
    assert len(blocks_of(REPO / "README.md")) >= 2  # the two first commands, and the example end to end
    missing = [
        f"{BLOCK_SOURCES[i].relative_to(REPO)}:{number}"
        for i, block in enumerate(BLOCKS)
        for number, line in block
        if expected_exit(line) is None
    ]
    assert not missing, f"command lines without '# exit N' in their comment: {missing}"


def test_the_readme_test_command_is_what_ci_runs():
    assert BLOCK_SOURCES[0] == REPO / "README.md"
    ci = (REPO / ".ci" / "run").read_text().splitlines()[-1].strip()
    test_line = BLOCKS[0][1][1].split("#")[0].strip()
    assert ci == test_line


@pytest.mark.parametrize("index", OTHER_BLOCKS, ids=block_id)
def test_readme_block_runs_as_written(index, clone):
    run_block(index, clone)
