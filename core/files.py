"""Files that appear only whole: a temporary file in the same folder, renamed into place when complete.

A command stopped by Ctrl-C, SIGTERM or an error while it writes leaves no partial file under
the final name (and no temporary file: it is removed on the way out); a reader sees either the
previous file or the new one, never a mixture, since the rename is atomic on POSIX file systems.

A process killed outright (SIGKILL, a power cut) cannot remove its temporary file: the next write
of the same file removes it (:func:`remove_stale_parts`). Each writer holds its temporary file
under an advisory lock (``flock``) while it lives, so a temporary file another live process is
writing is never taken for a stale one.
"""

from __future__ import annotations

import errno
import json
import os
import secrets
import stat
import tomllib
import zipfile
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

try:
    import fcntl
except ImportError:  # not a POSIX system: temporary files are then never taken for stale
    fcntl = None  # type: ignore[assignment]  # mypy: a module or, here, None

__all__ = [
    "MAX_NESTING",
    "StagedFiles",
    "atomic_path",
    "cache_root",
    "check_nesting",
    "loads_json",
    "loads_toml",
    "npz_shapes",
    "output_file_problem",
    "output_folder_problem",
    "read_bounded_bytes",
    "read_bounded_text",
    "remove_stale_parts",
    "trim_cache",
]

#: The deepest nesting of lists and tables a file read by the toolkit may have: every format it
#: reads is a few levels deep, and a parser or writer that recurses must not be asked for more.
MAX_NESTING = 64

_KINDS = (
    (stat.S_ISFIFO, "a named pipe"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
)


def read_bounded_bytes(path: str | Path, max_bytes: int, what: str = "file") -> bytes:
    """The bytes of the regular file ``path``, refused before reading when it is larger than ``max_bytes``.

    A named pipe, a device or a socket is refused without waiting on it (opened non-blocking,
    checked on the open descriptor): reading one could block forever or never end.

    Parameters
    ----------
    path : str or Path
        The file.
    max_bytes : int
        The largest size accepted.
    what : str
        What the file is, for the message (``"controller file"``).

    Returns
    -------
    bytes
        The whole file.

    Raises
    ------
    ValueError
        Starting with the path: not a regular file, or larger than ``max_bytes``.
    OSError
        The file cannot be opened or read (missing, a folder, no permission), its
        ``filename`` the path.

    Examples
    --------
    >>> read_bounded_bytes("/dev/zero", 10, "controller file")
    Traceback (most recent call last):
    ...
    ValueError: /dev/zero: a character device, not a regular file: not read as the controller file
    """
    path = Path(path)
    with _open_regular(path, max_bytes, what) as file:
        data = file.read(max_bytes + 1)
    if len(data) > max_bytes:  # it grew meanwhile
        raise ValueError(f"{path}: grew past {max_bytes} bytes while read; the largest {what} read is that")
    return data


def _open_regular(path: Path, max_bytes: int, what: str):
    """``path`` opened for reading (binary, blocking) once checked to be a regular file of at most ``max_bytes``."""
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0))
    file = os.fdopen(fd, "rb")
    try:
        info = os.fstat(fd)
        if stat.S_ISDIR(info.st_mode):
            raise IsADirectoryError(errno.EISDIR, os.strerror(errno.EISDIR), str(path))
        if not stat.S_ISREG(info.st_mode):
            kind = next((name for test, name in _KINDS if test(info.st_mode)), "a special file")
            raise ValueError(f"{path}: {kind}, not a regular file: not read as the {what}")
        if info.st_size > max_bytes:
            raise ValueError(f"{path}: {info.st_size} bytes; the largest {what} read is {max_bytes} bytes")
        os.set_blocking(fd, True)
    except BaseException:
        file.close()
        raise
    return file


def read_bounded_text(path: str | Path, max_bytes: int, what: str = "file") -> str:
    """:func:`read_bounded_bytes` decoded as UTF-8 (:class:`UnicodeDecodeError` when it is not text)."""
    return read_bounded_bytes(path, max_bytes, what).decode("utf-8")


