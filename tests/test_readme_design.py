"""The README's design-cycle block (run -> identify -> design -> run -> identify) runs as written.

The same check as tests/test_readme.py, in a file of its own: the cycle is the README's longest
block, and pytest-xdist (``--dist loadfile``) gives each file to one worker.
"""

from __future__ import annotations

import pytest
from readme_blocks import block_id, blocks_running, clone, run_block  # noqa: F401

pytestmark = [pytest.mark.slow, pytest.mark.dataset]

DESIGN_BLOCKS = blocks_running("qube-design")


def test_the_readme_has_a_design_cycle_block():
    assert DESIGN_BLOCKS, "no README bash block runs qube-design"


@pytest.mark.parametrize("index", DESIGN_BLOCKS, ids=block_id)
def test_readme_design_block_runs_as_written(index, clone):  # noqa: F811
    run_block(index, clone)
