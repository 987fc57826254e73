"""Files that appear only whole: a temporary file in the same folder, renamed into place when complete.

A command stopped by Ctrl-C, SIGTERM or an error while it writes leaves no partial file under
the final name (and no temporary file: it is removed on the way out); a reader sees either the
previous file or the new one, never a mixture, since the rename is atomic on POSIX file systems.
"""

from __future__ import annotations

import os
import secrets
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

__all__ = ["atomic_path"]


@contextmanager
def atomic_path(path: str | Path, overwrite: bool = True) -> Iterator[Path]:
    """A temporary path to write ``path``'s content to; renamed to ``path`` when the block ends normally.

    Parameters
    ----------
    path : str or Path
        The final file.
    overwrite : bool
        Replace an existing ``path``. When false, a file that appeared at ``path`` meanwhile is
        never clobbered: :class:`FileExistsError`.

    Yields
    ------
    Path
        A new, empty file beside ``path`` (hidden, with ``path``'s suffix, so writers that choose
        the format by the suffix still do); write it by name, as many times as needed. When
        ``path`` exists and is not a regular file (a device such as ``/dev/null``, a named pipe),
        ``path`` itself: there is nothing to replace, and renaming over it would replace the
        device with a file. A symbolic link is followed: the file it points to is replaced.

    Raises
    ------
    FileExistsError
        ``overwrite`` is false and ``path`` exists when the block ends.
    OSError
        The temporary file cannot be created (the folder is missing or read-only) or renamed.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> folder = pathlib.Path(tempfile.mkdtemp())
    >>> with atomic_path(folder / "a.txt") as tmp:
    ...     _ = tmp.write_text("whole")
    >>> (folder / "a.txt").read_text(), sorted(p.name for p in folder.iterdir())
    ('whole', ['a.txt'])
    """
    path = Path(path)
    if path.is_symlink():
        path = path.resolve()
    if path.exists() and not path.is_file():
        yield path
        return
    tmp = _new_file(path)
    try:
        yield tmp
        if overwrite:
            os.replace(tmp, path)
        else:
            try:
                os.link(tmp, path)  # fails if the file appeared meanwhile
            except FileExistsError:
                raise FileExistsError(f"{path}: file exists") from None
            except OSError:  # a file system without hard links
                if path.exists():
                    raise FileExistsError(f"{path}: file exists") from None
                os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def _new_file(path: Path) -> Path:
    """A new, empty hidden file beside ``path``, created as :func:`open` creates one.

    Mode 0666 less the umask (``tempfile.mkstemp`` makes 0600 whatever the umask, and the
    file keeps its mode when renamed into place), exclusively under a fresh random name.
    """
    for _ in range(100):
        tmp = path.with_name(f".{path.name}.{secrets.token_hex(4)}.part{path.suffix}")
        try:
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0), 0o666)
        except FileExistsError:
            continue
        os.close(fd)
        return tmp
    raise FileExistsError(f"{path}: no free temporary name beside it")