def check_nesting(value: Any, where: str | Path, max_depth: int = MAX_NESTING) -> Any:
    """``value`` (parsed JSON or TOML) unchanged, or a ValueError when it nests deeper than ``max_depth``.

    Walks the data with a stack of its own, never recursing, so any depth is measured.

    Examples
    --------
    >>> deep = []
    >>> for _ in range(100):
    ...     deep = [deep]
    >>> check_nesting(deep, "x.json")
    Traceback (most recent call last):
    ...
    ValueError: x.json: lists and tables nested more than 64 levels deep
    """
    stack = [(value, 1)] if isinstance(value, (dict, list, tuple)) else []
    while stack:
        item, depth = stack.pop()
        children = item.values() if isinstance(item, dict) else item
        if not any(issubclass(kind, (dict, list, tuple)) for kind in set(map(type, children))):
            continue  # a row of numbers or strings: the types of its entries, counted in C, say so
        for child in children:
            if isinstance(child, (dict, list, tuple)):
                if depth + 1 > max_depth:
                    raise _too_deep(where, max_depth)
                stack.append((child, depth + 1))
    return value


def _too_deep(where: str | Path, max_depth: int) -> ValueError:
    return ValueError(f"{where}: lists and tables nested more than {max_depth} levels deep")


def loads_json(text: str | bytes, where: str | Path, max_depth: int = MAX_NESTING) -> Any:
    """``json.loads(text)``, nesting bounded (:func:`check_nesting`), errors as :class:`ValueError`.

    A parse too deep for Python's stack is the same ValueError naming ``where``; a syntax error is
    :class:`json.JSONDecodeError` (a ValueError) as ``json.loads`` gives it.
    """
    try:
        value = json.loads(text)
    except RecursionError:
        raise _too_deep(where, max_depth) from None
    return check_nesting(value, where, max_depth)


def loads_toml(text: str, where: str | Path, max_depth: int = MAX_NESTING) -> dict:
    """``tomllib.loads(text)``, nesting bounded as :func:`loads_json`'s.

    Raises
    ------
    ValueError
        Naming ``where``: nested too deep.
    tomllib.TOMLDecodeError
        Not TOML.
    """
    try:
        value = tomllib.loads(text)
    except RecursionError:
        raise _too_deep(where, max_depth) from None
    return check_nesting(value, where, max_depth)


def npz_shapes(path: str | Path, max_bytes: int, what: str = ".npz file") -> dict[str, tuple[tuple[int, ...], Any]]:
    """The shape and dtype of each array of the ``.npz`` file ``path``, read from the headers alone.

    So that a small compressed file cannot make its reader allocate what its header declares
    before the size is checked: nothing is decompressed but each array's header.

    Parameters
    ----------
    path : str or Path
        The file (a regular file, at most ``max_bytes`` on disk, each array at most
        ``max_bytes`` once loaded).
    max_bytes : int
        The largest file, and the largest array it may declare.
    what : str
        What the file is, for the messages.

    Returns
    -------
    dict
        Array name -> (shape, dtype).

    Raises
    ------
    ValueError
        Starting with the path: not a regular file, too large, not an .npz, or an array larger
        than ``max_bytes``.
    OSError
        The file cannot be read.
    """
    import numpy as np

    path = Path(path)
    shapes = {}
    readers = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}
    with _open_regular(path, max_bytes, what) as file:  # a regular file of at most max_bytes, or a ValueError
        try:
            with zipfile.ZipFile(file) as archive:
                for name in archive.namelist():
                    with archive.open(name) as member:
                        version = np.lib.format.read_magic(member)
                        if version not in readers:
                            raise ValueError(f"array format version {version} is not read here")
                        shapes[name.removesuffix(".npy")] = readers[version](member)
        except (zipfile.BadZipFile, EOFError, KeyError, ValueError) as exc:
            raise ValueError(f"{path}: not a numpy .npz file ({exc})") from None
    out = {}
    for key, (shape, _, dtype) in shapes.items():
        if int(np.prod(shape, dtype=object)) * dtype.itemsize > max_bytes:
            shown = " x ".join(map(str, shape))
            raise ValueError(f"{path}: array {key} declares {shown} entries, more than the {what} may hold")
        out[key] = (tuple(shape), dtype)
    return out


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
    remove_stale_parts(path)
    fd, tmp = _new_file(path)
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
        os.close(fd)  # releases the lock


