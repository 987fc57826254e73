"""Limit the BLAS thread pool around many small matrix operations.

Identification works on matrices of about 60 x 60 and on tall-skinny QR
factorizations; threads buy nothing there, and on a busy 2-core machine
OpenBLAS threads spinning against other processes made a regularization
sweep 30x slower (QR 1 s instead of 30 ms). numpy and scipy each bundle an
OpenBLAS; both are found among the loaded libraries and limited, then
restored.
"""

from __future__ import annotations

import contextlib
import ctypes

_SETTERS = ("openblas_set_num_threads", "scipy_openblas_set_num_threads", "scipy_openblas_set_num_threads64_",
            "openblas_set_num_threads64_")
_GETTERS = ("openblas_get_num_threads", "scipy_openblas_get_num_threads", "scipy_openblas_get_num_threads64_",
            "openblas_get_num_threads64_")


def _openblas_libraries() -> list[tuple]:
    found = []
    try:
        with open("/proc/self/maps") as maps:
            paths = {line.split()[-1] for line in maps if "openblas" in line.lower() and "/" in line}
    except OSError:  # not Linux: leave the pools as they are
        return found
    for path in sorted(paths):
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        setter = next((getattr(lib, s) for s in _SETTERS if hasattr(lib, s)), None)
        getter = next((getattr(lib, g) for g in _GETTERS if hasattr(lib, g)), None)
        if setter is not None and getter is not None:
            found.append((setter, getter))
    return found


@contextlib.contextmanager
def limited_blas_threads(n: int = 1):
    """Run the block with at most ``n`` OpenBLAS threads (no-op where none is found)."""
    import numpy  # noqa: F401  (make sure the libraries are loaded)
    import scipy.linalg  # noqa: F401

    libs = _openblas_libraries()
    previous = [getter() for _, getter in libs]
    for setter, _ in libs:
        setter(n)
    try:
        yield
    finally:
        for (setter, _), value in zip(libs, previous):
            setter(value)
