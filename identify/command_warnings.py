"""The warnings the commands built on identify (qube-identify, qube-calibrate, qube-reproduce, qube-design)
print as one line: here, in identify, rather than in ``identify.cli``, since the applications above it share them."""

from __future__ import annotations

from qube_koopman.identify.data.logs import IncompleteLogSkipped
from qube_koopman.identify.metrics import DivergedPrediction

__all__ = ["ONE_LINE_WARNINGS"]

#: The warnings these commands print as one ``<prog>: warning:`` line (``run_command``'s
#: ``one_line_warnings``): a log left out of the data (incomplete or unreadable), a test
#: prediction that diverged.
ONE_LINE_WARNINGS = (IncompleteLogSkipped, DivergedPrediction)
