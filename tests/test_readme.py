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

import pytest
from readme_blocks import BLOCKS, OTHER_BLOCKS, REPO, block_id, clone, expected_exit, run_block  # noqa: F401

pytestmark = [pytest.mark.slow, pytest.mark.dataset]


def test_the_readme_has_command_blocks_and_each_line_shows_its_exit_code():
    assert len(BLOCKS) >= 4
    missing = [number for block in BLOCKS for number, line in block if expected_exit(line) is None]
    assert not missing, f"README lines without '# exit N' in their comment: {missing}"


def test_the_readme_test_command_is_what_ci_runs():
    ci = (REPO / ".ci" / "run").read_text().splitlines()[-1].strip()
    test_line = BLOCKS[0][1][1].split("#")[0].strip()
    assert ci == test_line


@pytest.mark.parametrize("index", OTHER_BLOCKS, ids=block_id)
def test_readme_block_runs_as_written(index, clone):  # noqa: F811
    run_block(index, clone)
