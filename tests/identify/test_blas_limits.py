"""qube_koopman.core.blas: the BLAS pools are limited inside the block and restored after it."""

from __future__ import annotations

from threadpoolctl import threadpool_info

from qube_koopman.core.blas import limited_blas_threads


def _blas_threads() -> list[int]:
    return [pool["num_threads"] for pool in threadpool_info() if pool["user_api"] == "blas"]


def test_blas_threads_are_limited_then_restored():
    import scipy.linalg  # noqa: F401  (load scipy's BLAS too)

    before = _blas_threads()
    assert before, "numpy loads a BLAS"
    with limited_blas_threads(1):
        assert _blas_threads() == [1] * len(before)
    assert _blas_threads() == before
