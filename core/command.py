"""How every command runs: user mistakes and failures as one line and an exit status, its outputs
checked before any work, its progress callback.

A command is ``main(argv)``: it parses its arguments (:class:`~qube_koopman.core.cli.OneLineParser`,
:func:`~qube_koopman.core.cli.add_standard_options`) and hands its work to :func:`run_command`; the
work raises :class:`CliError` for what the user must fix (or with ``status=1``, a failure at run
time) and returns the exit status otherwise.
"""

from __future__ import annotations

import json
import math
import os
import sys
import warnings
from collections.abc import Callable
from pathlib import Path

from qube_koopman.core.console import ProgressCallback, configure_logging
from qube_koopman.core.files import (
    atomic_path,
    output_file_problem,
    output_folder_problem,
)
from qube_koopman.core.signals import interrupted_status, sigterm_as_interrupt

__all__ = [
    "CliError",
    "check_output_file",
    "check_output_folder",
    "check_rerun_target",
    "output_dir",
    "progress",
    "run_command",
    "write_json",
]


class CliError(Exception):
    """A user mistake (exit status 2), or with ``status=1`` a failure at run time such as a write error.

    Printed as one line, no traceback.

    Parameters
    ----------
    message : str
        The problem, naming the file first when there is one.
    status : int, default 2
        The exit status: 2 for a user mistake, 1 for a run-time failure.
    """

    def __init__(self, message: str, status: int = 2) -> None:
        super().__init__(message)
        self.status = status


def _error(prog: str, message: str) -> None:
    """Print ``<prog>: error: <message>`` to stderr."""
    print(f"{prog}: error: {message}", file=sys.stderr)


#: Folders :func:`output_dir` created in this process: a command that stops before it has written
#: anything there removes them again (:func:`run_command`), not leaving empty folders behind.
_created: list[Path] = []


def output_dir(path: str | Path) -> Path:
    """Create the output folder (and parents); a clear error when that is impossible."""
    path = Path(path)
    missing = [p for p in (path, *path.parents) if not p.exists()]
    try:
        path.mkdir(parents=True, exist_ok=True)
        _created.extend(missing)  # deepest first
    except OSError as exc:
        raise CliError(f"{path}: cannot create output folder: {exc.strerror or exc}") from None
    if not path.is_dir():
        raise CliError(f"{path}: exists and is not a folder")
    return path


def check_output_file(path: str | Path | None, option: str = "--out", force: bool = False) -> None:
    """Refuse, before any work, an output file that cannot be written: its folder missing or not
    writable, the name taken by a folder, or an existing file without ``--force`` (a user error:
    exit 2, the file named). ``None`` (the option not given) passes."""
    if path is None:
        return
    if Path(path).is_dir():
        raise CliError(f"{path}: is a folder; {option} names the file to write")
    problem = output_file_problem(path, force=force)
    if problem:
        raise CliError(f"{problem} ({option})")


def check_output_folder(
    path: str | Path | None, files: tuple[str, ...] = (), option: str = "--out", force: bool = False
) -> None:
    """Refuse, before any work, an output folder that cannot take the command's ``files``: not a
    folder, not writable, or one of ``files`` there already without ``--force`` (exit 2).
    ``None`` (the option not given) passes."""
    if path is None:
        return
    problem = output_folder_problem(path, force=force, files=files)
    if problem:
        raise CliError(f"{problem} ({option})")


def check_rerun_target(path: str | Path | None, option: str = "--rerun", force: bool = False) -> None:
    """Refuse ``option FILE.rrd`` before any work: rerun-sdk not installed (status 1), no such
    folder, or (without ``force``) the file exists.

    Raises
    ------
    CliError
        Saying how to install the optional viewer, or naming the missing folder.
    """
    import importlib.util

    if path is None:
        return
    if importlib.util.find_spec("rerun") is None:
        raise CliError(f'{option} needs rerun-sdk, which is optional: pip install "qube-koopman[viz]"', status=1)
    check_output_file(path, option, force)


