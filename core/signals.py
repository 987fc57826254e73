"""SIGTERM handled as Ctrl-C is: an exception in the main thread, so commands stop the same way.

``core.command.run_command`` wraps every command's work in :func:`sigterm_as_interrupt`; SIGTERM then raises
:class:`Terminated`, a :class:`KeyboardInterrupt`, where the work is. One ``except
KeyboardInterrupt`` stops both, cleans up as for Ctrl-C, and :func:`interrupted_status` gives the
exit status the shell's convention asks for: 130 (128 + SIGINT) or 143 (128 + SIGTERM).
"""

from __future__ import annotations

import signal
import threading
from contextlib import contextmanager
from typing import Iterator

__all__ = ["Terminated", "sigterm_as_interrupt", "interrupted_status"]


class Terminated(KeyboardInterrupt):
    """Raised in the main thread when the process receives SIGTERM inside :func:`sigterm_as_interrupt`."""


def _raise_terminated(signum, frame) -> None:
    raise Terminated


@contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """Within the block, SIGTERM raises :class:`Terminated` (outside the main thread: nothing changes)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def interrupted_status(exc: BaseException) -> int:
    """Exit status of a command stopped by ``exc``: 143 for SIGTERM (:class:`Terminated`), else 130."""
    return 128 + (signal.SIGTERM if isinstance(exc, Terminated) else signal.SIGINT)
