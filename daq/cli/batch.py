"""Shared by the command-line tools that work through many files: the file list, a progress bar, the closing line."""

from __future__ import annotations

import sys
from pathlib import Path

__all__ = ["Progress", "expand_sources", "summarize"]


class Progress:
    """A bar on stderr counting files (tqdm; silent when stderr is not a terminal), and its messages."""

    def __init__(self, total: int, enabled: bool) -> None:
        from qube_koopman.core.console import progress_bar

        self.bar = progress_bar(total, unit="file", enabled=enabled and total > 0)

    def step(self, done: int, name: str) -> None:
        """Show that ``done`` files are through, the last being ``name``."""
        self.bar.set_postfix_str(name, refresh=False)
        self.bar.update(done - self.bar.n)
        if done >= self.bar.total:
            self.bar.close()

    def say(self, line: str) -> None:
        """Print ``line`` on stderr above the bar."""
        self.bar.write(line, file=sys.stderr)


def expand_sources(sources: list[str], suffix: str, problems: list[str]) -> list[Path]:
    """Files named on the command line, a folder standing for its ``*<suffix>`` files.

    A source that does not exist, or a folder without such files, is appended
    to ``problems`` as a message naming it. A file named twice (say, on its
    own and through its folder) is listed once.
    """
    files: list[Path] = []
    for source in sources:
        path = Path(source)
        if path.is_dir():
            found = sorted(path.glob(f"*{suffix}"))
            if not found:
                problems.append(f"{path}: folder holds no {suffix} files")
            files.extend(found)
        elif path.is_file():
            files.append(path)
        elif path.exists():  # a named pipe, a device: never read (it could block or never end)
            problems.append(f"{path}: not a regular file or folder")
        else:
            problems.append(f"{path}: no such file or folder")
    unique = {f.resolve(): f for f in reversed(files)}
    return [f for f in files if unique[f.resolve()] is f]


def summarize(done: str, n_done: int, n_total: int, noun: str, where: str, refused: int, problems: list[str]) -> int:
    """Print the closing line (e.g. ``imported 3 of 4 files into DIR; 1 refused``); return the exit status.

    The status is 2 when a source named on the command line does not exist or holds no such
    files (a usage error, as in every command; the other files still went through), else 1
    when a file was refused, else 0.
    """
    print(
        f"{done} {n_done} of {n_total} {noun}{'s' if n_total != 1 else ''} {where}"
        + (f"; {refused} refused" if refused else "")
        + (f"; {len(problems)} unusable source{'s' if len(problems) > 1 else ''}" if problems else "")
    )
    if problems:
        return 2
    return 0 if refused == 0 and n_done > 0 else 1
