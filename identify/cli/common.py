"""What the identification commands (qube-identify, qube-calibrate, qube-reproduce) and qube-design
share beyond the command toolkit (:mod:`qube_koopman.core.command`): their one-line warnings and
the logs named on their command lines."""

from __future__ import annotations

from pathlib import Path

from qube_koopman.core.command import CliError
from qube_koopman.identify.data.logs import IncompleteLogSkipped
from qube_koopman.identify.metrics import DivergedPrediction

__all__ = ["ONE_LINE_WARNINGS", "expand_logs"]

#: The warnings these commands print as one ``<prog>: warning:`` line (``run_command``'s
#: ``one_line_warnings``): a log left out of the data (incomplete or unreadable), a test
#: prediction that diverged.
ONE_LINE_WARNINGS = (IncompleteLogSkipped, DivergedPrediction)


def expand_logs(items) -> list[Path]:
    """Log paths from the command line: files as given, folders as the ``.mcap`` logs in them (by name).

    Raises
    ------
    CliError
        An item that does not exist, or a folder without logs (the message names it).
    """
    from qube_koopman.identify.data.logs import find_logs

    paths = []
    for item in items or []:
        path = Path(item)
        if path.is_dir():
            found = find_logs(path)
            if not found:
                raise CliError(f"{path}: folder has no .mcap logs")
            paths.extend(found)
        elif path.is_file():
            paths.append(path)
        else:
            raise CliError(f"{path}: no such file or folder")
    return paths
