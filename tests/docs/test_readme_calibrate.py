"""The calibration block of the documentation (import -> qube-calibrate -> replays on the calibrated
twin) runs as written.

The same check as tests/docs/test_readme.py (exit codes and quoted figures), in a file of its own: the
block is one of the longest, and pytest-xdist (``--dist loadfile``) gives each file to one worker.
"""

from __future__ import annotations

import pytest
from readme_blocks import block_id, blocks_running, run_block

pytestmark = [pytest.mark.slow, pytest.mark.dataset]

CALIBRATE_BLOCKS = blocks_running("qube-calibrate")


def test_the_readme_has_a_calibration_block():
    assert CALIBRATE_BLOCKS, "no README bash block runs qube-calibrate"


@pytest.mark.parametrize("index", CALIBRATE_BLOCKS, ids=block_id)
def test_readme_calibration_block_runs_as_written(index, clone):
    run_block(index, clone)