class StagedFiles:
    """Several files of one folder written under hidden names and moved into place together.

    A command whose outputs belong together (a model and its reports) writes each to
    :meth:`path` and calls :meth:`commit` once all are written: a failure before then (a full
    disk, a folder made read-only) leaves the folder as it was, none of the new files in it and
    the staged ones removed (on leaving the ``with`` block, or by :meth:`discard`).

    Parameters
    ----------
    folder : str or Path
        The existing folder the files go to.
    names : iterable of str
        The final names of the files.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> folder = pathlib.Path(tempfile.mkdtemp())
    >>> with StagedFiles(folder, ["a.json", "b.md"]) as staged:
    ...     _ = staged.path("a.json").write_text("{}")
    ...     _ = staged.path("b.md").write_text("# b")
    ...     staged.commit()
    >>> sorted(p.name for p in folder.iterdir())
    ['a.json', 'b.md']
    """

    def __init__(self, folder: str | Path, names) -> None:
        self.folder = Path(folder)
        token = secrets.token_hex(4)
        self._staged = {name: self.folder / f".{name}.{token}.staged{Path(name).suffix}" for name in names}

    def path(self, name: str) -> Path:
        """Where to write the file ``name`` until :meth:`commit`."""
        return self._staged[name]

    def final_path(self, filename: str | Path | None) -> Path | None:
        """The final file a staged path stands for (or :func:`atomic_path`'s temporary file beside it); else None."""
        if filename is None:
            return None
        given = Path(filename)
        for name, staged in self._staged.items():
            if given == staged or (given.parent == staged.parent and given.name.startswith(f".{staged.name}.")):
                return self.folder / name
        return None

    def commit(self) -> None:
        """Move every staged file that was written to its final name (replacing what was there)."""
        for name, staged in self._staged.items():
            if staged.exists():
                os.replace(staged, self.folder / name)

    def discard(self) -> None:
        """Remove the staged files not committed."""
        for staged in self._staged.values():
            staged.unlink(missing_ok=True)

    def __enter__(self) -> "StagedFiles":
        return self

    def __exit__(self, *exc) -> None:
        self.discard()


def _part_name(path: Path, tag: str) -> str:
    return f".{path.name}.{tag}.part{path.suffix}"


def _new_file(path: Path) -> tuple[int, Path]:
    """A new, empty hidden file beside ``path``, created as :func:`open` creates one, as ``(fd, path)``.

    Mode 0666 less the umask (``tempfile.mkstemp`` makes 0600 whatever the umask, and the
    file keeps its mode when renamed into place), exclusively under a fresh random name, and
    held under a shared ``flock`` until ``fd`` is closed: :func:`remove_stale_parts` takes only
    files no process holds. A cleaner that removed it in the instant between its creation and
    its lock is seen (the name no longer leads to it): another name is tried.
    """
    for _ in range(100):
        tmp = path.with_name(_part_name(path, secrets.token_hex(4)))
        try:
            fd = os.open(tmp, os.O_RDONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0), 0o666)
        except FileExistsError:
            continue
        if fcntl is not None:
            try:  # waits only while a cleaner holds it, an instant; then the name is checked below
                fcntl.flock(fd, fcntl.LOCK_SH)
            except OSError:  # a file system without locks: then never taken for stale either
                pass
        if _same_file(tmp, fd):
            return fd, tmp
        os.close(fd)
    raise FileExistsError(f"{path}: no free temporary name beside it")


def _same_file(path: Path, fd: int) -> bool:
    """Whether ``path`` still names the file open as ``fd``."""
    try:
        named, held = os.stat(path), os.fstat(fd)
    except FileNotFoundError:
        return False
    return (named.st_dev, named.st_ino) == (held.st_dev, held.st_ino)


def remove_stale_parts(path: str | Path) -> list[Path]:
    """Remove the temporary files of ``path`` that writers killed before their end left; return them.

    Only hidden ``.<name>.<tag>.part<suffix>`` regular files beside ``path`` (the names
    :func:`atomic_path` gives) are candidates, and of those only the ones no live process holds
    locked (every writer locks its temporary file as it creates it, and the lock goes with the
    process): a file another run is writing now is never removed, however old. Without ``fcntl``
    (not a POSIX system) nothing is removed; a file that cannot be removed is passed over.

    Parameters
    ----------
    path : str or Path
        The final file.

    Returns
    -------
    list of Path
        The files removed.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> folder = pathlib.Path(tempfile.mkdtemp())
    >>> _ = (folder / ".run.rrd.1a2b3c4d.part.rrd").write_bytes(b"RRF2")  # a writer killed mid-write
    >>> [p.name for p in remove_stale_parts(folder / "run.rrd")], sorted(folder.iterdir())
    (['.run.rrd.1a2b3c4d.part.rrd'], [])
    """
    path = Path(path)
    removed: list[Path] = []
    if fcntl is None or not path.parent.is_dir():
        return removed
    for tmp in sorted(path.parent.glob(_part_name(path, "*"))):
        try:
            fd = os.open(tmp, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0))
        except OSError:  # gone, a link, unreadable: not ours to judge
            continue
        try:
            if not stat.S_ISREG(os.fstat(fd).st_mode):
                continue
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)  # OSError: a live writer holds it
            if _same_file(tmp, fd):
                os.unlink(tmp)
                removed.append(tmp)
        except OSError:
            continue
        finally:
            os.close(fd)
    return removed


