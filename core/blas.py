"""Limit the BLAS thread pool around many small matrix operations.

Identification works on matrices of about 60 x 60 and on tall-skinny QR
factorizations; threads buy nothing there, and on a busy 2-core machine
OpenBLAS threads spinning against other processes made a regularization
sweep 30x slower (QR 1 s instead of 30 ms). numpy and scipy each bundle a
BLAS; threadpoolctl finds every one loaded, limits it, and restores it.
"""

from __future__ import annotations

import contextlib
from contextvars import ContextVar

# Episodes a fit may factor side by side in this context (None: as many as the BLAS threads allowed).
_EPISODE_THREADS: ContextVar[int | None] = ContextVar("episode_threads", default=None)


@contextlib.contextmanager
def limited_blas_threads(n: int = 1):
    """Run the block with at most ``n`` BLAS threads (every BLAS numpy and scipy loaded)."""
    import numpy  # noqa: F401  (make sure the libraries are loaded)
    import scipy.linalg  # noqa: F401
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=n, user_api="blas"):
        yield


def blas_threads() -> int:
    """The most threads any loaded BLAS may use now (1 inside :func:`limited_blas_threads`)."""
    import numpy  # noqa: F401  (make sure the libraries are loaded)
    import scipy.linalg  # noqa: F401
    from threadpoolctl import threadpool_info

    return max([int(pool["num_threads"]) for pool in threadpool_info() if pool.get("user_api") == "blas"] or [1])


@contextlib.contextmanager
def episode_threads(n: int):
    """Let fits in the block factor up to ``n`` training episodes side by side, one BLAS thread each.

    :func:`limited_blas_threads` keeps the many small products of a fit on one BLAS thread, which
    also leaves a fit's tall per-episode QR factorizations one after the other. Inside this block
    they run on ``n`` threads (each with one BLAS thread, the same factors bit for bit) whatever the
    BLAS limit: what ``qube-identify`` does with its cores. A search's worker processes, limited
    and without this block, still factor one episode at a time.
    """
    if n < 1:
        raise ValueError(f"episodes are factored on 1 thread or more, got {n}")
    token = _EPISODE_THREADS.set(n)
    try:
        yield
    finally:
        _EPISODE_THREADS.reset(token)


def episode_thread_count() -> int:
    """Training episodes a fit factors side by side here: :func:`episode_threads`' ``n`` inside one,
    else :func:`blas_threads`."""
    n = _EPISODE_THREADS.get()
    return blas_threads() if n is None else n