def _standard(value):
    """Non-finite floats as the strings "inf", "-inf", "nan": strict JSON has no such numbers."""
    if isinstance(value, float) and not math.isfinite(value):
        return "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf")
    if isinstance(value, dict):
        return {str(k): _standard(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_standard(v) for v in value]
    if hasattr(value, "item") and getattr(value, "ndim", None) == 0:  # numpy scalars
        return _standard(value.item())
    return value


def write_json(path: Path, data, *, shown: str | Path | None = None) -> None:
    """Write strict JSON (non-finite numbers as strings), whole file then rename.

    ``shown`` is the file an error names (default ``path``): the final name of a staged file.
    """
    text = json.dumps(_standard(data), indent=2, allow_nan=False) + "\n"
    try:
        with atomic_path(path) as tmp:
            tmp.write_text(text)
    except OSError as exc:
        raise CliError(f"{shown or path}: cannot write: {exc.strerror or exc}", status=1) from None


#: The ``progress(label, done, total)`` callback the library's long steps report to: a tqdm bar
#: on stderr, silent when stderr is not a terminal; :func:`run_command` silences it for ``-q``.
progress = ProgressCallback()


def run_command(prog: str, command: Callable, args, *, one_line_warnings: tuple[type[Warning], ...] = ()) -> int:
    """Run ``command(args)``: user mistakes and interruptions become one line and an exit status.

    Errors read ``<prog>: error: <problem>`` (the problem names the file first when there is
    one); a warning of one of the ``one_line_warnings`` categories (say, a log left out of the
    data) is one ``<prog>: warning: <message>`` line, each time it is raised; other warnings
    are Python's. Log lines go to stderr at the level ``-v``/``-q`` ask for; ``-q`` also
    silences the progress bars. Exit status: the command's, 2 for a user mistake
    (:class:`CliError`), 1 for a failure at run time (a :class:`CliError` saying so, or an
    ``OSError`` such as a full disk, named by its file), 130 when interrupted (Ctrl-C), 143
    when terminated (SIGTERM). A command that stops with an error or interrupted removes the
    output folders it created (:func:`output_dir`) and left empty.

    Parameters
    ----------
    prog : str
        The command's name, first on every line.
    command : callable
        ``command(args) -> int``, the command's work.
    args : argparse.Namespace
        The parsed arguments (``verbose``, ``quiet``; missing ones count as unset).
    one_line_warnings : tuple of Warning subclasses
        The categories shown as one ``<prog>: warning:`` line.

    Returns
    -------
    int
        The exit status.
    """
    configure_logging(prog, args)
    progress.enabled = not getattr(args, "quiet", False)
    default_show = warnings.showwarning

    def show(message, category, *rest, **kwargs):
        if issubclass(category, one_line_warnings):
            print(f"{prog}: warning: {message}", file=sys.stderr)
        else:
            default_show(message, category, *rest, **kwargs)

    del _created[:]
    status = 1
    try:
        with warnings.catch_warnings(), sigterm_as_interrupt():
            for category in one_line_warnings:
                warnings.simplefilter("always", category)
            warnings.showwarning = show
            status = command(args)
            return status
    except CliError as exc:
        _error(prog, str(exc))
        status = exc.status
        return status
    except KeyboardInterrupt as exc:
        _error(prog, "interrupted")
        status = interrupted_status(exc)  # 130 for Ctrl-C, 143 for SIGTERM
        return status
    except BrokenPipeError:
        # The reader went away (e.g. piped into `head`): nothing left to tell it.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1
    except OSError as exc:  # a write or read failing at run time (a full disk...): no traceback
        _error(prog, f"{exc.filename}: {exc.strerror}" if exc.filename and exc.strerror else str(exc))
        return 1
    finally:
        if status != 0:
            _remove_empty_created()


def _remove_empty_created() -> None:
    """Remove the folders :func:`output_dir` created that are still empty (deepest first)."""
    for folder in _created:
        try:
            folder.rmdir()  # only when empty: what the command wrote stays
        except OSError:
            pass
    del _created[:]