# The one rule every command follows for what it writes (checked before any work, so a mistake
# costs nothing): an output that cannot be written is a user error, and an existing file is
# replaced only when the user says so (--force). Each command turns the problem into its own
# one-line error, exit status 2.


def _writable_ancestor(path: Path) -> tuple[Path, bool]:
    """The nearest existing folder at or above ``path`` and whether new entries can be made in it."""
    for folder in (path, *path.parents):
        if folder.exists():
            return folder, folder.is_dir() and os.access(folder, os.W_OK | os.X_OK)
    return Path("."), os.access(".", os.W_OK | os.X_OK)


def output_folder_problem(path: str | Path, *, force: bool = False, files: tuple[str, ...] = ()) -> str | None:
    """Why the output folder ``path`` cannot take a command's output, or ``None`` when it can.

    Parameters
    ----------
    path : str or Path
        The folder (created, with its parents, when missing).
    force : bool
        Existing ``files`` may be replaced.
    files : tuple of str
        Names of the files the command writes there, checked against existing ones.

    Returns
    -------
    str or None
        The problem, starting with the path: not a folder, not writable, or a file that exists.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> folder = pathlib.Path(tempfile.mkdtemp())
    >>> _ = (folder / "model.json").write_text("{}")
    >>> output_folder_problem(folder / "new") is None
    True
    >>> output_folder_problem(folder, files=("model.json",)).endswith("exists (use --force to overwrite)")
    True
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        return f"{path}: exists and is not a folder"
    folder, writable = _writable_ancestor(path)
    if not folder.is_dir():
        return f"{path}: cannot create output folder: {folder} is not a folder"
    if not writable:
        return f"{path}: cannot write in {folder} (permission denied)"
    if not force:
        for name in files:
            if (path / name).exists():
                return f"{path / name}: exists (use --force to overwrite)"
    return None


def output_file_problem(path: str | Path, *, force: bool = False) -> str | None:
    """Why the output file ``path`` cannot be written, or ``None`` when it can.

    The file's folder must exist and be writable, the name must not be a folder, and an
    existing file is replaced only with ``force``.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> folder = pathlib.Path(tempfile.mkdtemp())
    >>> output_file_problem(folder / "x.toml") is None
    True
    >>> output_file_problem(folder / "missing" / "x.toml").endswith("does not exist")
    True
    """
    path = Path(path)
    folder = path.parent
    if path.is_dir():
        return f"{path}: is a folder, not a file"
    if not folder.is_dir():
        return f"{path}: folder {folder} does not exist"
    if not os.access(folder, os.W_OK | os.X_OK):
        return f"{path}: cannot write in {folder} (permission denied)"
    if path.exists() and not force and path.is_file():
        return f"{path}: exists (use --force to overwrite)"
    return None


def cache_root() -> Path:
    """The toolkit's cache folder: ``$XDG_CACHE_HOME/qube-koopman`` (``~/.cache/qube-koopman``).

    Builds of the bridge firmware and the search's twin probe sets are kept there; not created here.
    """
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "qube-koopman"


def trim_cache(folder: Path, pattern: str, max_bytes: int, keep: Path | None = None) -> list[Path]:
    """Delete the least recently used files matching ``pattern`` in ``folder`` until they hold at most ``max_bytes``.

    A cache's readers mark a file used by touching it (its modification time); the oldest go
    first. ``keep`` (the entry just written) is never deleted, even when it alone is larger. A
    file that vanishes or cannot be deleted meanwhile (another run trimming, a read-only
    folder) is passed over: a cache that cannot be trimmed only takes more room.

    Returns
    -------
    list of Path
        The files deleted.
    """
    entries = []
    for path in folder.glob(pattern):
        try:
            stat = path.stat()
        except OSError:
            continue
        entries.append((stat.st_mtime, stat.st_size, path))
    total = sum(size for _, size, _ in entries)
    deleted = []
    for _, size, path in sorted(entries, key=lambda e: e[0]):
        if total <= max_bytes:
            break
        if keep is not None and path == keep:
            continue
        try:
            path.unlink()
        except OSError:
            continue
        total -= size
        deleted.append(path)
    return deleted
