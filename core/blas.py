"""Limit the BLAS thread pool around many small matrix operations.

Identification works on matrices of about 60 x 60 and on tall-skinny QR
factorizations; threads buy nothing there, and on a busy 2-core machine
OpenBLAS threads spinning against other processes made a regularization
sweep 30x slower (QR 1 s instead of 30 ms). numpy and scipy each bundle a
BLAS; threadpoolctl finds every one loaded, limits it, and restores it.
"""

from __future__ import annotations

import contextlib


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
