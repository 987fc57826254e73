"""The warnings the commands built on identify (qube-identify, qube-calibrate, qube-reproduce, qube-design)
print as one line: here, in identify, rather than in ``identify.cli``, since the applications above it share them."""

from __future__ import annotations

from qube_koopman.identify.data.logs import IncompleteLogSkipped
from qube_koopman.identify.metrics import DivergedPrediction
from qube_koopman.identify.model_selection.split import PaperSplitWarning
from qube_koopman.identify.model_selection.sweep import AlphaAtGridEdge

__all__ = ["ONE_LINE_WARNINGS"]

#: The warnings these commands print as one ``<prog>: warning:`` line (``run_command``'s
#: ``one_line_warnings``): a log left out of the data (incomplete or unreadable), a test
#: prediction that diverged, the paper's split given other than its logs, a sweep's best alpha at its grid's edge.
ONE_LINE_WARNINGS = (IncompleteLogSkipped, DivergedPrediction, PaperSplitWarning, AlphaAtGridEdge)
