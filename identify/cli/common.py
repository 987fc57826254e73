"""What identify's own commands (qube-identify, qube-calibrate) share beyond the command toolkit
(:mod:`qube_koopman.core.command`): the logs named on their command lines. What the applications
above identify share with them is in identify itself
(:mod:`~qube_koopman.identify.command_warnings`, :mod:`~qube_koopman.identify.report.figure_options`)."""

from __future__ import annotations

from pathlib import Path

from qube_koopman.core.command import CliError

__all__ = ["expand_logs"]


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
