"""Shared plumbing of the command-line tools: clean errors, output folders."""

from __future__ import annotations

import json
import sys
from pathlib import Path


class CliError(Exception):
    """A user mistake: printed as one line, exit status 2, no traceback."""


def fail(message: str) -> int:
    """Print an error line to stderr and return the exit status for user errors."""
    print(f"error: {message}", file=sys.stderr)
    return 2


def output_dir(path: str | Path) -> Path:
    """Create the output folder (and parents); a clear error when that is impossible."""
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise CliError(f"cannot create output folder {path}: {exc.strerror or exc}") from None
    if not path.is_dir():
        raise CliError(f"output path {path} exists and is not a folder")
    return path


def write_json(path: Path, data) -> None:
    """Write JSON atomically enough for a report (whole file, then rename)."""
    tmp = path.with_suffix(path.suffix + ".tmp")
    try:
        tmp.write_text(json.dumps(data, indent=2, allow_nan=True) + "\n")
        tmp.replace(path)
    except OSError as exc:
        raise CliError(f"cannot write {path}: {exc.strerror or exc}") from None
