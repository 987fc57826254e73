"""The design blocks run as written: the README's example (record on the twin -> identify -> design
-> run) and the design page's cycle on the paper's data (identify -> design -> run -> identify).

The same check as tests/docs/test_readme.py (exit codes and quoted figures), in a file of its own: the
cycles are the longest blocks, and pytest-xdist (``--dist loadfile``) gives each file to one worker.
"""

from __future__ import annotations

import pytest
from readme_blocks import (
    BLOCK_SOURCES,
    REPO,
    block_id,
    blocks_running,
    run_block,
)

pytestmark = [pytest.mark.slow, pytest.mark.dataset]

DESIGN_BLOCKS = blocks_running("qube-design")


def test_the_readme_has_a_design_cycle_block():
    assert DESIGN_BLOCKS, "no README bash block runs qube-design"
    sources = {BLOCK_SOURCES[i] for i in DESIGN_BLOCKS}
    assert REPO / "README.md" in sources and REPO / "docs" / "design.md" in sources


@pytest.mark.parametrize("index", DESIGN_BLOCKS, ids=block_id)
def test_readme_design_block_runs_as_written(index, clone):
    run_block(index, clone)
