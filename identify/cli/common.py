"""What identify's own commands (qube-identify, qube-calibrate) share beyond the command toolkit
(:mod:`qube_koopman.core.command`): the logs named on their command lines (expanded in ``daq``, which
qube-compare uses too). What the applications
above identify share with them is in identify itself
(:mod:`~qube_koopman.identify.command_warnings`, :mod:`~qube_koopman.identify.report.figure_options`)."""

from __future__ import annotations

from qube_koopman.identify.data.logs import expand_logs

__all__ = ["expand_logs"]
